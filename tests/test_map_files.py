"""Map files are checked before use (issue 25, item 5): the generators of `lab/fuzz_maps.py`
(hypothesis drives them) make valid and corrupt `.npz` maps of every back-end, a fleet map and
the earlier formats; `SemanticMap.load` and `FleetMap.load` either load a file bit for bit as it
was saved or refuse it with one `MapFileError` line, never anything else. Sizes are checked
before anything is allocated; `smana mapper --load` refuses a bad file in one line, exit 2."""

from __future__ import annotations

import json
import subprocess
import sys
import tracemalloc
import zipfile
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from smana.lab import fuzz_maps as fm
from smana.lab.fuzz_values import Draw
from smana.services.mapper.mapfile import MAX_MAP_BYTES, MapFileError
from smana.services.mapper.semantic_map import SemanticMap

SETTINGS = settings(
    max_examples=40,
    deadline=None,
    derandomize=True,
    suppress_health_check=[
        HealthCheck.too_slow,
        HealthCheck.data_too_large,
        HealthCheck.function_scoped_fixture,  # tmp_path: one file, rewritten by each example
    ],
)


class HypothesisDraw(Draw):
    def __init__(self, data):
        self.data = data

    def integer(self, lo: int, hi: int) -> int:
        return self.data.draw(st.integers(lo, hi))

    def choice(self, options):
        return self.data.draw(st.sampled_from(options))


def base(name: str) -> fm.Base:
    return next(b for b in fm.bases() if b.name == name)


def judge(mutant: fm.MapMutant, b: fm.Base, tmp_path) -> tuple[str, str]:
    path = tmp_path / "map.npz"
    path.write_bytes(mutant.data)
    out, why = fm.try_load(path, b)
    assert out != "crash", f"{b.name} {mutant.how}: {why}"
    if out == "loaded":
        assert why == "same", f"{b.name} {mutant.how}: loaded, but {why}"
    if mutant.predict is True:
        assert out == "refused", f"{b.name} {mutant.how}: loaded, should be refused"
    if mutant.predict is False:
        assert out == "loaded", f"{b.name} {mutant.how}: refused ({why})"
    return out, why


@pytest.mark.parametrize("name", [b.name for b in fm.bases()])
def test_a_valid_file_of_every_kind_loads_bit_identically(name, tmp_path):
    """The three back-ends, a fleet map, a format-1 file and a TSDF file with float
    log-probabilities (the layout before int16 steps), stored or deflated."""
    b = base(name)
    for compress in (False, True):
        path = tmp_path / "map.npz"
        path.write_bytes(fm.file_bytes(b.arrays, compress))
        assert fm.try_load(path, b) == ("loaded", "same")
        SemanticMap.check_file(path, fm.CLASS_TABLE, b.backend)


def test_every_saved_map_names_the_smana_version_and_files_without_it_load(tmp_path):
    from importlib.metadata import version

    b = base("octree-max")
    assert b.meta["smana_version"] == version("smana")
    assert "smana_version" in base("fleet").meta
    old = {
        **b.arrays,
        "meta": fm.meta_bytes({k: v for k, v in b.meta.items() if k != "smana_version"}),
    }
    path = tmp_path / "old.npz"
    path.write_bytes(fm.file_bytes(old))
    assert fm.try_load(path, b) == ("loaded", "same")


@pytest.mark.parametrize("mutation", fm.MAP_MUTATIONS)
@SETTINGS
@given(data=st.data())
def test_a_mutated_map_file_loads_as_saved_or_is_refused_in_one_line(mutation, data, tmp_path):
    d = HypothesisDraw(data)
    b = d.choice(fm.bases())
    data_, how, predict = fm._MUTATORS[mutation](b, d)
    judge(fm.MapMutant(data_, b.name, f"{mutation}:{how}", predict), b, tmp_path)


def test_every_truncation_is_refused(tmp_path):
    b = base("fleet")
    data = fm.file_bytes(b.arrays)
    offsets = sorted(
        {*range(0, 300), *range(300, len(data), 211), *range(len(data) - 300, len(data))}
    )
    for k in offsets:
        path = tmp_path / "cut.npz"
        path.write_bytes(data[:k])
        out, why = fm.try_load(path, b)
        assert out == "refused", f"cut at {k}: {out} {why}"


