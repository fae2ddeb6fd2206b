"""The service as a node of rmw_zenoh's ROS 2 graph: liveliness tokens, publisher gids, discovery.

rmw_zenoh builds the graph (``ros2 node list``, ``ros2 topic list``, matched publisher and subscription
counts) from liveliness tokens only, laid out as in rmw_zenoh_cpp/src/detail/liveliness_utils.cpp:

  @ros2_lv/<domain>/<zid>/<nid>/<id>/<NN|MP|MS>/<enclave>/<namespace>/<node>[/<topic>/<type>/<hash>/<qos>]

with each '/' inside a name written as '%'. An entity's gid is the XXH3-128 of its token string (low 64
bits first, both little-endian); publishers send it in every sample's attachment.

The service declares one node per (zenoh namespace, domain) it meets, a publisher token (MP) for each ROS
output, a best-effort subscription token (MS) for every camera publisher whose topic matches a
``ros_inputs`` key (image_transport publishers send only while they count a subscriber), and a subscription
token with tf2_ros's listener QoS for every /tf and /tf_static publisher a grid's rmw_zenoh tf key matches (so
``ros2 topic info`` lists the service among their subscribers).
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any, Literal

import zenoh
from gcdtrav.schemas.inputs import RejectedInput
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.bus.entities import undeclare_all
from gcdtrav.service.ros import cdr as ros_io
from gcdtrav.service.ros.tf import TF_MESSAGE
from zenoh.ext import Int64, UInt8, z_serialize

log = logging.getLogger("gcdtrav.service")

ADMIN_SPACE = "@ros2_lv"
DEFAULT_DEPTH = 42  # rmw_zenoh's depth for KEEP_LAST with depth 0 (rmw_zenoh_cpp/src/detail/qos.cpp)
EntityKind = Literal["NN", "MP", "MS"]
KINDS = ("NN", "MP", "MS", "SS", "SC")


def mangle(name: str) -> str:
    return name.replace("/", "%")


def rmw_attachment(sequence: int, timestamp_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's attachment (since Jazzy 0.2.4, Humble 0.1.2, Rolling 0.6.0): sequence number, source
    timestamp in ns, the publisher's 16-byte gid, serialised as zenoh-ext does (int64, int64, sequence)."""
    return z_serialize((Int64(sequence), Int64(timestamp_ns), [UInt8(b) for b in gid])).to_bytes()


@dataclass(frozen=True)
class Qos:
    """The QoS fields the service uses; history is always KEEP_LAST, deadline/lifespan/liveliness default."""

    reliable: bool = True
    transient_local: bool = False
    depth: int = 10

    def keyexpr(self) -> str:
        """rmw_zenoh's qos_to_keyexpr: only what differs from its defaults (reliable, volatile, keep-last 42).

        <reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,<s>,<ns>
        with RELIABLE=1, BEST_EFFORT=2, TRANSIENT_LOCAL=1, VOLATILE=2 (rmw/types.h).
        """
        reliability = "" if self.reliable else "2"
        durability = "1" if self.transient_local else ""
        depth = "" if self.depth == DEFAULT_DEPTH else str(self.depth)
        return f"{reliability}:{durability}:,{depth}:,:,:,,"


IMAGE_QOS = Qos()  # rclcpp's default publisher profile: reliable, volatile, keep-last 10
GRID_QOS = Qos(transient_local=True, depth=1)  # a map: late joiners get the last one
CAMERA_SUBSCRIPTION_QOS = Qos(reliable=False, depth=1)  # matches best-effort and reliable cameras alike
TF_QOS = Qos(depth=100)  # tf2_ros DynamicListenerQoS: reliable, volatile, keep-last 100
TF_STATIC_QOS = Qos(transient_local=True, depth=100)  # tf2_ros StaticListenerQoS: transient local, keep-last 100


@dataclass(frozen=True)
class GraphInput:
    """A key the service subscribes to in rmw_zenoh's layout, and the QoS its subscription tokens carry."""

    key: str  # with the zenoh namespace, e.g. robot1/*/tf/tf2_msgs::msg::dds_::TFMessage_/*
    zenoh_namespace: str
    qos: Qos


