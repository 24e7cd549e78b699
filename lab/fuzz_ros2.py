"""Hostile ROS 2 input for `smana ros2` (issue 25): what a peer on rmw_zenoh can send the ros2
service of a real robot, and what the service must make of each message. No zenoh here: the
bench (`lab/bench/fuzz_ros2.py`) puts these cases on the wire.

- **Inputs** (`Ros2Inputs`): for each of the service's robot inputs (`/odom` Odometry, `/points`
  PointCloud2, `/tf_static` TFMessage) and its GetPlan service, genuine messages built with
  rosbags' typestore on one plausible track (a robot driving along x, a LiDAR frame under
  base_link), and mutants: CDR truncations, bit flips, a wrong encapsulation header, huge
  lengths and counts written over the CDR, field values NaN/inf/1e308, wild stamps and places,
  bursts of odometry that agree on another clock and place (the gates relock onto them),
  absurd width * height * point_step, field lists that lie, another type's CDR, random bytes,
  an empty payload, wrong or missing rmw_zenoh attachments.
- **Prediction** (`Ros2Reference`): each case's fate as the service counts it ("accepted", or
  the rejection kind), by the service's cores (`services/ros2/bridge.py`, its decoder) fed the
  same cases in the same order in this process. Where the generator knows the fate on its own
  (`Ros2Case.refuse`: an empty payload, a NaN position, a GetPlan without a valid attachment
  must be refused; a decodable /tf_static message is taken, its bad transforms counted as
  events) the reference is checked against it. A genuine message has no such fate: after a
  burst on another clock the gates refuse the genuine track until they relock onto it.
"""

from __future__ import annotations

import math
import struct
from collections import Counter
from dataclasses import dataclass

import numpy as np

from smana.common.messages import MAX_PAYLOAD_BYTES, MessageError, PathRequest, encode
from smana.common.service import Reject

TOPICS = ("odom", "cloud", "tf_static", "plan")
TYPES_OF = {
    "odom": "nav_msgs/msg/Odometry",
    "cloud": "sensor_msgs/msg/PointCloud2",
    "tf_static": "tf2_msgs/msg/TFMessage",
    "plan": "nav_msgs/srv/GetPlan_Request",
}
# Mutations and their weights; `values` is each topic's own (`_values_*`).
KINDS = {
    "valid": 6,
    "values": 6,
    "truncate": 2,
    "bitflip": 2,
    "header": 1,
    "length": 2,
    "wrong_type": 1,
    "random": 1,
    "empty": 1,
    "attachment": 2,
}
WILD_FLOATS = (math.nan, math.inf, -math.inf, 1e308, -1e308, 1e200, 3.4e38, -0.0, 5e-324)
WILD_U32 = (0, 1, 3, 2**16, 2**28, 2**31 - 1, 2**32 - 1)
WILD_I32 = (-(2**31), -1, 0, 1, 2**31 - 1)
SENSOR_FRAME, BASE_FRAME = "lidar", "base_link"
STAMP_STEP_S = 0.01  # the genuine track's clock, per genuine odometry
STEP_M = 0.004  # and its progress: 0.4 m/s


@dataclass
class Ros2Case:
    """One input: `topic` one of TOPICS, `kind` one of KINDS; `refuse` True / False where the
    generator knows the fate, None where only the reference says."""

    topic: str
    kind: str
    payload: bytes
    attachment: bytes | None
    refuse: bool | None = None
    how: str = ""


