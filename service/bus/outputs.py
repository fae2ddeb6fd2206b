"""Puts each processed frame's payloads, encoded in the runtime (``service/runtime/outputs.py``), on their keys
and ROS topics: the runtime's ``OutputSink``.

Publishers are declared once per key with congestion control DROP, so a slow consumer loses samples
instead of blocking inference. After ``close`` nothing is published: a frame finished during shutdown is
refused (``publish`` returns False) instead of racing the undeclaration.
"""

from __future__ import annotations

import logging
import threading

import zenoh
from gcdtrav.schemas.keys import Keys
from gcdtrav.schemas.messages import MSGPACK_ENCODING
from gcdtrav.service.bus.entities import undeclare_all
from gcdtrav.service.bus.ros_graph import GRID_QOS, IMAGE_QOS, RosGraph
from gcdtrav.service.runtime.outputs import Output

log = logging.getLogger("gcdtrav.service")
ENCODINGS = {
    "msgpack": zenoh.Encoding(MSGPACK_ENCODING),
    "jpeg": zenoh.Encoding.IMAGE_JPEG,
    "cdr": zenoh.Encoding.APPLICATION_CDR,
}


class FrameOutputs:
    def __init__(self, session: zenoh.Session, keys: Keys, ros_graph: RosGraph | None = None) -> None:
        self.session, self.keys, self.ros_graph = session, keys, ros_graph
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._keys_of_source: dict[str, set[str]] = {}
        self._ros_keys_of_source: dict[str, set[str]] = {}  # publishers (and their tokens) of the ROS graph
        self._latched: dict[str, bytes] = {}  # key -> the last payload put of a "latched" output
        self._lock = threading.Lock()  # publishing, forgetting and closing exclude each other
        self._closed = False

    def put(self, source: str, outputs: list[Output]) -> bool:
        """Put a frame's outputs; False (nothing put) once closed."""
        with self._lock:
            if self._closed:
                return False
            for output in outputs:
                self._put(source, output)
            return True

    def _put(self, source: str, output: Output) -> None:
        if output.qos == "latched":  # put once: its publisher's cache holds it for late subscribers
            if self._latched.get(output.key) == output.payload:
                return
            self._latched[output.key] = output.payload
        topic = output.topic
        if topic is not None and topic.layout == "rmw_zenoh" and self.ros_graph is not None:
            # On an rmw_zenoh robot through the graph (MP token, attachment); on a bridge robot, plainly.
            publisher = self.ros_graph.publisher(
                topic, IMAGE_QOS if output.qos == "image" else GRID_QOS, ENCODINGS["cdr"]
            )
            self._ros_keys_of_source.setdefault(source, set()).add(publisher.key)
            publisher.put(output.payload)
            return
        self._publisher(source, output.key, output.encoding).put(output.payload)

    def _publisher(self, source: str, key: str, encoding: str) -> zenoh.Publisher:
        """The key's publisher, declared at its first use (under ``_lock``)."""
        publisher = self._publishers.get(key)
        if publisher is None:
            publisher = self.session.declare_publisher(
                key, encoding=ENCODINGS[encoding], congestion_control=zenoh.CongestionControl.DROP
            )
            self._publishers[key] = publisher
            self._keys_of_source.setdefault(source, set()).add(key)
        return publisher

    def wants_compact(self, source: str) -> bool:
        """Whether anyone subscribes to the source's compact maps: they are encoded only then. The publisher
        is declared with the source's first frame; zenoh knows its matching subscribers from then on."""
        with self._lock:
            if self._closed:
                return False
            publisher = self._publisher(source, self.keys.maps8(source), "msgpack")
            status = publisher.matching_status  # a MatchingStatus at runtime (the 1.x stub says bool)
            return bool(getattr(status, "matching", status))

    def forget(self, source: str) -> None:
        """Undeclare the publishers of a source the service no longer tracks."""
        with self._lock:  # the sweep runs on the worker, publishing maybe on the output thread
            keys = self._keys_of_source.pop(source, set())
            publishers = [self._publishers.pop(key) for key in keys]
            ros_keys = self._ros_keys_of_source.pop(source, set())
            for key in keys | ros_keys:
                self._latched.pop(key, None)  # a publisher declared again puts its latched payload again
            if self.ros_graph is not None:
                self.ros_graph.forget(ros_keys)
            undeclare_all(publishers)

    def close(self) -> None:
        with self._lock:
            self._closed = True
            undeclare_all(self._publishers.values())
            self._publishers.clear()
            self._keys_of_source.clear()
            self._ros_keys_of_source.clear()
            self._latched.clear()
