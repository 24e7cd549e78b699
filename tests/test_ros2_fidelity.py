"""rmw_zenoh fidelity: the gid rmw_zenoh_cpp computes, its QoS token strings, the sample-miss
heartbeat of reliable transient-local publishers, nav2_msgs/Costmap (type hash, key, CDR and
values against zenoh-ros2-sdk, pamoja-ros2 and Nav2's cost_values.hpp), and the map's voxel
budget."""

from __future__ import annotations

import struct

import numpy as np
import pytest

pytest.importorskip("rosbags")

from smana.common.messages import Pose  # noqa: E402
from smana.common.navgrid import FLAG_KNOWN, FLAG_OBSTACLE, FLAG_SAFETY_ZONE, NavGrid  # noqa: E402
from smana.services.ros2 import convert, costmap_types, rmw  # noqa: E402
from tests.conftest import wait_for  # noqa: E402
from tests.support.ros2_sdk import sdk_session  # noqa: E402

TYPES = rmw.RosTypes()
COSTMAP = costmap_types.COSTMAP


class _Session:
    """What RosNode reads of a zenoh session, recording the tokens it declares."""

    def __init__(self):
        self.tokens: list[str] = []

    def zid(self):
        return "0123abcd"

    def liveliness(self):
        return self

    def declare_token(self, key):
        self.tokens.append(key)
        return self


# -- the gid -------------------------------------------------------------------------------------


def test_gid_is_xxh3_128_of_the_token_low_then_high_little_endian():
    # rmw_zenoh_cpp (liveliness_utils.cpp, Entity::Entity): simplified_XXH3_128bits over the
    # token's characters, then memcpy of low64 and of high64 (host order: little-endian).
    # XXH3-128 of the empty input is xxHash's published test vector 0x99aa06d3...497f.
    high, low = 0x99AA06D3014798D8, 0x6001C324468D497F
    assert rmw.gid_of("") == low.to_bytes(8, "little") + high.to_bytes(8, "little")
    import xxhash

    token = "@ros2_lv/0/0123abcd/0/1/MP/%/%smana%r1/smana/%smana%r1%map/x/RIHS01_00/::,1:,:,:,,"
    h = xxhash.xxh3_128_intdigest(token.encode())
    assert rmw.gid_of(token) == struct.pack("<QQ", h & (2**64 - 1), h >> 64)
    assert rmw.gid_of(token) != rmw.gid_of(token + "x")


def test_a_publishers_gid_is_that_of_its_own_token_and_its_qos_rmw_zenohs():
    pytest.importorskip("zenoh")
    session = _Session()
    node = rmw.RosNode(session, TYPES, 0, "smana", "/smana/r1")
    tokens = []

    class Pub:  # a declared zenoh publisher, as RosPublisher reads it
        key_expr = "k"

        def put(self, payload, attachment):
            tokens.append(attachment)

    declared = []
    node.session.declare_publisher = lambda key, **kw: declared.append(kw) or Pub()
    pub = node.publisher("/smana/r1/odom", "nav_msgs/msg/Odometry")
    assert session.tokens[-1].split("/")[5] == rmw.PUBLISHER
    assert pub.gid == rmw.gid_of(session.tokens[-1])
    other = node.publisher("/smana/r1/odom2", "nav_msgs/msg/Odometry")
    assert other.gid != pub.gid
    # Reliability and congestion control as rmw_zenoh_cpp's rmw_publisher_data.cpp sets them:
    # DROP but for a reliable KEEP_ALL publisher.
    import zenoh

    node.publisher("/a", "nav_msgs/msg/Odometry", rmw.SENSOR_QOS)
    node.publisher("/b", "nav_msgs/msg/Odometry", rmw.QoS(keep_all=True))
    got = [(d["reliability"], d["congestion_control"]) for d in declared]
    R, C = zenoh.Reliability, zenoh.CongestionControl
    assert got == [
        (R.RELIABLE, C.DROP),
        (R.RELIABLE, C.DROP),
        (R.BEST_EFFORT, C.DROP),
        (R.RELIABLE, C.BLOCK),
    ]


