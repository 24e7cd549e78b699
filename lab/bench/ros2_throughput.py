"""`smana bench ros2-throughput`: large ROS 2 messages across a zenoh router on loopback, both
ways, for a set time: a LiDAR's PointCloud2 into smana and smana's map out.

Three processes, as on a robot: a zenoh router (`smana router`, in the place of `rmw_zenohd`),
an independent rmw_zenoh client (zenoh-ros2-sdk, nobody here wrote it) and smana's side (this
process: `services/ros2/rmw.py`, the mapping the ros2 service uses), each a client of the router.

- in: the SDK publishes a `sensor_msgs/PointCloud2` of `--points` points (x, y, z, intensity:
  16 bytes each; 131,072 points = 2 MiB) on `/points` at `--rate-hz`, reliable, congestion
  control BLOCK (`--cloud-congestion`: as rmw_zenoh_cpp declares a reliable KEEP_ALL publisher;
  `drop` is its keep-last choice and the SDK's default); smana's side subscribes as the ros2
  service does (its token and the data key) and decodes each cloud. Latency: from the
  attachment's source timestamp (set by the SDK at its put) to smana's callback.
- out: smana publishes its map (`/smana/bench/map`, reliable, transient-local, depth 1: the
  ros2 service's publisher) of `--map-voxels` voxels, passed through the voxel budget
  (`ros2.map_max_points`) once a second; the SDK subscribes and decodes it. Latency: from the
  header stamp (set just before serialising) to the SDK's callback.

Sent, received, dropped (sent and not received, by sequence number) and p50 / p99 latency for
each direction, the load average at start and end and the CPU time of each process. A run
with a dropped message, or no message at all, exits with status 1.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from smana.common.cli import ArgumentParser, doc_summary, positive_float
from smana.lab.bench import procs

CLOUD = "sensor_msgs/msg/PointCloud2"
NS = "/smana/bench"
DRAIN_S = 10.0  # after the last cloud: what is still on its way gets this long to arrive


def _cloud_fields(msg):
    """x, y, z, intensity: float32 each; `msg` maps a type name to its message class."""
    field = msg("sensor_msgs/msg/PointField")
    fields = [field(name=c, offset=4 * i, datatype=7, count=1) for i, c in enumerate("xyz")]
    fields.append(field(name="intensity", offset=12, datatype=7, count=1))
    return fields


def _percentiles(values_s: list[float]) -> dict:
    if not values_s:
        return {"p50_ms": None, "p99_ms": None, "max_ms": None}
    a = np.asarray(values_s) * 1e3
    return {
        "p50_ms": round(float(np.percentile(a, 50)), 2),
        "p99_ms": round(float(np.percentile(a, 99)), 2),
        "max_ms": round(float(a.max()), 2),
    }


# -- the SDK's side (a child process) ------------------------------------------------------------


def sdk_side(
    port: int, points: int, rate_hz: float, duration_s: float, block: bool, work: Path
) -> int:
    """Publish clouds with zenoh-ros2-sdk and receive smana's map; results in work/sdk.json."""
    os.environ["ZENOH_ROS2_SDK_CACHE"] = str(work / "sdk-cache")
    os.environ["ZENOH_CONFIG_OVERRIDE"] = "scouting/multicast/enabled=false"
    from zenoh_ros2_sdk import ROS2Publisher, ROS2Subscriber, message_registry
    from zenoh_ros2_sdk.qos import QosDurability, QosProfile

    from smana.services.ros2.rmw import write_msg_files

    write_msg_files(work / "msgs", [CLOUD])
    message_registry.get_registry(str(work / "msgs"))
    map_in: list[tuple[int, float, int]] = []  # (stamp ns, latency s, points)

    def on_map(msg) -> None:
        now = time.time_ns()
        stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        map_in.append((stamp, (now - stamp) * 1e-9, int(msg.width)))

    latched = QosProfile(durability=QosDurability.TRANSIENT_LOCAL, history_depth=1)
    sub = ROS2Subscriber(f"{NS}/map", CLOUD, on_map, router_port=port, qos=latched)
    pub = ROS2Publisher("/points", CLOUD, node_name="lidar", router_port=port)
    if block:
        # zenoh-ros2-sdk 0.1.8 looks for `zenoh.qos.CongestionControl`, which zenoh-python 1.x
        # does not have, and so keeps zenoh's default, DROP (rmw_zenoh_cpp's choice for a
        # keep-last publisher too). `--cloud-congestion block` declares its publisher as
        # rmw_zenoh_cpp declares a reliable KEEP_ALL one: reliable, BLOCK.
        import zenoh

        key = pub.pub.key_expr
        pub.pub.undeclare()
        pub.pub = pub.session_mgr.session.declare_publisher(
            key,
            congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE,
        )
    from rosbags.typesys import Stores, get_typestore

    types_store = get_typestore(Stores.ROS2_JAZZY)
    fields = _cloud_fields(types_store.types.__getitem__)
    rng = np.random.default_rng(0)
    data = rng.random((points, 4), dtype=np.float32).view(np.uint8).reshape(-1)
    deadline = time.monotonic() + 30.0
    while not pub.pub.matching_status.matching:  # smana's subscription has reached the router
        if time.monotonic() > deadline:
            print("smana's /points subscription never matched", file=sys.stderr)
            return 1
        time.sleep(0.05)
    (work / "sdk.ready").write_text("ready")
    sent = 0
    period = 1.0 / rate_hz
    t0 = time.monotonic()
    header = types_store.types["std_msgs/msg/Header"]
    stamp_t = types_store.types["builtin_interfaces/msg/Time"]
    while time.monotonic() - t0 < duration_s:
        now = time.time()
        pub.publish(
            header=header(stamp=stamp_t(sec=int(now), nanosec=int(now % 1 * 1e9)), frame_id="os"),
            height=1,
            width=points,
            fields=fields,
            is_bigendian=False,
            point_step=16,
            row_step=16 * points,
            data=data,
            is_dense=True,
        )
        sent += 1
        time.sleep(max(0.0, t0 + sent * period - time.monotonic()))
    (work / "sdk.sent").write_text(str(sent))
    # The map keeps coming until smana stops it (it reads sdk.sent, drains, and says done).
    deadline = time.monotonic() + DRAIN_S + 30.0
    while not (work / "smana.done").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(1.0)  # the last map smana sent is on its way
    usage = resource.getrusage(resource.RUSAGE_SELF)
    out = {
        "clouds_sent": sent,
        "maps": map_in,
        "cpu_s": round(usage.ru_utime + usage.ru_stime, 1),
    }
    (work / "sdk.json").write_text(json.dumps(out))
    pub.close()
    sub.close()
    return 0


