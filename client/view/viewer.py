"""The viewer: the service's outputs from zenoh, as Foxglove channels on a WebSocket server (and in MCAP files),
with the active anchor set as Foxglove parameters.

Threads: zenoh's callbacks only keep each payload as the newest of its (source, kind) slot; one worker turns
slots into Foxglove messages; one poller asks for status (and the anchor set when its version changes) and
sends the anchor set again every ANCHORS_REPEAT_S; parameter edits and subscriptions arrive on the server's
thread (a new subscriber to the anchor channel gets the set at once; edits swap it on the service).
Nothing here can block the service: its publishers drop rather than wait, and the viewer holds at most one
payload per slot.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import foxglove
import numpy as np
import zenoh
from foxglove.channels import CompressedImageChannel, GridChannel, LogChannel
from foxglove.messages import (
    CompressedImage,
    Grid,
    Log,
    LogLevel,
    PackedElementField,
    PackedElementFieldNumericType,
    Pose,
    Quaternion,
    Timestamp,
    Vector2,
    Vector3,
)
from foxglove.websocket import Capability, ChannelView, Client, ServerListener
from gcdtrav.client.client import AnchorSetRejected, Maps, ServiceError, TraversabilityClient
from gcdtrav.client.client import Grid as GridMaps
from gcdtrav.client.view import pictures
from gcdtrav.client.view.anchor_parameters import anchor_parameters, apply_parameters, parameter_message
from gcdtrav.client.view.json_schema import model_schema
from gcdtrav.client.view.latest import LatestSlots
from gcdtrav.client.view.recorder import McapRecorder
from gcdtrav.schemas.anchors import AnchorSetError
from gcdtrav.schemas.experience import OperatorQuestion
from gcdtrav.schemas.inputs import decode_payload, image_format, input_kind
from gcdtrav.schemas.keys import Keys, input_key, input_source_of
from gcdtrav.schemas.messages import AnchorSetReply, ServiceStatus, SourceView
from numpy.typing import NDArray
from pydantic import BaseModel

log = logging.getLogger(__name__)

MAX_CAMERA_PIXELS = 40_000_000  # the service's default max_pixels: larger camera files are not shown
KINDS = ("maps", "grid", "preview", "camera")  # what arrives per source, each in its own latest-only slot
ANCHORS_REPEAT_S = 2.0  # the anchor set is sent again this often, so each MCAP file and a seek find it
NUMERIC_TYPES = {
    "float32": PackedElementFieldNumericType.Float32,
    "uint32": PackedElementFieldNumericType.Uint32,
    "uint8": PackedElementFieldNumericType.Uint8,
}


@dataclass(frozen=True)
class ViewOptions:
    host: str = "127.0.0.1"
    port: int = 8765  # 0: any free port
    prefix: str = "gcdtrav"  # the service's key prefix; also the first level of every topic
    sources: str = "**"  # which sources: a key expression of source names, e.g. 'r1/*'
    input_prefix: str = "gcdtrav/in"  # where robots publish images (the camera channel); '' for none
    max_sources: int = 32
    status_period_s: float = 1.0
    timeout_s: float = 5.0
    record: Path | None = None
    record_file_bytes: int = 256 * 1024 * 1024  # a new MCAP file beyond this
    record_max_bytes: int | None = None  # the whole recording: the oldest files are deleted beyond this
    message_backlog: int = 64  # per browser: the oldest message is dropped beyond this


def now_ns() -> int:
    return time.time_ns()


def stamp(seconds: float) -> Timestamp:
    return Timestamp.from_epoch_secs(max(seconds, 0.0))


class ServiceStatuses(BaseModel):
    """The status channel's message: every instance's status."""

    instances: list[ServiceStatus]


class SourceChannels:
    """The Foxglove channels of one source: status with its first message, each other channel with the first
    message of its kind, so a source without a grid (or previews, or camera) advertises no empty channel."""

    def __init__(self, topic: str, context: foxglove.Context) -> None:
        self.topic, self.context = topic, context
        self.status = foxglove.Channel(
            f"{topic}/status", schema=model_schema(SourceView, "gcdtrav.SourceView"), context=context
        )
        self.view: SourceView | None = None
        self._images: dict[str, CompressedImageChannel] = {}
        self._grid: GridChannel | None = None

    def image(self, name: str) -> CompressedImageChannel:
        """The image channel ``{topic}/{name}``: camera, preview, traversability or uncertainty."""
        if name not in self._images:
            self._images[name] = CompressedImageChannel(f"{self.topic}/{name}", context=self.context)
        return self._images[name]

    @property
    def grid(self) -> GridChannel:
        if self._grid is None:
            self._grid = GridChannel(f"{self.topic}/grid", context=self.context)
        return self._grid


class Viewer:
    """Start with ``start()``, stop with ``close()`` (or use it as a context manager)."""

    def __init__(self, client: TraversabilityClient, options: ViewOptions) -> None:
        self.client, self.options = client, options
        self.context = foxglove.Context()
        self.logged: Counter[str] = Counter()  # messages per topic, all sinks
        self.errors: Counter[str] = Counter()  # payloads that could not be shown, by kind
        self._slots: LatestSlots[tuple[str, str], bytes] = LatestSlots(options.max_sources * len(KINDS))
        self._sources: dict[str, SourceChannels] = {}
        self._ignored_sources: set[str] = set()
        self._emit_lock = threading.Lock()  # one message at a time into the sinks, so rotation splits cleanly
        self._swap_lock = threading.Lock()  # one anchor swap at a time
        self._active: AnchorSetReply | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._subscribers: list[zenoh.Subscriber[None]] = []
        topic = f"/{options.prefix}"
        self._anchors_sent = 0.0  # time.monotonic() of the last anchor-set message
        self.anchors_channel = foxglove.Channel(
            f"{topic}/anchors", schema=model_schema(AnchorSetReply, "gcdtrav.AnchorSetReply"), context=self.context
        )
        self.status_channel = foxglove.Channel(
            f"{topic}/status", schema=model_schema(ServiceStatuses, "gcdtrav.ServiceStatuses"), context=self.context
        )
        self.log_channel = LogChannel(f"{topic}/log", context=self.context)
        self.recorder = (
            McapRecorder(options.record, self.context, options.record_file_bytes, options.record_max_bytes)
            if options.record
            else None
        )
        self.server = foxglove.start_server(
            name=f"gcdtrav view ({options.prefix})",
            host=options.host,
            port=options.port,
            capabilities=[Capability.Parameters],
            server_listener=ViewerListener(self),
            context=self.context,
            message_backlog_size=options.message_backlog,
        )

    @property
    def url(self) -> str:
        host = "localhost" if self.options.host in ("127.0.0.1", "localhost") else self.options.host
        return f"ws://{host}:{self.server.port}"

    # ---- life cycle ------------------------------------------------------------------------------------
    def start(self) -> Viewer:
        prefix, sources = self.options.prefix, self.options.sources
        keys = {kind: Keys(prefix).output(sources, kind) for kind in ("maps", "grid", "preview", "question")}
        if self.options.input_prefix:
            keys["camera"] = input_key(self.options.input_prefix, sources)
        for kind, key in keys.items():
            self._subscribers.append(self.client.session.declare_subscriber(key, self._keeper(kind)))
        for target in (self._work, self._poll):
            thread = threading.Thread(target=target, name=f"gcdtrav-view-{target.__name__[1:]}", daemon=True)
            thread.start()
            self._threads.append(thread)
        return self

    def close(self) -> None:
        """Stop taking data, finish the MCAP file, stop the server."""
        self._stop.set()
        self._slots.wake()
        for subscriber in self._subscribers:
            subscriber.undeclare()
        for thread in self._threads:
            thread.join(10)
        with self._emit_lock:
            if self.recorder is not None:
                self.recorder.close()
        self.server.stop()

    def __enter__(self) -> Viewer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- zenoh in: latest-only -------------------------------------------------------------------------
    def _keeper(self, kind: str) -> Callable[[zenoh.Sample], None]:
        keys = Keys(self.options.prefix)
        if kind == "camera":
            head = self.options.input_prefix.rstrip("/")

            def keep_camera(sample: zenoh.Sample) -> None:
                if keys.input_message(str(sample.key_expr)) is not None:
                    return  # an outcome or an answer (experience), not a camera image
                source = input_source_of(str(sample.key_expr), head)
                self._slots.put((source, kind), sample.payload.to_bytes())

            return keep_camera

        def keep(sample: zenoh.Sample) -> None:
            source = keys.source_of(str(sample.key_expr), kind)
            if source is not None:
                self._slots.put((source, kind), sample.payload.to_bytes())

        return keep

    # ---- worker: slots -> Foxglove ---------------------------------------------------------------------
    def _work(self) -> None:
        handlers = {"maps": self._show_maps, "grid": self._show_grid, "preview": self._show_preview}
        handlers |= {"camera": self._show_camera, "question": self._show_question}
        while not self._stop.is_set():
            for (source, kind), payload in self._slots.take_all(timeout=0.5).items():
                channels = self._channels(source)
                if channels is None:
                    continue
                try:
                    handlers[kind](channels, payload)
                except Exception as err:  # a bad payload is counted and skipped; the next one is shown
                    self.errors[kind] += 1
                    count = self.errors[kind]
                    if count in (1, 10, 100) or count % 1000 == 0:  # at a falling rate
                        self.log_message(LogLevel.Warning, f"{kind} of {source} not shown ({count}x): {err}")

    def _channels(self, source: str) -> SourceChannels | None:
        channels = self._sources.get(source)
        if channels is None:
            if len(self._sources) >= self.options.max_sources:
                if source not in self._ignored_sources and len(self._ignored_sources) < 1000:
                    self._ignored_sources.add(source)
                    self.log_message(
                        LogLevel.Warning,
                        f"source {source} not shown: the view shows at most {self.options.max_sources} sources "
                        "(--max-sources)",
                    )
                return None
            channels = self._sources[source] = SourceChannels(f"/{self.options.prefix}/{source}", self.context)
        return channels

    def emit(self, channel: Any, message: Any, log_time: int | None = None) -> None:
        """Log one message to every sink (browsers, the MCAP file); rotate the file when it is full."""
        with self._emit_lock:
            channel.log(message, log_time=log_time or now_ns())
            self.logged[channel.topic()] += 1
            if self.recorder is not None:
                self.recorder.rotate_if_full()

    def _show_maps(self, channels: SourceChannels, payload: bytes) -> None:
        maps = Maps.from_payload(payload)
        header = maps.header
        when = stamp(header.stamp)
        layers: tuple[tuple[str, NDArray[np.float32], pictures.MapKind], ...] = (
            ("traversability", maps.traversability, "T"),
            ("uncertainty", maps.uncertainty, "U"),
        )
        for name, values, kind in layers:
            picture = pictures.png(pictures.map_with_legend(values, kind, header.image_size))
            message = CompressedImage(timestamp=when, frame_id=header.frame_id, data=picture, format="png")
            self.emit(channels.image(name), message)
        previous = channels.view or SourceView(source=header.source)
        latency = (time.time() - header.stamp) * 1e3
        channels.view = previous.model_copy(update={"maps": header, "latency_ms": round(latency, 2)})
        self.emit(channels.status, channels.view.model_dump(mode="json"))

    def _show_grid(self, channels: SourceChannels, payload: bytes) -> None:
        grid = GridMaps.from_payload(payload)
        header = grid.header
        fields = [
            PackedElementField(name=name, offset=offset, type=NUMERIC_TYPES[kind])
            for name, offset, kind in pictures.GRID_FIELDS
        ]
        origin = Pose(position=Vector3(x=header.origin[0], y=header.origin[1], z=0.0), orientation=Quaternion(w=1.0))
        message = Grid(
            timestamp=stamp(header.stamp),
            frame_id=header.frame_id,
            pose=origin,
            column_count=header.cells,
            cell_size=Vector2(x=header.resolution, y=header.resolution),
            row_stride=header.cells * pictures.GRID_CELL_BYTES,
            cell_stride=pictures.GRID_CELL_BYTES,
            fields=fields,
            data=pictures.grid_cells(grid),
        )
        self.emit(channels.grid, message)

    def _show_preview(self, channels: SourceChannels, payload: bytes) -> None:
        self.emit(channels.image("preview"), CompressedImage(timestamp=stamp(time.time()), data=payload, format="jpeg"))

    def _show_question(self, channels: SourceChannels, payload: bytes) -> None:
        """An operator question: its crop on ``{topic}/question``, its text on the log channel."""
        question = OperatorQuestion.unpack(payload)
        if question.crop_jpeg:
            image = CompressedImage(timestamp=stamp(time.time()), data=question.crop_jpeg, format="jpeg")
            self.emit(channels.image("question"), image)
        concepts = " vs ".join(c.concept for c in question.concepts)
        self.log_message(
            LogLevel.Warning,
            f"question {question.id}: {question.reason} ground ahead of {question.source} ({concepts}); "
            f"gcdtrav answer {question.source} drivable|blocked|SCORE",
        )

    def _show_camera(self, channels: SourceChannels, payload: bytes) -> None:
        data, kind, when, frame_id = camera_image(payload)
        message = CompressedImage(timestamp=stamp(when), frame_id=frame_id, data=data, format=kind)
        self.emit(channels.image("camera"), message)

    # ---- poller: status and the anchor set -------------------------------------------------------------
    def _poll(self) -> None:
        answering = True
        while not self._stop.is_set():
            try:
                statuses = self.client.statuses(timeout=min(self.options.timeout_s, 2.0))
                self._show_statuses(statuses)
                if not answering:
                    self.log_message(LogLevel.Info, "the service answers again")
                answering = True
            except Exception as err:  # no answer, or a session closing: say so once, keep trying
                if answering:
                    self.log_message(LogLevel.Warning, f"no status from the service: {err}")
                answering = False
            self._stop.wait(self.options.status_period_s)

    def _show_statuses(self, statuses: list[ServiceStatus]) -> None:
        self.emit(self.status_channel, {"instances": [s.model_dump(mode="json") for s in statuses]})
        versions = {s.anchor_set_version for s in statuses}
        if self._active is None or self._active.version not in versions or len(versions) > 1:
            with self._swap_lock:  # not in the middle of a swap from the Parameters panel
                self.refresh_anchors()
        if time.monotonic() - self._anchors_sent >= ANCHORS_REPEAT_S:
            self.send_anchors()
        for source, channels in list(self._sources.items()):
            counters = {s.instance: s.sources[source] for s in statuses if source in s.sources}
            channels.view = (channels.view or SourceView(source=source)).model_copy(update={"instances": counters})
            self.emit(channels.status, channels.view.model_dump(mode="json"))

    def refresh_anchors(self) -> AnchorSetReply:
        """Read the active set; when it changed, show it and publish its parameters."""
        active = self.client.anchors(timeout=self.options.timeout_s)
        changed = self._active is None or self._active.version != active.version or self._active != active
        self._active = active
        if changed:
            self.send_anchors()
            self.server.publish_parameter_values(self.parameters())
        return active

    def send_anchors(self) -> None:
        """The active set on /{prefix}/anchors (once it is known): when it changes, every ANCHORS_REPEAT_S and
        when a client subscribes, since a channel keeps no last message for late subscribers."""
        active = self._active
        if active is not None:
            self.emit(self.anchors_channel, active.model_dump(mode="json"))
            self._anchors_sent = time.monotonic()

    # ---- parameters ------------------------------------------------------------------------------------
    def parameters(self, names: list[str] | None = None) -> list[foxglove.Parameter]:
        active = self._active or self.refresh_anchors()
        values = anchor_parameters(active.anchor_set)
        wanted = names or list(values)
        return [to_parameter(name, values[name]) for name in wanted if name in values]

    def set_parameters(self, changes: dict[str, object]) -> list[foxglove.Parameter]:
        """Swap to the set the edits describe, whole or not at all; the parameters as they are afterwards."""
        with self._swap_lock:
            active = self.refresh_anchors()
            changed = ", ".join(changes)
            try:
                new = apply_parameters(active.anchor_set, changes)
                if new == active.anchor_set:
                    return self.parameters()
                self.client.set_anchors(new, timeout=self.options.timeout_s)
            except AnchorSetError as err:
                self.reject(changed, err.messages, active.version)
                return self.parameters()
            except AnchorSetRejected as err:  # the service's own validation: its fields, named as parameters
                self.reject(changed, [parameter_message(m, list(changes)) for m in err.messages], active.version)
                return self.parameters()
            except ServiceError as err:
                self.reject(changed, [str(err)], active.version)
                return self.parameters()
            swapped = self.refresh_anchors()
            self.server.remove_status(["anchors"])
            self.log_message(LogLevel.Info, f"anchor set {swapped.version} active ({changed} changed)")
            return self.parameters()

    def reject(self, changed: str, problems: list[str], active_version: str) -> None:
        text = f"anchor set not changed ({changed}): {'; '.join(problems)}; active set still {active_version}"
        self.log_message(LogLevel.Error, text)
        self.server.publish_status(text, foxglove.StatusLevel.Error, id="anchors")

    def log_message(self, level: LogLevel, text: str) -> None:
        log.log(logging.ERROR if level == LogLevel.Error else logging.INFO, "%s", text)
        self.emit(self.log_channel, Log(timestamp=stamp(time.time()), level=level, message=text, name="gcdtrav view"))


def to_parameter(name: str, value: str | float) -> foxglove.Parameter:
    if isinstance(value, float):  # whole numbers such as 1.0 stay floats in Foxglove's panel
        return foxglove.Parameter(name, value=value, type=foxglove.ParameterType.Float64)
    return foxglove.Parameter(name, value=value)


def camera_image(payload: bytes, encoding: str = "") -> tuple[bytes, str, float, str]:
    """(data, 'jpeg'|'png', stamp, frame id) of an input image, told apart as the service does (``input_kind``):
    JPEG and PNG files pass through untouched, other files (BMP, ...) and raw envelopes are encoded as JPEG."""
    from gcdtrav.schemas.images import peek_image_size
    from gcdtrav.schemas.messages import ImageEnvelope, PixelEncoding

    if input_kind(payload, encoding) == "image":
        kind = image_format(payload)
        if kind in ("PNG", "JPEG"):
            return payload, kind.lower(), time.time(), ""
        decoded = decode_payload(payload, encoding, time.time(), len(payload), MAX_CAMERA_PIXELS)
        return pictures.jpeg(decoded.image), "jpeg", decoded.stamp, ""
    envelope = ImageEnvelope.unpack(payload)
    if envelope.encoding in (PixelEncoding.JPEG, PixelEncoding.PNG):
        if peek_image_size(envelope.data) is None:
            raise ValueError(f"envelope data is not a {envelope.encoding.value} file")
        return envelope.data, envelope.encoding.value, envelope.stamp, envelope.frame_id
    frame = decode_payload(payload, "application/msgpack", time.time(), len(payload), envelope.width * envelope.height)
    return pictures.jpeg(frame.image), "jpeg", envelope.stamp, envelope.frame_id


class ViewerListener(ServerListener):
    """Foxglove's Parameters panel reads the active set, and edits swap it on the service; a subscriber to the
    anchor channel gets the active set at once."""

    def __init__(self, viewer: Viewer) -> None:
        self.viewer = viewer

    def on_get_parameters(
        self, client: Client, param_names: list[str], request_id: str | None = None
    ) -> list[foxglove.Parameter]:
        try:
            return self.viewer.parameters(param_names)
        except ServiceError as err:
            self.viewer.log_message(LogLevel.Warning, f"anchor parameters unavailable: {err}")
            return []

    def on_set_parameters(
        self, client: Client, parameters: list[foxglove.Parameter], request_id: str | None = None
    ) -> list[foxglove.Parameter]:
        try:
            return self.viewer.set_parameters({p.name: p.get_value() for p in parameters})
        except ServiceError as err:
            self.viewer.log_message(LogLevel.Error, f"anchor set not changed: {err}")
            return []

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        log.debug("client %s subscribed to %s", client.id, channel.topic)
        if channel.topic == self.viewer.anchors_channel.topic():
            self.viewer.send_anchors()  # to every sink: foxglove-sdk's Python Client has no sink id to aim at