def tf_graph_input(key: str, qos: Qos) -> GraphInput | None:
    """A grid's tf key as a graph input, if in rmw_zenoh's layout ([<zenoh ns>/]<domain>/<topic>/TFMessage type/
    <hash>, the domain a number or '*'); None for zenoh-bridge-ros2dds's plain 'tf', which has no tokens."""
    parts = key.split("/")
    if len(parts) < 4 or parts[-2] != ros_io.dds_type_name(TF_MESSAGE):
        return None
    domain = next((i for i, part in enumerate(parts[:-3]) if part.isdigit() or part == "*"), None)
    return None if domain is None else GraphInput(key, "/".join(parts[:domain]), qos)


def graph_inputs(settings: ServiceSettings) -> list[GraphInput]:
    """The grids' tf keys (first: a key that also matches a camera input gets tf's QoS), then the rmw_zenoh
    camera inputs."""
    found: list[GraphInput] = []
    for grid in settings.grids:
        if grid.tf is not None:
            for key, qos in ((grid.tf.tf_static_key, TF_STATIC_QOS), (grid.tf.tf_key, TF_QOS)):
                tf_input = tf_graph_input(key, qos)
                if tf_input is not None and tf_input not in found:
                    found.append(tf_input)
    cameras = [i for i in settings.ros_inputs if i.layout == "rmw_zenoh"]
    return found + [GraphInput(i.key, i.zenoh_namespace, CAMERA_SUBSCRIPTION_QOS) for i in cameras]


@dataclass(frozen=True)
class NodeName:
    domain: int
    namespace: str  # ROS namespace, "/" for none
    name: str
    enclave: str = "/"


@dataclass(frozen=True)
class TopicInfo:
    name: str  # /camera/front/image_raw
    dds_type: str  # sensor_msgs::msg::dds_::Image_
    type_hash: str  # RIHS01_... or TypeHashNotSupported
    qos: Qos

    @staticmethod
    def of(topic: ros_io.RosTopic, qos: Qos) -> TopicInfo:
        assert topic.msgtype is not None
        hash_chunk = topic.type_hash or ros_io.type_hash(topic.msgtype)
        return TopicInfo(topic.topic, ros_io.dds_type_name(topic.msgtype), hash_chunk, qos)


@dataclass(frozen=True)
class Entity:
    zid: str
    nid: int
    id: int
    kind: EntityKind
    node: NodeName
    topic: TopicInfo | None = None

    @property
    def token(self) -> str:
        """The liveliness key, as rmw_zenoh's Entity constructor writes it (before any zenoh namespace)."""
        node = self.node
        parts = [ADMIN_SPACE, str(node.domain), self.zid, str(self.nid), str(self.id), self.kind]
        parts += [mangle(node.enclave), mangle(node.namespace), mangle(node.name)]
        if self.topic is not None:
            topic = self.topic
            parts += [mangle(topic.name), mangle(topic.dds_type), mangle(topic.type_hash), topic.qos.keyexpr()]
        return "/".join(parts)

    @property
    def gid(self) -> bytes:
        return entity_gid(self.token)


def entity_gid(token: str) -> bytes:
    """XXH3-128 of the token: the low 64 bits then the high 64 bits, each little-endian (a memcpy on x86)."""
    import xxhash

    return int(xxhash.xxh3_128_intdigest(token.encode())).to_bytes(16, "little")


@dataclass(frozen=True)
class PeerPublisher:
    """A publisher token seen on the graph."""

    domain: int
    zid: str
    topic: str
    dds_type: str
    type_hash: str


def parse_publisher_token(key: str) -> PeerPublisher | None:
    """A publisher's token (MP); None for another entity's. Raises RejectedInput for a malformed token."""
    parts = key.split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE or parts[5] not in KINDS or not all(parts) or not parts[1].isdigit():
        raise RejectedInput("bad_graph_token", f"'{key[:200]}' is not an rmw_zenoh liveliness token")
    if parts[5] != "MP":
        return None
    if len(parts) != 13:
        raise RejectedInput("bad_graph_token", f"publisher token '{key[:200]}' has {len(parts)} of 13 parts")
    return PeerPublisher(int(parts[1]), parts[2], parts[9].replace("%", "/"), parts[10], parts[11].replace("%", "/"))


def with_namespace(namespace: str, key: str) -> str:
    return f"{namespace}/{key}" if namespace else key