# -- smana's side (this process) -----------------------------------------------------------------


class SmanaSide:
    """smana's rmw_zenoh endpoints on a client session of the router: a /points subscription and
    the map publisher, as the ros2 service declares them."""

    def __init__(self, endpoint: str, map_voxels: int, map_max_points: int):
        import zenoh

        from smana.services.ros2 import convert, rmw

        self.convert, self.rmw = convert, rmw
        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("timestamping/enabled", "true")  # the transient-local map's cache
        self.session = zenoh.open(conf)
        self.types = rmw.RosTypes()
        self.node = rmw.RosNode(self.session, self.types, 0, "smana", NS)
        self._lock = threading.Lock()
        self.clouds: dict[int, float] = {}  # sequence number -> latency s
        self.bad_clouds = 0
        key, _ = self.node.endpoint(rmw.SUBSCRIPTION, "/points", CLOUD, rmw.QoS())
        self._sub = self.session.declare_subscriber(key, self._on_cloud)
        self.map_pub = self.node.publisher(f"{NS}/map", CLOUD, rmw.LATCHED_QOS)
        rng = np.random.default_rng(1)
        res = 0.1
        # A map as a ground robot builds it: a square of ground at 0.1 m (a surface, so the
        # budget's coarser cells merge voxels four to one), with a random height step.
        side = int(np.ceil(np.sqrt(map_voxels)))
        ix, iy = np.divmod(np.arange(map_voxels), side)
        iz = (rng.random(map_voxels) < 0.1).astype(np.int64)
        idx = np.stack([ix - side // 2, iy - side // 2, iz], axis=1)
        self.centres = ((idx + 0.5) * res).astype(np.float32)
        self.labels = rng.integers(0, 9, len(idx)).astype(np.uint16)
        self.resolution_m = res
        self.map_max_points = map_max_points
        self.colours = rng.integers(0, 255, size=(16, 3)).astype(np.uint8)
        self.maps_sent: list[int] = []  # header stamps, ns
        self.map_bytes = 0

    def _on_cloud(self, sample) -> None:
        now = time.time_ns()
        try:
            seq, stamp_ns, _ = self.rmw.parse_attachment(sample.attachment.to_bytes())
            msg = self.types.deserialize(sample.payload.to_bytes(), CLOUD)
            ok = msg.width * msg.point_step == len(msg.data)
        except Exception:  # noqa: BLE001 - counted: the bench fails on it
            ok, seq, stamp_ns = False, -1, now
        with self._lock:
            if ok:
                self.clouds[seq] = (now - stamp_ns) * 1e-9
            else:
                self.bad_clouds += 1

    def publish_map(self) -> None:
        centres, labels, _ = self.convert.within_budget(
            self.centres, self.labels, self.resolution_m, self.map_max_points
        )
        now = time.time()
        msg = self.convert.map_cloud(self.types, centres, labels, self.colours, now)
        self.map_bytes = self.map_pub.put(msg)
        stamp = msg.header.stamp
        self.maps_sent.append(stamp.sec * 1_000_000_000 + stamp.nanosec)

    def map_matched(self) -> bool:
        """A probe on the map's key sees the SDK's subscriber (the router has passed it on)."""
        probe = self.session.declare_publisher(self.map_pub.key)
        try:
            deadline = time.monotonic() + 30.0
            while not probe.matching_status.matching:
                if time.monotonic() > deadline:
                    return False
                time.sleep(0.05)
            return True
        finally:
            probe.undeclare()

    def close(self) -> None:
        self.node.close()
        self._sub.undeclare()
        self.session.close()


def run(args, out: Path) -> dict:
    from smana.common.zenoh_config import free_loopback_port, wait_port

    out.mkdir(parents=True, exist_ok=True)
    port = free_loopback_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    load_start = os.getloadavg()
    router = procs.spawn(
        [sys.executable, "-m", "smana.deploy.router", "--listen", endpoint], out / "router.log"
    )
    side = sdk = None
    try:
        wait_port(port, timeout_s=30.0)
        side = SmanaSide(endpoint, args.map_voxels, args.map_max_points)
        sdk = procs.spawn(
            [
                sys.executable,
                "-m",
                "smana.lab.bench.ros2_throughput",
                "--sdk-side",
                *(str(port), str(args.points), str(args.rate_hz), str(args.duration)),
                args.cloud_congestion,
                str(out),
            ],
            out / "sdk.log",
        )
        if not _wait_file(out / "sdk.ready", sdk, 120.0):
            raise RuntimeError(f"the SDK's side did not start:\n{_tail(out / 'sdk.log')}")
        if not side.map_matched():
            raise RuntimeError("the SDK's map subscription never reached the router")
        t_start = time.monotonic()
        next_map = t_start
        while not (out / "sdk.sent").exists():
            if sdk.poll() is not None:
                raise RuntimeError(f"the SDK's side exited early:\n{_tail(out / 'sdk.log')}")
            if time.monotonic() >= next_map:
                side.publish_map()
                next_map += 1.0
            time.sleep(0.02)
        sent = int((out / "sdk.sent").read_text())
        deadline = time.monotonic() + DRAIN_S
        while len(side.clouds) + side.bad_clouds < sent and time.monotonic() < deadline:
            time.sleep(0.05)
        wall_s = time.monotonic() - t_start
        (out / "smana.done").write_text("done")
        if sdk.wait(timeout=60.0) != 0:
            raise RuntimeError(f"the SDK's side failed:\n{_tail(out / 'sdk.log')}")
        theirs = json.loads((out / "sdk.json").read_text())
    finally:
        if sdk is not None:
            procs.stop([sdk], 5.0)
        if side is not None:
            side.close()
        procs.stop([router], 5.0)
    usage = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    got = {stamp for stamp, _, _ in theirs["maps"]}
    cloud_lat = list(side.clouds.values())
    map_lat = [lat for _, lat, _ in theirs["maps"]]
    result = {
        "duration_s": args.duration,
        "wall_s": round(wall_s, 1),
        "points": args.points,
        "rate_hz": args.rate_hz,
        "cloud_bytes": 16 * args.points,
        "cloud_congestion": args.cloud_congestion,
        "clouds": {
            "sent": sent,
            "received": len(side.clouds),
            "undecodable": side.bad_clouds,
            "dropped": max(0, sent - len(side.clouds)),
            "missing": sorted(set(range(sent)) - set(side.clouds))[:50],
            **_percentiles(cloud_lat),
        },
        "map": {
            "voxels": args.map_voxels,
            "points": int(theirs["maps"][-1][2]) if theirs["maps"] else None,
            "payload_bytes": side.map_bytes,
            "sent": len(side.maps_sent),
            "received": len(got & set(side.maps_sent)),
            "dropped": len(set(side.maps_sent) - got),
            **_percentiles(map_lat),
        },
        "load_average_start": [round(v, 2) for v in load_start],
        "load_average_end": [round(v, 2) for v in os.getloadavg()],
        "cpu_s": {
            "smana_side": round(usage.ru_utime + usage.ru_stime, 1),
            "sdk_side": theirs["cpu_s"],
            "router_and_sdk": round(children.ru_utime + children.ru_stime, 1),
        },
    }
    (out / "result.json").write_text(json.dumps(result, indent=1))
    return result


def _wait_file(path: Path, proc, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if path.exists():
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.05)
    return False


def _tail(path: Path, n: int = 20) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-n:])
    except OSError:
        return ""


