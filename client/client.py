"""TraversabilityClient: publish images, receive maps, query distributions, manage the anchor set.

No torch: robots and planners install only the base package.
"""

from __future__ import annotations

import contextlib
import json
import math
import queue
import threading
import time
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
import zenoh
from gcdtrav.client.freshness import FreshnessWatch, Staleness
from gcdtrav.client.session.source_info import put_identified
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.experience import (
    AnchorProposal,
    AnswerReply,
    CalibrationReport,
    ExclusionList,
    ExclusionRequest,
    OperatorAnswer,
    OperatorQuestion,
    PlannedPath,
    StoreContents,
    TraversalOutcome,
)
from gcdtrav.schemas.grid_layers import decode_layers
from gcdtrav.schemas.images import decode_map_png8, decode_map_png16, encode_jpeg, encode_png, peek_image_size
from gcdtrav.schemas.keys import Keys, input_key
from gcdtrav.schemas.messages import (
    MSGPACK_ENCODING,
    AnchorHistoryEntry,
    AnchorHistoryReply,
    AnchorSetRejection,
    AnchorSetReply,
    CompactMapsMessage,
    ContextDistribution,
    CreditGrant,
    ErrorReply,
    GridHeader,
    GridMessage,
    ImageEnvelope,
    M,
    MapsHeader,
    MapsMessage,
    MessageError,
    PathReply,
    PixelEncoding,
    RelayHealth,
    ServiceStatus,
    peek_fields,
)
from numpy.typing import NDArray

DEFAULT_TIMEOUT_S = 5.0
FLEET_POLL_S = 0.1  # how often a rollback asks whether every instance holds the set yet
MSGPACK = zenoh.Encoding(MSGPACK_ENCODING)


class ServiceError(RuntimeError):
    """The service answered with an error; the message is the service's."""


class QueryTimeout(ServiceError):
    """No answer in time: the service is not running, not reachable, or busy."""


class AnchorSetRejected(ServiceError):
    """The service refused an anchor set; ``messages`` says why, the active set is unchanged."""

    def __init__(self, messages: list[str], active_version: str, instance: str | None = None) -> None:
        where = f" by {instance}" if instance else ""
        super().__init__(f"anchor set rejected{where}: " + "; ".join(messages))
        self.messages = messages
        self.active_version = active_version
        self.instance = instance


class ActivationLost(AnchorSetRejected):
    """Another set became active first while this swap expected the one it saw (compare-and-swap): ``winner``
    is that set's version; nothing was swapped."""

    def __init__(self, messages: list[str], winner: str, instance: str | None = None) -> None:
        super().__init__(messages, winner, instance)
        self.args = (f"lost to anchor set {winner}: " + "; ".join(messages),)
        self.winner = winner


class PartialSwap(ServiceError):
    """A swap some instances took and others refused or did not answer: ``swapped`` (instance -> version) and
    ``failed`` (instance -> error). They converge to the newest accepted set by themselves (the fleet's
    anchor tokens); the message names which instance holds what."""

    def __init__(self, version: str, swapped: dict[str, str], failed: dict[str, ServiceError]) -> None:
        held = "; ".join(f"{name}: {error}" for name, error in sorted(failed.items()))
        super().__init__(
            f"anchor set {version} active on {', '.join(sorted(swapped))}; not on the others: {held}. The "
            "others adopt it once they can (gcdtrav status shows each instance's set)"
        )
        self.version, self.swapped, self.failed = version, swapped, failed


