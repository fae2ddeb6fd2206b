"""A stand-in for the service as the viewer sees it through TraversabilityClient: its zenoh subscriptions (the
test hands them samples), status and anchor-set queries. No zenoh, no torch: the viewer's Foxglove side runs
for real."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.schemas.config import Method
from gcdtrav.schemas.images import encode_count_png, encode_map_png16
from gcdtrav.schemas.keys import Keys
from gcdtrav.schemas.messages import (
    AnchorSetReply,
    GridHeader,
    GridMessage,
    MapsHeader,
    MapsMessage,
    ServiceStatus,
)

KEYS = Keys("gcdtrav")
PAPER = default_anchor_set()


@dataclass
class Payload:
    data: bytes

    def to_bytes(self) -> bytes:
        return self.data


@dataclass
class Sample:
    key_expr: str
    payload: Payload


@dataclass
class Subscriber:
    key: str
    callback: Callable[[Sample], None]

    def undeclare(self) -> None:
        pass


@dataclass
class Session:
    subscribers: list[Subscriber] = field(default_factory=list)

    def declare_subscriber(self, key: str, callback: Callable[[Sample], None]) -> Subscriber:
        self.subscribers.append(Subscriber(key, callback))
        return self.subscribers[-1]

    def put(self, key: str, payload: bytes) -> None:
        """Deliver ``payload`` on ``key`` to the subscriber whose key's kind (last level) matches."""
        for subscriber in self.subscribers:
            if subscriber.key.rsplit("/", 1)[-1] == key.rsplit("/", 1)[-1]:
                subscriber.callback(Sample(key, Payload(payload)))


@dataclass
class FakeClient:
    session: Session = field(default_factory=Session)
    anchor_queries: int = 0

    def statuses(self, timeout: float = 5.0) -> list[ServiceStatus]:
        return [
            ServiceStatus(
                instance="fake-1", uptime_s=1.0, model="tiny", anchor_set_version=PAPER.version,
                method=Method.GCD, queued=0, sources={}, rejected_by_reason={}, last_errors=[],
            )
        ]  # fmt: skip

    def anchors(self, timeout: float = 5.0) -> AnchorSetReply:
        self.anchor_queries += 1
        return AnchorSetReply(anchor_set=PAPER, version=PAPER.version)

    def set_anchors(self, *args: Any, **kwargs: Any) -> None:
        raise AssertionError("not in these tests")


def maps_payload(source: str, map_shape: tuple[int, int], image_size: tuple[int, int], seq: int = 0) -> bytes:
    rows, columns = map_shape
    t = np.linspace(0, 1, rows * columns, dtype=np.float32).reshape(rows, columns)
    header = MapsHeader(
        source=source, key=f"gcdtrav/in/{source}", seq=seq, stamp=100.0 + seq, frame_id="front",
        received_at=100.0, published_at=100.0, inference_ms=1.0, model="tiny", instance="fake-1",
        anchor_set_version=PAPER.version, method=Method.GCD, map_shape=map_shape, image_size=image_size,
        scale=(image_size[0] / columns, image_size[1] / rows),
    )  # fmt: skip
    return MapsMessage(
        header=header, traversability_png=encode_map_png16(t), uncertainty_png=encode_map_png16(t / 2)
    ).pack()


def grid_payload(source: str, cells: int = 4) -> bytes:
    values = np.full((cells, cells), 0.5, np.float32)
    header = GridHeader(
        source=source, seq=0, stamp=100.0, frame_id="odom", origin=(0.0, 0.0), resolution=0.5, cells=cells,
        anchor_set_version=PAPER.version, resets=0, known_cells=cells * cells, instance="fake-1",
    )  # fmt: skip
    count = np.ones((cells, cells), np.int64)
    return GridMessage(
        header=header,
        traversability_png=encode_map_png16(values),
        uncertainty_png=encode_map_png16(values / 2),
        count_png=encode_count_png(count),
    ).pack()