# -- QoS tokens ----------------------------------------------------------------------------------


def _rmw_zenoh_keyexpr_to_qos(text: str) -> dict:
    """rmw_zenoh_cpp's `keyexpr_to_qos` (liveliness_utils.cpp), as it checks a token's QoS: six
    ':' parts; history, deadline and lifespan two ',' parts; liveliness three; an empty field is
    the default (reliable 1, volatile 2, keep-last 1, depth 42)."""
    parts = text.split(":")
    assert len(parts) >= 6, text
    history, deadline, lifespan = (parts[i].split(",") for i in (2, 3, 4))
    liveliness = parts[5].split(",")
    assert len(history) >= 2 and len(deadline) >= 2 and len(lifespan) >= 2, text
    assert len(liveliness) >= 3, text
    enum = {"reliability": {"1", "2"}, "durability": {"1", "2"}, "history": {"1", "2"}}
    out = {
        "reliability": parts[0] or "1",
        "durability": parts[1] or "2",
        "history": history[0] or "1",
        "depth": int(history[1] or 42),
    }
    for k, allowed in enum.items():
        assert out[k] in allowed, text
    return out


@pytest.mark.parametrize(
    "qos, token, parsed",
    [
        (rmw.QoS(), "::,10:,:,:,,", ("1", "2", "1", 10)),
        (rmw.QoS(depth=42), "::,:,:,:,,", ("1", "2", "1", 42)),
        (rmw.SENSOR_QOS, "2::,5:,:,:,,", ("2", "2", "1", 5)),
        (rmw.LATCHED_QOS, ":1:,1:,:,:,,", ("1", "1", "1", 1)),
        (rmw.QoS(keep_all=True), "::2,10:,:,:,,", ("1", "2", "2", 10)),
    ],
)
def test_qos_tokens_are_written_as_rmw_zenoh_writes_them(qos, token, parsed):
    assert qos.token() == token
    got = _rmw_zenoh_keyexpr_to_qos(token)
    assert (got["reliability"], got["durability"], got["history"], got["depth"]) == parsed


def test_qos_tokens_decode_in_the_sdk():
    pytest.importorskip("zenoh_ros2_sdk")
    from zenoh_ros2_sdk.qos import QosDurability, QosProfile, QosReliability

    latched = QosProfile.decode(rmw.LATCHED_QOS.token())
    assert latched.durability == QosDurability.TRANSIENT_LOCAL and latched.history_depth == 1
    assert QosProfile.decode(rmw.SENSOR_QOS.token()).reliability == QosReliability.BEST_EFFORT


# -- the heartbeat -------------------------------------------------------------------------------


def _client(endpoint: str):
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", f'["{endpoint}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("timestamping/enabled", "true")
    return zenoh.open(conf)


