"""The fuzz campaign's families (fuzz_campaign.py lists them): one class a family, built once per
worker, whose `run(i, d)` makes input i from its `Draw` and hands it to its target in this
process; it returns when the target took the input, raises `Rejected` when the target refused it
for a reason of its own, and anything else it raises is a crash."""

from __future__ import annotations

import math
import os
import random
import time
import warnings
from collections import Counter
from pathlib import Path

import numpy as np


class Rejected(Exception):
    """The target refused the input, for `reason` (its own words, one token)."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


def draw_for(seed: int, family: str, i: int):
    from smana.lab.fuzz_values import RandomDraw

    return RandomDraw(random.Random(f"{seed}:{family}:{i}"))


CHUNKS = ("smana", "r1", "robot", "cmd_vel", "*", "**", "$*", "a$*b", "", "@ros2_lv", "é", "..")


# (no lone surrogate: a key on the wire is UTF-8 bytes, which cannot hold one)
WILD = ("?", "#", " ", "\x00", "/", "//", "**/**", "*$*", "a*", "$", "😀", "\n")


class Keys:
    def __init__(self, seed, tmp):
        import zenoh

        from smana.common import keys

        self.zenoh, self.keys = zenoh, keys

    def _text(self, d) -> str:
        n = d.choice((1, 2, 3, 4, 8, 40))
        parts = []
        for _ in range(n):
            if d.boolean(0.2):
                parts.append(d.choice(WILD) * d.choice((1, 2, 5)))
            elif d.boolean(0.1):
                parts.append(d.blob(d.integer(1, 12)).decode("latin-1"))
            else:
                parts.append(d.choice(CHUNKS))
        s = "/".join(parts)
        if d.boolean(0.3):
            params = [
                f"{d.choice(CHUNKS)}={d.choice(CHUNKS + WILD)}" for _ in range(d.integer(0, 4))
            ]
            s += "?" + d.choice((";", "&", ";;")).join(params)
        if d.boolean(0.01):
            s = s * 300
        return s

    def run(self, i, d) -> None:
        s = self._text(d)
        name = s.split("/", 1)[0]
        try:
            self.keys.check_name(name)
        except ValueError:
            pass
        else:  # a name smana accepts must make keys zenoh accepts
            for k in (self.keys.cmd_vel(name), self.keys.status(name, "mapper")):
                self.zenoh.KeyExpr(k)
        try:
            sel = self.zenoh.Selector(s)
            dict(sel.parameters) if sel.parameters else {}  # as query_form reads them
        except self.zenoh.ZError:
            raise Rejected("selector") from None
        try:
            self.zenoh.KeyExpr(s.split("?", 1)[0])
        except self.zenoh.ZError:
            raise Rejected("key_expr") from None


class Messages:
    def __init__(self, seed, tmp):
        from smana.common import messages as m
        from smana.lab import fuzz_messages

        self.m, self.fuzz = m, fuzz_messages
        self.classes = [c for c in vars(m).values() if _is_message(c, m)]

    def run(self, i, d) -> None:
        cls = d.choice(self.classes)
        as_json = d.boolean(0.25)
        modes = tuple(x for x in self.fuzz.MODES if x != "oversize")  # 64 MiB each: --inputs
        mode = d.choice(modes)
        make = self.fuzz.json_payload if as_json else self.fuzz.message_payload
        mutant = make(cls, d, None, mode if not as_json else None)
        kind = self.fuzz.predict(mutant.payload, cls, as_json=as_json)  # a bug propagates
        if kind is not None:
            raise Rejected(kind)


def _is_message(c, m) -> bool:
    return isinstance(c, type) and issubclass(c, m.Message) and c is not m.Message


class MapFiles:
    def __init__(self, seed, tmp):
        from smana.lab import fuzz_maps

        self.fm, self.bases, self.path = fuzz_maps, fuzz_maps.bases(), Path(tmp) / "map.npz"

    def run(self, i, d) -> None:
        base = d.choice(self.bases)
        mutant = self.fm.mutate_map(base, d)
        self.path.write_bytes(mutant.data)
        out, why = self.fm.try_load(self.path, base)
        if out == "crash":
            raise RuntimeError(why)
        if out == "loaded" and why != "same":
            raise AssertionError(f"{mutant.how}: loaded, but {why}")
        if mutant.predict is True and out != "refused":
            raise AssertionError(f"{mutant.how}: a corrupt file was loaded")
        if mutant.predict is False and out != "loaded":
            raise AssertionError(f"{mutant.how}: a valid file was refused: {why}")
        if out == "refused":
            raise Rejected(mutant.how.split(":", 1)[0])


class Journals:
    def __init__(self, seed, tmp):
        from smana.lab import fuzz_journals as fj
        from smana.services.mapper.journal import JournalReader

        self.fj, self.reader_cls, self.tmp = fj, JournalReader, Path(tmp)
        self.journals = [fj.journal(self.tmp, n_records=4, seed=s) for s in range(3)]

    def run(self, i, d) -> None:
        fj = self.fj
        j = d.choice(self.journals)
        how = d.choice(("valid", "truncated", "flipped", "flipped", "crafted", "crafted", "bytes"))
        if how == "truncated":
            data = fj.truncated(j, d.integer(0, len(j.data)))
        elif how == "flipped":
            data = fj.flipped(j, d.integer(0, len(j.data) - 1), d.integer(0, 7))
        elif how == "crafted":
            data = fj.crafted(j, d.integer(0, len(j.records) - 1), d.choice(sorted(fj.CRAFTED)))
        elif how == "bytes":
            at = d.integer(0, len(j.data))
            data = j.data[:at] + d.blob(d.integer(1, 64)) + j.data[at:]
        else:
            data = j.data
        path = self.tmp / "map.journal"
        path.write_bytes(data)
        reader = self.reader_cls(path)
        try:
            reader.attach(fj.small_map(j.backend))
            end = reader.finish()
        finally:
            reader.close()
        b = reader.books
        # every byte ends in the books: read to `end` (records, damage), or torn after it
        if b.skipped:
            raise Rejected("skipped")
        if end + b.torn_bytes != len(data):
            raise AssertionError(f"{how}: {end} + torn {b.torn_bytes} != {len(data)} bytes")
        if how == "valid" and (b.damaged or b.records != len(j.records)):
            raise AssertionError(f"an intact journal replayed {b.records} of {len(j.records)}")
        if b.bad_records:
            raise Rejected("bad_record")
        if b.damaged_bytes or b.header_missing:
            raise Rejected("damaged_bytes")
        if b.torn_bytes:
            raise Rejected("torn_tail")


class Blocks:
    def __init__(self, seed, tmp):
        from smana.lab import fuzz_journals as fj
        from smana.services.mapper.blockstore import BlockStore
        from smana.services.mapper.semantic_map import SemanticMap

        self.fj = fj
        m = SemanticMap("octree-max", resolution_m=0.2, max_range_m=8.0, class_table="rellis3d")
        rng = np.random.default_rng(3)
        for x0 in range(0, 24, 2):
            pts = np.c_[rng.uniform(x0 - 2, x0 + 2, 300), rng.uniform(-2, 2, 300), np.zeros(300)]
            m.integrate(pts.astype(np.float32), np.full(300, 1, np.uint16), origin=(x0, 0.0, 1.0))
        self.store = BlockStore(m, Path(tmp) / "store", keep_radius_m=12.0, region_m=6.4)
        self.store.after((300.0, 0.0), force=True)
        self.entries = dict(self.store.stored)
        self.good = {r: e[0].read_bytes() for r, e in self.entries.items()}
        self.empty = np.zeros(0, np.int64)

    def run(self, i, d) -> None:
        region = d.choice(sorted(self.entries))
        path, good = self.entries[region][0], self.good[region]
        if path.is_dir():
            path.rmdir()
        for p in path.parent.glob("*.damaged"):
            os.remove(p) if p.is_file() else p.rmdir()
        how = d.choice(("valid", "truncate", "flip", "flip", "bytes", *self.fj.REGION_DAMAGE))
        if how == "truncate":
            path.write_bytes(good[: d.integer(0, len(good) - 1)])
        elif how == "flip":
            b = bytearray(good)
            for _ in range(d.choice((1, 1, 2, 8))):
                b[d.integer(0, len(b) - 1)] ^= 1 << d.integer(0, 7)
            path.write_bytes(bytes(b))
        elif how == "bytes":
            path.write_bytes(d.blob(d.integer(0, 4096)))
        else:
            path.write_bytes(good)
            if how != "valid":
                self.fj.region_file(path, how, good)
        self.store.stored[region] = self.entries[region]
        before = len(self.store.problems)
        got = self.store._read_region(region, self.empty)
        if got is None:
            if len(self.store.problems) != before + 1:
                raise AssertionError("a refused region left no problem")
            if how == "valid":
                raise AssertionError(f"an intact region was refused: {self.store.problems[-1]}")
            raise Rejected(how)
        if how in ("truncate", "nan", "foreign_blocks", "missing_column", "not_a_file"):
            raise AssertionError(f"a damaged region ({how}) was read")


class Ros2Topics:
    def __init__(self, seed, tmp):
        from smana.common.config import SmanaConfig
        from smana.lab.fuzz_ros2 import TOPICS, Ros2Inputs, Ros2Reference
        from smana.services.ros2.rmw import RosTypes

        self.types, self.topics = RosTypes(), TOPICS
        self.config = SmanaConfig.load()
        self.ref = Ros2Reference(self.config, self.types)
        self.make = lambda d: Ros2Inputs(self.types, d, 1.7e9)
        self.inputs = None

    def run(self, i, d) -> None:
        if self.inputs is None:  # one track per worker: the gates follow it
            self.inputs = self.make(d)
        self.inputs.draw = d
        case = self.inputs.case(d.choice(self.topics))
        before = len(self.ref.crashes)
        fate = self.ref.fate(case)
        if len(self.ref.crashes) > before:
            raise RuntimeError(self.ref.crashes[-1])
        if case.refuse is True and fate == "accepted":
            raise AssertionError(f"{case.topic} {case.kind} {case.how}: must be refused")
        if fate != "accepted":
            raise Rejected(f"{case.topic}:{fate}")


class _Recorder:
    def __init__(self):
        self.n = 0

    def put(self, msg) -> None:
        self.n += 1


class _Declared:
    def undeclare(self) -> None:
        pass


class _Session:
    """What the bridge's handlers and action server use of a zenoh session, without zenoh."""

    def declare_queryable(self, *a, **k):
        return _Declared()

    def declare_subscriber(self, *a, **k):
        return _Declared()


