"""smana as its users install it: build the wheel and the sdist, install the wheel (not editable)
into a clean venv, and run it from a folder outside any checkout.

    python tests/wheel_smoke.py [--python python3.13] [--constraints requirements/lock.txt]
                                [--no-up] [--keep DIR]

Steps, each one line on stdout, the first failure ends the run with status 1:

1. `python -m build` makes the sdist and, from it, the wheel (what PyPI would serve);
2. every `.py`, `.toml`, `.json5` and `.json` under common/ services/ deploy/ lab/ is in the wheel
   (as `smana/<folder>/...`), and nothing in the wheel is missing from the tree;
3. a new venv of `--python` gets the wheel with `pip install` (dependencies from the package
   index within pyproject's ranges, or pinned by `--constraints`);
4. from an empty folder: `smana --version` is pyproject's version, `smana` imports from the venv
   and not from the checkout, `smana world info` describes the default world, `smana --help` and
   the `--help` of every command, bench, experiment and subcommand exit 0;
5. `smana up --duration 240 --set sim.garden.size_m=8` ends `smana up: ok` with exit 0, and its
   run directory's config.toml, metrics.json and map.npz carry the version.

`.ci/run` runs it on Python 3.13 (the suite runs on 3.11); `tests/test_packaging.py` runs it
when SMANA_WHEEL_SMOKE=1, and checks step 2 in every run of the suite.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
import tomllib
import zipfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ROOTS = ("common", "services", "deploy", "lab")
SHIPPED = (".py", ".toml", ".json5", ".json")


class SmokeError(Exception):
    """A step that failed: its message is the one line the run ends with."""


def pyproject_version() -> str:
    return tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]


def tree_files() -> set[str]:
    """Every file a wheel must carry, as its path inside the wheel (`smana/common/keys.py`)."""
    out = set()
    for root in ROOTS:
        for p in (REPO / root).rglob("*"):
            if p.is_file() and p.suffix in SHIPPED and "__pycache__" not in p.parts:
                out.add("smana/" + p.relative_to(REPO).as_posix())
    return out


def wheel_files(wheel: Path) -> set[str]:
    with zipfile.ZipFile(wheel) as z:
        return {n for n in z.namelist() if n.startswith("smana/") and not n.endswith("/")}


def check_wheel(wheel: Path) -> str:
    want, got = tree_files(), wheel_files(wheel)
    missing, extra = sorted(want - got), sorted(n for n in got - want if n.endswith(SHIPPED))
    if missing:
        raise SmokeError(f"{len(missing)} files of the tree are not in the wheel: {missing[:5]}")
    if extra:
        raise SmokeError(f"the wheel holds files the tree does not: {extra[:5]}")
    return f"{len(got)} files, every .py/.toml/.json5/.json of {', '.join(ROOTS)}"


def build(out: Path) -> tuple[Path, Path]:
    """The sdist, and the wheel built from it (`python -m build`'s default)."""
    run([sys.executable, "-m", "build", "--outdir", str(out), str(REPO)], cwd=REPO, timeout=600)
    wheels, sdists = sorted(out.glob("smana-*.whl")), sorted(out.glob("smana-*.tar.gz"))
    if len(wheels) != 1 or len(sdists) != 1:
        raise SmokeError(f"expected one wheel and one sdist in {out}, got {wheels + sdists}")
    return wheels[0], sdists[0]


def run(argv, cwd: Path, timeout: float, env=None, check=True) -> subprocess.CompletedProcess:
    r = subprocess.run(
        [str(a) for a in argv],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
        stdin=subprocess.DEVNULL,
    )
    if check and r.returncode != 0:
        tail = (r.stdout + r.stderr).strip().splitlines()[-15:]
        raise SmokeError(
            f"{' '.join(map(str, argv[:4]))} exited {r.returncode}:\n" + "\n".join(tail)
        )
    return r


def clean_env(constraints: Path | None) -> dict:
    """The environment without what would make the venv see the checkout."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PIP_CONSTRAINT")}
    env.pop("VIRTUAL_ENV", None)
    if constraints is not None:
        env["PIP_CONSTRAINT"] = str(constraints)
    return env


def subcommands(help_text: str) -> list[str]:
    """The choices of an argparse subparser (`{info,export,preview}`) in a usage line; an
    option's choices (`[--mode {peer,client,router}]`) are not subcommands."""
    usage = help_text.split("\n\n")[0]
    while (bare := re.sub(r"\[[^\[\]]*\]", "", usage)) != usage:  # optional groups, innermost first
        usage = bare
    m = re.search(r"\{([a-z0-9_,-]+)\}", usage)
    return m.group(1).split(",") if m else []


def smoke(python: str, constraints: Path | None, up: bool, work: Path) -> None:
    t0 = time.monotonic()

    def step(text: str) -> None:
        print(f"[{time.monotonic() - t0:6.1f} s] {text}", flush=True)

    version = pyproject_version()
    wheel, sdist = build(work / "dist")
    step(f"built {wheel.name} and {sdist.name}")
    step(f"wheel contents: {check_wheel(wheel)}")
    venv = work / "venv"
    env = clean_env(constraints)
    run([python, "-m", "venv", venv], cwd=work, timeout=300, env=env)
    pip = [venv / "bin" / "python", "-m", "pip", "install", "-q", "--disable-pip-version-check"]
    run([*pip, wheel], cwd=work, timeout=3600, env=env)
    py = venv / "bin" / "python"
    pyv = run([py, "--version"], cwd=work, timeout=60, env=env).stdout.strip()
    step(f"installed into a clean venv ({pyv}{', constrained' if constraints else ''})")
    outside = work / "elsewhere"
    outside.mkdir()
    smana = venv / "bin" / "smana"

    got = run([smana, "--version"], cwd=outside, timeout=120, env=env).stdout.strip()
    if got != version:
        raise SmokeError(f"smana --version says {got!r}, pyproject.toml {version!r}")
    where = run(
        [py, "-c", "import smana.common, smana.services.sim.worlds as w; print(w.__file__)"],
        cwd=outside,
        timeout=120,
        env=env,
    ).stdout.strip()
    if not Path(where).is_relative_to(venv):
        raise SmokeError(f"smana imports from {where}, not from the venv")
    step(f"smana --version: {got}; imports from the venv")
    info = json.loads(run([smana, "world", "info"], cwd=outside, timeout=300, env=env).stdout)
    step(f"smana world info: {info.get('name', info.get('source', '?'))}, {len(info)} fields")

    listing = run([py, "-c", LIST_COMMANDS], cwd=outside, timeout=120, env=env).stdout
    commands, benches = json.loads(listing)

    def helps(argv: list[str]) -> int:
        """`smana ARGV --help` and the --help of each of its subcommands: how many ran."""
        text = run([smana, *argv, "--help"], cwd=outside, timeout=300, env=env).stdout
        subs = subcommands(text.split("\n\n")[0])
        for sub in subs:
            run([smana, *argv, sub, "--help"], cwd=outside, timeout=300, env=env)
        return 1 + len(subs)

    # each --help is a Python start and an import: four at once on two cores
    with ThreadPoolExecutor(4) as pool:
        argvs = [[]] + [[c] for c in commands] + [["bench", b] for b in benches]
        n = sum(pool.map(helps, argvs))  # [] is `smana --help` itself
    step(f"--help of {n} commands, benches and subcommands: exit 0")

    if not up:
        return
    run_dir = outside / "run"
    args = ["up", "--duration", "240", "--set", "sim.garden.size_m=8", "--run-dir", run_dir]
    r = run([smana, *args], cwd=outside, timeout=900, env=env, check=False)
    if r.returncode != 0 or "smana up: ok" not in r.stdout:
        tail = (r.stdout + r.stderr).strip().splitlines()[-20:]
        raise SmokeError(f"smana up exited {r.returncode}:\n" + "\n".join(tail))
    check_versions(run_dir, version, py, outside, env)
    line = next(x for x in r.stdout.splitlines() if "usable coverage (against" in x)
    step(f"smana up: ok ({' '.join(line.split())})")


def check_versions(run_dir: Path, version: str, py: Path, cwd: Path, env: dict) -> None:
    header = (run_dir / "config.toml").read_text().splitlines()[0]
    if header != f"# written by smana {version}":
        raise SmokeError(f"config.toml starts {header!r}")
    metrics = json.loads((run_dir / "metrics.json").read_text())
    if metrics.get("smana_version") != version:
        raise SmokeError(f"metrics.json smana_version = {metrics.get('smana_version')!r}")
    code = (
        "import json, sys, numpy as np\n"
        "with np.load(sys.argv[1]) as z: print(json.loads(bytes(z['meta']).decode()).get("
        "'smana_version'))"
    )
    got = run([py, "-c", code, run_dir / "map.npz"], cwd=cwd, timeout=120, env=env).stdout
    if got.strip() != version:
        raise SmokeError(f"map.npz's metadata says smana_version {got.strip()!r}")


LIST_COMMANDS = (
    "import json; from smana.deploy.cli import COMMANDS; from smana.lab.bench import BENCHES; "
    "print(json.dumps([list(COMMANDS), list(BENCHES)]))"
)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="wheel_smoke.py", description=__doc__.splitlines()[0])
    p.add_argument("--python", default=sys.executable, help="the venv's Python (default: this)")
    p.add_argument("--constraints", type=Path, help="a lock file to install from (PIP_CONSTRAINT)")
    p.add_argument("--no-up", dest="up", action="store_false", help="skip the smana up run")
    p.add_argument("--keep", type=Path, help="work here and keep it (default: a temp folder)")
    args = p.parse_args(argv)
    constraints = args.constraints.resolve() if args.constraints else None
    with tempfile.TemporaryDirectory(prefix="smana-wheel-") as tmp:
        work = args.keep.resolve() if args.keep else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        try:
            smoke(args.python, constraints, args.up, work)
        except (SmokeError, subprocess.TimeoutExpired) as exc:
            print(f"wheel smoke: FAILED: {exc}", flush=True)
            return 1
    print("wheel smoke: ok", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