@dataclass(frozen=True)
class Maps:
    """A decoded MapsMessage: T and U in [0, 1] as float32 at the decoder's resolution (1/65535 steps), or a
    decoded CompactMapsMessage (``compact``: 1/255 steps, at its header's ``map_shape``)."""

    header: MapsHeader
    traversability: NDArray[np.float32]
    uncertainty: NDArray[np.float32]
    traversability_full: NDArray[np.float32] | None = None
    uncertainty_full: NDArray[np.float32] | None = None
    compact: bool = False
    arrived_at: float | None = None  # this machine's clock when decoded (at receipt, in subscribe_maps)

    @classmethod
    def from_payload(cls, payload: bytes) -> Maps:
        message = MapsMessage.unpack(payload)
        return cls(
            arrived_at=time.time(),
            header=message.header,
            traversability=decode_map_png16(message.traversability_png),
            uncertainty=decode_map_png16(message.uncertainty_png),
            traversability_full=_optional_map(message.traversability_full_png),
            uncertainty_full=_optional_map(message.uncertainty_full_png),
        )

    @classmethod
    def from_compact_payload(cls, payload: bytes) -> Maps:
        message = CompactMapsMessage.unpack(payload)
        t, u = decode_map_png8(message.traversability_png), decode_map_png8(message.uncertainty_png)
        return cls(header=message.header, traversability=t, uncertainty=u, compact=True, arrived_at=time.time())

    @property
    def reused(self) -> bool:
        """Computed from an earlier frame whose view had not changed since (``header.computed_from``): the
        service published that frame's maps again for this one instead of inferring it."""
        return self.header.computed_from is not None

    @property
    def computed_stamp(self) -> float:
        """The capture stamp of the frame these maps were computed from: this frame's, unless reused."""
        computed = self.header.computed_from
        return self.header.stamp if computed is None else computed[0]

    @property
    def age_s(self) -> float:
        """How old the frame behind these maps is now, whatever the robot's, the service's and this machine's
        clocks read: its age when the service received it (``header.age_at_receipt_s``, judged by delay as the
        service judges frames), plus its time in the service (``published_at - received_at``, the service's
        clock), plus the time since these maps were decoded here (this clock). It leaves out the link's
        smallest delay and the maps' way here, tens of milliseconds on a LAN.

        From a service before 1.4 (no ``age_at_receipt_s``), or maps built by hand: now minus the capture
        stamp, exact on the robot that stamped the image and elsewhere only with clocks in step."""
        header = self.header
        if header.age_at_receipt_s is None or self.arrived_at is None:
            return time.time() - header.stamp
        return header.age_at_receipt_s + (header.published_at - header.received_at) + time.time() - self.arrived_at


@dataclass(frozen=True)
class Grid:
    """A decoded GridMessage: its ``layers`` by name (the table in schemas/grid_layers.py), those the writer
    sent. T and U per cell (NaN where unknown: never observed, or expired) and observation counts (0 where
    unknown) always; from 1.2 writers also the planner's layers, None from older ones:

    - ``cvar``: CVaR of T at ``header.alpha`` (the mean of its worst alpha), NaN where unknown;
    - ``p_below``: P(T < ``header.tau``), NaN where unknown;
    - ``match``: the fused match score (near 0: no anchor describes the ground), NaN where unknown;
    - ``age``: seconds from each cell's last observation to ``header.stamp`` (add ``header.age_s`` for its age
      when published), NaN where never observed; expired cells keep theirs.
    """

    header: GridHeader
    layers: Mapping[str, NDArray[Any]]

    @classmethod
    def from_payload(cls, payload: bytes) -> Grid:
        message = GridMessage.unpack(payload)
        return cls(message.header, decode_layers(message))

    @property
    def traversability(self) -> NDArray[np.float32]:
        return self.layers["traversability"]

    @property
    def uncertainty(self) -> NDArray[np.float32]:
        return self.layers["uncertainty"]

    @property
    def count(self) -> NDArray[np.int64]:
        return self.layers["count"]

    @property
    def cvar(self) -> NDArray[np.float32] | None:
        return self.layers.get("cvar")

    @property
    def p_below(self) -> NDArray[np.float32] | None:
        return self.layers.get("p_below")

    @property
    def match(self) -> NDArray[np.float32] | None:
        return self.layers.get("match")

    @property
    def age(self) -> NDArray[np.float32] | None:
        return self.layers.get("age")

    @property
    def speed(self) -> NDArray[np.float32] | None:
        """Fraction of the robot's maximum speed per cell, unknown cells included (docs/grid.md, "Speed from
        uncertainty"); None: the grid has no speed layer (or a writer before 1.5)."""
        return self.layers.get("speed")

    def planning_layers(self) -> dict[str, NDArray[np.float32]]:
        """The layers ``client.planning.plan`` reads (traversability, cvar, p_below), those the grid has."""
        found = {"traversability": self.traversability, "cvar": self.cvar, "p_below": self.p_below}
        return {name: values for name, values in found.items() if values is not None}

    @property
    def age_s(self) -> float:
        """Now minus the stamp of the last frame fused (the same clock assumption as ``Maps.age_s``)."""
        return time.time() - self.header.stamp

    def cell_index(self, x: float, y: float) -> tuple[int, int]:
        """(row, column) of the cell holding the point (x, y), metres in the grid's frame."""
        r = self.header.resolution
        return int((y - self.header.origin[1]) // r), int((x - self.header.origin[0]) // r)


R = TypeVar("R", AnchorHistoryReply, ServiceStatus)  # the replies every instance gives, each naming it
EARLY_END = 0.9  # a query that ended before this share of its timeout was ended by zenoh: nothing to ask
CLOCK_STEP_BACK_S = 10.0  # over the service's max_frame_age_s (5 s): no fresh frame is stamped this much older


ZENOH_TIMEOUT_ENCODINGS = ("zenoh/string", "zenoh/bytes")


def zenoh_timeout(err: zenoh.ReplyError | None) -> bool:
    """Zenoh's own error reply when a query's time runs out with a queryable reached but no answer yet (a busy
    service): "Timeout", as a zenoh string from the querying session's own timer, or with the default encoding
    from the routing of a session on the way (zenoh's dispatcher/queries.rs, QueryCleanup), whichever comes
    first. The service's own errors are msgpack or JSON, never that."""
    if err is None or err.payload.to_bytes() != b"Timeout":
        return False
    return str(err.encoding) in ZENOH_TIMEOUT_ENCODINGS


def no_reply_message(key: str, timeout: float, waited: float) -> str:
    """Why a query got nothing. Zenoh ends a query at once when nothing it can reach serves the key: then
    saying 'within 5 s' after a second would send the user looking for a slow service."""
    if waited < EARLY_END * timeout:
        return (
            f"nothing reachable answers on '{key}' (the query ended after {waited:.1f} s): is the gcdtrav service "
            "running, with this prefix, and reachable (zenoh flags -e/-m)?"
        )
    return f"no reply on '{key}' within {timeout:g} s: is the gcdtrav service running and reachable?"


class MapsOrder:
    """Per source, the order (``MapsHeader.order``) of the last map let through: a map not above it is older
    than what was shown, or the same frame again (two instances during a hand-over), and is held back.

    The order is the robot's stamp, so a robot clock that is off orders its maps all the same; one that steps
    back would hold them back until it caught up. A map stamped more than ``CLOCK_STEP_BACK_S`` before the
    last one shown yet received later by its service is such a step (a frame that much older would have been
    dropped stale): it is shown, and the source's order starts again from it."""

    def __init__(self) -> None:
        self._last: dict[str, tuple[float, float]] = {}
        self._stepped_at: dict[str, float] = {}  # receipt of the map after the source's last clock step
        self._lock = threading.Lock()
        self.held_back = 0

    def is_newer(self, header: MapsHeader) -> bool:
        order = header.order or (header.stamp, header.received_at)  # a 1.1 service: the same two fields
        with self._lock:
            last = self._last.get(header.source)
            stepped_back = last is not None and order[0] < last[0] - CLOCK_STEP_BACK_S and order[1] > last[1]
            before_step = order[1] < self._stepped_at.get(header.source, -math.inf)
            if last is not None and (order <= last or before_step) and not stepped_back:
                self.held_back += 1
                return False
            if stepped_back:
                self._stepped_at[header.source] = order[1]
            self._last[header.source] = order
            return True


class MapsFreshness:
    """A running ``TraversabilityClient.watch_freshness``: ``watch`` answers ``age_s(source)`` at any time."""

    def __init__(
        self,
        watch: FreshnessWatch,
        subscribers: list[zenoh.Subscriber[None]],
        on_change: Callable[[Staleness], None],
        period_s: float,
    ) -> None:
        self.watch, self._subscribers, self._on_change, self._period_s = watch, subscribers, on_change, period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="gcdtrav-freshness", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self._period_s):
            for change in self.watch.check():
                self._on_change(change)

    def reason(self, source: str) -> str | None:
        """Why the service gives ``source`` no maps, as it last said (a credit, or a relay's health), or None."""
        return self.watch.reason(source)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        for subscriber in self._subscribers:
            subscriber.undeclare()