def _report(r: dict) -> str:
    c, m = r["clouds"], r["map"]
    lines = [
        f"{r['duration_s']:g} s: PointCloud2 of {r['points']} points ({r['cloud_bytes']} B) at "
        f"{r['rate_hz']:g} Hz in ({r['cloud_congestion']}); map of {m['points']} points "
        f"({m['payload_bytes']} B) at 1 Hz out",
        f"{'':8} {'sent':>6} {'recv':>6} {'dropped':>8} {'p50 ms':>8} {'p99 ms':>8} {'max ms':>8}",
    ]
    for name, d in (("clouds", c), ("map", m)):
        lines.append(
            f"{name:8} {d['sent']:>6} {d['received']:>6} {d['dropped']:>8} "
            f"{d['p50_ms']!s:>8} {d['p99_ms']!s:>8} {d['max_ms']!s:>8}"
        )
    la, le = r["load_average_start"], r["load_average_end"]
    lines.append(
        f"load average {la[0]:.2f} {la[1]:.2f} {la[2]:.2f} at start, {le[0]:.2f} {le[1]:.2f} "
        f"{le[2]:.2f} at end; CPU s: smana side {r['cpu_s']['smana_side']}, SDK side "
        f"{r['cpu_s']['sdk_side']}, router + SDK {r['cpu_s']['router_and_sdk']}"
    )
    return "\n".join(lines)


