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
from foxglove.channels import (
    CameraCalibrationChannel,
    CompressedImageChannel,
    FrameTransformsChannel,
    GridChannel,
    LogChannel,
    SceneUpdateChannel,
)
from foxglove.messages import (
    CompressedImage,
    FrameTransforms,
    Grid,
    Log,
    LogLevel,
    PackedElementField,
    PackedElementFieldNumericType,
    Pose,
    Quaternion,
    SceneUpdate,
    Timestamp,
    Vector2,
    Vector3,
)
from foxglove.websocket import Capability, ChannelView, Client, ServerListener
from gcdtrav.client.client import AnchorSetRejected, Maps, ServiceError, TraversabilityClient
from gcdtrav.client.client import Grid as GridMaps
from gcdtrav.client.view import frames, grid_layers, pictures, probe
from gcdtrav.client.view.anchor_parameters import ParameterValue, anchor_parameters, apply_parameters, parameter_message
from gcdtrav.client.view.json_schema import model_schema
from gcdtrav.client.view.latest import LatestSlots
from gcdtrav.client.view.recorder import McapRecorder
from gcdtrav.client.view.replay import LOG_LINES_KEPT, QUESTION_SCHEMA, OpenQuestions, Recent, question_json
from gcdtrav.schemas.anchors import AnchorSetError
from gcdtrav.schemas.inputs import decode_payload, image_format, input_kind
from gcdtrav.schemas.keys import INPUT_MESSAGE_KINDS, Keys, input_key, input_source_of
from gcdtrav.schemas.messages import (
    AnchorSetReply,
    ContextDistribution,
    GridCameraStatus,
    GridHeader,
    ServiceStatus,
    SourceView,
)
from numpy.typing import NDArray
from pydantic import BaseModel

log = logging.getLogger(__name__)

MAX_CAMERA_PIXELS = 40_000_000  # the service's default max_pixels: larger camera files are not shown
KINDS = ("maps", "grid", "costmap", "preview", "camera")  # what arrives per source, each in a latest-only slot
COSTMAP_KIND = "grid/costmap"  # the key's last levels: {prefix}/out/{source}/grid/costmap
QUESTION_KIND = "question"  # {prefix}/out/{source}/question: forwarded as they come, not latest-only
ANSWER_KIND = "answer"  # {prefix}/in/{source}/answer: the question with its id is no longer open
RECORDED = {"gcdtrav": "recorded"}  # metadata of the recording's own camera channel (downsampled)
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
    record_camera_every: int = 1  # the camera in recordings: every frame (1), one in N, or none (0)
    settings: Path | None = None  # the service's settings file: its grid cameras' mounts and intrinsics
    message_backlog: int = 64  # per browser: the oldest message is dropped beyond this


def stamp(seconds: float) -> Timestamp:
    return Timestamp.from_epoch_secs(max(seconds, 0.0))


class ServiceStatuses(BaseModel):
    """The status channel's message: every instance's status."""

    instances: list[ServiceStatus]