def test_reliable_transient_local_publishers_send_rmw_zenohs_heartbeat(zenoh_stack):
    """A reliable transient-local publisher (the map, the costmaps) sends the last sequence
    number on `<key>/@adv/pub/<zid>/<eid>/_` (u32 little-endian) within 0.5 s of a change, as
    rmw_zenoh_cpp's publishers do; a volatile one sends none. Every sample's attachment carries
    the gid of the publisher's liveliness token."""
    smana, watcher = _client(zenoh_stack.endpoint), zenoh_stack.session
    try:
        tokens, beats, samples = [], [], []
        # history: the tokens declared before this subscriber reached the router too
        watcher.liveliness().declare_subscriber(
            "@ros2_lv/0/**", lambda s: tokens.append(str(s.key_expr)), history=True
        )
        node = rmw.RosNode(smana, TYPES, 0, "smana", "/smana/test")
        latched = node.publisher("/smana/test/costmap_raw", COSTMAP, rmw.LATCHED_QOS)
        odom = node.publisher("/smana/test/odom", "nav_msgs/msg/Odometry", rmw.QoS())
        for pub in (latched, odom):
            watcher.declare_subscriber(
                f"{pub.key}/@adv/pub/**", lambda s: beats.append((str(s.key_expr), s.payload))
            )
            watcher.declare_subscriber(pub.key, lambda s: samples.append(s))
        assert wait_for(lambda: len({t for t in tokens if "/MP/" in t}) == 2, 10)
        grid = _grid()
        msg = convert.nav2_costmap(TYPES, grid, _LUT, 5.0, 5.0)
        probe = smana.declare_publisher(latched.key)  # waits until the subscriber is routed
        assert wait_for(lambda: probe.matching_status.matching, 10)
        probe.undeclare()
        latched.put(msg)
        odom.put(convert.odometry(TYPES, Pose(5.0, 1, np.zeros(3), np.array([0, 0, 0, 1.0]))))
        assert wait_for(lambda: len(beats) >= 1, 5)
        latched.put(msg)
        assert wait_for(lambda: any(p.to_bytes() == struct.pack("<I", 1) for _, p in beats), 5)
        key, payload = beats[0]
        assert key.startswith(f"{latched.key}/@adv/pub/{smana.zid()}/") and key.endswith("/_")
        assert payload.to_bytes() == struct.pack("<I", 0)
        assert all(k.startswith(latched.key + "/") for k, _ in beats)  # none from odom's key
        assert wait_for(lambda: len(samples) >= 3, 5)
        for s in samples:
            topic = "costmap_raw" if str(s.key_expr) == latched.key else "odom"
            token = next(t for t in tokens if f"%smana%test%{topic}/" in t)
            assert rmw.parse_attachment(s.attachment.to_bytes())[2] == rmw.gid_of(token)
    finally:
        smana.close()


# -- nav2_msgs/Costmap ---------------------------------------------------------------------------

_LUT = np.array([np.inf, 2.0, 1.0, np.inf, np.inf])  # unknown, grass, terrain, -, hedge


def _grid():
    grid = NavGrid.from_bounds((-2.0, -1.0), (2.0, 1.0), 0.5, tile_size=4)
    cells = np.array([[0, 0], [1, 0], [2, 0], [0, 1], [1, 1], [2, 1]])
    labels = np.array([2, 1, 4, 2, 2, 1])
    k = FLAG_KNOWN
    flags = np.array([k, k, k, k | FLAG_SAFETY_ZONE, k | FLAG_OBSTACLE, 0], np.uint8)
    grid.apply_patch(cells, labels, np.zeros(6), flags)
    return grid


def test_nav2_costmap_values_follow_nav2s_cost_values():
    # nav2_costmap_2d/cost_values.hpp: 255 unknown, 254 lethal, 253 inscribed, 0 .. 252 free.
    assert (costmap_types.NO_INFORMATION, costmap_types.LETHAL_OBSTACLE) == (255, 254)
    assert (costmap_types.INSCRIBED_INFLATED_OBSTACLE, costmap_types.MAX_NON_OBSTACLE) == (253, 252)
    labels = np.array([2, 1, 4, 2, 2, 1, 1])
    k = FLAG_KNOWN
    flags = np.array(
        [k, k, k, k | FLAG_SAFETY_ZONE, k | FLAG_OBSTACLE, 0, k | FLAG_SAFETY_ZONE | FLAG_OBSTACLE],
        np.uint8,
    )
    got = convert.nav2_costmap_values(labels, flags, _LUT)
    assert got.dtype == np.uint8
    assert got.tolist() == [0, 252, 254, 253, 254, 255, 254]


