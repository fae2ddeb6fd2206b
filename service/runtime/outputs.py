"""What the service publishes for one processed frame, as payloads: maps, preview, ROS images, ground grid and
the question its fusion asked an operator. Only encoding: the worker has fused the grid (``ProcessedFrame.grid``,
the question included); ``FramePublisher`` is the worker's one hand-off out, and the bus
(``service/bus/outputs.py``, an ``OutputSink``) only puts the payloads on their keys and topics.

The preview is drawn at its own size (at most ``preview_max_width`` for T-over-image beside U): T and U are
resized once to that size, not to the image's and back. T and U at the image's size are made only when
something needs them (``full_resolution``, ROS outputs).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal, Protocol, TypeVar

import cv2
import numpy as np
from gcdtrav.schemas.images import (
    colorize_traversability,
    colorize_uncertainty,
    encode_jpeg,
    encode_map_png8,
    encode_maps_png16,
    overlay,
    resize_map,
)
from gcdtrav.schemas.keys import Keys
from gcdtrav.schemas.messages import CompactMapsMessage, MapsHeader, MapsMessage
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.ros import cdr as ros_io
from gcdtrav.service.runtime.frames import PendingFrame, ProcessedFrame
from gcdtrav.service.runtime.grids import FusedGrid, GridUpdate, SpeedUpdate
from gcdtrav.service.runtime.triage.change import Glance
from gcdtrav.service.runtime.triage.reuse import Republished
from numpy.typing import NDArray

Encoding = Literal["msgpack", "jpeg", "cdr"]
# rclcpp's default publisher profile; a map's (transient local, depth 1); a map's put only when its bytes change
# (the speed filter's info: each new one makes Nav2's SpeedFilter drop its mask and subscribe again)
RosQos = Literal["image", "grid", "latched"]
PREVIEW_JPEG_QUALITY = 80
log = logging.getLogger("gcdtrav.service")


@dataclass(frozen=True)
class Output:
    """One payload for a zenoh key (``topic`` None) or, for ROS cameras, a ROS topic."""

    key: str
    payload: bytes
    encoding: Encoding
    topic: ros_io.RosTopic | None = None
    qos: RosQos = "image"


def preview_size(width: int, height: int, max_width: int) -> tuple[int, int]:
    """(width, height) of one half of the preview panel (T over the image, or U)."""
    half = min(width, max(1, max_width // 2))
    return half, max(1, round(height * half / width))


def preview_panel(
    image: NDArray[np.uint8], t: NDArray[np.floating], u: NDArray[np.floating], max_width: int
) -> NDArray[np.uint8]:
    """T over the image, beside U, at most ``max_width`` wide (RGB): maps resized straight to that size."""
    height, width = image.shape[:2]
    size = preview_size(width, height, max_width)
    small = image if size == (width, height) else cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    t_small, u_small = resize_map(t, *size), resize_map(u, *size)
    left = overlay(np.asarray(small, np.uint8), colorize_traversability(t_small))
    return np.concatenate([left, colorize_uncertainty(u_small)], axis=1)


@dataclass(frozen=True)
class Encoded:
    """A processed frame's payloads, and its maps as kept for reuse (the same messages, never re-encoded)."""

    outputs: list[Output]
    maps: MapsMessage
    compact_maps: CompactMapsMessage | None


class OutputSink(Protocol):
    """Where a frame's payloads go: the bus puts them (``service/bus/outputs.py``)."""

    def wants_compact(self, source: str) -> bool:
        """Whether anyone takes the source's compact maps (they are encoded only then)."""
        ...

    def put(self, source: str, outputs: list[Output]) -> bool:
        """Put every payload; False, nothing put, once closed (shutdown)."""
        ...


