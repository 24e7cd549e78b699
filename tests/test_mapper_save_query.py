"""The mapper's save query refuses a name the file system cannot take instead of failing inside
the handler (found by `smana bench fuzz`: a 300-character name ended as an `internal` rejection
with a traceback). In-process: the handler is called without zenoh."""

from __future__ import annotations

import msgpack
import pytest

from smana.common.config import SmanaConfig
from smana.common.service import ReplyError, Request
from smana.services.mapper.service import MapperService
from smana.services.mapper.takeover import build_map


@pytest.fixture
def mapper(tmp_path):
    cfg = SmanaConfig.load(None, [f'mapper.save_path="{tmp_path}/map.npz"'])
    svc = MapperService(cfg)
    svc.map = build_map(cfg, svc.table)
    return svc


def save(svc, name):
    return svc.on_save(Request("smana/r1/mapper/save", {}, msgpack.packb({"name": name}), False))


@pytest.mark.parametrize(
    "name", ["n" * 300 + ".npz", "n" * 248 + ".npz", "a\x00b.npz", "x\n.npz", "../x.npz", ".npz"]
)
def test_unwritable_names_are_refused(mapper, tmp_path, name):
    with pytest.raises(ReplyError) as info:
        save(mapper, name)
    assert info.value.kind == "value"
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_longest_name_is_saved(mapper, tmp_path):
    name = "n" * 247 + ".npz"  # with ".tmp": 255 bytes
    assert save(mapper, name)["ok"]
    assert (tmp_path / name).is_file()


def test_a_failed_save_is_an_io_refusal(mapper, tmp_path):
    (tmp_path / "taken.npz.tmp").mkdir()  # the temporary file cannot be opened
    with pytest.raises(ReplyError) as info:
        save(mapper, "taken.npz")
    assert info.value.kind == "io"