def test_nav2_costmap_message_layout_and_metadata():
    grid = _grid()
    msg = convert.nav2_costmap(TYPES, grid, _LUT, 12.25, 3.5)
    meta = msg.metadata
    assert msg.header.frame_id == "map" and meta.layer == "master"
    assert (meta.map_load_time.sec, meta.map_load_time.nanosec) == (3, 500_000_000)
    assert (meta.update_time.sec, meta.update_time.nanosec) == (12, 250_000_000)
    assert meta.resolution == 0.5
    ix0, iy0, ix1, iy1 = grid.known_box()
    assert (meta.size_x, meta.size_y) == (ix1 - ix0, iy1 - iy0)
    assert meta.origin.position.x == pytest.approx(-2.0 + 0.5 * ix0)
    assert meta.origin.position.y == pytest.approx(-1.0 + 0.5 * iy0)
    data = np.asarray(msg.data).reshape(meta.size_y, meta.size_x)  # row-major, x fastest
    assert data[0 - iy0, 0 - ix0] == 0 and data[0 - iy0, 1 - ix0] == 252
    assert data[0 - iy0, 2 - ix0] == 254 and data[1 - iy0, 0 - ix0] == 253
    assert data[1 - iy0, 1 - ix0] == 254 and data[1 - iy0, 2 - ix0] == 255
    assert convert.nav2_costmap(TYPES, NavGrid.from_bounds((0, 0), (1, 1), 0.5), _LUT, 0, 0) is None


