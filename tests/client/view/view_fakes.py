"""A stand-in for the service as the viewer sees it through TraversabilityClient: its zenoh subscriptions (the
test hands them samples), status, anchor-set and distribution queries. No zenoh session, no torch: the
viewer's Foxglove side runs for real."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.schemas.config import Method
from gcdtrav.schemas.images import encode_age_png, encode_count_png, encode_map_png16
from gcdtrav.schemas.keys import Keys
from gcdtrav.schemas.messages import (
    AnchorSetReply,
    ContextDistribution,
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
        """Deliver ``payload`` on ``key`` to the subscribers whose key expression includes it, as zenoh would."""
        for subscriber in self.subscribers:
            if zenoh.KeyExpr(subscriber.key).includes(zenoh.KeyExpr(key)):
                subscriber.callback(Sample(key, Payload(payload)))


@dataclass
class FakeClient:
    session: Session = field(default_factory=Session)
    anchor_queries: int = 0
    queries: list[tuple[str, str, float, float]] = field(default_factory=list)  # (patch|cell, source, x, y)

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

    def patch(self, source: str, x: float, y: float, timeout: float = 5.0) -> ContextDistribution:
        self.queries.append(("patch", source, x, y))
        return distribution(source, patch=(int(y), int(x)))

    def cell(self, source: str, x: float, y: float, timeout: float = 5.0) -> ContextDistribution:
        self.queries.append(("cell", source, x, y))
        return distribution(source)


def distribution(source: str, patch: tuple[int, int] | None = None) -> ContextDistribution:
    """A distribution with its risk measures (weights on 'mud' and 'grass'), as the service answers."""
    from gcdtrav.service.runtime.queries import distribution_of

    weights = np.full(len(PAPER), 0.01, np.float32)
    weights[[4, 9]] = 1.0
    answer = distribution_of(weights / weights.sum(), PAPER, source, 3, 100.0, "front", patch=patch)
    return answer.model_copy(update={"alpha": 0.1, "quantile": 0.3, "cvar": 0.25, "tau": 0.3, "p_below": 0.4})


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


def grid_payload(
    source: str, cells: int = 4, robot: tuple[float, float, float] | None = None, layers: bool = False
) -> bytes:
    """A grid of 0.5 m cells in odom, T 0.5 everywhere; with ``layers`` the 1.2 layers too (CVaR 0.25,
    P(T < 0.3) 0.75, match 0.9, ages 1.5 s), 1.5's speed (0.6) and cell (0, 0) unknown."""
    values = np.full((cells, cells), 0.5, np.float32)
    header = GridHeader(
        source=source, seq=0, stamp=100.0, frame_id="odom", origin=(0.0, 0.0), resolution=0.5, cells=cells,
        anchor_set_version=PAPER.version, resets=0, known_cells=cells * cells, instance="fake-1", robot=robot,
        alpha=0.1 if layers else None, tau=0.3 if layers else None,
    )  # fmt: skip
    count = np.ones((cells, cells), np.int64)
    extra: dict[str, bytes] = {}
    if layers:
        count[0, 0] = 0
        extra = {
            "cvar_png": encode_map_png16(values / 2),
            "p_below_png": encode_map_png16(np.full_like(values, 0.75)),
            "match_png": encode_map_png16(np.full_like(values, 0.9)),
            "age_png": encode_age_png(np.where(count > 0, 1.5, np.nan)),
            "speed_png": encode_map_png16(np.full_like(values, 0.6)),
        }
    return GridMessage(
        header=header,
        traversability_png=encode_map_png16(values),
        uncertainty_png=encode_map_png16(values / 2),
        count_png=encode_count_png(count),
        **extra,
    ).pack()
