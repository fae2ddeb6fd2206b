"""Credits: the service tells a source's sender when it is ready for the next frame. No zenoh here.

A robot on a slow link should send a frame only when the service will compute it: every frame sent while
one already waits is replaced unseen, its bytes wasted on the link. The instance that owns a source (only it
takes the source's frames) grants a credit whenever the source's slot frees: its frame went to inference, or
was refused at intake (stale, over a limit). The sender (``gcdtrav relay``) then sends its newest frame, so
at most one frame of the source is inferred and one waits. Lost credits are the sender's to recover (it sends
after a timeout); the ledger only numbers and describes the grants (the words of their reasons are
schemas/messages/credits.py's).

Credits follow the scheduler's shares (service/runtime/schedule/share.py): a frame to infer frees its slot when the
worker takes it, so a source's credits come at its share of the inference, a low-weight source's less often.
A frame whose view had not changed frees it as soon as it is answered with the last maps (``unchanged``): a
parked robot sends at its camera's rate, and a change is seen at its next frame. A view unchanged past
``max_reuse_s`` waits for its refresh (the scheduler's lowest need) and frees the slot at once
(``refresh``), so the robot's next unchanged frames are still answered meanwhile.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Protocol

from gcdtrav.schemas.messages import CreditGrant
from gcdtrav.schemas.messages.credits import TAKEN
from gcdtrav.service.runtime.frames import FrameTimes, PendingFrame
from gcdtrav.service.runtime.stats import ServiceStats


class CreditLedger:
    """Thread-safe: grants come from the subscriber callbacks (refusals) and the worker (takes)."""

    def __init__(
        self,
        instance: str,
        model_input: tuple[int, int],
        max_frame_age_s: float | None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.instance = instance
        self.model_input = model_input
        self.max_frame_age_s = max_frame_age_s
        self._clock = clock
        self._granted: dict[str, int] = {}
        self._last_maps: dict[str, float] = {}
        self._lock = threading.Lock()

    def freed(
        self, source: str, reason: str, frame: FrameTimes | None = None, problem: str | None = None
    ) -> CreditGrant:
        """The source's slot is free: the grant to publish on ``{prefix}/credit/{source}``; ``problem``: why
        the source's last frame gave no maps (the stats' count), so that the robot side sees it."""
        with self._lock:
            number = self._granted.get(source, 0)
            self._granted[source] = number + 1
            last_maps = self._last_maps.get(source)
        return CreditGrant(
            source=source,
            instance=self.instance,
            grant=number,
            reason=reason,
            granted_at=self._clock(),
            model_input=self.model_input,
            max_frame_age_s=self.max_frame_age_s,
            frame_stamp=frame.stamp if frame else None,
            frame_sent_at=frame.sent_at if frame else None,
            frame_received_at=frame.received_at if frame else None,
            last_maps_stamp=last_maps,
            problem=problem or None,
        )

    def published(self, source: str, stamp: float) -> None:
        """Maps of ``source`` captured at ``stamp`` went out: later grants say so."""
        with self._lock:
            self._last_maps[source] = max(stamp, self._last_maps.get(source, stamp))

    def forget(self, source: str) -> None:
        with self._lock:
            self._granted.pop(source, None)
            self._last_maps.pop(source, None)


class CreditSink(Protocol):
    """Where grants go: the bus puts them on ``{prefix}/credit/{source}`` (service/bus/credits.py)."""

    def put(self, source: str, grant: CreditGrant) -> bool:
        """Put the grant; False, nothing put, once closed (shutdown)."""
        ...

    def forget(self, source: str) -> None: ...


class Credits:
    """The runtime's side of the credits: when a slot frees (admission's refusals, the worker's takes, the
    triage's answers), the ledger's grant, with the source's problem, goes to the sink and is counted."""

    def __init__(self, ledger: CreditLedger, stats: ServiceStats, sink: CreditSink) -> None:
        self.ledger, self.stats, self.sink = ledger, stats, sink

    def freed(self, source: str, reason: str, times: FrameTimes | None) -> None:
        """The source's slot is free (called from subscriber callbacks and the worker)."""
        if self.sink.put(source, self.ledger.freed(source, reason, times, self.stats.problem(source))):
            self.stats.credit(source)

    def taken(self, pending: PendingFrame) -> None:
        self.freed(pending.source, TAKEN, pending.times)

    def published(self, source: str, stamp: float) -> None:
        """Maps of ``source`` captured at ``stamp`` went out: later credits say how fresh the maps are."""
        self.ledger.published(source, stamp)

    def answered(self, pending: PendingFrame, reason: str) -> None:
        """The frame freed its slot without being taken: answered with the last maps (``unchanged``), or
        waiting for its refresh (``refresh``)."""
        self.freed(pending.source, reason, pending.times)

    def forget(self, source: str) -> None:
        self.ledger.forget(source)
        self.sink.forget(source)
