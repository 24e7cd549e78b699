"""Every schema round-trips (msgpack and JSON); every kind of malformed payload is rejected with the
right MessageError kind."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest

from smana.common import messages as m
from smana.common.messages import MessageError, decode, encode, from_json, to_json
from smana.common.navgrid import FLAG_KNOWN, FLAG_OBSTACLE

rng = np.random.default_rng(0)


def cloud(n=50, label_dtype="u1"):
    return m.SemanticCloud(
        stamp_s=12.5,
        seq=7,
        points=rng.normal(size=(n, 3)).astype("f4"),
        labels=rng.integers(0, 9, n).astype(label_dtype),
        confidences=rng.uniform(0.33, 1, n).astype("f4"),
        sensor_position=np.array([1.0, 2.0, 0.5]),
        sensor_orientation_xyzw=np.array([0, 0, 0.38268343, 0.92387953]),
        source="lidar",
    )


EXAMPLES = [
    cloud(),
    cloud(0, "u2"),
    m.Pose.from_xyz_yaw(1.0, -2.0, 0.3, 0.7, stamp_s=3.0, seq=4),
    m.VelocityCommand(1.0, 2, 0.5, -0.2, "explorer"),
    m.MapDelta(
        1.0,
        2,
        3,
        "tsdf",
        0.1,
        centres=rng.normal(size=(5, 3)).astype("f4"),
        labels=np.arange(5, dtype="u2"),
        confidences=np.ones(5, "f4"),
        occupied=np.array([1, 0, 1, 1, 0], "u1"),
        values=np.zeros(5, "f4"),
    ),
    m.GraphPatch(
        1.0,
        2,
        0.2,
        np.array([-5.0, -5.0]),
        cells=np.array([[1, 2], [3, 4]], "i4"),
        labels=np.array([1, 2], "u2"),
        heights=np.array([0.1, 0.2], "f4"),
        flags=np.array([FLAG_KNOWN, FLAG_KNOWN | FLAG_OBSTACLE], "u1"),
    ),
    m.PathRequest(
        "q1",
        np.array([0.0, 0.0]),
        np.array([4.0, 3.0, 0.1]),
        h_f=0.2,
        class_costs={1: 4.0},
        allow_unknown=True,
    ),
    m.PathReply(
        "q1",
        True,
        path=np.zeros((4, 3), "f4"),
        cost_total=5.5,
        label_share={"grass": 0.25, "terrain": 0.75},
        nodes_expanded=10,
        nearest_free=np.array([1.0, 2.0]),
    ),
    m.ServiceStatus(
        1.0,
        1,
        "r1",
        "mapper",
        42,
        3.5,
        "running",
        10,
        9,
        6,
        {"stale": 1},
        {"nonfinite": 2},
        1,
        {"gap": 3},
        {"voxels": 100},
    ),
]


def same(a, b):
    assert type(a) is type(b)
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape, f.name
            np.testing.assert_array_equal(x, y)
        else:
            assert x == y, f.name


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda x: type(x).__name__)
def test_round_trip_msgpack(msg):
    same(msg, decode(encode(msg), type(msg)))


@pytest.mark.parametrize("msg", EXAMPLES, ids=lambda x: type(x).__name__)
def test_round_trip_json(msg):
    back = from_json(to_json(msg), type(msg))
    for f in dataclasses.fields(msg):
        x, y = getattr(msg, f.name), getattr(back, f.name)
        if isinstance(x, np.ndarray):
            np.testing.assert_allclose(x, y.astype(x.dtype), rtol=1e-6)
        else:
            assert x == y


def test_every_message_type_has_an_example():
    assert {type(x).__name__ for x in EXAMPLES} == set(m.REGISTRY)


def test_large_cloud_is_compact():
    c = cloud(131_072)
    size = len(encode(c))
    # 12 + 1 + 4 bytes a point, plus a small header: raw bytes, no per-point objects
    assert size < 131_072 * 17 + 1024


def wire(msg):
    return msgpack.unpackb(encode(msg), strict_map_key=False)


def pack(d):
    return msgpack.packb(d, use_bin_type=True)


def reject(payload, kind, expect=None, **kw):
    with pytest.raises(MessageError) as info:
        decode(payload, expect, **kw)
    assert info.value.kind == kind, str(info.value)


def test_garbage_is_malformed():
    reject(b"\xc1\xc1 not msgpack", "malformed")
    reject(pack([1, 2, 3]), "malformed")
    reject(pack({"no": "type"}), "malformed")


def test_wrong_type_and_version():
    reject(encode(m.Pose()), "type", m.SemanticCloud)
    d = wire(m.Pose())
    d["_type"] = "Nonsense"
    reject(pack(d), "type")
    d = wire(m.Pose())
    d["_v"] = 99
    reject(pack(d), "version")


def test_missing_and_unknown_fields():
    d = wire(cloud())
    del d["labels"]
    reject(pack(d), "missing_field")
    d = wire(cloud())
    d["colour"] = 1
    reject(pack(d), "unknown_field")


def test_bad_arrays():
    d = wire(cloud())
    d["points"]["dtype"] = "<f8"
    d["points"]["data"] = np.zeros((50, 3)).tobytes()
    reject(pack(d), "dtype")
    d = wire(cloud())
    d["points"]["shape"] = [50, 4]
    reject(pack(d), "shape")
    d = wire(cloud())
    d["points"]["data"] = d["points"]["data"][:-4]
    reject(pack(d), "shape")
    d = wire(cloud())
    d["labels"]["dtype"] = "not-a-dtype"
    reject(pack(d), "dtype")


def test_lengths_disagree():
    c = cloud()
    c.labels = c.labels[:-1]
    reject(encode(c), "length")


def test_nonfinite_points_rejected_or_dropped():
    c = cloud(10)
    c.points = c.points.copy()
    c.points[3, 1] = np.nan
    c.points[5, 0] = np.inf
    reject(encode(c), "nonfinite")
    kept = decode(encode(c), m.SemanticCloud, drop_nonfinite=True)
    assert kept.n_dropped_nonfinite == 2
    assert len(kept.points) == len(kept.labels) == len(kept.confidences) == 8
    assert np.isfinite(kept.points).all()


def test_nonfinite_scalars_and_poses():
    p = m.Pose()
    p.position = np.array([np.nan, 0.0, 0.0])
    reject(encode(p), "nonfinite")
    d = wire(m.VelocityCommand())
    d["linear_mps"] = float("inf")
    reject(pack(d), "nonfinite")


def test_wrong_scalar_type():
    d = wire(m.VelocityCommand())
    d["linear_mps"] = "fast"
    reject(pack(d), "value")
    d = wire(m.VelocityCommand())
    d["seq"] = True
    reject(pack(d), "value")


def test_oversize():
    reject(b"\x00" * 101, "oversize", max_bytes=100)


def test_json_query_defaults_and_errors():
    r = from_json(b'{"start": [0, 0], "goal": [5, 3], "class_costs": {"1": 8}}', m.PathRequest)
    assert r.class_costs == {1: 8.0} and r.allow_unknown is False
    with pytest.raises(MessageError) as info:
        from_json(b'{"start": [0, 0]}', m.PathRequest)
    assert info.value.kind == "missing_field"
    with pytest.raises(MessageError) as info:
        from_json(b'{"start": [0, 0, 0, 0], "goal": [1, 1]}', m.PathRequest)
    assert info.value.kind == "shape"
    with pytest.raises(MessageError) as info:
        from_json(b"{not json", m.PathRequest)
    assert info.value.kind == "malformed"


def test_pose_helpers():
    p = m.Pose.from_xyz_yaw(1, 2, 3, 2.5)
    assert p.yaw == pytest.approx(2.5)
    q = m.matrix_to_quat(p.rotation())
    assert np.allclose(np.abs(q), np.abs(p.orientation_xyzw))
    assert np.allclose(p.matrix()[:3, 3], [1, 2, 3])