def probe_cases() -> dict[str, tuple[dict, str]]:
    """The outside probe's findings (2026-12-02), each as a file and the reason it must give."""
    b = base("octree-max")
    a = b.arrays
    meta = b.meta
    keys = a["block_keys"].copy()
    keys[1] = keys[0]
    cases = {
        "a column of one element": ({**a, "col_logodds": a["col_logodds"][:1]}, "shape (1,)"),
        "duplicate block keys": ({**a, "block_keys": keys}, "a block twice"),
        "float block keys": ({**a, "block_keys": a["block_keys"].astype(np.float64)}, "dtype <f8"),
        "a complex column": ({**a, "col_prob": a["col_prob"].astype(np.complex64)}, "dtype <c8"),
        "integrations as text": (
            {**a, "meta": fm.meta_bytes({**meta, "integrations": "x"})},
            "meta.integrations",
        ),
        "max_range_m 1e308": (
            {**a, "meta": fm.meta_bytes({**meta, "max_range_m": 1e308})},
            "meta.max_range_m",
        ),
        "no meta": ({k: v for k, v in a.items() if k != "meta"}, "no array 'meta'"),
        "a pickle": (
            {**a, "col_flags": fm.npy_bytes(np.array([None], object), allow_pickle=True)},
            "not a plain number type",
        ),
        "a module:Class back-end": (
            {**a, "meta": fm.meta_bytes({**meta, "backend": "antigravity:Fly"})},
            "none of the known back-ends",
        ),
        "a path as class table": (
            {**a, "meta": fm.meta_bytes({**meta, "class_table": "/etc/passwd"})},
            "not a bundled table",
        ),
    }
    return cases