class _Node:
    """What the action server uses of the bridge's ROS 2 node, without zenoh."""

    def __init__(self, types):
        from smana.services.ros2 import rmw

        self.types, self.rmw = types, rmw
        self.publishers: dict[str, _Recorder] = {}

    def endpoint(self, kind, name, typename, qos=None):
        return f"key{name}", 0

    def publisher(self, topic, typename, qos=None):
        return self.publishers.setdefault(topic, _Recorder())

    def reply_attachment(self, att):
        seq, _, gid = self.rmw.parse_attachment(att)
        return self.rmw.attachment(seq, time.time_ns(), gid)


class _Bytes:
    def __init__(self, b: bytes):
        self.b = b

    def to_bytes(self) -> bytes:
        return self.b

    def __len__(self) -> int:
        return len(self.b)


class _Query:
    def __init__(self, payload: bytes | None, attachment: bytes | None):
        self.payload = None if payload is None else _Bytes(payload)
        self.attachment = None if attachment is None else _Bytes(attachment)
        self.replies = 0

    def reply(self, *a, **k):
        self.replies += 1

    def reply_err(self, *a, **k):
        self.replies += 1

    def drop(self):
        pass


def _bridge(config=None):
    """A real ros2 service, its zenoh parts replaced by stand-ins that count what goes out."""
    from smana.common.config import SmanaConfig
    from smana.services.ros2.rmw import RosTypes
    from smana.services.ros2.service import Ros2Service

    svc = Ros2Service(config or SmanaConfig.load())
    svc.types = RosTypes()
    svc.session = _Session()
    svc.node = _Node(svc.types)
    svc.pubs = {}
    svc._send = lambda what, msg: None
    svc.log.disabled = True
    return svc