class SourceChannels:
    """The Foxglove channels of one source: status with its first message, each other channel with the first
    message of its kind, so a source without a grid (or previews, or camera) advertises no empty channel."""

    def __init__(self, source: str, topic: str, context: foxglove.Context) -> None:
        self.source, self.topic, self.context = source, topic, context
        self.status = foxglove.Channel(
            f"{topic}/status", schema=model_schema(SourceView, "gcdtrav.SourceView"), context=context
        )
        self.view: SourceView | None = None
        self.grid_header: GridHeader | None = None  # the latest grid's: the robot's pose, the costmap's place
        self.camera_frames = 0  # camera frames received (the recording keeps one in record_camera_every)
        self._channels: dict[str, Any] = {}
        self._lock = threading.Lock()  # the worker, the probe and zenoh's callbacks open channels

    def _channel(self, name: str, kind: Callable[..., Any], **extra: Any) -> Any:
        key = name + ("#recorded" if extra.get("metadata") == RECORDED else "")
        with self._lock:  # one channel per name: a second one would be advertised, then closed
            if key not in self._channels:
                self._channels[key] = kind(f"{self.topic}/{name}", context=self.context, **extra)
            return self._channels[key]

    def image(self, name: str) -> CompressedImageChannel:
        """The image channel ``{topic}/{name}``: camera, preview, traversability, uncertainty, distribution,
        grid/{layer}/image."""
        return self._channel(name, CompressedImageChannel)

    def recorded_camera(self) -> CompressedImageChannel:
        """The camera as recorded when the recording downsamples it: the same topic, MCAP files only."""
        return self._channel("camera", CompressedImageChannel, metadata=RECORDED)

    @property
    def grid(self) -> GridChannel:
        return self._channel("grid", GridChannel)

    def layer(self, name: str) -> GridChannel:
        """The grid layer ``{topic}/grid/{name}``: one value and its colour per cell."""
        return self._channel(f"grid/{name}", GridChannel)

    @property
    def transforms(self) -> FrameTransformsChannel:
        return self._channel("tf", FrameTransformsChannel)

    @property
    def scene(self) -> SceneUpdateChannel:
        return self._channel("robot", SceneUpdateChannel)

    @property
    def calibration(self) -> CameraCalibrationChannel:
        return self._channel("camera_info", CameraCalibrationChannel)

    @property
    def question(self) -> foxglove.Channel:
        return self._channel(QUESTION_KIND, foxglove.Channel, schema=QUESTION_SCHEMA)


