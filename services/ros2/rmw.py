"""The rmw_zenoh mapping: what a zenoh session must declare and send so that ROS 2 nodes running
`rmw_zenoh_cpp` (Humble to Rolling) see smana as one of theirs, following ros2/rmw_zenoh's
`docs/design.md` and its liveliness and attachment code.

- Data: a topic `/a/b` of type `pkg/msg/T` travels on `<domain>/a/b/pkg::msg::dds_::T_/<hash>`,
  where `<hash>` is the type's RIHS01 hash; payloads are CDR (little-endian, with the 4-byte
  encapsulation header). A service is a queryable on the same form of key.
- Every sample and query carries an attachment: sequence number (int64), source timestamp
  (int64, ns) and the 16-byte source gid, in zenoh-ext's serialisation (a length-prefixed gid).
  A service reply repeats the request's sequence number and client gid. The gid is what
  rmw_zenoh_cpp computes (`liveliness_utils.cpp`, `Entity::Entity`): the 128-bit XXH3 hash (seed
  0) of the entity's whole liveliness token, its low 64 bits then its high 64 bits, each in the
  host's (little-endian) byte order; so `message_info.publication_gid` is the gid `ros2 topic
  info -v` shows for smana's publisher.
- Discovery is liveliness tokens: `@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/
  <enclave>/<namespace>/<node>` for a node (kind NN) and the same followed by
  `/<topic>/<dds type>/<hash>/<qos>` for a publisher (MP), subscription (MS) or service (SS);
  '/' in names becomes '%'.
- A TRANSIENT_LOCAL publisher is a zenoh-ext AdvancedPublisher with a cache of `depth` samples:
  a late subscriber (RViz2) queries it for the last ones. A RELIABLE one also sends the sample-miss
  heartbeat (`rmw_publisher_data.cpp`: sporadic, period 500 ms): on `<key>/@adv/pub/<zid>/<eid>/_`
  the last sequence number (u32, little-endian), only when it changed, so that a subscriber that
  missed the latest sample fetches it from the cache.
- Publishers are reliable or best effort as their QoS says; congestion control is DROP, BLOCK only
  for a reliable KEEP_ALL publisher (rmw_zenoh_cpp's choice: a slow subscriber does not hold up
  a keep-last publisher; an rmw_zenoh transient-local subscriber recovers the latest sample it
  missed through the heartbeat).

Message types, CDR and type hashes come from rosbags' typestore (ROS 2 Jazzy definitions);
smana writes only this mapping. No ROS install is needed.
"""

from __future__ import annotations

import struct
import time
from dataclasses import dataclass

from . import costmap_types

ADMIN_SPACE = "@ros2_lv"
GID_SIZE = 16
NODE, PUBLISHER, SUBSCRIPTION, SERVICE = "NN", "MP", "MS", "SS"
DEFAULT_DEPTH = 42  # rmw_zenoh_cpp's default history depth (qos.cpp): left out of a QoS token
HEARTBEAT_PERIOD_S = 0.5  # SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD (rmw_publisher_data.cpp)

# Services smana answers. rosbags' typestore holds messages only: a service type is described
# the way rosidl describes it (request, response and event messages) so that its RIHS01 hash is
# the one ROS 2 computes.
SERVICES = {
    "nav_msgs/srv/GetPlan": (
        "geometry_msgs/PoseStamped start\ngeometry_msgs/PoseStamped goal\nfloat32 tolerance",
        "nav_msgs/Path plan",
    ),
}


class RosTypes:
    """The ROS 2 message types smana speaks: CDR in and out, and their RIHS01 hashes."""

    def __init__(self):
        from rosbags.typesys import Stores, get_typestore

        self.store = get_typestore(Stores.ROS2_JAZZY)
        costmap_types.register(self.store)
        _char_as_uint8(self.store, "service_msgs/msg/ServiceEventInfo")
        for name, (request, response) in SERVICES.items():
            self.store.register(_service_types(name, request, response))
        from . import nav2_types  # the actions smana serves (their services and messages)

        nav2_types.register(self.store, _service_types)
        self._hashes: dict[str, str] = {}

    def msg(self, typename: str):
        """The message class, e.g. `msg("std_msgs/msg/Header")(stamp=..., frame_id=...)`."""
        return self.store.types[typename]

    def hash(self, typename: str) -> str:
        if typename not in self._hashes:
            self._hashes[typename] = self.store.hash_rihs01(typename)
        return self._hashes[typename]

    def serialize(self, msg, typename: str) -> bytes:
        return bytes(self.store.serialize_cdr(msg, typename))

    def deserialize(self, raw: bytes, typename: str):
        return self.store.deserialize_cdr(raw, typename)


def write_msg_files(root, typenames) -> None:
    """`<root>/<pkg>/msg/<Name>.msg` for each type and every type it uses, as ROS 2 packages ship
    them, from rosbags' Jazzy typestore: what an rmw_zenoh client that parses .msg files
    (zenoh-ros2-sdk) reads instead of downloading them."""
    from pathlib import Path

    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    for typename in typenames:
        text, _ = store.generate_msgdef(typename, ros_version=2)
        name = typename
        for i, block in enumerate(text.split("=" * 80 + "\n")):
            if i:
                head, block = block.split("\n", 1)
                name = head.removeprefix("MSG: ")
            pkg, msg = name.replace("/msg/", "/").split("/")
            path = Path(root) / pkg / "msg" / f"{msg}.msg"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(block.rstrip("\n") + "\n")


