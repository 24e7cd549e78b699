"""What a service imports before it is live (STYLE.md: "a sentence that promises behaviour is a
test"): the explorer and the sim import no numba (a quarter of a second of CPU a process, five
processes at once on 2 cores) until they use a kernel, after they are live; the explorer imports
no scipy. Each probe runs in a fresh interpreter; a last probe shows the check sees numba when it
is imported."""

from __future__ import annotations

import subprocess
import sys

import pytest


def imported(code: str) -> set[str]:
    """Top-level packages and smana modules in sys.modules after running `code`."""
    probe = (
        f"import sys\n{code}\n"
        "print(' '.join(sorted(m for m in sys.modules if '.' not in m or m.startswith('smana.'))))"
    )
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return set(out.stdout.split())


@pytest.mark.parametrize(
    "module",
    ["smana.services.explorer.service", "smana.services.sim.service"],
)
def test_a_service_module_imports_no_numba(module):
    mods = imported(f"import {module}, {module.rsplit('.', 1)[0]}.__main__")
    assert "numba" not in mods and "llvmlite" not in mods
    # nor the kernels' modules
    assert not {"smana.services.explorer.kernels", "smana.services.sim.camera_kernel"} & mods


def test_the_explorer_imports_no_scipy():
    """scipy.ndimage is the explorer's only when it plans (0.15 s of CPU). (The sim needs it for
    its spawn; on a warm world cache, not the generator's modules: test_sim_world_cache.py.)"""
    assert "scipy" not in imported("import smana.services.explorer.service")


def test_the_kernels_load_on_first_use():
    mods = imported(
        "import numpy as np\n"
        "from smana.services.explorer import frontier as fr\n"
        "fr.travel_distance_m(np.ones((3, 3), bool), np.array([[1, 1]]), np.zeros(1), 0.1)"
    )
    assert {"numba", "smana.services.explorer.kernels"} <= mods