class Ros2Inputs:
    """Genuine and hostile cases from a `lab.fuzz_values.Draw`, on a track starting at `t0_s`."""

    def __init__(self, types, draw, t0_s: float):
        from smana.services.ros2 import rmw

        self.types, self.draw, self.rmw = types, draw, rmw
        self.t_s, self.x = float(t0_s), 0.0
        self.seq = 0
        self.gid = bytes(range(16))

    # -- genuine ---------------------------------------------------------------------------------

    def attachment(self) -> bytes:
        import time

        self.seq += 1
        return self.rmw.attachment(self.seq, time.time_ns(), self.gid)

    def _msg(self, name: str):
        return self.types.msg(name)

    def header(self, t_s: float, frame: str):
        from smana.services.ros2 import convert

        return convert.header(self.types, t_s, frame)

    def odometry_msg(self, t_s: float, x: float, y: float = 0.0):
        T = self._msg
        cov = np.zeros(36)
        v = T("geometry_msgs/msg/Vector3")(x=0.0, y=0.0, z=0.0)
        pose = T("geometry_msgs/msg/Pose")(
            position=T("geometry_msgs/msg/Point")(x=x, y=y, z=0.0),
            orientation=T("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0),
        )
        return T(TYPES_OF["odom"])(
            header=self.header(t_s, "odom"),
            child_frame_id=BASE_FRAME,
            pose=T("geometry_msgs/msg/PoseWithCovariance")(pose=pose, covariance=cov),
            twist=T("geometry_msgs/msg/TwistWithCovariance")(
                twist=T("geometry_msgs/msg/Twist")(linear=v, angular=v), covariance=cov
            ),
        )

    def advance(self) -> tuple[float, float]:
        """The genuine track's next (stamp, x)."""
        self.t_s += STAMP_STEP_S
        self.x += STEP_M
        return self.t_s, self.x

    def cloud_msg(self, t_s: float, frame: str, n: int = 64):
        T = self._msg
        d = self.draw
        rng = d.rng()
        pts = np.stack(
            [rng.uniform(1.0, 6.0, n), rng.uniform(-3.0, 3.0, n), np.full(n, -0.3)], axis=1
        ).astype(np.float32)
        rec = np.zeros(
            n, np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("label", "<u2"), ("p", "<u2")])
        )
        rec["x"], rec["y"], rec["z"], rec["label"] = pts[:, 0], pts[:, 1], pts[:, 2], 2
        field = T("sensor_msgs/msg/PointField")
        fields = [
            field(name=nm, offset=o, datatype=dt, count=1)
            for nm, o, dt in (("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("label", 12, 4))
        ]
        return T(TYPES_OF["cloud"])(
            header=self.header(t_s, frame),
            height=1,
            width=n,
            fields=fields,
            is_bigendian=False,
            point_step=16,
            row_step=16 * n,
            data=rec.view(np.uint8).reshape(-1).copy(),
            is_dense=True,
        )

    def tf_msg(self, frames=((BASE_FRAME, SENSOR_FRAME, (0.1, 0.0, 0.3)),)):
        T = self._msg
        out = []
        for parent, child, (x, y, z) in frames:
            out.append(
                T("geometry_msgs/msg/TransformStamped")(
                    header=self.header(0.0, parent),
                    child_frame_id=child,
                    transform=T("geometry_msgs/msg/Transform")(
                        translation=T("geometry_msgs/msg/Vector3")(x=x, y=y, z=z),
                        rotation=T("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0),
                    ),
                )
            )
        return T(TYPES_OF["tf_static"])(transforms=out)

    def plan_msg(self, start=(0.0, 0.0), goal=(2.0, 1.0)):
        from smana.services.ros2 import convert

        return self._msg(TYPES_OF["plan"])(
            start=convert.pose_stamped(self.types, start, 0.0, self.t_s),
            goal=convert.pose_stamped(self.types, goal, 0.0, self.t_s),
            tolerance=0.0,
        )

    def genuine_msg(self, topic: str, advance: bool = True):
        if topic == "odom":
            t, x = self.advance() if advance else (self.t_s, self.x)
            return self.odometry_msg(t, x)
        if topic == "cloud":
            frame = SENSOR_FRAME if self.draw.integer(0, 1) else "odom"
            return self.cloud_msg(self.t_s, frame)
        if topic == "tf_static":
            return self.tf_msg()
        return self.plan_msg()

    def ser(self, msg, topic: str) -> bytes:
        return self.types.serialize(msg, TYPES_OF[topic])

    def genuine(self, topic: str) -> Ros2Case:
        payload = self.ser(self.genuine_msg(topic), topic)
        return Ros2Case(topic, "valid", payload, self.attachment(), refuse=None, how="genuine")

    # -- hostile ---------------------------------------------------------------------------------

    def case(self, topic: str) -> Ros2Case:
        """One case for `topic`, its kind drawn by KINDS' weights."""
        kinds = [k for k, w in KINDS.items() for _ in range(w)]
        kind = self.draw.choice(kinds)
        if kind == "valid":
            return self.genuine(topic)
        d = self.draw
        if kind == "values":
            msg, how, refuse = getattr(self, f"_values_{topic}")()
            return Ros2Case(topic, kind, self.ser(msg, topic), self.attachment(), refuse, how)
        if kind == "attachment":
            payload = self.ser(self.genuine_msg(topic, advance=False), topic)
            att, how = self._bad_attachment()
            # a topic's subscriber reads the payload only; a service reply needs the attachment
            return Ros2Case(topic, kind, payload, att, True if topic == "plan" else None, how)
        if kind == "empty":
            return Ros2Case(topic, kind, b"", self.attachment(), True, "empty")
        if kind == "random":
            n = d.integer(0, 400)
            data = d.blob(n)
            return Ros2Case(topic, kind, data, self.attachment(), None, f"random {n} bytes")
        if kind == "wrong_type":
            other = d.choice([t for t in TOPICS if t != topic])
            payload = self.ser(self.genuine_msg(other, advance=False), other)
            return Ros2Case(topic, kind, payload, self.attachment(), None, f"a {other} CDR")
        raw = bytearray(self.ser(self.genuine_msg(topic, advance=False), topic))
        if kind == "truncate":
            cut = d.integer(0, len(raw) - 1)
            return Ros2Case(topic, kind, bytes(raw[:cut]), self.attachment(), None, f"cut {cut}")
        if kind == "bitflip":
            flips = d.integer(1, 8)
            for _ in range(flips):
                i = d.integer(0, len(raw) - 1)
                raw[i] ^= 1 << d.integer(0, 7)
            return Ros2Case(topic, kind, bytes(raw), self.attachment(), None, f"{flips} flips")
        if kind == "header":
            head = d.choice(
                (b"\x00\x00\x00\x00", b"\x00\x07\x00\x00", b"\xff\xff\xff\xff", b"\x00\x01")
            )
            raw = head + raw[4:]
            return Ros2Case(topic, kind, bytes(raw), self.attachment(), None, f"header {head!r}")
        # kind == "length": a huge length or count over an aligned word of the CDR
        i = 4 + 4 * d.integer(0, max(0, (min(len(raw), 160) - 8) // 4))
        v = d.choice((2**31 - 1, 2**32 - 1, 2**28, 2**24 + 1, 65536))
        raw[i : i + 4] = struct.pack("<I", v)
        return Ros2Case(topic, kind, bytes(raw), self.attachment(), None, f"{v} at {i}")

    def hijack(self, n: int = 6) -> list[Ros2Case]:
        """`n` odometry messages that agree with each other on another clock and place (a second
        robot on the same topic, a bag replayed): enough for the gates to relock onto them."""
        d = self.draw
        t, x = self.t_s + d.choice((1e5, -50.0, 3600.0)), self.x + d.choice((500.0, -80.0))
        out = []
        for i in range(n):
            msg = self.odometry_msg(t + i * STAMP_STEP_S, x + i * STEP_M)
            how = f"hijack {i + 1}/{n} at t{t - self.t_s:+g} s, x{x - self.x:+g} m"
            out.append(
                Ros2Case("odom", "hijack", self.ser(msg, "odom"), self.attachment(), None, how)
            )
        return out

    def oversize(self, topic: str) -> Ros2Case:
        """A payload one byte over the services' limit (64 MiB): refused before it is copied."""
        payload = bytes(MAX_PAYLOAD_BYTES + 1)
        return Ros2Case(topic, "oversize", payload, self.attachment(), True, "64 MiB + 1")

    def _bad_attachment(self) -> tuple[bytes | None, str]:
        d = self.draw
        good = self.attachment()
        noise = bytearray(d.blob(33))
        noise[16] = d.integer(17, 255)  # never the gid's length: 16 would make it a valid one
        return d.choice(
            (
                (None, "no attachment"),
                (b"", "empty attachment"),
                (good[:16], "16 bytes"),
                (good + b"\x00", "34 bytes"),
                (good[:16] + b"\x20" + good[17:], "gid length 32"),
                (bytes(noise), "33 bytes of noise"),
            )
        )

    def _values_odom(self):
        d = self.draw
        t, x = self.t_s, self.x
        msg = self.odometry_msg(t, x)
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        what = d.integer(0, 6)
        if what == 0:
            axis = d.choice("xyz")
            v = d.choice(WILD_FLOATS)
            setattr(p, axis, v)
            # a non-finite or 1000 km+ coordinate; -0.0 and 5e-324 are plausible places
            refuse = not math.isfinite(v) or abs(v) > 1e6 or None
            return msg, f"position.{axis}={v!r}", refuse
        if what == 1:
            axis = d.choice("xyzw")
            v = d.choice(WILD_FLOATS)
            setattr(q, axis, v)
            return msg, f"orientation.{axis}={v!r}", (not math.isfinite(v)) or None
        if what == 2:
            q.x = q.y = q.z = q.w = 0.0
            return msg, "zero quaternion", True
        if what == 3:
            msg.header.stamp.sec = d.choice(WILD_I32)
            msg.header.stamp.nanosec = d.choice(WILD_U32)
            return msg, f"stamp {msg.header.stamp.sec}.{msg.header.stamp.nanosec}", None
        if what == 4:  # a place farther than the robot can travel (the pose gate)
            jump = d.choice((50.0, -200.0, 5e5))
            p.x = x + jump
            # 50 m may be within reach of a place a hijack moved the gate to (tens of seconds
            # away on its clock); 500 km is out of reach of anything
            return msg, f"jump to x={p.x}", True if jump == 5e5 else None
        if what == 5:
            msg.pose.covariance[:] = d.choice(WILD_FLOATS)
            msg.twist.twist.linear.x = d.choice(WILD_FLOATS)
            return msg, "covariance and twist wild", None  # not read: no fate of their own
        msg.header.frame_id = "x" * d.choice((0, 300, 70_000))
        msg.child_frame_id = "\u00e9" * d.integer(0, 50)
        return msg, "frame names", None

    def _values_cloud(self):
        d = self.draw
        frame = SENSOR_FRAME if d.integer(0, 1) else "odom"
        msg = self.cloud_msg(self.t_s, frame, n=d.choice((0, 1, 64)))
        what = d.integer(0, 10)
        if what == 9:  # valid but heavy: 50,000 points (800 kB)
            return self.cloud_msg(self.t_s, frame, n=50_000), "50,000 points", None
        if what == 10:  # valid, organised: 8 rows of 8 with 16 bytes of padding after each
            msg = self.cloud_msg(self.t_s, frame, n=64)
            rows = msg.data.reshape(8, 128)
            msg.data = np.concatenate([rows, np.zeros((8, 16), np.uint8)], axis=1).reshape(-1)
            msg.height, msg.width, msg.row_step = 8, 8, 144
            return msg, "8x8 with row padding", None
        if what == 0:
            name = d.choice(("width", "height", "point_step", "row_step"))
            setattr(msg, name, d.choice(WILD_U32))
            return msg, f"{name}={getattr(msg, name)}", None
        if what == 1:  # the claimed size far beyond the data
            msg.width, msg.height = d.choice(WILD_U32), d.choice(WILD_U32)
            msg.point_step = d.choice((16, 2**16, 2**31 - 1))
            msg.row_step = d.choice((2**32 - 1, msg.point_step))
            return msg, f"{msg.width}x{msg.height}x{msg.point_step}", None
        if what == 2:  # a field list that lies
            f = d.choice(msg.fields)
            which = d.integer(0, 4)
            if which == 0:
                f.offset = d.choice(WILD_U32)
            elif which == 1:
                f.datatype = d.choice((0, 9, 255, 7, 8, 1))
            elif which == 2:
                f.count = d.choice(WILD_U32)
            elif which == 3:
                f.name = d.choice(("", "x", "label", "X", "\x00"))
            else:
                msg.fields = [f for f in msg.fields if f.name != d.choice("xyz")] * d.integer(0, 2)
            return msg, f"field {f.name!r} lies ({which})", None
        if what == 3:  # points not finite, or far
            pts = msg.data.view("<f4").reshape(-1, 4)[:, :3] if len(msg.data) else None
            if pts is not None:
                with np.errstate(over="ignore"):  # 1e308 as float32 is inf
                    pts[d.integer(0, len(pts) - 1), d.integer(0, 2)] = d.choice(WILD_FLOATS)
            return msg, "a wild point", None
        if what == 4:
            msg.is_bigendian = True
            return msg, "big-endian", None
        if what == 5:
            msg.data = msg.data[: d.integer(0, len(msg.data))]
            return msg, f"data cut to {len(msg.data)}", None
        if what == 6:
            msg.header.frame_id = d.choice(("nowhere", "/" + SENSOR_FRAME, "", "x" * 300))
            return msg, f"frame {msg.header.frame_id[:20]!r}", None
        if what == 7:
            msg.header.stamp.sec = d.choice(WILD_I32)
            msg.header.stamp.nanosec = d.choice(WILD_U32)
            return msg, f"stamp {msg.header.stamp.sec}.{msg.header.stamp.nanosec}", None
        msg.fields = [f for f in msg.fields if f.name != "label"]
        return msg, "no label field", len(msg.data) > 0 or None

    def _values_tf_static(self):
        d = self.draw
        what = d.integer(0, 4)
        if what == 0:
            msg = self.tf_msg()
            t = msg.transforms[0].transform
            setattr(t.translation, d.choice("xyz"), d.choice(WILD_FLOATS))
            t.rotation.w = d.choice((1.0, 0.0, math.nan))
            return msg, "wild transform", None  # a transform refused is an event, not a fate
        if what == 1:  # new frames by the dozen (the table's cap)
            k = d.integer(0, 1_000_000)
            frames = [(BASE_FRAME, f"f{k}_{i}", (0.0, 0.0, 0.0)) for i in range(50)]
            return self.tf_msg(frames), "50 new frames", False
        if what == 2:
            frames = [("a", "b", (0.0, 0.0, 0.0)), ("b", "a", (0.0, 0.0, 0.0))]
            return self.tf_msg(frames), "a cycle", False
        if what == 3:
            name = "y" * d.choice((257, 5000))
            return self.tf_msg([(BASE_FRAME, name, (0.0, 0.0, 0.0))]), "a long name", False
        return self.tf_msg([]), "no transforms", False

    def _values_plan(self):
        d = self.draw
        v = d.choice(WILD_FLOATS)
        msg = self.plan_msg(start=(v, 0.0)) if d.integer(0, 1) else self.plan_msg(goal=(0.0, v))
        if d.integer(0, 3) == 0:
            msg.goal.pose.orientation.w = 0.0
            return msg, "zero quaternion", True
        return msg, f"a coordinate {v!r}", (not math.isfinite(v)) or None


class Ros2Reference:
    """The fate of each case as `Ros2Service` counts it, by the same cores fed the same cases in
    the same order (`services/ros2/service.py`: `on_odometry`, `on_cloud`, `on_tf_static`,
    `on_plan` without the planner query, whose failure is no rejection)."""

    def __init__(self, config, types):
        from smana.services.ros2.bridge import CloudInput, OdometryInput

        self.types = types
        self.odometry = OdometryInput(config.general)
        self.clouds = CloudInput(config, None)
        self.received = {"clouds": 0, "odometry": 0, "tf_static": 0, "plans": 0}
        self.fates: Counter = Counter()
        self.crashes: list[str] = []

    def _ros(self, payload: bytes, typename: str):
        try:
            return self.types.deserialize(payload, typename)
        except Exception as exc:  # noqa: BLE001 - as the service: any CDR that is not this type
            raise MessageError("malformed", f"not a {typename}: {type(exc).__name__}") from None

    def fate(self, case: Ros2Case) -> str:
        if len(case.payload) > MAX_PAYLOAD_BYTES:  # common/service.py: refused uncopied
            self.fates["oversize"] += 1
            return "oversize"
        try:
            with np.errstate(all="ignore"):  # wild values overflow on the way to a refusal
                getattr(self, f"_{case.topic}")(case)
        except (Reject, MessageError) as exc:
            fate = exc.kind
        except ValueError:
            fate = "value"
        except Exception as exc:  # noqa: BLE001 - the service would count `internal`: a crash
            self.crashes.append(f"{case.topic} {case.kind} {case.how}: {type(exc).__name__}: {exc}")
            fate = "internal"
        else:
            fate = "accepted"
        self.fates[fate] += 1
        return fate

    def _odom(self, case: Ros2Case) -> None:
        pose, _ = self.odometry.checked(self._ros(case.payload, TYPES_OF["odom"]))
        self.clouds.poses.add(pose.stamp_s, pose.position, pose.orientation_xyzw)
        self.received["odometry"] += 1

    def _cloud(self, case: Ros2Case) -> None:
        from smana.services.ros2.bridge import checked

        cloud = self.clouds.convert(self._ros(case.payload, TYPES_OF["cloud"]))
        checked(cloud, "cloud")
        self.received["clouds"] += 1

    def _tf_static(self, case: Ros2Case) -> None:
        msg = self._ros(case.payload, TYPES_OF["tf_static"])
        self.received["tf_static"] += self.clouds.add_static(msg)

    def _plan(self, case: Ros2Case) -> None:
        from smana.services.ros2 import convert, rmw

        try:
            rmw.parse_attachment(case.attachment)
        except ValueError as exc:
            raise Reject("malformed", f"GetPlan request: {exc}") from None
        msg = self._ros(case.payload, TYPES_OF["plan"])
        try:
            start, _ = convert.pose_of(msg.start.pose)
            goal, _ = convert.pose_of(msg.goal.pose)
        except ValueError as exc:
            raise Reject("value", f"GetPlan request: {exc}") from None
        self.received["plans"] += 1
        encode(PathRequest(request_id="ref", start=start[:2], goal=goal[:2]))