def _char_as_uint8(store, typename: str) -> None:
    """rosidl reads a .msg `char` as IDL `uint8` (rosidl_adapter's MSG_TYPE_TO_IDL), so a type
    hash sees uint8; rosbags' store keeps `char` and would hash it as FIELD_TYPE_CHAR. Same
    bytes on the wire. Only ServiceEventInfo (in every service's event message) needs it."""
    consts, fields = store.fielddefs[typename]
    fixed = []
    for fname, (node, spec) in fields:
        if isinstance(spec, tuple) and spec and isinstance(spec[0], tuple):
            (inner_node, (base, size)), count = spec
            if base == "char":
                spec = ((inner_node, ("uint8", size)), count)
        fixed.append((fname, (node, spec)))
    store.fielddefs[typename] = (consts, fixed)
    store.cache.clear()


def _service_types(name: str, request: str, response: str) -> dict:
    from rosbags.typesys import get_types_from_msg
    from rosbags.typesys.store import Nodetype

    def one(text: str, typename: str):
        ((_, definition),) = get_types_from_msg(text, typename).items()
        return definition

    req, res, event = name + "_Request", name + "_Response", name + "_Event"
    return {
        req: one(request, req),
        res: one(response, res),
        event: (
            [],
            [
                ("info", (Nodetype.NAME, "service_msgs/msg/ServiceEventInfo")),
                ("request", (Nodetype.SEQUENCE, ((Nodetype.NAME, req), 1))),
                ("response", (Nodetype.SEQUENCE, ((Nodetype.NAME, res), 1))),
            ],
        ),
        name: (
            [],
            [
                ("request_message", (Nodetype.NAME, req)),
                ("response_message", (Nodetype.NAME, res)),
                ("event_message", (Nodetype.NAME, event)),
            ],
        ),
    }


def dds_type_name(typename: str) -> str:
    """`sensor_msgs/msg/PointCloud2` -> `sensor_msgs::msg::dds_::PointCloud2_`."""
    pkg, kind, name = typename.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def mangle(name: str) -> str:
    """A ROS name as one key segment: '/' -> '%'; the root namespace is '%'."""
    return "%" if name in ("", "/") else name.replace("/", "%")


def data_key(domain_id: int, name: str, typename: str, type_hash: str) -> str:
    return f"{domain_id}/{name.strip('/')}/{dds_type_name(typename)}/{type_hash}"


@dataclass(frozen=True)
class QoS:
    """The QoS smana's endpoints declare, in rmw_zenoh's token form (`qos_to_keyexpr`):
    `reliability:durability:history,depth:deadline s,ns:lifespan s,ns:liveliness,lease s,ns`,
    each policy as its rmw enum value and left empty when it equals rmw_zenoh's default
    (reliable, volatile, keep-last 42, infinite deadline, lifespan and lease, automatic)."""

    reliable: bool = True
    transient_local: bool = False
    depth: int = 10
    keep_all: bool = False

    def token(self) -> str:
        reliability = "" if self.reliable else "2"  # RMW_QOS_POLICY_RELIABILITY_BEST_EFFORT
        durability = "1" if self.transient_local else ""  # ..._DURABILITY_TRANSIENT_LOCAL
        history = "2" if self.keep_all else ""  # RMW_QOS_POLICY_HISTORY_KEEP_ALL
        depth = "" if self.depth == DEFAULT_DEPTH else str(self.depth)
        return f"{reliability}:{durability}:{history},{depth}:,:,:,,"


SENSOR_QOS = QoS(reliable=False, depth=5)
LATCHED_QOS = QoS(transient_local=True, depth=1)


def gid_of(token: str) -> bytes:
    """The gid rmw_zenoh_cpp gives the entity whose liveliness token is `token`: XXH3-128 of the
    token, low 64 bits then high 64 bits, little-endian (xxhash's digest is the canonical,
    big-endian form of the same 128-bit number)."""
    import xxhash

    return xxhash.xxh3_128_digest(token.encode())[::-1]


