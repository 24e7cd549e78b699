"""The TSDF's parallel integration (`mapper.tsdf.threads`) against its serial kernel: the same
map bit for bit (every voxel column, the block order, each cloud's Delta and the counters) on
random clouds, synthetic garden scans and real KITTI scans, and on numba's workqueue threading
layer, the one a wheel install falls back to without tbb or OpenMP."""

from __future__ import annotations

import os
import subprocess
import sys
from typing import NamedTuple

import numba
import numpy as np
import pytest

from smana.services.mapper.backends import tsdf as tsdf_mod
from smana.services.mapper.backends.params import TsdfConfig
from smana.services.mapper.semantic_map import SemanticMap

SEM_IDS = np.array([1, 2, 4, 5, 6, 7, 8], np.uint16)
two_threads = pytest.mark.skipif(
    numba.config.NUMBA_NUM_THREADS < 2, reason="numba has one thread here (NUMBA_NUM_THREADS)"
)


def random_scans(n_scans=3, n=20_000, seed=0):
    """Points in a 30 m box around a moving origin (some closer than min_range, some beyond
    max_range, exact duplicates for the start-voxel subsampling), random labels."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n_scans):
        origin = np.array([0.5 * k, 0.2 * k, 1.0])
        pts = origin + rng.uniform(-15, 15, (n, 3))
        pts[:50] = origin + rng.uniform(-0.05, 0.05, (50, 3))
        pts[50:100] = pts[100:150]
        out.append((pts.astype(np.float32), rng.choice(SEM_IDS, n), np.ones(n, np.float32), origin))
    return out


def garden_scans(n_scans=3):
    from smana.lab.data.scans import GardenWorld

    w = GardenWorld(n_beams=32, n_cols=1024)
    return [(s.points, s.labels, s.confidences, s.origin) for s in map(w.scan, range(n_scans))]


def kitti_scans(n_scans=3):
    from smana.lab.experiments.resources import kitti_sequence

    rng = np.random.default_rng(1)
    return [
        (p, rng.choice(SEM_IDS, len(p)), np.ones(len(p), np.float32), o)
        for p, o in kitti_sequence(n_scans, 2)
    ]


def run(scans, threads, res, max_range=20.0):
    """Each cloud's Delta columns and the final map's columns, block keys and counters."""
    m = SemanticMap("tsdf", res, max_range, 0.0, config=TsdfConfig(threads=threads))
    out = []
    for p, lab, conf, org in scans:
        d = m.integrate(p, lab, conf, org)
        out.append(
            ("delta", d.keys, d.values, d.labels, d.confidences, d.occupied)
            + (d.alt_labels, d.alt_confidences)
        )
    core, grid = m._core, m._core.grid
    n = grid.n_blocks * grid.voxels_per_block
    out.append(("blocks", grid.block_keys[: grid.n_blocks].copy()))
    out += [(name, col[:n].copy()) for name, col in sorted(grid.cols.items())]
    out.append(("counts", np.array([core.n_observed, core.n_occupied, core.last_updates])))
    return out


def assert_identical(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b, strict=True):
        assert x[0] == y[0]
        for u, v in zip(x[1:], y[1:], strict=True):
            assert u.dtype == v.dtype and u.shape == v.shape, x[0]
            assert u.tobytes() == v.tobytes(), f"{x[0]} differs"


@two_threads
@pytest.mark.parametrize("source", [random_scans, garden_scans, kitti_scans])
@pytest.mark.parametrize("res", [0.1, 0.2])
def test_parallel_integration_is_bit_identical_to_the_serial_kernel(source, res):
    scans = source()
    serial = run(scans, 1, res)
    assert serial[-1][1][0] > 10_000  # a map worth comparing
    assert_identical(run(scans, 2, res), serial)


@two_threads
def test_small_chunks_and_growth_keep_the_map_identical(monkeypatch):
    """Many chunks per cloud, and the touched list and the block storage grown mid-chunk."""
    scans = garden_scans(2)
    serial = run(scans, 1, 0.1)
    monkeypatch.setattr(tsdf_mod, "_CHUNK_RAYS", 777)
    monkeypatch.setattr(tsdf_mod.Tsdf, "__init__", _small_touched(tsdf_mod.Tsdf.__init__))
    assert_identical(run(scans, 2, 0.1), serial)


def _small_touched(init):
    def wrapped(self, *a, **kw):
        init(self, *a, **kw)
        self._touched = np.empty(64, np.int64)

    return wrapped


def test_threads_setting_picks_the_path(monkeypatch):
    calls = []
    for name in ("_integrate_serial", "_integrate_parallel"):
        orig = getattr(tsdf_mod.Tsdf, name)
        monkeypatch.setattr(
            tsdf_mod.Tsdf, name, lambda self, *a, _o=orig, _n=name: calls.append(_n) or _o(self, *a)
        )
    p, lab, conf, org = random_scans(1, 2000)[0]
    for threads in (1, 0, 2, 64):
        m = SemanticMap("tsdf", 0.2, 20.0, 0.0, config=TsdfConfig(threads=threads))
        assert m._core.threads == (
            1 if threads == 1 else min(threads or 10**6, numba.config.NUMBA_NUM_THREADS)
        )
        m.integrate(p, lab, conf, org)
    want = "_integrate_parallel" if numba.config.NUMBA_NUM_THREADS > 1 else "_integrate_serial"
    assert calls == ["_integrate_serial", want, want, want]


def test_threads_must_not_be_negative():
    with pytest.raises(ValueError, match="threads"):
        TsdfConfig(threads=-1)


_CHILD = """
import numba, numpy as np
from tests.test_tsdf_parallel import assert_identical, garden_scans, run
scans = garden_scans(2)
assert_identical(run(scans, 2, 0.1), run(scans, 1, 0.1))
print(numba.threading_layer(), numba.get_num_threads())
"""


@pytest.mark.parametrize("layer", ["workqueue", "default"])
def test_parallel_integration_runs_on_numbas_threading_layers(layer):
    """workqueue is what numba falls back to on a wheel install without tbb or OpenMP."""
    env = {**os.environ, "NUMBA_NUM_THREADS": "2", "NUMBA_THREADING_LAYER": layer}
    out = subprocess.run(
        [sys.executable, "-c", _CHILD],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
        cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
    )
    assert out.returncode == 0, out.stderr[-2000:]
    got_layer, n = out.stdout.split()
    assert n == "2"
    if layer == "workqueue":
        assert got_layer == "workqueue"


@two_threads
def test_a_three_point_warm_up_loads_every_parallel_kernel():
    """The mapper service's warm-up integrates 3 points: on the parallel path that must reach
    every parallel kernel, or the first real scan would load (or compile) the rest."""
    from numba.core.registry import CPUDispatcher

    from smana.services.mapper.backends import tsdf_parallel as par

    m = SemanticMap("tsdf", 0.2, 20.0, 0.0, config=TsdfConfig(threads=2))
    pts = np.array([[1.0, 0.1, 0.1], [0.1, 1.0, 0.2], [20.0, 0.1, 0.1]], np.float32)
    m.integrate(pts, np.array([1, 0, 0], np.uint16), np.ones(3, np.float32), (0.0, 0.0, 0.0))
    kernels = {n: f for n, f in vars(par).items() if isinstance(f, CPUDispatcher)}
    assert len(kernels) >= 8
    for name, f in kernels.items():
        if f.py_func.__module__ == par.__name__:
            assert f.signatures, f"{name} not loaded by the warm-up"


class _Cols(NamedTuple):
    a: np.ndarray
    b: np.ndarray


@numba.njit(parallel=True)
def _named_in_the_loop(cols):
    for i in numba.prange(cols.a.shape[0]):
        cols.a[i] = 1.0
        cols.b[i] = 1


@numba.njit(parallel=True)
def _unpacked_before_the_loop(cols):
    a, b = cols
    for i in numba.prange(a.shape[0]):
        a[i] = 1.0
        b[i] = 1


@numba.njit(parallel=True)
def _named_before_the_loop(cols):
    a = cols.a
    b = cols.b
    for i in numba.prange(a.shape[0]):
        a[i] = 1.0
        b[i] = 1


def test_numba_parallel_loops_and_arrays_taken_from_a_tuple():
    """What the parallel passes' arguments rest on (tsdf_parallel.py's docstring), on the numba
    installed: in a parallel loop, writes through an array taken from a tuple inside the loop,
    or unpacked from it before, are lost (numba issues 7135, 10338); through one named from it
    before the loop (`a = cols.a`), they land. Should numba keep the first writes one day, the
    passes may take their outputs as tuples too, and their docstrings must change."""
    for kernel, lands in (
        (_named_in_the_loop, False),
        (_unpacked_before_the_loop, False),
        (_named_before_the_loop, True),
    ):
        cols = _Cols(np.zeros(1000), np.zeros(1000, np.int64))
        kernel(cols)
        assert (cols.a == 1).all() == lands and (cols.b == 1).all() == lands, kernel.__name__
        assert (cols.a == 1).any() == lands, kernel.__name__  # all or nothing
