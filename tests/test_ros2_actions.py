"""The ROS 2 actions without a stack: their type hashes against rosidl's known Jazzy values,
zenoh-ros2-sdk's hashing and keys and pamoja-ros2's keys, hash strings and CDR (two rmw_zenoh
implementations nobody here wrote); rcl_action's goal book (cancel policy, held results,
expiry); goal checks."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("rosbags")

from smana.services.ros2 import nav2_types, rmw  # noqa: E402
from smana.services.ros2.action_goals import (  # noqa: E402
    GOAL_OUTSIDE_MAP,
    START_OUTSIDE_MAP,
    GoalBook,
    goal_pose_checked,
    plan_error_code,
    to_world,
)
from smana.services.ros2.nav2_types import (  # noqa: E402
    CANCEL_GOAL_TERMINATED,
    CANCEL_NONE,
    CANCEL_UNKNOWN_GOAL_ID,
    STATUS_ABORTED,
    STATUS_ACCEPTED,
    STATUS_CANCELING,
    STATUS_SUCCEEDED,
    STATUS_UNKNOWN,
)
from tests.support.ros2_sdk import sdk_session  # noqa: E402

TYPES = rmw.RosTypes()
NS = "/smana/r1"
ACTION_NAMES = {
    "nav2_msgs/action/NavigateToPose": "navigate_to_pose",
    "nav2_msgs/action/ComputePathToPose": "compute_path_to_pose",
}


def all_endpoints() -> dict[str, str]:
    """{ROS name: type} of every endpoint of both actions, and /goal_pose."""
    out = {"/goal_pose": "geometry_msgs/msg/PoseStamped"}
    for action, name in ACTION_NAMES.items():
        for what, typename in nav2_types.action_names(action).items():
            out[f"{NS}/{name}/_action/{what}"] = typename
    return out


def test_action_construction_gives_rosidls_jazzy_hashes():
    """rosidl's hashes of a ROS 2 Jazzy install (action_tutorials_interfaces' Fibonacci and
    action_msgs), as an rmw_zenoh implementation locks them: the same construction (SendGoal,
    GetResult as services with an event message; FeedbackMessage) gives them."""
    types = rmw.RosTypes()
    fib = {
        "action_tutorials_interfaces/action/Fibonacci": (
            "int32 order",
            "int32[] sequence",
            "int32[] partial_sequence",
        )
    }
    nav2_types.register(types.store, rmw._service_types, fib)
    f = "action_tutorials_interfaces/action/Fibonacci_"
    assert types.hash(f + "SendGoal") == (
        "RIHS01_a0603060ed69fe2dfbd1a6f3b982a1749957ef346e4a4d2b311a05e305ec37bb"
    )
    assert types.hash(f + "GetResult") == (
        "RIHS01_8b47e383f1e31f6d8df6417ab54957e7d5ea24dad315646ad711ac3fdea81d58"
    )
    assert types.hash(f + "FeedbackMessage") == (
        "RIHS01_50fc26b9cac313652ecbeab3adf9b5414d59fd4d4d5f9058ddcc7525169927f1"
    )
    assert TYPES.hash("action_msgs/srv/CancelGoal") == (
        "RIHS01_573d8b0a534451d7bc2ac8c5ffde8ac14b8593b7001175d0cd6516dcbeb8689a"
    )
    assert TYPES.hash("action_msgs/msg/GoalStatusArray") == (
        "RIHS01_6c1684b00f177d37438febe6e709fc4e2b0d4248dca4854946f9ed8b30cda83e"
    )
    # An empty feedback (ComputePathToPose's) hashes with rosidl's placeholder member, as
    # std_msgs/Empty does (Jazzy's value).
    assert TYPES.hash("std_msgs/msg/Empty").startswith("RIHS01_20b625256f32d5dbc0d04fee44f43c41")
    fields = TYPES.store.fielddefs["nav2_msgs/action/ComputePathToPose_Feedback"][1]
    assert [name for name, _ in fields] == ["structure_needs_at_least_one_member"]


@pytest.fixture
def sdk(tmp_path, monkeypatch):
    pytest.importorskip("zenoh_ros2_sdk")
    with sdk_session(tmp_path, monkeypatch):
        from zenoh_ros2_sdk import get_registry

        yield get_registry()


def test_action_type_hashes_agree_with_the_sdk(sdk):
    """Every message of both actions, and CancelGoal, hashed by the SDK from the .action text
    (tests/support/ros2_action_client.py) equals smana's. The SDK cannot hash an action's
    services: `compute_service_type_hash` names their request `<pkg>/srv/<Name>_Request`
    (zenoh_ros2_sdk/utils.py) where rosidl writes `<pkg>/action/...` (rosidl_parser's Action);
    rosidl's value wins (the Fibonacci test above), and moved to `srv` smana's equals the SDK's."""
    from zenoh_ros2_sdk.utils import compute_service_type_hash, get_type_hash

    from tests.support.ros2_action_client import (
        CANCEL_REQUEST,
        CANCEL_RESPONSE,
        COMPUTE_PATH_TO_POSE,
        DEPENDENCIES,
        NAVIGATE_TO_POSE,
    )

    deps: dict[str, str] = {}
    from zenoh_ros2_sdk.utils import load_dependencies_recursive

    for t in DEPENDENCIES:
        text = sdk.get_msg_file_path(t).read_text()
        deps[t] = text
        deps.update(load_dependencies_recursive(t, text, sdk))
    texts = {
        "nav2_msgs/action/NavigateToPose": NAVIGATE_TO_POSE,
        "nav2_msgs/action/ComputePathToPose": COMPUTE_PATH_TO_POSE,
    }
    for action, (goal, result, feedback) in texts.items():
        base = action.rsplit("/", 1)[1]
        own = {
            f"{action}_Goal": goal,
            f"{action}_Result": result,
            # rosidl's placeholder member in an empty message (as a dependency it must be there)
            f"{action}_Feedback": feedback or "uint8 structure_needs_at_least_one_member",
            f"{action}_FeedbackMessage": (
                f"unique_identifier_msgs/UUID goal_id\nnav2_msgs/action/{base}_Feedback feedback"
            ),
        }
        all_deps = {**deps, **own}
        if not feedback:  # the SDK adds the placeholder itself to an empty top-level type
            assert get_type_hash(f"{action}_Feedback", "") == TYPES.hash(f"{action}_Feedback")
        for typename, text in own.items():
            assert get_type_hash(typename, text, all_deps) == TYPES.hash(typename), typename
        # The action's services, hashed by the SDK under `srv`, equal smana's construction
        # registered under `srv`: only the namespace the SDK writes differs.
        moved = rmw.RosTypes()
        srv_deps = dict(all_deps)
        for what, (req, res) in nav2_types.service_parts(action).items():
            req = req.replace(f"{base}_", f"nav2_msgs/action/{base}_")
            res = res.replace(f"{base}_", f"nav2_msgs/action/{base}_")
            srv = what.replace("/action/", "/srv/")
            moved.store.register(rmw._service_types(srv, req, res))
            assert compute_service_type_hash(srv, req, res, srv_deps) == moved.hash(srv)
            assert moved.hash(srv) != TYPES.hash(what)
    cancel = compute_service_type_hash(
        "action_msgs/srv/CancelGoal", CANCEL_REQUEST, CANCEL_RESPONSE, deps
    )
    assert cancel == TYPES.hash("action_msgs/srv/CancelGoal")
    status = deps["action_msgs/msg/GoalStatusArray"]
    assert get_type_hash("action_msgs/msg/GoalStatusArray", status, deps) == TYPES.hash(
        "action_msgs/msg/GoalStatusArray"
    )


def test_action_keys_and_tokens_agree_with_the_sdk_and_pamoja():
    """Data keys of every action endpoint and /goal_pose as both libraries build them; the
    tokens as the SDK builds them; the hash strings parse to their digests in pamoja."""
    pytest.importorskip("zenoh_ros2_sdk")
    ros2 = pytest.importorskip("pamoja.ros2")
    from zenoh_ros2_sdk.entity import EndpointEntity, EntityKind, NodeEntity
    from zenoh_ros2_sdk.keyexpr import endpoint_liveliness_keyexpr, topic_keyexpr
    from zenoh_ros2_sdk.qos import QosProfile
    from zenoh_ros2_sdk.utils import ros2_to_dds_type

    class Session:  # what RosNode reads of a zenoh session
        def zid(self):
            return "0123abcd"

        def liveliness(self):
            return self

        def declare_token(self, key):
            tokens.append(key)
            return self

    tokens: list[str] = []
    node = rmw.RosNode(Session(), TYPES, 0, "smana", NS)
    theirs = NodeEntity(0, "0123abcd", 0, "smana", NS)
    endpoints = all_endpoints()
    assert len(endpoints) == 11
    for name, typename in endpoints.items():
        h = TYPES.hash(typename)
        key = rmw.data_key(0, name, typename, h)
        assert key == ros2.entity_key(0, name, typename, h), name
        assert key == topic_keyexpr(0, name, ros2_to_dds_type(typename), h), name
        assert (
            rmw.dds_type_name(typename)
            == ros2.dds_type_name(typename)
            == (ros2_to_dds_type(typename))
        )
        assert bytes(ros2.type_hash_digest(h)) == bytes.fromhex(h.removeprefix("RIHS01_"))
        assert ros2.is_valid_name(name) and rmw.mangle(name) == ros2.percent_mangle(name)
        kind = rmw.SERVICE if name.endswith(("send_goal", "get_result", "cancel_goal")) else None
        if kind is None:
            continue
        _, eid = node.endpoint(kind, name, typename)
        ep = EndpointEntity(
            theirs,
            eid,
            EntityKind.SERVICE,
            name,
            rmw.dds_type_name(typename),
            h,
            QosProfile().encode(),
        )
        assert tokens[-1] == endpoint_liveliness_keyexpr(ep), name
    assert (
        rmw.data_key(0, f"{NS}/navigate_to_pose/_action/send_goal", nav2_types.part(
            "nav2_msgs/action/NavigateToPose", "SendGoal"), "H")
        == "0/smana/r1/navigate_to_pose/_action/send_goal/"
        "nav2_msgs::action::dds_::NavigateToPose_SendGoal_/H"
    )  # fmt: skip


def test_cdr_of_a_goal_reads_back_in_the_sdk_store(sdk):
    """A SendGoal request written by smana's store reads in a store of the SDK's definitions,
    and back: same bytes."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    from tests.support.ros2_action_client import NAVIGATE_TO_POSE

    theirs = get_typestore(Stores.ROS2_JAZZY)  # messages only: the action's parts from the text
    a = "nav2_msgs/action/NavigateToPose"
    theirs.register(get_types_from_msg(NAVIGATE_TO_POSE[0], a + "_Goal"))
    theirs.register(
        get_types_from_msg(
            "unique_identifier_msgs/UUID goal_id\nnav2_msgs/action/NavigateToPose_Goal goal",
            a + "_SendGoal_Request",
        )
    )
    from smana.services.ros2 import convert

    goal = TYPES.msg(a + "_Goal")(
        pose=convert.pose_stamped(TYPES, (4.0, -1.0), 0.5, 12.25), behavior_tree=""
    )
    uuid = bytes(range(16))
    req = TYPES.msg(a + "_SendGoal_Request")(
        goal_id=TYPES.msg("unique_identifier_msgs/msg/UUID")(uuid=np.frombuffer(uuid, np.uint8)),
        goal=goal,
    )
    raw = TYPES.serialize(req, a + "_SendGoal_Request")
    back = theirs.deserialize_cdr(raw, a + "_SendGoal_Request")
    assert bytes(back.goal_id.uuid) == uuid and back.goal.pose.pose.position.x == 4.0
    assert bytes(theirs.serialize_cdr(back, a + "_SendGoal_Request")) == raw


# -- the goal book (rcl_action's rules) -----------------------------------------------------------


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def uuid(i: int) -> bytes:
    return bytes([i]) * 16


def test_goal_book_cancel_policy_is_rcl_actions():
    book = GoalBook(clock=Clock())
    for i, stamp in ((1, 100), (2, 200), (3, 300)):
        assert book.add(uuid(i), None, stamp) is not None
    assert book.add(uuid(1), None, 400) is None  # an id in use
    assert book.cancel(uuid(9), 0) == (CANCEL_UNKNOWN_GOAL_ID, [])
    code, goals = book.cancel(uuid(2), 0)
    assert code == CANCEL_NONE and [g.uuid for g in goals] == [uuid(2)]
    assert book.get(uuid(2)).status == STATUS_CANCELING
    assert book.cancel(uuid(2), 0)[0] == CANCEL_GOAL_TERMINATED  # no longer cancelable
    book.finish(uuid(3), STATUS_SUCCEEDED, "r3")
    assert book.cancel(uuid(3), 0) == (CANCEL_GOAL_TERMINATED, [])
    # A zero id and a stamp: every cancelable goal accepted at or before it.
    code, goals = book.cancel(bytes(16), 150)
    assert code == CANCEL_NONE and [g.uuid for g in goals] == [uuid(1)]
    book.add(uuid(4), None, 500)
    book.add(uuid(5), None, 600)
    # An id and a stamp: that goal and every goal accepted at or before the stamp.
    code, goals = book.cancel(uuid(5), 550)
    assert sorted(g.uuid for g in goals) == [uuid(4), uuid(5)]
    book.add(uuid(6), None, 700)
    code, goals = book.cancel(bytes(16), 0)  # everything
    assert [g.uuid for g in goals] == [uuid(6)]


def test_goal_book_holds_results_until_they_exist_then_expires_them():
    clock = Clock()
    book = GoalBook(result_timeout_s=10.0, max_goals=3, clock=clock)
    got = []
    assert book.result(uuid(1), lambda s, r: got.append((s, r))) == "unknown"
    assert got == [(STATUS_UNKNOWN, None)]
    book.add(uuid(1), None, 1)
    assert book.get(uuid(1)).status == STATUS_ACCEPTED
    got.clear()
    assert book.result(uuid(1), lambda s, r: got.append((s, r))) == "held"
    assert book.result(uuid(1), lambda s, r: got.append((s, r))) == "held"
    assert got == []
    assert book.finish(uuid(1), STATUS_ABORTED, "why")
    assert got == [(STATUS_ABORTED, "why")] * 2
    assert not book.finish(uuid(1), STATUS_SUCCEEDED, "late")  # ended once only
    assert book.result(uuid(1), lambda s, r: got.append((s, r))) == "answered"
    assert got[-1] == (STATUS_ABORTED, "why")
    book.add(uuid(2), None, 2)
    book.add(uuid(3), None, 3)
    clock.t = 10.5
    assert book.add(uuid(4), None, 4) is not None  # goal 1's result expired: room again
    assert book.result(uuid(1), lambda s, r: got.append((s, r))) == "unknown"
    assert book.add(uuid(5), None, 5) is None  # full of goals that have not ended
    for _ in range(16):
        book.result(uuid(2), lambda s, r: None)
    assert book.result(uuid(2), lambda s, r: None) == "full"


def test_a_flood_of_ended_goals_leaves_room_for_the_next_one():
    # 64 goals flooded and ended: a valid goal was refused until their results expired (10 s)
    clock = Clock()
    book = GoalBook(result_timeout_s=10.0, max_goals=4, clock=clock)
    for i in range(1, 5):
        book.add(uuid(i), None, i)
        book.finish(uuid(i), STATUS_ABORTED, f"r{i}")
        clock.t += 0.1
    assert book.add(uuid(9), None, 9) is not None  # at once, not 10 s later
    assert book.get(uuid(1)) is None and book.get(uuid(2)) is not None  # the oldest made room
    for i in (10, 11, 12):
        assert book.add(uuid(i), None, i) is not None
    assert book.add(uuid(13), None, 13) is None  # four goals that have not ended: full


def test_goal_pose_checks():
    from smana.services.ros2 import convert

    ok = convert.pose_stamped(TYPES, (3.0, -2.0), 1.2, 0.0)
    frame, x, y, yaw = goal_pose_checked(ok, ("map", "odom"))
    assert (frame, x, y) == ("map", 3.0, -2.0) and yaw == pytest.approx(1.2)
    in_base = convert.pose_stamped(TYPES, (1.0, 0.0), 0.0, 0.0, "base_link")
    assert goal_pose_checked(in_base, ("map", "odom", "base_link"))[0] == "base_link"
    nan = convert.pose_stamped(TYPES, (math.nan, 0.0), 0.0, 0.0)
    with pytest.raises(ValueError, match="non-finite"):
        goal_pose_checked(nan, ("map",))
    with pytest.raises(ValueError, match="frame"):
        goal_pose_checked(convert.pose_stamped(TYPES, (1.0, 0.0), 0.0, 0.0, "base_link"), ("map",))
    # an empty frame is refused, as Nav2 cannot transform it either
    unframed = convert.pose_stamped(TYPES, (1.0, 0.0), 0.0, 0.0, "")
    with pytest.raises(ValueError, match="no frame_id"):
        goal_pose_checked(unframed, ("map",))
    zero_q = convert.pose_stamped(TYPES, (1.0, 0.0), 0.0, 0.0)
    zero_q.pose.orientation.w = 0.0
    with pytest.raises(ValueError):
        goal_pose_checked(zero_q, ("map",))


def test_planner_errors_are_nav2s_codes():
    assert plan_error_code("out_of_bounds", "start (1.00, 2.00) is outside") == START_OUTSIDE_MAP
    assert plan_error_code("out_of_bounds", "goal (1.00, 2.00) is outside") == GOAL_OUTSIDE_MAP
    assert plan_error_code("unreachable", "") == 208  # NO_VALID_PATH
    from smana.services.planner.planner import NO_GRAPH

    assert plan_error_code(NO_GRAPH, "") == 208  # the planner's reply before any graph
    assert (
        plan_error_code("start_blocked", "") == 205 and plan_error_code("goal_blocked", "") == 206
    )
    assert plan_error_code("malformed", "") == 200
    consts = dict(TYPES.store.fielddefs["nav2_msgs/action/ComputePathToPose_Result"][0] and [
        (c[0], c[2]) for c in TYPES.store.fielddefs["nav2_msgs/action/ComputePathToPose_Result"][0]
    ])  # fmt: skip
    assert consts["NO_VALID_PATH"] == 208 and consts["TIMEOUT"] == 207
    assert consts["START_OUTSIDE_MAP"] == START_OUTSIDE_MAP


def test_action_names_in_the_config_are_checked():
    from smana.common.config import ConfigError, SmanaConfig

    cfg = SmanaConfig.load(None, [])
    assert (cfg.ros2.navigate_action, cfg.ros2.compute_path_action, cfg.ros2.goal_pose_topic) == (
        "navigate_to_pose",
        "compute_path_to_pose",
        "/goal_pose",
    )
    for bad in ('ros2.navigate_action="a/b"', 'ros2.compute_path_action=""',
                'ros2.goal_pose_topic="goal_pose"'):  # fmt: skip
        with pytest.raises(ConfigError):
            SmanaConfig.load(None, [bad])


def test_cdr_of_the_action_services_agrees_with_pamoja():
    """pamoja-ros2's CDR reader and writer (32-bit primitives, alignment, the encapsulation
    header) on the action types made of them: a CancelGoal request (GoalInfo: a 16-byte UUID
    and a Time) both ways, and a SendGoal response (a bool, then a Time aligned to 4)."""
    ros2 = pytest.importorskip("pamoja.ros2")
    T = TYPES.msg
    uuid_bytes = bytes(range(1, 17))
    info = T("action_msgs/msg/GoalInfo")(
        goal_id=T("unique_identifier_msgs/msg/UUID")(uuid=np.frombuffer(uuid_bytes, np.uint8)),
        stamp=T("builtin_interfaces/msg/Time")(sec=-7, nanosec=123456789),
    )
    ours = TYPES.serialize(
        T("action_msgs/srv/CancelGoal_Request")(goal_info=info),
        "action_msgs/srv/CancelGoal_Request",
    )
    r = ros2.CdrReader(list(ours))
    words = [r.read_u32() for _ in range(4)]
    assert b"".join(w.to_bytes(4, "little") for w in words) == uuid_bytes
    assert (r.read_i32(), r.read_u32(), r.read_u32()) == (-7, 123456789, None)

    w = ros2.CdrWriter()
    for i in range(4):
        w.write_u32(int.from_bytes(uuid_bytes[4 * i : 4 * i + 4], "little"))
    w.write_i32(1_700_000_000)
    w.write_u32(5)
    theirs = TYPES.deserialize(bytes(w.bytes), "action_msgs/srv/CancelGoal_Request")
    assert bytes(theirs.goal_info.goal_id.uuid) == uuid_bytes
    assert (theirs.goal_info.stamp.sec, theirs.goal_info.stamp.nanosec) == (1_700_000_000, 5)

    a = "nav2_msgs/action/NavigateToPose_SendGoal_Response"
    resp = T(a)(accepted=True, stamp=T("builtin_interfaces/msg/Time")(sec=42, nanosec=9))
    r = ros2.CdrReader(list(TYPES.serialize(resp, a)))
    assert r.read_u32() & 0xFF == 1  # the bool, then padding to the Time's alignment
    assert (r.read_i32(), r.read_u32()) == (42, 9)


def test_a_navigate_goal_with_a_huge_behavior_tree_or_no_frame_is_refused_before_the_explorer():
    import types

    from smana.services.ros2 import convert
    from smana.services.ros2.actions import Ros2Actions

    a = "nav2_msgs/action/NavigateToPose"
    me = types.SimpleNamespace(frames=("map",))  # navigate() refuses before anything else

    def goal(frame="map", tree=""):
        pose = convert.pose_stamped(TYPES, (1.0, 0.0), 0.0, 0.0, frame)
        return TYPES.msg(a + "_Goal")(pose=pose, behavior_tree=tree)

    ok, why = Ros2Actions.navigate(me, b"u" * 16, goal(tree="x" * 10_000_000), None)
    assert not ok and why.startswith("value: behavior_tree of 10000000 characters"), why
    ok, why = Ros2Actions.navigate(me, b"u" * 16, goal(frame=""), None)
    assert not ok and "no frame_id" in why, why


def test_a_goal_in_the_base_frame_is_placed_by_the_robot_pose():
    """tf's odom -> base_link for a planar robot, against the 4 x 4 product written out."""
    rng = np.random.default_rng(5)
    for _ in range(50):
        base = rng.uniform(-10, 10), rng.uniform(-10, 10), rng.uniform(-math.pi, math.pi)
        x, y, yaw = rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-math.pi, math.pi)

        def m(px, py, a):
            return np.array([[math.cos(a), -math.sin(a), px], [math.sin(a), math.cos(a), py],
                             [0.0, 0.0, 1.0]])  # fmt: skip

        want = m(*base) @ m(x, y, yaw)
        wx, wy, wyaw = to_world(x, y, yaw, base)
        np.testing.assert_allclose([wx, wy], want[:2, 2], atol=1e-9)
        np.testing.assert_allclose(m(wx, wy, wyaw)[:2, :2], want[:2, :2], atol=1e-9)
        assert -math.pi <= wyaw <= math.pi