def cli(argv: list[str] | None = None) -> int:
    p = ArgumentParser(
        prog="smana bench ros2-throughput",
        description=doc_summary(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Takes --duration, plus the start-up and up to 10 s for the last clouds. Needs "
        "zenoh-ros2-sdk (pip install 'smana[test]').",
    )
    p.add_argument("--duration", type=positive_float, default=60.0, metavar="S")
    p.add_argument("--points", type=int, default=131_072, help="points per cloud")
    p.add_argument("--rate-hz", type=positive_float, default=10.0, help="clouds per second")
    p.add_argument("--map-voxels", type=int, default=300_000, help="voxels in smana's map")
    p.add_argument(
        "--map-max-points",
        type=int,
        default=200_000,
        help="the voxel budget of a map message (ros2.map_max_points)",
    )
    p.add_argument(
        "--cloud-congestion",
        choices=("block", "drop"),
        default="block",
        help="the cloud publisher's congestion control: block (rmw_zenoh_cpp's for a reliable "
        "KEEP_ALL publisher) or drop (its choice for keep-last, and the SDK's default)",
    )
    p.add_argument("--out", type=Path, help="result folder (default: a temporary one)")
    args = p.parse_args(argv)
    if args.points < 1 or args.map_voxels < 1 or args.map_max_points < 1:
        p.error("--points, --map-voxels and --map-max-points must be at least 1")
    try:
        import zenoh_ros2_sdk  # noqa: F401
    except ImportError:
        print("smana bench ros2-throughput: needs zenoh-ros2-sdk: pip install 'smana[test]'")
        return 2
    out = args.out or Path(tempfile.mkdtemp(prefix="smana-bench-ros2-"))
    result = run(args, out)
    print(_report(result))
    print(f"result: {out / 'result.json'}")
    c, m = result["clouds"], result["map"]
    return 0 if c["sent"] and m["sent"] and not (c["dropped"] or m["dropped"]) else 1


def _sdk_main(argv: list[str]) -> int:
    port, points, rate, duration, congestion, work = argv
    block = congestion == "block"
    return sdk_side(int(port), int(points), float(rate), float(duration), block, Path(work))


if __name__ == "__main__":
    if sys.argv[1:2] == ["--sdk-side"]:
        sys.exit(_sdk_main(sys.argv[2:]))
    sys.exit(cli(sys.argv[1:]))