class Viewer:
    """Start with ``start()``, stop with ``close()`` (or use it as a context manager)."""

    def __init__(self, client: TraversabilityClient, options: ViewOptions) -> None:
        self.client, self.options = client, options
        self.context = foxglove.Context()
        self.logged: Counter[str] = Counter()  # messages per topic, all sinks
        self.errors: Counter[str] = Counter()  # payloads that could not be shown, by kind
        self.shown: Counter[str] = Counter()  # payloads shown, by kind
        self._slots: LatestSlots[tuple[str, str], bytes] = LatestSlots(options.max_sources * len(KINDS))
        self._sources: dict[str, SourceChannels] = {}
        self._sources_lock = threading.Lock()
        self._ignored_sources: set[str] = set()
        self._emit_lock = threading.Lock()  # one message at a time into the sinks, so rotation splits cleanly
        self._swap_lock = threading.Lock()  # one anchor swap at a time
        self._active: AnchorSetReply | None = None
        self.cameras = frames.cameras_from_settings(options.settings) if options.settings else {}
        self.grid_cameras: dict[str, GridCameraStatus] = {}  # by camera source, from the grids' status
        self.recent_log: Recent[Log] = Recent(LOG_LINES_KEPT)
        self.questions = OpenQuestions()
        self.probe = probe.ProbeTarget()
        self._probe_wake = threading.Event()
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
            McapRecorder(
                options.record,
                self.context,
                options.record_file_bytes,
                options.record_max_bytes,
                channel_filter=self._recorded,
            )
            if options.record
            else None
        )
        self.server = foxglove.start_server(
            name=f"gcdtrav view ({options.prefix})",
            host=options.host,
            port=options.port,
            capabilities=[Capability.Parameters, Capability.ClientPublish],
            supported_encodings=["json"],  # published points (Publish panel, 3D panel tool)
            server_listener=ViewerListener(self),
            context=self.context,
            channel_filter=lambda channel: channel.metadata != RECORDED,
            message_backlog_size=options.message_backlog,
        )

    @property
    def url(self) -> str:
        host = "localhost" if self.options.host in ("127.0.0.1", "localhost") else self.options.host
        return f"ws://{host}:{self.server.port}"

    # ---- life cycle ------------------------------------------------------------------------------------
    def _recorded(self, channel: foxglove.ChannelDescriptor) -> bool:
        """Which channels the MCAP files get: all, but the live camera when the recording downsamples it
        (its RECORDED twin then) or leaves it out."""
        if self.options.record_camera_every == 1:
            return channel.metadata != RECORDED
        return not (channel.topic.endswith("/camera") and channel.metadata != RECORDED)

    def start(self) -> Viewer:
        prefix, sources = self.options.prefix, self.options.sources
        keys = {kind: Keys(prefix).output(sources, kind) for kind in ("maps", "grid", "preview")}
        keys["costmap"] = Keys(prefix).grid(sources, "costmap")
        if self.options.input_prefix:
            keys["camera"] = input_key(self.options.input_prefix, sources)
        for kind, key in keys.items():
            self._subscribers.append(self.client.session.declare_subscriber(key, self._keeper(kind)))
        question_key = f"{prefix}/out/{sources}/{QUESTION_KIND}"  # OperatorQuestion (schemas/experience.py)
        answer_key = f"{prefix}/in/{sources}/{ANSWER_KIND}"  # OperatorAnswer
        self._subscribers.append(self.client.session.declare_subscriber(question_key, self._forward_question))
        self._subscribers.append(self.client.session.declare_subscriber(answer_key, self._close_question))
        for target in (self._work, self._poll, self._probe_loop):
            thread = threading.Thread(target=target, name=f"gcdtrav-view-{target.__name__[1:]}", daemon=True)
            thread.start()
            self._threads.append(thread)
        return self

    def close(self) -> None:
        """Stop taking data, finish the MCAP file, stop the server."""
        self._stop.set()
        self._slots.wake()
        self._probe_wake.set()
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
        if kind == "camera":
            head = self.options.input_prefix.rstrip("/")

            def keep_camera(sample: zenoh.Sample) -> None:
                source = input_source_of(str(sample.key_expr), head)
                if source.rsplit("/", 1)[-1] in INPUT_MESSAGE_KINDS:  # the experience's messages beside images
                    return
                self._slots.put((source, kind), sample.payload.to_bytes())

            return keep_camera
        keys = Keys(self.options.prefix)
        key_kind = COSTMAP_KIND if kind == "costmap" else kind

        def keep(sample: zenoh.Sample) -> None:
            source = keys.source_of(str(sample.key_expr), key_kind)
            if source is not None:
                self._slots.put((source, kind), sample.payload.to_bytes())

        return keep

    # ---- worker: slots -> Foxglove ---------------------------------------------------------------------
    def _work(self) -> None:
        handlers = {"maps": self._show_maps, "grid": self._show_grid, "preview": self._show_preview}
        handlers["camera"], handlers["costmap"] = self._show_camera, self._show_costmap
        while not self._stop.is_set():
            for (source, kind), payload in self._slots.take_all(timeout=0.5).items():
                channels = self._channels(source)
                if channels is None:
                    continue
                try:
                    handlers[kind](channels, payload)
                    self.shown[kind] += 1
                except Exception as err:  # a bad payload is counted and skipped; the next one is shown
                    self.errors[kind] += 1
                    count = self.errors[kind]
                    if count in (1, 10, 100) or count % 1000 == 0:  # at a falling rate
                        self.log_message(LogLevel.Warning, f"{kind} of {source} not shown ({count}x): {err}")

    def _channels(self, source: str) -> SourceChannels | None:
        with self._sources_lock:  # the worker, the probe and zenoh's callbacks ask
            return self._source_channels(source)

    def _source_channels(self, source: str) -> SourceChannels | None:
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
            channels = self._sources[source] = SourceChannels(source, f"/{self.options.prefix}/{source}", self.context)
        return channels

    def emit(self, channel: Any, message: Any, log_time: int | None = None) -> None:
        """Log one message to every sink (browsers, the MCAP file); rotate the file when it is full."""
        with self._emit_lock:
            channel.log(message, log_time=log_time or time.time_ns())
            recorded = " (recorded)" if channel.metadata() == RECORDED else ""  # the camera's MCAP-only twin
            self.logged[channel.topic() + recorded] += 1
            if self.recorder is not None:
                self.recorder.rotate_if_full()

    def _show_maps(self, channels: SourceChannels, payload: bytes) -> None:
        maps = Maps.from_payload(payload)
        header = maps.header
        when = stamp(header.stamp)
        frame_id = frames.camera_frame(header.source, header.frame_id)
        layers: tuple[tuple[str, NDArray[np.float32], pictures.MapKind], ...] = (
            ("traversability", maps.traversability, "T"),
            ("uncertainty", maps.uncertainty, "U"),
        )
        for name, values, kind in layers:
            picture = pictures.png(pictures.map_with_legend(values, kind, header.image_size))
            message = CompressedImage(timestamp=when, frame_id=frame_id, data=picture, format="png")
            self.emit(channels.image(name), message)
        self._show_camera_place(channels, header.source, frame_id, when, header.image_size)
        previous = channels.view or SourceView(source=header.source)
        latency = (time.time() - header.stamp) * 1e3
        channels.view = previous.model_copy(update={"maps": header, "latency_ms": round(latency, 2)})
        self.emit(channels.status, channels.view.model_dump(mode="json"))

    def _show_camera_place(
        self, channels: SourceChannels, source: str, frame_id: str, when: Timestamp, size: tuple[int, int] | None
    ) -> None:
        """base_link -> the camera's optical frame where its grid fuses it (frames.camera_mount), and for a
        camera the settings file gives intrinsics, its calibration and its frustum (with the robot's marker)."""
        camera = self.cameras.get(source)
        mount = frames.camera_mount(camera, self.grid_cameras.get(source))
        if mount is None:
            return
        self.emit(channels.transforms, FrameTransforms(transforms=[frames.mount_transform(when, mount, frame_id)]))
        if camera is not None and camera.intrinsics is not None:
            self.emit(channels.calibration, frames.calibration(when, camera.intrinsics, frame_id, size))
            frustum = frames.frustum_entity(when, source, camera.intrinsics, frame_id)
            self.emit(channels.scene, SceneUpdate(entities=[frustum, frames.robot_entity(when, source)]))

    def _show_grid(self, channels: SourceChannels, payload: bytes) -> None:
        grid = GridMaps.from_payload(payload)
        header = grid.header
        channels.grid_header = header
        fields = [
            PackedElementField(name=name, offset=offset, type=NUMERIC_TYPES[kind])
            for name, offset, kind in pictures.GRID_FIELDS
        ]
        self.emit(channels.grid, grid_message(header, fields, pictures.GRID_CELL_BYTES, pictures.grid_cells(grid)))
        for name, (kind, values) in grid_layers.layer_values(grid).items():
            self._show_layer(channels, name, kind, values, header)
        when = stamp(header.stamp)
        if header.robot is not None and header.frame_id != frames.BASE_FRAME:
            transform = frames.robot_transform(when, header.frame_id, header.robot)
            self.emit(channels.transforms, FrameTransforms(transforms=[transform]))
        entities = [] if self._draws_frustum(header.source) else [frames.robot_entity(when, header.source)]
        if header.capture_pose is not None and header.frame_id != frames.BASE_FRAME:
            entities.append(frames.capture_entity(when, header.source, header.frame_id, header.capture_pose))
        if entities:
            self.emit(channels.scene, SceneUpdate(entities=entities))

    def _draws_frustum(self, source: str) -> bool:
        """Whether the camera's place draws the robot's marker beside the frustum (_show_camera_place)."""
        camera = self.cameras.get(source)
        drawn = camera is not None and camera.intrinsics is not None
        return drawn and frames.camera_mount(camera, self.grid_cameras.get(source)) is not None

    def _show_layer(
        self,
        channels: SourceChannels,
        name: str,
        kind: pictures.MapKind,
        values: NDArray[np.float32],
        header: GridHeader,
    ) -> None:
        """One layer as a Grid (value and colour per cell) and as a top-down picture with its legend."""
        fields = [
            PackedElementField(name=name, offset=0, type=PackedElementFieldNumericType.Float32),
            *(PackedElementField(name=colour, offset=4 + k, type=PackedElementFieldNumericType.Uint8)
              for k, colour in enumerate(("red", "green", "blue", "alpha"))),
        ]  # fmt: skip
        layer, image_channel = channels.layer(name), channels.image(f"grid/{name}/image")
        if layer.has_sinks():  # nobody watching, nothing recording: not drawn (seven layers a grid update)
            cells = grid_layers.layer_cells(values, kind)
            self.emit(layer, grid_message(header, fields, grid_layers.LAYER_CELL_BYTES, cells))
        if image_channel.has_sinks():
            picture = pictures.png(grid_layers.layer_picture(values, kind, header))
            when = stamp(header.stamp)
            image = CompressedImage(timestamp=when, frame_id=header.frame_id, data=picture, format="png")
            self.emit(image_channel, image)

    def _show_costmap(self, channels: SourceChannels, payload: bytes) -> None:
        costmap = grid_layers.decode_occupancy_grid(payload)
        header = grid_layers.costmap_header(costmap)
        if channels.grid_header is not None and channels.grid_header.frame_id == costmap.frame_id:
            header = header.model_copy(update={"robot": channels.grid_header.robot})
        self._show_layer(channels, grid_layers.COSTMAP, "cost", costmap.values(), header)

    def _show_preview(self, channels: SourceChannels, payload: bytes) -> None:
        maps = channels.view.maps if channels.view is not None else None  # the preview is of the latest maps
        frame_id = frames.camera_frame(channels.source, maps.frame_id if maps is not None else "")
        message = CompressedImage(timestamp=stamp(time.time()), frame_id=frame_id, data=payload, format="jpeg")
        self.emit(channels.image("preview"), message)

    def _show_camera(self, channels: SourceChannels, payload: bytes) -> None:
        data, kind, when, frame_id = camera_image(payload)
        source = channels.source
        frame_id = frames.camera_frame(source, frame_id)
        message = CompressedImage(timestamp=stamp(when), frame_id=frame_id, data=data, format=kind)
        self.emit(channels.image("camera"), message)
        every = self.options.record_camera_every
        if self.recorder is not None and every > 1 and channels.camera_frames % every == 0:
            self.emit(channels.recorded_camera(), message)
        channels.camera_frames += 1
        if channels.view is None or channels.view.maps is None:  # no maps yet: place the camera from its frames
            self._show_camera_place(channels, source, frame_id, stamp(when), None)

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
        self.grid_cameras = {  # where each grid fuses its cameras: the next frame draws them there
            camera: placed
            for status in statuses
            for grid in status.grids or []
            for camera, placed in grid.cameras.items()
        }
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
        values: dict[str, ParameterValue | None] = {**anchor_parameters(active.anchor_set)}
        values.update(probe.probe_parameters(self.probe))
        wanted = names or list(values)
        return [to_parameter(name, values[name]) for name in wanted if name in values]

    def set_parameters(self, changes: dict[str, object]) -> list[foxglove.Parameter]:
        """Probe edits choose what is probed; anchor edits swap to the set they describe, whole or not at all.
        The parameters as they are afterwards, also to every Parameters panel: a refused edit shows the
        active value again."""
        probe_changes = {name: value for name, value in changes.items() if probe.is_probe_parameter(name)}
        anchor_changes = {name: value for name, value in changes.items() if name not in probe_changes}
        if probe_changes:
            self.set_probe(probe_changes)
        if anchor_changes:
            self.set_anchor_parameters(anchor_changes)
        current = self.parameters()
        self.server.publish_parameter_values(current)
        return current

    def set_probe(self, changes: dict[str, object]) -> None:
        try:
            self.probe = probe.apply_probe_parameters(self.probe, changes)
        except ValueError as err:
            self.log_message(LogLevel.Error, f"probe not changed: {err}")
            return
        channels = self._channels(self.probe.source) if self.probe.active else None
        if channels is not None:  # advertised now, before the first drawing: viewers can subscribe early
            channels.image("distribution")
        self.log_message(LogLevel.Info, f"probing {self.probe.target} ({self.probe.x:g}, {self.probe.y:g}) of "
                         f"{self.probe.source or 'nothing'}")  # fmt: skip
        self._probe_wake.set()

    def set_anchor_parameters(self, changes: dict[str, object]) -> None:
        with self._swap_lock:
            active = self.refresh_anchors()
            changed = ", ".join(changes)
            try:
                new = apply_parameters(active.anchor_set, changes)
                if new == active.anchor_set:
                    return
                self.client.set_anchors(new, timeout=self.options.timeout_s)
            except AnchorSetError as err:
                self.reject(changed, err.messages, active.version)
                return
            except AnchorSetRejected as err:  # the service's own validation: its fields, named as parameters
                self.reject(changed, [parameter_message(m, list(changes)) for m in err.messages], active.version)
                return
            except ServiceError as err:
                self.reject(changed, [str(err)], active.version)
                return
            swapped = self.refresh_anchors()
            self.server.remove_status(["anchors"])
            self.log_message(LogLevel.Info, f"anchor set {swapped.version} active ({changed} changed)")

    def reject(self, changed: str, problems: list[str], active_version: str) -> None:
        text = f"anchor set not changed ({changed}): {'; '.join(problems)}; active set still {active_version}"
        self.log_message(LogLevel.Error, text)
        self.server.publish_status(text, foxglove.StatusLevel.Error, id="anchors")

    def log_message(self, level: LogLevel, text: str) -> None:
        log.log(logging.ERROR if level == LogLevel.Error else logging.INFO, "%s", text)
        message = Log(timestamp=stamp(time.time()), level=level, message=text, name="gcdtrav view")
        self.recent_log.add(message)
        self.emit(self.log_channel, message)

    def replay_log(self) -> None:
        """The last LOG_LINES_KEPT lines again, for a viewer that subscribed late (every sink gets them:
        foxglove-sdk cannot aim at one browser)."""
        for message in self.recent_log.items():
            self.emit(self.log_channel, message)

    # ---- operator questions: forwarded as JSON, the open ones replayed -------------------------------
    def _forward_question(self, sample: zenoh.Sample) -> None:
        source = Keys(self.options.prefix).source_of(str(sample.key_expr), QUESTION_KIND)
        channels = self._channels(source) if source is not None else None
        if source is None or channels is None:
            return
        try:
            question = question_json(sample.payload.to_bytes())
        except ValueError as err:
            self.errors[QUESTION_KIND] += 1
            self.log_message(LogLevel.Warning, f"question of {source} not shown: {err}")
            return
        self.questions.add(source, question)
        self.emit(channels.question, question)

    def _close_question(self, sample: zenoh.Sample) -> None:
        parsed = Keys(self.options.prefix).input_message(str(sample.key_expr))
        if parsed is None or parsed[1] != ANSWER_KIND:
            return
        source = parsed[0]
        try:
            identifier = question_json(sample.payload.to_bytes()).get("id")
        except ValueError:
            return  # the service counts bad answers; the viewer only listens
        if isinstance(identifier, str) and self.questions.answered(source, identifier):
            self.log_message(LogLevel.Info, f"question {identifier} of {source} answered")

    def replay_questions(self, topic: str) -> None:
        for source, channels in list(self._sources.items()):
            if channels.question.topic() == topic:
                for question in self.questions.of(source):
                    self.emit(channels.question, question)

    # ---- the probed distribution ---------------------------------------------------------------------
    def clicked(self, data: bytes) -> None:
        """A point a client published: probe the grid cell there, of the source whose grid it is on."""
        try:
            point = probe.clicked_point(data)
        except ValueError as err:
            self.log_message(LogLevel.Warning, f"published point not used: {err}")
            return
        for source, channels in sorted(self._sources.items(), key=lambda item: item[0] != self.probe.source):
            header = channels.grid_header
            if header is None:
                continue
            place = probe.to_grid_frame(point, header.frame_id, header.robot, frames.BASE_FRAME)
            if place is not None:
                self.set_probe({"probe/source": source, "probe/target": "cell", "probe/x": place[0],
                                "probe/y": place[1]})  # fmt: skip
                self.server.publish_parameter_values(self.parameters(list(probe.probe_parameters(self.probe))))
                return
        self.log_message(LogLevel.Warning, f"published point in frame '{point.frame_id}' is on no grid shown")

    def _probe_loop(self) -> None:
        """The probed distribution again every status period (new frames change it) and at once on a new
        choice; one query at a time, nothing queued."""
        failed = ""
        while not self._stop.is_set():
            target = self.probe
            channels = self._channels(target.source) if target.active else None
            if channels is not None and channels.image("distribution").has_sinks():  # else nobody to draw for
                try:
                    self.show_distribution(target, self.query_distribution(target))
                    failed = ""
                except Exception as err:  # no such source or patch, no answer, no matplotlib: said once
                    problem = f"distribution at {target.target} ({target.x:g}, {target.y:g}) of {target.source}: {err}"
                    if problem != failed:
                        self.log_message(LogLevel.Warning, problem)
                    failed = problem
            self._probe_wake.wait(max(self.options.status_period_s, 0.2))
            self._probe_wake.clear()

    def query_distribution(self, target: probe.ProbeTarget) -> ContextDistribution:
        timeout = min(self.options.timeout_s, 2.0)
        if target.target == "cell":
            return self.client.cell(target.source, target.x, target.y, timeout=timeout)
        return self.client.patch(target.source, target.x, target.y, timeout=timeout)

    def show_distribution(self, target: probe.ProbeTarget, distribution: ContextDistribution) -> None:
        from gcdtrav.client.commands.density_plot import distribution_png

        channels = self._channels(target.source)
        if channels is None:
            return
        frame_id = frames.camera_frame(target.source, distribution.frame_id)
        message = CompressedImage(
            timestamp=stamp(distribution.stamp), frame_id=frame_id, data=distribution_png(distribution), format="png"
        )
        self.emit(channels.image("distribution"), message)


