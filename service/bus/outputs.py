"""What the service publishes for each processed frame: maps, preview, ROS images, ground grid.

Publishers are declared once per key with congestion control DROP, so a slow consumer loses samples
instead of blocking inference.
"""

from __future__ import annotations

import logging
import threading
import time

import cv2
import numpy as np
import zenoh
from gcdtrav.schemas.images import decode_image, encode_jpeg, encode_maps_png16, resize_map
from gcdtrav.schemas.keys import Keys
from gcdtrav.schemas.messages import MSGPACK_ENCODING, MapsHeader, MapsMessage
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service import viz
from gcdtrav.service.bus.ros_graph import GRID_QOS, IMAGE_QOS, Qos, RosGraph
from gcdtrav.service.ros import cdr as ros_io
from gcdtrav.service.runtime.frames import ProcessedFrame
from gcdtrav.service.runtime.grids import GridOutputs

log = logging.getLogger("gcdtrav.service")
MSGPACK = zenoh.Encoding(MSGPACK_ENCODING)
CDR = zenoh.Encoding.APPLICATION_CDR


def preview_jpeg(image: np.ndarray, t: np.ndarray, u: np.ndarray, max_width: int) -> bytes:
    """T over the image, beside U, scaled to at most ``max_width``."""
    left = viz.overlay(image, viz.colorize_traversability(t))
    panel = np.concatenate([left, viz.colorize_uncertainty(u)], axis=1)
    if panel.shape[1] > max_width:
        size = (max_width, max(1, round(panel.shape[0] * max_width / panel.shape[1])))
        panel = cv2.resize(panel, size, interpolation=cv2.INTER_AREA)
    return encode_jpeg(panel, quality=80)