def _settle(svc, before: tuple) -> None:
    """The one counter a message moved in the service's books: accepted, or Rejected."""
    b = svc.books
    acc, drop, rej = before
    moved = (b.accepted - acc) + sum((b.dropped - drop).values()) + sum((b.rejected - rej).values())
    if moved != 1:
        raise AssertionError(f"the books moved by {moved}")
    if b.rejected["internal"] > rej["internal"]:
        raise RuntimeError("the bridge counted an internal error")
    if b.accepted > acc:
        return
    kind = next(iter((b.dropped - drop) or (b.rejected - rej)))
    raise Rejected(("dropped:" if b.dropped - drop else "") + kind)


def _books(svc) -> tuple:
    b = svc.books
    return b.accepted, Counter(b.dropped), Counter(b.rejected)


class BridgeSmana:
    """smana's messages into the bridge, through `_handle_payload` (decode, hand over, settle)."""

    def __init__(self, seed, tmp):
        from smana.common import messages as m
        from smana.lab import fuzz_messages

        self.m, self.fuzz, self.svc = m, fuzz_messages, _bridge()
        self.ctx = fuzz_messages.Context()
        self.handlers = {
            "cmd_vel": (self.svc.on_cmd_vel, m.VelocityCommand),
            "pose": (self.svc.on_pose, m.Pose),
            "delta": (self.svc.on_delta, m.MapDelta),
            "patch": (self.svc.on_patch, m.GraphPatch),
            "explorer_state": (self.svc.on_explorer_state, None),
        }

    def run(self, i, d) -> None:
        what = d.choice(sorted(self.handlers))
        handler, cls = self.handlers[what]
        if cls is None:
            payload, _ = self.fuzz.explorer_state(d, self.ctx)
        else:
            modes = tuple(x for x in self.fuzz.MODES if x != "oversize")
            payload = self.fuzz.message_payload(cls, d, self.ctx, d.choice(modes)).payload
        svc = self.svc
        with svc.books.lock:
            svc.books.received += 1
            svc.books.in_flight += 1
        before = _books(svc)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            svc._handle_payload(handler, cls, payload, False)
        try:
            _settle(svc, before)
        except Rejected as exc:
            raise Rejected(f"{what}:{exc.reason}") from None