class FramePublisher:
    """The one hand-off out: encode a processed frame (the worker's) or an unchanged one's reused maps (the
    triage's), give the payloads to the sink and, once they are out, tell ``published(source, stamp)`` (the
    credits: later grants say how fresh the maps are) and, for an unchanged one, ``unchanged(source)`` (the
    grids: its camera's view still holds, so its grid is not stale).

    One ordering point per frame: its maps are kept for reuse, then ``kept`` is told (the glance's new
    reference), then they are put, all under one lock that reuse's answers take too. A frame glanced once
    the reference is set (a robot sends it the moment it sees the maps) is compared with this frame and
    answered with its maps, never the previous frame's, and only after them (a client drops older maps); one
    glanced before but answered after must fit them too (``republish``'s ``fits``), else it is dropped."""

    def __init__(
        self,
        builder: OutputBuilder,
        sink: OutputSink,
        published: Callable[[str, float], None] = lambda source, stamp: None,
        unchanged: Callable[[str], None] = lambda source: None,
    ) -> None:
        self.builder, self.sink, self.published, self.unchanged = builder, sink, published, unchanged
        self._out = threading.Lock()  # keep, reference and put of a frame; a reused frame's answer

    def __call__(self, done: ProcessedFrame, kept: Callable[[ProcessedFrame], None] = lambda done: None) -> bool:
        """Put the frame's payloads; ``kept(done)`` runs once its maps are kept for reuse, before they go out.
        False, nothing put, once closed."""
        encoded = self.builder.encode(done, compact=self.sink.wants_compact(done.source))  # outside: the slow part
        with self._out:
            self.builder.keep(done.source, encoded)
            kept(done)
            if not self.sink.put(done.source, encoded.outputs):
                return False
        self.published(done.source, done.image.stamp)
        return True

    def republish(self, pending: PendingFrame, seen: Glance, fits: Callable[[], bool] = lambda: True) -> Republished:
        """The source's last maps again for an unchanged frame (reuse). ``fits()``, asked under the hand-off's
        lock (the kept maps cannot change while it answers): whether the frame still matches the maps kept now
        (newer maps may have been kept since it was judged); SUPERSEDED, nothing put, if not. NOT_PUT once
        closed or when no maps of the source are kept."""
        compact = self.sink.wants_compact(pending.source)
        with self._out:
            if not fits():
                return Republished.SUPERSEDED
            outputs = self.builder.reused(pending, seen.stamp, seen.frame_id, compact)
            if not outputs or not self.sink.put(pending.source, outputs):
                return Republished.NOT_PUT
        self.published(pending.source, seen.stamp)
        self.unchanged(pending.source)
        return Republished.PUT

    def publish_speed(self, updates: list[SpeedUpdate]) -> bool:
        """Grids' speed outputs outside a frame (the safe mask of a stale grid, or at shutdown); False if the
        sink refused any (closed)."""
        put = True
        for update in updates:
            put = self.sink.put(update.source, self.builder.speed(update)) and put
        return put

    def forget(self, source: str) -> None:
        self.builder.forget(source)