def test_nav2_costmap_cdr_reads_back_in_pamoja():
    """The CDR of a Costmap, read field by field with pamoja-ros2's CDR reader (its own
    alignment rules): header, metadata, then the data sequence."""
    pamoja = pytest.importorskip("pamoja.ros2")
    msg = convert.nav2_costmap(TYPES, _grid(), _LUT, 12.25, 3.5)
    raw = TYPES.serialize(msg, COSTMAP)
    r = pamoja.CdrReader(list(raw))

    def string(expect: str):
        n = r.read_u32()
        assert n == len(expect) + 1  # CDR strings count their NUL
        body = b"".join(struct.pack("<I", r.read_u32()) for _ in range((n + 3) // 4))
        assert body[:n] == expect.encode() + b"\0"

    assert (r.read_i32(), r.read_u32()) == (12, 250_000_000)
    string("map")
    assert (r.read_i32(), r.read_u32(), r.read_i32(), r.read_u32()) == (
        3,
        500_000_000,
        12,
        250_000_000,
    )
    string("master")
    m = msg.metadata
    assert r.read_f32() == 0.5 and (r.read_u32(), r.read_u32()) == (m.size_x, m.size_y)
    pose = [r.read_f64() for _ in range(7)]
    assert pose == [m.origin.position.x, m.origin.position.y, 0.0, 0.0, 0.0, 0.0, 1.0]
    n = r.read_u32()
    assert n == m.size_x * m.size_y
    body = b"".join(struct.pack("<I", r.read_u32()) for _ in range(n // 4))
    assert body == bytes(np.asarray(msg.data)[: 4 * (n // 4)])


def test_nav2_costmap_hash_and_key_agree_with_the_sdk_and_pamoja(tmp_path, monkeypatch):
    pytest.importorskip("zenoh_ros2_sdk")
    pamoja = pytest.importorskip("pamoja.ros2")
    with sdk_session(tmp_path, monkeypatch):
        from zenoh_ros2_sdk import get_registry
        from zenoh_ros2_sdk.keyexpr import topic_keyexpr
        from zenoh_ros2_sdk.utils import (
            get_type_hash,
            load_dependencies_recursive,
            ros2_to_dds_type,
        )

        registry = get_registry()  # its .msg files: tests/support/ros2_sdk.py
        for t in (costmap_types.COSTMAP_META, COSTMAP):
            text = registry.get_msg_file_path(t).read_text()
            deps = load_dependencies_recursive(t, text, registry)
            assert get_type_hash(t, msg_definition=text, dependencies=deps) == TYPES.hash(t), t
        h = TYPES.hash(COSTMAP)
        ours = rmw.data_key(0, "/smana/r1/costmap_raw", COSTMAP, h)
        assert ours == topic_keyexpr(0, "/smana/r1/costmap_raw", ros2_to_dds_type(COSTMAP), h)
    assert ours == pamoja.entity_key(0, "/smana/r1/costmap_raw", COSTMAP, h)
    assert rmw.dds_type_name(COSTMAP) == pamoja.dds_type_name(COSTMAP)
    assert rmw.mangle("/smana/r1/costmap_raw") == pamoja.percent_mangle("/smana/r1/costmap_raw")
    assert len(pamoja.type_hash_digest(h)) == 32


# -- the map's voxel budget ----------------------------------------------------------------------


def test_map_within_budget_bounds_the_message_and_keeps_its_extent():
    rng = np.random.default_rng(5)
    idx = np.unique(rng.integers(-200, 200, size=(60_000, 3)), axis=0)
    centres = ((idx + 0.5) * 0.1).astype(np.float32)
    labels = rng.integers(0, 9, len(idx)).astype(np.uint16)
    same = convert.within_budget(centres, labels, 0.1, len(idx))
    assert same[0] is not None and len(same[0]) == len(idx) and same[2] == 0.1
    out, lab, cell = convert.within_budget(centres, labels, 0.1, 10_000)
    assert len(out) <= 10_000 and cell in (0.2, 0.4, 0.8, 1.6, 3.2, 6.4)
    # The finest such cell: half of it would not fit.
    half = np.floor(centres.astype(np.float64) / (cell / 2)).astype(int)
    assert len(np.unique(half, axis=0)) > 10_000
    # Every voxel lies in one kept cell, and each kept cell holds a voxel of that label.
    kept = {tuple(k): lab[i] for i, k in enumerate(np.floor(out / cell).astype(int))}
    cells = np.floor(centres.astype(np.float64) / cell).astype(int)
    assert {tuple(c) for c in cells} == set(kept)
    first = {}
    for c, label in zip(map(tuple, cells), labels, strict=True):
        first.setdefault(c, label)
    assert first == kept
    msg = convert.map_cloud(TYPES, out, lab, np.zeros((16, 3), np.uint8), 0.0)
    assert len(TYPES.serialize(msg, "sensor_msgs/msg/PointCloud2")) <= 20 * 10_000 + 1000


def test_an_rmw_zenoh_transient_local_subscriber_gets_the_cached_map_and_the_next(zenoh_stack):
    """A subscriber declared as rmw_zenoh_cpp declares a reliable transient-local subscription
    (rmw_subscription_data.cpp: an AdvancedSubscriber with history, late-publisher detection,
    `depth` samples, heartbeat recovery and subscriber detection), joining after smana's map went
    out: it gets that map from the cache, then the next one, each with its publisher's gid."""
    from zenoh import ext

    smana, ros = _client(zenoh_stack.endpoint), _client(zenoh_stack.endpoint)
    try:
        node = rmw.RosNode(smana, TYPES, 0, "smana", "/smana/test")
        pub = node.publisher("/smana/test/costmap_raw", COSTMAP, rmw.LATCHED_QOS)
        grid = _grid()
        pub.put(convert.nav2_costmap(TYPES, grid, _LUT, 5.0, 5.0))
        got = []
        sub = ext.declare_advanced_subscriber(
            ros,
            pub.key,
            lambda s: got.append((s.payload.to_bytes(), s.attachment.to_bytes())),
            history=ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
            recovery=ext.RecoveryConfig(periodic_queries=None, heartbeat=True),
            subscriber_detection=True,
        )
        assert wait_for(lambda: len(got) >= 1, 10)
        pub.put(convert.nav2_costmap(TYPES, grid, _LUT, 6.0, 5.0))
        assert wait_for(lambda: len(got) >= 2, 10)
        stamps = [TYPES.deserialize(p, COSTMAP).header.stamp.sec for p, _ in got]
        assert stamps[:2] == [5, 6]
        assert {rmw.parse_attachment(a)[2] for _, a in got} == {pub.gid}
        assert [rmw.parse_attachment(a)[0] for _, a in got][:2] == [1, 2]
        sub.undeclare()
    finally:
        ros.close()
        smana.close()