class Ros2Actions:
    """Action requests into the bridge's action server (`services/ros2/actions.py`), the
    explorer and the planner answering in this process."""

    WHATS = ("send_goal", "send_goal", "cancel_goal", "get_result")

    def __init__(self, seed, tmp):
        from smana.services.ros2 import actions as act
        from smana.services.ros2 import convert, rmw

        self.act, self.convert, self.rmw = act, convert, rmw
        act.request = self._explorer  # the explorer's goal query, answered here
        self.svc = _bridge()
        self.svc.robot = "r1"
        self.actions = act.Ros2Actions(self.svc, "/smana/r1")
        self.types = self.svc.types
        self.uuids = [bytes([k]) * 16 for k in range(8)]
        self.seq = 0

    def _explorer(self, session, key, body, timeout_s):
        """The explorer accepts every goal; the planner answers a straight path, or no graph."""
        from smana.common.messages import PathReply

        if isinstance(body, dict):
            return {"accepted": True, "id": body.get("id", ""), "reason": ""}
        if body.goal[0] > 0:
            path = np.array([[*body.start, 0.0], [*body.goal, 0.0]], np.float32)
            return PathReply(request_id=body.request_id, ok=True, path=path)
        return PathReply(request_id=body.request_id, error="no_graph", message="no graph")

    def _pose(self, d):
        wild = (math.nan, math.inf, 1e308, -1e308, 5e-324, 0.0, 1.0)
        xy = [d.choice(wild) if d.boolean(0.2) else d.unit() * 20 - 10 for _ in range(2)]
        pose = self.convert.pose_stamped(self.types, (0.0, 0.0), d.unit() * 6.3, 12.0)
        pose.pose.position.x, pose.pose.position.y = xy
        if d.boolean(0.1):
            pose.header.frame_id = d.choice(("", "base_link", "x" * 300, "map", "odom"))
        if d.boolean(0.05):
            pose.pose.orientation.w = d.choice(wild)
        return pose

    def _request(self, endpoints, what, d):
        T = endpoints.msg
        uuid = self.types.msg("unique_identifier_msgs/msg/UUID")(
            uuid=np.frombuffer(d.choice(self.uuids), np.uint8)
        )
        if what == "send_goal":
            if endpoints is self.actions.nav:
                goal = T("Goal")(pose=self._pose(d), behavior_tree=d.choice(("", "<root/>")))
            else:
                goal = T("Goal")(
                    goal=self._pose(d),
                    start=self._pose(d),
                    planner_id=d.choice(("", "GridBased", "x" * 100)),
                    use_start=d.boolean(),
                )
            msg = T("SendGoal_Request")(goal_id=uuid, goal=goal)
        elif what == "get_result":
            msg = T("GetResult_Request")(goal_id=uuid)
        else:
            info = self.convert.goal_info(self.types, bytes(uuid.uuid), d.integer(0, 2**40))
            msg = self.types.msg("action_msgs/srv/CancelGoal_Request")(goal_info=info)
        return self.types.serialize(msg, endpoints.names[what] + "_Request")

    def run(self, i, d) -> None:
        a = self.actions
        endpoints = d.choice((a.nav, a.plan))
        what = d.choice(self.WHATS)
        payload = self._request(endpoints, what, d)
        how = d.choice(("valid", "valid", "valid", "truncate", "flip", "random", "empty", "att"))
        if how == "truncate":
            payload = payload[: d.integer(0, len(payload) - 1)]
        elif how == "flip":
            b = bytearray(payload)
            b[d.integer(0, len(b) - 1)] ^= 1 << d.integer(0, 7)
            payload = bytes(b)
        elif how == "random":
            payload = d.blob(d.integer(1, 256))
        elif how == "empty":
            payload = b""
        self.seq += 1
        att = self.rmw.attachment(self.seq, time.time_ns(), bytes(range(16)))
        if how == "att":
            att = d.choice((None, b"", att[:5], d.blob(40)))
        svc = self.svc
        with svc.books.lock:
            svc.books.received += 1
            svc.books.in_flight += 1
        before = _books(svc)
        q = _Query(payload, att)
        with np.errstate(all="ignore"):
            a._handle(endpoints, what, endpoints.keys[what], q)
        if what == "get_result" and not q.replies:  # held until the goal ends: accepted
            pass
        try:
            _settle(svc, before)
        except Rejected as exc:
            raise Rejected(f"{what}:{exc.reason}") from None


TARGETS = {
    "keys": Keys,
    "messages": Messages,
    "map_files": MapFiles,
    "journals": Journals,
    "blocks": Blocks,
    "ros2_topics": Ros2Topics,
    "ros2_actions": Ros2Actions,
    "bridge_smana": BridgeSmana,
}