def _optional_map(data: bytes | None) -> NDArray[np.float32] | None:
    return None if data is None else decode_map_png16(data)


def _risk_params(alpha: float | None, tau: float | None) -> dict[str, Any]:
    """The risk levels a query asks for; none given, the service's defaults apply."""
    return {name: repr(float(value)) for name, value in (("alpha", alpha), ("tau", tau)) if value is not None}


def _selector(key: str, params: Mapping[str, Any]) -> str:
    return key + ("?" + ";".join(f"{name}={value}" for name, value in params.items()) if params else "")


class TraversabilityClient:
    """Talks to a gcdtrav service. Give it an open zenoh session, or a config to open one it then owns."""

    def __init__(
        self,
        session: zenoh.Session | None = None,
        config: zenoh.Config | None = None,
        prefix: str = "gcdtrav",
        input_prefix: str = "gcdtrav/in",
        timeout: float = DEFAULT_TIMEOUT_S,
    ) -> None:
        self._owns_session = session is None
        self.session = session if session is not None else zenoh.open(config or zenoh.Config())
        self.prefix = prefix
        self.keys = Keys(prefix)
        self.input_prefix = input_prefix
        self.timeout = timeout
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._orders: list[MapsOrder] = []  # one per subscription: each delivers every source in order

    def close(self) -> None:
        for publisher in self._publishers.values():
            publisher.undeclare()
        self._publishers.clear()
        if self._owns_session:
            self.session.close()

    def __enter__(self) -> TraversabilityClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- images in -----------------------------------------------------------------------------------
    def publish_image(
        self,
        source: str,
        image: NDArray[np.uint8] | bytes,
        stamp: float | None = None,
        frame_id: str = "",
        compression: str | None = "jpeg",
        jpeg_quality: int = 90,
    ) -> None:
        """Send one image as source ``source`` (published on ``{input_prefix}/{source}``).

        ``image`` is an (H, W, 3) RGB or (H, W) mono uint8 array, or already-encoded JPEG/PNG bytes.
        Arrays are compressed (``compression`` 'jpeg' or 'png') or sent raw (None): raw is exact but large.
        """
        stamp = time.time() if stamp is None else stamp
        envelope = self._envelope(image, stamp, frame_id, compression, jpeg_quality)
        key = input_key(self.input_prefix, source)
        publisher = self._publishers.get(key)
        if publisher is None:
            publisher = self.session.declare_publisher(key, encoding=MSGPACK)
            self._publishers[key] = publisher
        put_identified(publisher, envelope.pack())  # lets the service cap the sources per publisher

    @staticmethod
    def _envelope(
        image: NDArray[np.uint8] | bytes, stamp: float, frame_id: str, compression: str | None, quality: int
    ) -> ImageEnvelope:
        if isinstance(image, bytes | bytearray | memoryview):
            data = bytes(image)
            kind = PixelEncoding.PNG if data[:4] == b"\x89PNG" else PixelEncoding.JPEG
            size = peek_image_size(data)
            if size is None:
                raise ValueError("image bytes must be a JPEG or PNG file")
            return ImageEnvelope(
                stamp=stamp, frame_id=frame_id, encoding=kind, width=size[0], height=size[1], data=data
            )
        array = np.asarray(image)
        if array.dtype != np.uint8 or not (array.ndim == 2 or (array.ndim == 3 and array.shape[2] == 3)):
            raise ValueError(f"expected an (H, W, 3) RGB or (H, W) uint8 array, got {array.dtype} {array.shape}")
        height, width = array.shape[:2]
        rgb = array if array.ndim == 3 else np.repeat(array[:, :, None], 3, axis=2)
        if compression == "jpeg":
            data, kind = encode_jpeg(rgb, quality), PixelEncoding.JPEG
        elif compression == "png":
            data, kind = encode_png(rgb), PixelEncoding.PNG
        elif compression is None:
            kind = PixelEncoding.RGB8 if array.ndim == 3 else PixelEncoding.MONO8
            data = np.ascontiguousarray(array).tobytes()
        else:
            raise ValueError(f"compression must be 'jpeg', 'png' or None, not {compression!r}")
        return ImageEnvelope(stamp=stamp, frame_id=frame_id, encoding=kind, width=width, height=height, data=data)

    # ---- maps out ------------------------------------------------------------------------------------
    def maps_key(self, selector: str = "**", compact: bool = False) -> str:
        return self.keys.maps8(selector) if compact else self.keys.maps(selector)

    def subscribe_maps(
        self,
        selector: str,
        callback: Callable[[Maps], None],
        on_error: Callable[[Exception], None] | None = None,
        compact: bool = False,
        in_order: bool = True,
    ) -> zenoh.Subscriber[None]:
        """Call ``callback`` with every decoded Maps of the matching sources ('**' = all, 'r1/*', ...).

        ``compact``: the 8-bit maps (``maps8``, a fraction of the bytes: for slow links; the service encodes
        them only while someone subscribes). ``in_order``: a map older than one already delivered for its
        source (a previous owner's, late, during a hand-over between instances) is held back and counted in
        ``maps_held_back``. Keep the returned subscriber; undeclare() it to stop.
        """
        decode = Maps.from_compact_payload if compact else Maps.from_payload

        order = self._new_order()

        def handle(sample: zenoh.Sample) -> None:
            try:
                maps = decode(sample.payload.to_bytes())
            except (MessageError, ValueError) as err:
                if on_error is not None:
                    on_error(err)
                return
            if not in_order or order.is_newer(maps.header):
                callback(maps)

        return self.session.declare_subscriber(self.maps_key(selector, compact), handle)

    def watch_freshness(
        self,
        sources: list[str],
        stale_after_s: float,
        on_change: Callable[[Staleness], None],
        compact: bool = False,
        period_s: float = 0.5,
    ) -> MapsFreshness:
        """Call ``on_change`` when the maps of a source go stale (none newer than ``stale_after_s``, by the
        clock assumption of ``Maps.age_s``; also when none came at all) and when they are fresh again: a robot
        slows down or stops. A stale change carries the ``reason`` the service gave for the source's frames
        (e.g. 'stale: captured 3600.0 s ago, ...'), heard from its credits (on the service's bus) or from a
        relay's health (on the robot's bus). ``close()`` the returned watcher to stop."""
        watch = FreshnessWatch(stale_after_s)
        for source in sources:
            watch.watch(source)

        def observe(sample: zenoh.Sample) -> None:
            source = self.keys.source_of(str(sample.key_expr), "maps8" if compact else "maps")
            if source is not None and source in sources:
                try:
                    stamp = peek_fields(sample.payload.to_bytes(), ("header",))["header"]["stamp"]
                    watch.observe(source, float(stamp))
                except (MessageError, KeyError, TypeError, ValueError):
                    return

        def hear_credit(sample: zenoh.Sample) -> None:
            source = self.keys.credit_source_of(str(sample.key_expr))
            if source in sources:
                with contextlib.suppress(MessageError):
                    watch.note_reason(source, CreditGrant.unpack(sample.payload.to_bytes()).problem)

        def hear_relay(sample: zenoh.Sample) -> None:
            with contextlib.suppress(MessageError):
                health = RelayHealth.unpack(sample.payload.to_bytes())
                if health.source in sources:
                    watch.note_reason(health.source, health.problem)

        # Each source's own keys, not **: a robot on the routers' identity endpoint may read only its own
        # (schemas/access.py), and a subscription to ** would be refused whole.
        subscribers = [
            subscriber
            for source in sources
            for subscriber in (
                self.session.declare_subscriber(self.maps_key(source, compact), observe),
                self.session.declare_subscriber(self.keys.credit(source), hear_credit),
                self.session.declare_subscriber(self.keys.relay_health(source), hear_relay),
            )
        ]
        return MapsFreshness(watch, subscribers, on_change, period_s)

    def iter_maps(self, selector: str = "**", timeout: float | None = None, limit: int | None = None) -> Iterator[Maps]:
        """Yield decoded maps as they arrive, each newer than the last of its source (``subscribe_maps``); stop
        after ``limit`` maps or ``timeout`` s without one."""
        inbox: queue.Queue[bytes] = queue.Queue(maxsize=64)

        def keep_newest(sample: zenoh.Sample) -> None:
            while True:
                try:
                    inbox.put_nowait(sample.payload.to_bytes())
                    return
                except queue.Full:  # a slow consumer loses the oldest maps, never blocks zenoh
                    with contextlib.suppress(queue.Empty):
                        inbox.get_nowait()

        subscriber = self.session.declare_subscriber(self.maps_key(selector), keep_newest)
        order = self._new_order()
        try:
            count = 0
            while limit is None or count < limit:
                try:
                    payload = inbox.get(timeout=timeout)
                except queue.Empty:
                    return
                maps = Maps.from_payload(payload)
                if order.is_newer(maps.header):
                    yield maps
                    count += 1
        finally:
            subscriber.undeclare()

    def _new_order(self) -> MapsOrder:
        order = MapsOrder()
        self._orders.append(order)
        return order

    @property
    def maps_held_back(self) -> int:
        """Maps not delivered by subscribe_maps or iter_maps because their source had shown a newer one."""
        return sum(order.held_back for order in self._orders)

    # ---- queries -------------------------------------------------------------------------------------
    def _replies(
        self,
        key: str,
        reply_type: type[M],
        params: Mapping[str, Any] | None = None,
        payload: bytes | None = None,
        timeout: float | None = None,
        every_instance: bool = False,
    ) -> tuple[list[M], list[ServiceError]]:
        """Answers and errors of the instances that replied; ``every_instance`` asks all of them."""
        timeout = self.timeout if timeout is None else timeout
        options: dict[str, Any] = {}
        if every_instance:  # all queryables, and no merging of replies that share a key
            options = {"target": zenoh.QueryTarget.ALL, "consolidation": zenoh.ConsolidationMode.NONE}
        started = time.monotonic()
        replies = self.session.get(_selector(key, params or {}), payload=payload, timeout=timeout, **options)
        answers: list[M] = []
        errors: list[ServiceError] = []
        for reply in replies:
            if reply.ok is not None:
                answers.append(reply_type.unpack(reply.ok.payload.to_bytes()))
                if not every_instance:
                    break
            elif not zenoh_timeout(reply.err):
                errors.append(self._error_from(reply.err.payload.to_bytes() if reply.err is not None else b"", key))
        if not answers and not errors:
            raise QueryTimeout(no_reply_message(key, timeout, time.monotonic() - started))
        return answers, errors

    def _query(
        self,
        key: str,
        reply_type: type[M],
        params: Mapping[str, Any] | None = None,
        payload: bytes | None = None,
        timeout: float | None = None,
    ) -> M:
        answers, errors = self._replies(key, reply_type, params, payload, timeout)
        if answers:
            return answers[0]
        raise errors[0]

    @staticmethod
    def _error_from(payload: bytes, key: str) -> ServiceError:
        try:
            rejection = AnchorSetRejection.unpack(payload)
            if rejection.lost_to is not None:
                return ActivationLost(rejection.errors, rejection.lost_to, rejection.instance)
            return AnchorSetRejected(rejection.errors, rejection.active_version, rejection.instance)
        except MessageError:
            pass
        try:
            return ServiceError(ErrorReply.unpack(payload).error)
        except MessageError:
            return ServiceError(f"error reply on '{key}': {payload[:200]!r}")

    def patch(
        self,
        source: str,
        x: float,
        y: float,
        seq: int | None = None,
        timeout: float | None = None,
        stamp: float | None = None,
        alpha: float | None = None,
        tau: float | None = None,
    ) -> ContextDistribution:
        """The context distribution under image pixel (x, y) of ``source``'s latest frame, or of the kept
        frame with sequence number ``seq`` or input ``stamp`` (e.g. a ROS header stamp, seconds). Its
        ``quantile`` and ``cvar`` are at level ``alpha``, ``p_below`` at ``tau`` (else the service's defaults)."""
        params: dict[str, Any] = {"x": x, "y": y}
        if stamp is not None:
            params["stamp"] = repr(float(stamp))
        return self._patch_query(source, params, seq, timeout, alpha, tau)

    def patch_by_index(
        self,
        source: str,
        i: int,
        j: int,
        seq: int | None = None,
        timeout: float | None = None,
        alpha: float | None = None,
        tau: float | None = None,
    ) -> ContextDistribution:
        """The same by the patch's place in the maps: row i, column j (a "cell" is always a ground-grid cell)."""
        return self._patch_query(source, {"i": i, "j": j}, seq, timeout, alpha, tau)

    def patch_cell(
        self, source: str, i: int, j: int, seq: int | None = None, timeout: float | None = None
    ) -> ContextDistribution:
        """Deprecated name of ``patch_by_index``."""
        warnings.warn("patch_cell is now patch_by_index", DeprecationWarning, stacklevel=2)
        return self.patch_by_index(source, i, j, seq, timeout)

    def region(
        self,
        source: str,
        x0: float,
        y0: float,
        x1: float,
        y1: float,
        seq: int | None = None,
        timeout: float | None = None,
        alpha: float | None = None,
        tau: float | None = None,
    ) -> ContextDistribution:
        """The distribution pooled over a box of image pixels (mean of its patch weights)."""
        return self._patch_query(source, {"region": f"{x0},{y0},{x1},{y1}"}, seq, timeout, alpha, tau)

    def cell(
        self,
        source: str,
        x: float,
        y: float,
        timeout: float | None = None,
        alpha: float | None = None,
        tau: float | None = None,
    ) -> ContextDistribution:
        """The fused distribution of the ground-grid cell at (x, y), metres in the grid's frame."""
        params = {"x": x, "y": y} | _risk_params(alpha, tau)
        return self._query(self.keys.cell(source), ContextDistribution, params, timeout=timeout)

    def path(
        self,
        source: str,
        points: list[tuple[float, float]],
        timeout: float | None = None,
        alpha: float | None = None,
        tau: float | None = None,
    ) -> PathReply:
        """The known cells along a polyline (metres), with the indices of the lowest T, highest U and lowest
        CVaR, and the probability that some cell is below ``tau``."""
        text = ";".join(f"{x!r},{y!r}" for x, y in points)
        params = {"path": text} | _risk_params(alpha, tau)
        return self._query(self.keys.cell(source), PathReply, params, timeout=timeout)

    def subscribe_grid(self, selector: str, callback: Callable[[Grid], None]) -> zenoh.Subscriber[None]:
        """Call ``callback`` with every decoded ground grid of the matching sources."""
        return self.session.declare_subscriber(
            self.keys.grid(selector), lambda sample: callback(Grid.from_payload(sample.payload.to_bytes()))
        )

    def _patch_query(
        self,
        source: str,
        params: dict[str, Any],
        seq: int | None,
        timeout: float | None,
        alpha: float | None = None,
        tau: float | None = None,
    ) -> ContextDistribution:
        if seq is not None:
            params["seq"] = seq
        params |= _risk_params(alpha, tau)
        return self._query(self.keys.patch(source), ContextDistribution, params, timeout=timeout)

    def anchors(self, timeout: float | None = None) -> AnchorSetReply:
        return self._query(self.keys.anchors, AnchorSetReply, timeout=timeout)

    def set_anchors(
        self,
        anchor_set: AnchorSet | Mapping[str, Any] | str,
        timeout: float | None = None,
        expected_version: str | None = None,
    ) -> str:
        """Swap the service's anchor set; returns the new version or raises AnchorSetRejected.
        ``expected_version``: swap only if that set is still the active one (the one the caller reviewed the
        change against): of two callers swapping at once one wins, the other gets ActivationLost naming the
        winner. Services before 1.5 (no ``accepted_at`` in their AnchorSetReply) refuse it as a parameter."""
        if isinstance(anchor_set, AnchorSet):
            text = anchor_set.to_json()
        else:
            text = anchor_set if isinstance(anchor_set, str) else json.dumps(dict(anchor_set))
        # Every instance of the prefix swaps, so that all sources use the same set.
        params = {"expected": expected_version} if expected_version else None
        answers, errors = self._replies(
            self.keys.anchors,
            AnchorSetReply,
            params,
            payload=text.encode("utf-8"),
            timeout=timeout,
            every_instance=True,
        )
        return self._swapped(answers, errors)

    @staticmethod
    def _swapped(answers: list[AnchorSetReply], errors: list[ServiceError]) -> str:
        """The version every instance swapped to; the lost race (ActivationLost) or the first refusal when
        none did; PartialSwap when some did and others not."""
        if errors and not answers:
            raise next((error for error in errors if isinstance(error, ActivationLost)), errors[0])
        if errors:
            swapped = {answer.instance or f"instance {k + 1}": answer.version for k, answer in enumerate(answers)}
            failed = {getattr(error, "instance", None) or f"unnamed {k + 1}": error for k, error in enumerate(errors)}
            raise PartialSwap(answers[0].version, swapped, failed)
        return answers[0].version

    def apply_proposal(
        self, version: str, force: bool = False, expected_version: str | None = None, timeout: float | None = None
    ) -> str:
        """Apply the proposal kept in the store under its proposed ``version`` (``anchor_proposal().kept``):
        exactly the set that was reviewed, never a refit; only while the set it was judged against is active
        (or ``expected_version``), and only if judged better unless ``force`` (then marked forced in the
        history). Every instance is asked; an instance whose own store lacks it adopts it from the one that
        applied it, and this waits (up to ``timeout``) until every instance holds it."""
        params: dict[str, Any] = {"proposal": version} | ({"force": "true"} if force else {})
        if expected_version:
            params["expected"] = expected_version
        answers, errors = self._replies(self.keys.anchors, AnchorSetReply, params, timeout=timeout, every_instance=True)
        if not answers:
            raise next((error for error in errors if isinstance(error, ActivationLost)), errors[0])
        self._await_fleet_on(answers[0].version, self.timeout if timeout is None else timeout)
        return answers[0].version

    def anchor_history(self, timeout: float | None = None) -> list[AnchorHistoryReply]:
        """Every instance's last accepted anchor sets, newest (the active one) first."""
        return self._every_instance(self.keys.anchor_history, AnchorHistoryReply, timeout)

    def rollback(self, steps: int = 1, timeout: float | None = None) -> tuple[AnchorHistoryEntry, AnchorSetReply]:
        """Roll the fleet back ``steps`` sets: the server's rollback, asked of the instance whose active set is
        the fleet's newest (instances' histories may differ: one may have joined later); the others adopt the
        set it then announces, and this waits (up to ``timeout``) until every instance holds it. Returns the
        entry that was active and the reply naming the set now active; raises ``PartialSwap`` if some
        instance does not hold it in time, ``AnchorSetRejected`` if there is no set that far back."""
        histories = [history for history in self.anchor_history(timeout) if history.entries]
        if not histories:
            raise ServiceError("no instance answered with an anchor history")
        newest = max(histories, key=lambda h: (h.entries[0].accepted_at, h.entries[0].version, h.instance))
        params: dict[str, Any] = {"steps": steps, "instance": newest.instance}
        if newest.entries[0].how is not None:  # a 1.5 service: roll back only from the set shown (compare-and-swap)
            params["expected"] = newest.entries[0].version
        answers, errors = self._replies(
            self.keys.anchor_rollback, AnchorSetReply, params, timeout=timeout, every_instance=True
        )
        if not answers:
            raise errors[0]
        self._await_fleet_on(answers[0].version, self.timeout if timeout is None else timeout)
        return newest.entries[0], answers[0]

    def rollback_anchors(self, steps: int = 1, timeout: float | None = None) -> str:
        """Swap the whole fleet back to the set ``steps`` before the fleet's active one (``rollback``);
        returns the version now active everywhere."""
        return self.rollback(steps, timeout)[1].version

    def _await_fleet_on(self, version: str, timeout: float) -> None:
        """Until every instance that answers its status holds ``version``; PartialSwap after ``timeout``."""
        deadline = time.monotonic() + timeout
        while True:
            held = {status.instance: status.anchor_set_version for status in self.statuses(timeout)}
            behind = {name: held_version for name, held_version in held.items() if held_version != version}
            if not behind:
                return
            if time.monotonic() >= deadline:
                swapped = {name: version for name in held if name not in behind}
                failed = {name: ServiceError(f"still on {held_version}") for name, held_version in behind.items()}
                raise PartialSwap(version, swapped, failed)
            time.sleep(FLEET_POLL_S)

    def status(self, timeout: float | None = None) -> ServiceStatus:
        """The nearest instance's status; ``statuses()`` gives every instance's."""
        return self._query(self.keys.status, ServiceStatus, timeout=timeout)

    def statuses(self, timeout: float | None = None) -> list[ServiceStatus]:
        """The status of every live instance that answers within ``timeout``."""
        return self._every_instance(self.keys.status, ServiceStatus, timeout)

    def _every_instance(self, key: str, reply_type: type[R], timeout: float | None) -> list[R]:
        """Every instance's answer, by instance name; the first error when none answered."""
        answers, errors = self._replies(key, reply_type, timeout=timeout, every_instance=True)
        if not answers and errors:
            raise errors[0]
        return sorted(answers, key=lambda answer: answer.instance)

    # ---- experience (docs/calibration.md) ------------------------------------------------------------
    def publish_outcome(self, source: str, outcome: TraversalOutcome) -> None:
        """How driving over a place went, for the grid ``source`` (a service with experience enabled)."""
        self.session.put(self.keys.outcome(source), outcome.pack(), encoding=MSGPACK)

    def publish_planned_path(
        self, source: str, points: Sequence[tuple[float, float]], stamp: float | None = None, frame_id: str = "odom"
    ) -> None:
        """The path ``source`` will drive, (x, y) metres in its grid's frame: the service's questions (``ask:``)
        look along it instead of the heading while it is renewed within ``ask.path_timeout_s``; [] clears it."""
        path = PlannedPath(stamp=time.time() if stamp is None else stamp, frame_id=frame_id, points=list(points))
        self.session.put(self.keys.planned_path(source), path.pack(), encoding=MSGPACK)

    def calibration(
        self, source: str, timeout: float | None = None, by_source: bool = False, window: str = "all"
    ) -> CalibrationReport:
        """The active anchor set graded by the fleet's stored outcomes of the grid ``source``'s concept tuple;
        ``by_source``: each source's (robot's) figures too; ``window``: all, or the pairs of the last day or hour
        (a service before 1.7 knows only all)."""
        params = {"by_source": "true"} if by_source else {}
        if window != "all":
            params["window"] = window
        return self._query(self.keys.calibration(source), CalibrationReport, params or None, timeout=timeout)

    def anchor_proposal(self, source: str | None = None, timeout: float | None = None) -> AnchorProposal:
        """An anchor set fitted on the experience (of ``source``'s grid; default the service's), never applied:
        ``set_anchors(proposal.proposed)`` applies it."""
        params = {"source": source} if source else None
        return self._query(self.keys.anchor_proposal, AnchorProposal, params, timeout=timeout)

    def answer(
        self, source: str, question_id: str, score: float, operator: str = "", timeout: float | None = None
    ) -> AnswerReply:
        """Answer an OperatorQuestion: ``score`` 1 drivable, 0 blocked; its cells become operator outcomes."""
        answer = OperatorAnswer(id=question_id, source=source, score=score, operator=operator)
        return self._query(self.keys.answer(source), AnswerReply, payload=answer.pack(), timeout=timeout)

    def exclusions(
        self,
        robot: str | None = None,
        excluded: bool = True,
        actor: str = "",
        reason: str = "",
        timeout: float | None = None,
    ) -> ExclusionList:
        """The robots whose pairs calibration and fits leave out; with ``robot``, first exclude it (or include
        it again, ``excluded=False``), recorded in the fleet's store with ``actor`` and ``reason``."""
        request = None if robot is None else ExclusionRequest(robot=robot, excluded=excluded, actor=actor,
                                                              reason=reason)  # fmt: skip
        payload = request.pack() if request is not None else None
        return self._query(self.keys.exclusions, ExclusionList, payload=payload, timeout=timeout)

    def kept(self, timeout: float | None = None) -> StoreContents:
        """What the fleet's store keeps: each source's raw pairs (oldest, newest, bytes), the calibration sums."""
        return self._query(self.keys.kept, StoreContents, timeout=timeout)

    def question(self, source: str, timeout: float | None = None) -> OperatorQuestion:
        """The open OperatorQuestion about the grid ``source``, crop included; ServiceError when none is open."""
        return self._query(self.keys.question(source), OperatorQuestion, timeout=timeout)

    def subscribe_questions(
        self, selector: str, callback: Callable[[OperatorQuestion], None]
    ) -> zenoh.Subscriber[None]:
        """Call ``callback`` with every OperatorQuestion of the matching sources."""
        return self.session.declare_subscriber(
            self.keys.question(selector), lambda sample: callback(OperatorQuestion.unpack(sample.payload.to_bytes()))
        )