class RosPublisher:
    """One ROS output: a zenoh publisher on the topic's key, its MP token, and rmw_zenoh's attachment."""

    def __init__(self, key: str, publisher: Any, entity: Entity, token: zenoh.LivelinessToken) -> None:
        self.key, self.publisher, self.entity, self.token = key, publisher, entity, token
        self.gid = entity.gid
        self.sequence = 0

    def put(self, payload: bytes) -> None:
        self.sequence += 1  # rmw_zenoh's first sample is 1
        self.publisher.put(payload, attachment=rmw_attachment(self.sequence, time.time_ns(), self.gid))

    def close(self) -> None:
        undeclare_all((self.token, self.publisher))


class RosGraph:
    """The service's nodes, publishers and camera subscriptions in the ROS graph; thread-safe."""

    def __init__(
        self, session: zenoh.Session, settings: ServiceSettings, rejected: Callable[[str | None, str, str], None]
    ) -> None:
        self.session = session
        self.settings = settings
        self.rejected = rejected  # counts a malformed graph token like any bad input
        self.zid = str(session.info.zid())
        self._lock = threading.Lock()
        self._ids = itertools.count()  # one counter for nodes and entities, as rmw_zenoh's context
        self._nodes: dict[tuple[str, int], Entity] = {}
        self._tokens: dict[str, zenoh.LivelinessToken] = {}  # declared key -> token
        self._publishers: dict[str, RosPublisher] = {}  # data key -> publisher
        self._subscriptions: dict[tuple[str, TopicInfo, int], tuple[Entity, set[str]]] = {}
        self._watchers: list[Any] = []
        self._closed = False
        self.inputs = graph_inputs(settings)
        self._input_keys = [(i, zenoh.KeyExpr(i.key)) for i in self.inputs]

    # ---- lifecycle -----------------------------------------------------------------------------------
    def start(self) -> None:
        """Node tokens for the inputs' literal domains, and discovery of camera and tf publishers."""
        watched: set[str] = set()
        for ros_input in self.inputs:
            domain = ros_io.strip_namespace(ros_input.key, ros_input.zenoh_namespace).split("/")[0]
            if domain.isdigit():
                self.node(ros_input.zenoh_namespace, int(domain))
            expression = with_namespace(
                ros_input.zenoh_namespace, f"{ADMIN_SPACE}/{domain if domain.isdigit() else '*'}/**"
            )
            if expression not in watched:
                watched.add(expression)
                handler = partial(self._on_token, zenoh_namespace=ros_input.zenoh_namespace)
                self._watchers.append(self.session.liveliness().declare_subscriber(expression, handler, history=True))

    def close(self) -> None:
        with self._lock:
            self._closed = True
            watchers, self._watchers = self._watchers, []
            publishers, self._publishers = list(self._publishers.values()), {}
            tokens, self._tokens = list(self._tokens.values()), {}
            self._subscriptions.clear()
            self._nodes.clear()
        undeclare_all([*watchers, *tokens])
        for publisher in publishers:
            publisher.close()

    def forget(self, keys: set[str]) -> None:
        """Undeclare the publishers (and their tokens) of a source the service no longer tracks."""
        with self._lock:
            publishers = [self._publishers.pop(key) for key in keys if key in self._publishers]
        for publisher in publishers:
            publisher.close()

    # ---- entities ------------------------------------------------------------------------------------
    def node(self, zenoh_namespace: str, domain: int) -> Entity:
        with self._lock:
            return self._node(zenoh_namespace, domain)

    def _node(self, zenoh_namespace: str, domain: int) -> Entity:
        node = self._nodes.get((zenoh_namespace, domain))
        if node is None:
            settings = self.settings.ros_node
            name = NodeName(domain, settings.namespace, settings.name)
            node_id = next(self._ids)
            node = Entity(self.zid, node_id, node_id, "NN", name)
            self._nodes[(zenoh_namespace, domain)] = node
            self._declare_kept(zenoh_namespace, node)
        return node

    def _declare(self, zenoh_namespace: str, entity: Entity) -> zenoh.LivelinessToken:
        return self.session.liveliness().declare_token(with_namespace(zenoh_namespace, entity.token))

    def _declare_kept(self, zenoh_namespace: str, entity: Entity) -> None:
        """A node's or subscription's token, kept here until undeclared or closed."""
        self._tokens[with_namespace(zenoh_namespace, entity.token)] = self._declare(zenoh_namespace, entity)

    def _undeclare(self, zenoh_namespace: str, entity: Entity) -> None:
        token = self._tokens.pop(with_namespace(zenoh_namespace, entity.token), None)
        if token is not None:
            token.undeclare()

    def publisher(self, topic: ros_io.RosTopic, qos: Qos, encoding: zenoh.Encoding) -> RosPublisher:
        """The publisher of an rmw_zenoh output topic, declared (with its MP token) on first use."""
        key = ros_io.topic_key(topic)
        with self._lock:
            existing = self._publishers.get(key)
            if existing is not None:
                return existing
            if self._closed:
                raise RuntimeError("the ROS graph is closed")
            node = self._node(topic.namespace, topic.domain)
            entity = Entity(self.zid, node.nid, next(self._ids), "MP", node.node, TopicInfo.of(topic, qos))
            declared = self._declare_publisher(key, qos, encoding)
            publisher = RosPublisher(key, declared, entity, self._declare(topic.namespace, entity))
            self._publishers[key] = publisher
            return publisher

    def _declare_publisher(self, key: str, qos: Qos, encoding: zenoh.Encoding) -> Any:
        if not qos.transient_local:
            return self.session.declare_publisher(
                key, encoding=encoding, congestion_control=zenoh.CongestionControl.DROP
            )
        # What rmw_zenoh declares for a transient-local publisher (rmw_publisher_data.cpp): an advanced
        # publisher that caches the last `depth` samples, is detectable through liveliness (so subscribers
        # joining later query its cache) and, being reliable, sends sporadic heartbeats every 0.5 s.
        from zenoh import ext

        return ext.declare_advanced_publisher(
            self.session,
            key,
            encoding=encoding,
            congestion_control=zenoh.CongestionControl.DROP,
            cache=ext.CacheConfig(qos.depth),
            sample_miss_detection=ext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=0.5),
            publisher_detection=True,
        )

    # ---- discovery -----------------------------------------------------------------------------------
    def _on_token(self, sample: zenoh.Sample, zenoh_namespace: str) -> None:
        """A camera's (or tf's) publisher token came or went: subscribe while one matching an input lives."""
        key = str(sample.key_expr)
        try:
            peer = parse_publisher_token(ros_io.strip_namespace(key, zenoh_namespace))
        except RejectedInput as err:
            self.rejected(None, err.reason, err.detail)
            return
        if peer is None or peer.zid == self.zid or ros_io.ros_type_name(peer.dds_type) is None:
            return
        data_key = with_namespace(
            zenoh_namespace, f"{peer.domain}/{peer.topic.strip('/')}/{peer.dds_type}/{peer.type_hash}"
        )
        matched = next(
            (i for i, k in self._input_keys if i.zenoh_namespace == zenoh_namespace and k.intersects(data_key)), None
        )
        if matched is None or ros_io.is_output_topic(peer.topic, self.settings.ros_output.topic_templates()):
            return
        topic = TopicInfo(peer.topic, peer.dds_type, peer.type_hash, matched.qos)
        try:
            if sample.kind == zenoh.SampleKind.PUT:
                self._publisher_appeared(zenoh_namespace, peer.domain, topic, key)
            else:
                self._publisher_left(zenoh_namespace, peer.domain, topic, key)
        except zenoh.ZError as err:
            log.warning("ROS graph: subscription token for %s not changed: %s", peer.topic, err)

    def _publisher_appeared(self, zenoh_namespace: str, domain: int, topic: TopicInfo, publisher_token: str) -> None:
        with self._lock:
            if self._closed:
                return
            entry = self._subscriptions.get((zenoh_namespace, topic, domain))
            if entry is None:
                node = self._node(zenoh_namespace, domain)
                entity = Entity(self.zid, node.nid, next(self._ids), "MS", node.node, topic)
                self._declare_kept(zenoh_namespace, entity)
                entry = (entity, set())
                self._subscriptions[(zenoh_namespace, topic, domain)] = entry
                log.info("ROS graph: subscribed to %s (%s, %s)", topic.name, topic.dds_type, topic.type_hash)
            entry[1].add(publisher_token)

    def _publisher_left(self, zenoh_namespace: str, domain: int, topic: TopicInfo, publisher_token: str) -> None:
        with self._lock:
            entry = self._subscriptions.get((zenoh_namespace, topic, domain))
            if entry is None:
                return
            entry[1].discard(publisher_token)
            if not entry[1]:
                del self._subscriptions[(zenoh_namespace, topic, domain)]
                self._undeclare(zenoh_namespace, entry[0])
                log.info("ROS graph: %s has no publisher left, unsubscribed", topic.name)