class OutputBuilder:
    """The payloads of one frame, by the settings. Encoding only (the worker fused the grid before); what it
    keeps is the last maps it encoded per source, to send again for unchanged frames (reuse)."""

    def __init__(self, settings: ServiceSettings, model_id: str) -> None:
        self.settings, self.model_id = settings, model_id
        self.keys = Keys(settings.prefix)
        # Per source, the last inferred frame's maps (and compact maps, if made), to publish again for its
        # unchanged views (reuse): the PNGs as they went out, never re-encoded. Threads: the output thread
        # writes, the triage thread reads (FramePublisher orders the two); one reference each, swapped whole.
        self._last: dict[str, tuple[MapsMessage, CompactMapsMessage | None]] = {}

    def build(self, done: ProcessedFrame, compact: bool = False) -> list[Output]:
        """Every payload of the frame, its maps kept for reuse; ``compact``: the 8-bit maps too (only while
        someone subscribes)."""
        encoded = self.encode(done, compact)
        self.keep(done.source, encoded)
        return encoded.outputs

    def keep(self, source: str, encoded: Encoded) -> None:
        """The source's last maps from now on: what its unchanged frames are answered with (reuse)."""
        if self.settings.reuse.enabled:
            self._last[source] = (encoded.maps, encoded.compact_maps)

    def encode(self, done: ProcessedFrame, compact: bool = False) -> Encoded:
        """Every payload of the frame, nothing kept yet."""
        t, u = done.result.maps.traversability, done.result.maps.uncertainty
        width, height = done.record.image_size
        ros_out = self.settings.ros_output.enabled and done.pending.ros is not None
        full = None
        if self.settings.full_resolution or ros_out:
            full = resize_map(t, width, height), resize_map(u, width, height)
        maps = self.maps(done, full)
        outputs = [Output(self.keys.maps(done.source), maps.pack(), "msgpack")]
        compact_maps = self.compact_maps(done, maps.header) if compact else None
        if compact_maps is not None:
            outputs.append(Output(self.keys.maps8(done.source), compact_maps.pack(), "msgpack"))
        panel = None
        if self.settings.preview or (ros_out and self.settings.ros_output.preview != "none"):
            panel = preview_panel(done.image.image, t, u, self.settings.preview_max_width)
        jpeg = encode_jpeg(panel, PREVIEW_JPEG_QUALITY) if panel is not None else None
        if self.settings.preview and jpeg is not None:
            outputs.append(Output(self.keys.preview(done.source), jpeg, "jpeg"))
        if ros_out and full is not None:
            outputs += self._ros_images(done, *full, panel, jpeg)
        if done.grid is not None:
            outputs += self._grid(done.grid.encode())
            outputs += self._question(done.grid)
        return Encoded(outputs, maps, compact_maps)

    def reused(self, pending: PendingFrame, stamp: float, frame_id: str, compact: bool = False) -> list[Output]:
        """The source's last maps again for an unchanged frame: this frame's stamp, key and order, the computed
        frame's seq and ``computed_from``. The grid, the preview and ROS images follow inferred frames only (a
        reused frame is no new evidence). Empty if no maps of the source are kept."""
        last = self._last.get(pending.source)
        if last is None:
            return []
        maps, compact_maps = last
        computed = maps.header.computed_from or (maps.header.stamp, maps.header.seq)
        now = time.time()
        update = {
            "key": pending.key,
            "stamp": stamp,
            "frame_id": frame_id,
            "received_at": pending.received_at,
            "published_at": now,
            "order": (stamp, pending.received_at),
            "computed_from": computed,
            "age_at_receipt_s": age_at_receipt(pending),
        }
        outputs = [Output(self.keys.maps(pending.source), _with_header(maps, update).pack(), "msgpack")]
        if compact and compact_maps is not None:
            compact_payload = _with_header(compact_maps, update).pack()
            outputs.append(Output(self.keys.maps8(pending.source), compact_payload, "msgpack"))
        return outputs

    def forget(self, source: str) -> None:
        self._last.pop(source, None)

    def maps(self, done: ProcessedFrame, full: tuple[NDArray[np.float32], NDArray[np.float32]] | None) -> MapsMessage:
        record, result = done.record, done.result
        header = MapsHeader(
            source=done.source,
            key=done.pending.key,
            seq=record.seq,
            stamp=done.image.stamp,
            frame_id=done.image.frame_id,
            received_at=done.pending.received_at,
            published_at=time.time(),
            inference_ms=result.inference_ms,
            model=self.model_id,
            instance=self.settings.instance,
            anchor_set_version=result.anchors.version,
            method=result.method,
            map_shape=record.map_shape,
            image_size=record.image_size,
            scale=record.scale,
            order=(done.image.stamp, done.pending.received_at),
            age_at_receipt_s=age_at_receipt(done.pending),
        )
        with_full = self.settings.full_resolution and full is not None
        maps = [result.maps.traversability, result.maps.uncertainty, *(full if with_full and full else ())]
        encoded = encode_maps_png16(*maps)
        return MapsMessage(
            header=header,
            traversability_png=encoded[0],
            uncertainty_png=encoded[1],
            traversability_full_png=encoded[2] if with_full else None,
            uncertainty_full_png=encoded[3] if with_full else None,
        )

    def compact_maps(self, done: ProcessedFrame, header: MapsHeader) -> CompactMapsMessage:
        """T and U as 8-bit PNGs, at the map's size or within ``compact_maps_max_side``."""
        height, width = done.record.map_shape
        side = self.settings.compact_maps_max_side
        if side is not None and max(width, height) > side:
            width, height = (
                max(1, round(width * side / max(width, height))),
                max(1, round(height * side / max(width, height))),
            )
        image_width, image_height = done.record.image_size
        header = header.model_copy(
            update={"map_shape": (height, width), "scale": (image_width / width, image_height / height)}
        )
        maps = done.result.maps
        return CompactMapsMessage(
            header=header,
            traversability_png=encode_map_png8(maps.traversability, (width, height)),
            uncertainty_png=encode_map_png8(maps.uncertainty, (width, height)),
        )

    def _ros_images(
        self,
        done: ProcessedFrame,
        t: NDArray[np.float32],
        u: NDArray[np.float32],
        panel: NDArray[np.uint8] | None,
        jpeg: bytes | None,
    ) -> list[Output]:
        """T and U as 32FC1 images at the input's size with the input's header, and the preview."""
        topic, header, names = done.pending.ros, done.inferred.ros_header, self.settings.ros_output
        assert topic is not None
        images = [
            (names.traversability_topic, ros_io.IMAGE, ros_io.float_image_cdr(header, t)),
            (names.uncertainty_topic, ros_io.IMAGE, ros_io.float_image_cdr(header, u)),
        ]
        if names.preview == "compressed" and jpeg is not None:  # image_transport: <base topic>/compressed
            compressed = ros_io.compressed_jpeg_cdr(header, jpeg)
            images.append((names.preview_topic + "/compressed", ros_io.COMPRESSED_IMAGE, compressed))
        elif names.preview == "image" and panel is not None:
            images.append((names.preview_topic, ros_io.IMAGE, ros_io.rgb_image_cdr(header, panel)))
        return [self._ros(topic, template, msgtype, payload, "image") for template, msgtype, payload in images]

    def _grid(self, update: GridUpdate) -> list[Output]:
        """The grid the frame's camera feeds, under the grid's source (the camera's own, or the grid's name)."""
        source, names = update.source, self.settings.ros_output
        outputs = [Output(self.keys.grid(source), update.message.pack(), "msgpack")]
        layers = (
            ("occupancy", update.occupancy, names.occupancy_topic, ros_io.OCCUPANCY_GRID),
            ("uncertainty", update.uncertainty, names.grid_uncertainty_topic, ros_io.OCCUPANCY_GRID),
            ("gridmap", update.grid_map, names.gridmap_topic, ros_io.GRID_MAP),
            ("costmap", update.costmap, names.costmap_topic, ros_io.OCCUPANCY_GRID),
            ("nav2_costmap", update.nav2_costmap, names.nav2_costmap_topic, ros_io.NAV2_COSTMAP),
        )
        for layer, payload, template, msgtype in layers:
            if payload is None:
                continue
            outputs.append(Output(self.keys.grid(source, layer), payload, "cdr"))
            if update.ros is not None and names.enabled:
                outputs.append(self._ros(update.ros, template, msgtype, payload, "grid"))
        if update.speed is not None:
            outputs += self.speed(update.speed)
        return outputs

    def speed(self, update: SpeedUpdate) -> list[Output]:
        """A grid's speed filter outputs: the mask (when due) with its filter info, and the SpeedLimit at the
        robot's pose (docs/grid.md, "Speed from uncertainty")."""
        source, names = update.source, self.settings.ros_output
        ros = update.ros if names.enabled else None
        outputs = [Output(self.keys.grid(source, "speed_limit"), update.limit, "cdr")]
        if ros is not None:
            outputs.append(self._ros(ros, names.speed_limit_topic, ros_io.SPEED_LIMIT, update.limit, "image"))
        if update.mask is None:
            return outputs
        outputs.append(Output(self.keys.grid(source, "speed_mask"), update.mask, "cdr"))
        if ros is not None:
            mask_topic = ros_io.output_topic(names.speed_mask_topic, ros.topic)
            info = ros_io.costmap_filter_info_cdr(update.frame_id, mask_topic)
            outputs.append(self._ros(ros, names.speed_filter_info_topic, ros_io.COSTMAP_FILTER_INFO, info, "latched"))
            outputs.append(self._ros(ros, names.speed_mask_topic, ros_io.OCCUPANCY_GRID, update.mask, "grid"))
        return outputs

    def _question(self, fused: FusedGrid) -> list[Output]:
        """The question the grid's fusion made the experience ask an operator, under the grid's source."""
        question = fused.question
        if question is None:
            return []
        log.info("question %s to the operator: %s ahead (%s)", question.id, question.reason, question.source)
        return [Output(self.keys.question(fused.config.source), question.pack(), "msgpack")]

    @staticmethod
    def _ros(camera: ros_io.RosTopic, template: str, msgtype: str, payload: bytes, qos: RosQos) -> Output:
        topic = camera.derived(ros_io.output_topic(template, camera.topic), msgtype)
        return Output(ros_io.topic_key(topic), payload, "cdr", topic, qos)


_Maps = TypeVar("_Maps", MapsMessage, CompactMapsMessage)


def age_at_receipt(pending: PendingFrame) -> float | None:
    """The frame's lag at intake, as the freshness gate judged it; a negative one (a clock slightly ahead) ages
    nothing there either."""
    return None if pending.lag_s is None else max(pending.lag_s, 0.0)


def _with_header(message: _Maps, update: dict[str, Any]) -> _Maps:
    """The message with some header fields replaced; the PNGs are shared, not copied."""
    return message.model_copy(update={"header": message.header.model_copy(update=update)})