def attachment(seq: int, stamp_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's attachment: int64 sequence number, int64 source timestamp, the gid as a
    zenoh-ext byte sequence (LEB128 length, here always one byte: 16)."""
    if len(gid) != GID_SIZE:
        raise ValueError(f"a gid has {GID_SIZE} bytes, got {len(gid)}")
    return struct.pack("<qqB", seq, stamp_ns, GID_SIZE) + bytes(gid)


def parse_attachment(raw: bytes | None) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, gid); ValueError for anything else."""
    if raw is None or len(raw) != 17 + GID_SIZE or raw[16] != GID_SIZE:
        n = "none" if raw is None else f"{len(raw)} bytes"
        raise ValueError(f"not an rmw_zenoh attachment ({n}; expected {17 + GID_SIZE} bytes)")
    seq, stamp_ns = struct.unpack_from("<qq", raw)
    return seq, stamp_ns, bytes(raw[17:])


class RosNode:
    """One ROS 2 node on a zenoh session: its liveliness token and its endpoints' tokens, keys
    and gids. Receiving stays with the caller (a smana `Service` subscribes to `key` itself, so
    its books count ROS messages like any other); publishing goes through `RosPublisher`."""

    def __init__(
        self,
        session,
        types: RosTypes,
        domain_id: int,
        name: str,
        namespace: str,
        announce: bool = True,
    ):
        """`announce=False`: the endpoints' tokens wait for `announce()`, so that a ROS 2 client
        that sees a server's tokens finds its queryables and subscribers already declared
        (rmw_zenoh_cpp declares the zenoh entity first, then its token)."""
        self.session, self.types, self.domain_id = session, types, int(domain_id)
        self.name, self.namespace = name, namespace
        self.zid = str(session.zid())
        self.node_id = 0
        self._next_entity = 1
        self._declared: list = [session.liveliness().declare_token(self._prefix(0, NODE))]
        self._pending: list[str] | None = None if announce else []

    def _prefix(self, entity_id: int, kind: str) -> str:
        return (
            f"{ADMIN_SPACE}/{self.domain_id}/{self.zid}/{self.node_id}/{entity_id}/{kind}/%/"
            f"{mangle(self.namespace)}/{mangle(self.name)}"
        )

    def endpoint(self, kind: str, name: str, typename: str, qos: QoS = QoS()) -> tuple[str, int]:
        """Declare an endpoint's liveliness token (or hold it for `announce`); returns its data
        key and entity id."""
        key, entity_id, _ = self._endpoint(kind, name, typename, qos)
        return key, entity_id

    def _endpoint(self, kind: str, name: str, typename: str, qos: QoS) -> tuple[str, int, bytes]:
        entity_id = self._next_entity
        self._next_entity += 1
        type_hash = self.types.hash(typename)
        token = (
            f"{self._prefix(entity_id, kind)}/{mangle(name)}/{dds_type_name(typename)}/"
            f"{type_hash}/{qos.token()}"
        )
        if self._pending is None:
            self._declared.append(self.session.liveliness().declare_token(token))
        else:
            self._pending.append(token)
        return data_key(self.domain_id, name, typename, type_hash), entity_id, gid_of(token)

    def announce(self) -> int:
        """Declare the endpoints' tokens held back (`announce=False`), in the order their
        endpoints were made; endpoints made afterwards are announced at once. Returns how many."""
        pending, self._pending = self._pending or [], None
        for token in pending:
            self._declared.append(self.session.liveliness().declare_token(token))
        return len(pending)

    def publisher(self, topic: str, typename: str, qos: QoS = QoS()) -> RosPublisher:
        import zenoh
        from zenoh import ext

        key, _, gid = self._endpoint(PUBLISHER, topic, typename, qos)
        block = qos.reliable and qos.keep_all
        options = {
            "congestion_control": zenoh.CongestionControl.BLOCK
            if block
            else zenoh.CongestionControl.DROP,
            "reliability": zenoh.Reliability.RELIABLE
            if qos.reliable
            else zenoh.Reliability.BEST_EFFORT,
        }
        if not qos.transient_local:
            # rmw_zenoh_cpp declares an AdvancedPublisher without cache or heartbeat here: on
            # the wire, a plain publisher.
            zpub = self.session.declare_publisher(key, **options)
        else:
            options["cache"] = ext.CacheConfig(max_samples=qos.depth)
            options["publisher_detection"] = True
            if qos.reliable:
                options["sample_miss_detection"] = ext.MissDetectionConfig(
                    heartbeat=None, sporadic_heartbeat=HEARTBEAT_PERIOD_S
                )
            zpub = ext.declare_advanced_publisher(self.session, key, **options)
        self._declared.append(zpub)
        return RosPublisher(self.types, zpub, typename, gid)

    def reply_attachment(self, request_attachment: bytes | None) -> bytes:
        """The attachment of a service reply: the request's sequence number and client gid, the
        reply's own timestamp."""
        seq, _, gid = parse_attachment(request_attachment)
        return attachment(seq, time.time_ns(), gid)

    def close(self) -> None:
        for d in reversed(self._declared):
            try:
                d.undeclare()
            except Exception:  # noqa: BLE001 - the session may already be closing
                pass
        self._declared.clear()


class RosPublisher:
    """Serialises a message to CDR and puts it with rmw_zenoh's attachment."""

    def __init__(self, types: RosTypes, zpub, typename: str, gid: bytes):
        self.types, self._zpub, self.typename, self.gid = types, zpub, typename, gid
        self.seq = 0
        self.key = str(zpub.key_expr)

    def put(self, msg) -> int:
        """Publish; returns the payload's size in bytes."""
        self.seq += 1
        payload = self.types.serialize(msg, self.typename)
        self._zpub.put(payload, attachment=attachment(self.seq, time.time_ns(), self.gid))
        return len(payload)