def grid_message(header: GridHeader, fields: list[PackedElementField], cell_bytes: int, data: bytes) -> Grid:
    """A foxglove.Grid of the grid's cells: pose = the corner of cell (0, 0), rows along y."""
    origin = Pose(position=Vector3(x=header.origin[0], y=header.origin[1], z=0.0), orientation=Quaternion(w=1.0))
    columns = header.cells  # the grid is square; a costmap's header gives its width
    return Grid(
        timestamp=stamp(header.stamp),
        frame_id=header.frame_id,
        pose=origin,
        column_count=columns,
        cell_size=Vector2(x=header.resolution, y=header.resolution),
        row_stride=columns * cell_bytes,
        cell_stride=cell_bytes,
        fields=fields,
        data=data,
    )


def to_parameter(name: str, value: str | float | None) -> foxglove.Parameter:
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
        # to every sink: foxglove-sdk's Python Client has no sink id to aim at
        if channel.topic == self.viewer.anchors_channel.topic():
            self.viewer.send_anchors()
        elif channel.topic == self.viewer.log_channel.topic():
            self.viewer.replay_log()
        elif channel.topic.endswith(f"/{QUESTION_KIND}"):
            self.viewer.replay_questions(channel.topic)

    def on_message_data(self, client: Client, client_channel_id: int, data: bytes) -> None:
        """A point a client published (any topic: the Publish panel's or 3D tool's topic is the operator's choice)."""
        self.viewer.clicked(data)