def test_a_file_never_makes_the_loader_import_the_module_it_names(tmp_path, monkeypatch):
    """A `module:Class` back-end in a file is refused unless the caller trusts that spec (its
    own `mapper.backend`): the module is not even imported."""
    mark = tmp_path / "imported"
    (tmp_path / "spy_backend.py").write_text(f"open({str(mark)!r}, 'w').close()\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    b = base("octree-max")
    path = tmp_path / "spy.npz"
    path.write_bytes(
        fm.file_bytes({**b.arrays, "meta": fm.meta_bytes({**b.meta, "backend": "spy_backend:Spy"})})
    )
    with pytest.raises(MapFileError, match="none of the known back-ends"):
        SemanticMap.load(path)
    with pytest.raises(MapFileError, match="none of the known back-ends"):
        SemanticMap.check_file(path)
    assert not mark.exists()
    with pytest.raises(MapFileError, match="is not a MapBackend class"):  # trusted: imported
        SemanticMap.load(path, backend="spy_backend:Spy")
    assert mark.exists()


def test_a_range_beyond_the_maps_extent_is_refused_in_the_library_too():
    # 1e308 overflowed the octree's kernels set-up (OverflowError) from a file or a config
    for kw in ({"max_range_m": 1e308}, {"max_range_m": 1e20}, {"raycast_range_m": 1e308}):
        with pytest.raises(ValueError, match="must be in"):
            SemanticMap("octree-max", 0.1, **kw)
    SemanticMap("octree-max", 0.1, max_range_m=4 * 32768 * 0.1)  # the limit itself is fine


@pytest.mark.parametrize("case", list(probe_cases()))
def test_the_probes_corrupt_files_are_refused_in_one_line(case, tmp_path):
    arrays, reason = probe_cases()[case]
    path = tmp_path / "probe.npz"
    path.write_bytes(fm.file_bytes(arrays))
    with pytest.raises(MapFileError) as info:
        SemanticMap.load(path)
    msg = str(info.value)
    assert reason in msg and "\n" not in msg and str(path) in msg


def _peak_bytes(fn) -> int:
    tracemalloc.start()
    try:
        fn()
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    return peak


def test_a_declared_terabyte_array_is_refused_before_anything_is_allocated(tmp_path):
    """The probe's 7.3 TiB: an .npy header declaring 2**40 float64 in a file of a few kB."""
    b = base("octree-max")
    head = fm.npy_header("<f8", (2**40,))
    path = tmp_path / "huge.npz"
    path.write_bytes(fm.file_bytes({**b.arrays, "col_logodds": head + bytes(64)}))

    def load():
        with pytest.raises(MapFileError, match=r"col_logodds: declares 8796093022208 bytes"):
            SemanticMap.load(path)

    assert _peak_bytes(load) < 5 << 20


def test_a_zip_bomb_is_refused_without_inflating_it(tmp_path):
    """A deflated member of zeros declaring 256 MiB (its data: about 250 kB), over a 64 MiB
    limit; and a directory entry declaring 8 GiB, over the default limit of 4 GiB."""
    b = base("octree-max")
    members = [(f"{n}.npy", fm.npy_bytes(a)) for n, a in b.arrays.items()]
    entries = [(n, x, zipfile.ZIP_STORED, len(x), zlib.crc32(x)) for n, x in members]
    stream, crc = fm.bomb_stream()
    bomb = [e if e[0] != "col_prob.npy" else (e[0], stream, 8, fm.BOMB_BYTES, crc) for e in entries]
    path = tmp_path / "bomb.npz"
    path.write_bytes(fm.raw_zip(bomb))
    assert path.stat().st_size < 1 << 20

    def load():
        with pytest.raises(MapFileError, match="more than 67108864 bytes"):
            SemanticMap.load(path, max_bytes=64 << 20)

    assert _peak_bytes(load) < 5 << 20
    huge = [e if e[0] != "col_prob.npy" else (e[0], e[1], 8, 8 << 30, e[4]) for e in entries]
    path.write_bytes(fm.raw_zip(huge))  # a 32-bit size field: wraps; the header says the rest
    with pytest.raises(MapFileError):
        SemanticMap.load(path)
    assert MAX_MAP_BYTES == 4 << 30


def test_a_fleet_map_file_is_checked_as_a_plain_one(tmp_path):
    """Its layers too: a NaN in a member's log-odds, a layer's block twice."""
    b = base("fleet")
    lo = b.arrays["layer1_logodds"].copy()
    lo[3] = np.nan
    keys = b.arrays["layer0_block_keys"].copy()
    keys[-1] = keys[0]
    for arrays, reason in (
        ({**b.arrays, "layer1_logodds": lo}, "layer1_logodds: 1 values not finite"),
        ({**b.arrays, "layer0_block_keys": keys}, "layer0_block_keys: a block twice"),
    ):
        path = tmp_path / "fleet.npz"
        path.write_bytes(fm.file_bytes(arrays))
        out, why = fm.try_load(path, b)
        assert out == "refused" and reason in why
        with pytest.raises(MapFileError, match=reason):
            SemanticMap.load(path)


@pytest.mark.parametrize(
    "case",
    ["truncated", "a column of one element", "max_range_m 1e308", "a pickle", "declared 8 TiB"],
)
def test_smana_mapper_load_refuses_a_bad_file_in_one_line_with_exit_2(case, tmp_path):
    """Before zenoh opens: nothing to connect to is needed for the refusal."""
    b = base("octree-max")
    path = tmp_path / "bad.npz"
    if case == "truncated":
        path.write_bytes(fm.file_bytes(b.arrays)[:1000])
    elif case == "declared 8 TiB":
        path.write_bytes(fm.file_bytes({**b.arrays, "col_logodds": fm.npy_header("<f8", (2**40,))}))
    else:
        path.write_bytes(fm.file_bytes(probe_cases()[case][0]))
    out = subprocess.run(
        [sys.executable, "-m", "smana.services.mapper", "--load", str(path)]
        + ["--mode", "client", "--connect", "tcp/127.0.0.1:9"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2, out.stderr
    assert len(lines) == 1 and lines[0].startswith(f"smana mapper: {path}: not a smana map file")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.npz"]  # nothing written


@pytest.mark.multiprocess
def test_a_map_whose_values_are_bad_is_refused_by_the_mapper_process(zenoh_stack, tmp_path):
    """A NaN in a column passes the quick check (headers only): the service refuses it as it
    loads the map, in one line, exit 2, no traceback; and the file is left as it was."""
    b = base("octree-max")
    col = b.arrays["col_logodds"].copy()
    col[7] = np.nan
    path = tmp_path / "nan.npz"
    data = fm.file_bytes({**b.arrays, "col_logodds": col})
    path.write_bytes(data)
    save = tmp_path / "autosave.npz"
    proc = zenoh_stack.service("mapper", "--load", str(path), "--save", str(save))
    assert proc.wait(timeout=120) == 2
    log = zenoh_stack.log(proc)
    mine = [ln for ln in log.splitlines() if ln.startswith("smana mapper:")]
    assert "Traceback" not in log
    assert mine == [
        f"smana mapper: {path}: not a smana map file (col_logodds: 1 values not finite)"
    ]
    assert path.read_bytes() == data and not save.exists()


def test_meta_json_is_strict(tmp_path):
    b = base("octree-max")
    text = json.dumps(b.meta).replace('"points": ', '"points": NaN, "p": ', 1)
    path = tmp_path / "nan.npz"
    path.write_bytes(fm.file_bytes({**b.arrays, "meta": np.frombuffer(text.encode(), np.uint8)}))
    with pytest.raises(MapFileError, match="NaN is not a number"):
        SemanticMap.load(path)


def test_smana_mapper_refuses_a_range_beyond_the_maps_extent_in_one_line(tmp_path):
    # 1e308 from the config overflowed the octree's set-up, a traceback in the log
    out = subprocess.run(
        [sys.executable, "-m", "smana.services.mapper", "--set", "mapper.max_range_m=1e308"]
        + ["--mode", "client", "--connect", "tcp/127.0.0.1:9"],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert out.returncode == 2, out.stderr
    assert out.stderr.strip().splitlines() == [
        "smana mapper: mapper.max_range_m: must be in (0, 13107.2] at resolution_m 0.1, got 1e+308"
    ]