class FrameOutputs:
    def __init__(
        self,
        session: zenoh.Session,
        settings: ServiceSettings,
        model_id: str,
        grids: GridOutputs | None,
        ros_graph: RosGraph | None = None,
    ) -> None:
        self.session = session
        self.settings = settings
        self.keys = Keys(settings.prefix)
        self.model_id = model_id
        self.grids = grids
        self.ros_graph = ros_graph
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._keys_of_source: dict[str, set[str]] = {}
        self._ros_keys_of_source: dict[str, set[str]] = {}  # publishers (and their tokens) of the ROS graph
        self._declare_lock = threading.Lock()

    def publish(self, done: ProcessedFrame) -> None:
        t, u = done.result.maps.traversability, done.result.maps.uncertainty
        width, height = done.record.image_size
        ros_out = self.settings.ros_output.enabled and done.pending.ros is not None
        full = None
        if self.settings.full_resolution or self.settings.preview or ros_out:
            full = resize_map(t, width, height), resize_map(u, width, height)
        self._put(done.source, self.keys.maps(done.source), self._maps(done, full).pack(), MSGPACK)
        preview = None
        if self.settings.preview and full is not None:
            preview = preview_jpeg(done.image.image, *full, self.settings.preview_max_width)
            self._put(done.source, self.keys.preview(done.source), preview, zenoh.Encoding.IMAGE_JPEG)
        if ros_out and done.pending.ros is not None and full is not None:
            self._publish_ros(done, *full, preview)
        if self.grids is not None:
            self._publish_grid(done)

    def _maps(self, done: ProcessedFrame, full: tuple[np.ndarray, np.ndarray] | None) -> MapsMessage:
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

    def _publish_ros(self, done: ProcessedFrame, t: np.ndarray, u: np.ndarray, preview: bytes | None) -> None:
        """T and U as 32FC1 images (and the preview) at the input's size, with the input's header."""
        topic, header, names = done.pending.ros, done.inferred.ros_header, self.settings.ros_output
        assert topic is not None
        outputs = [
            (names.traversability_topic, ros_io.IMAGE, ros_io.float_image_cdr(header, t)),
            (names.uncertainty_topic, ros_io.IMAGE, ros_io.float_image_cdr(header, u)),
        ]
        kind = names.preview
        if kind != "none":
            jpeg = (
                preview
                if preview is not None
                else preview_jpeg(done.image.image, t, u, self.settings.preview_max_width)
            )
            if kind == "compressed":  # image_transport: <base topic>/compressed
                compressed = ros_io.compressed_jpeg_cdr(header, jpeg)
                outputs.append((names.preview_topic + "/compressed", ros_io.COMPRESSED_IMAGE, compressed))
            else:
                outputs.append((names.preview_topic, ros_io.IMAGE, ros_io.rgb_image_cdr(header, decode_image(jpeg))))
        for template, msgtype, payload in outputs:
            output = topic.derived(ros_io.output_topic(template, topic.topic), msgtype)
            self._put_ros(done.source, output, payload, IMAGE_QOS)

    def _publish_grid(self, done: ProcessedFrame) -> None:
        assert self.grids is not None
        update = self.grids.on_frame(done.source, done.record, done.result.maps.weights)
        if update is None:
            return
        self._put(done.source, self.keys.grid(done.source), update.message.pack(), MSGPACK)
        if update.occupancy is not None and update.uncertainty is not None:
            self._put(done.source, self.keys.grid(done.source, "occupancy"), update.occupancy, CDR)
            self._put(done.source, self.keys.grid(done.source, "uncertainty"), update.uncertainty, CDR)
            camera = done.pending.ros
            if camera is not None and self.settings.ros_output.enabled:
                names = self.settings.ros_output
                for template, payload in (
                    (names.occupancy_topic, update.occupancy),
                    (names.grid_uncertainty_topic, update.uncertainty),
                ):
                    grid_topic = camera.derived(ros_io.output_topic(template, camera.topic), ros_io.OCCUPANCY_GRID)
                    self._put_ros(done.source, grid_topic, payload, GRID_QOS)

    def _put_ros(self, source: str, topic: ros_io.RosTopic, payload: bytes, qos: Qos) -> None:
        """On an rmw_zenoh robot through the graph (MP token, attachment); on a bridge robot, plainly."""
        if topic.layout != "rmw_zenoh" or self.ros_graph is None:
            self._put(source, ros_io.topic_key(topic), payload, CDR)
            return
        publisher = self.ros_graph.publisher(topic, qos, CDR)
        with self._declare_lock:
            self._ros_keys_of_source.setdefault(source, set()).add(publisher.key)
        publisher.put(payload)

    def _put(
        self, source: str, key: str, payload: bytes, encoding: zenoh.Encoding, attachment: bytes | None = None
    ) -> None:
        publisher = self._publishers.get(key)
        if publisher is None:
            publisher = self.session.declare_publisher(
                key, encoding=encoding, congestion_control=zenoh.CongestionControl.DROP
            )
            with self._declare_lock:
                self._publishers[key] = publisher
                self._keys_of_source.setdefault(source, set()).add(key)
        if attachment is None:
            publisher.put(payload)
        else:
            publisher.put(payload, attachment=attachment)

    def forget(self, source: str) -> None:
        """Undeclare the publishers of a source the service no longer tracks."""
        with self._declare_lock:  # the sweep runs on the worker, publishing maybe on the output thread
            keys = self._keys_of_source.pop(source, set())
            publishers = [self._publishers.pop(key) for key in keys]
            ros_keys = self._ros_keys_of_source.pop(source, set())
        if self.ros_graph is not None:
            self.ros_graph.forget(ros_keys)
        for publisher in publishers:
            self._undeclare(publisher)

    def close(self) -> None:
        for publisher in self._publishers.values():
            self._undeclare(publisher)
        self._publishers.clear()
        self._keys_of_source.clear()
        self._ros_keys_of_source.clear()

    @staticmethod
    def _undeclare(publisher: zenoh.Publisher) -> None:
        try:
            publisher.undeclare()
        except zenoh.ZError as err:  # the session may already be closing
            log.debug("undeclare failed: %s", err)
