"""Counters, latency percentiles and rate-limited error logging; their snapshot for the status queryable."""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from gcdtrav.schemas.messages import SourceStatus
from gcdtrav.service.runtime.schedule.latest_queue import QueueCounters
from gcdtrav.service.runtime.schedule.share import Share

LATENCY_WINDOW = 1000
RATE_WINDOW_S = 10.0
ERROR_LOG_INTERVAL_S = 5.0
LAST_ERRORS = 20
REFUSED_SOURCES = 32  # untracked sources shown with their counts (a camera whose every frame fails), newest kept


def percentiles(values: deque[float], levels: tuple[int, ...] = (50, 90, 99)) -> dict[str, float]:
    """{"p50": ..., ...} at ``levels``, rounded to 0.01; {} for no values."""
    if not values:
        return {}
    found = np.percentile(np.fromiter(values, dtype=np.float64), levels)
    return {f"p{level}": round(float(value), 2) for level, value in zip(levels, found, strict=True)}


@dataclass
class SourceStats:
    processed: int = 0
    rejected: int = 0
    dropped: int = 0  # taken or finished but not published (shutdown, ...); the queue counts replaced frames
    last_seq: int | None = None
    latency_ms: deque[float] = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))
    inference_ms: deque[float] = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))
    stale: int = 0  # of the dropped: captured over max_frame_age_s ago
    credits: int = 0
    unchanged: int = 0  # not inferred: the view had not changed, the last maps were published again
    age_ms: deque[float] = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))  # lag at intake
    arrivals: deque[tuple[float, int]] = field(default_factory=deque)  # (monotonic time, bytes), last 10 s
    dropped_by: Counter[str] = field(default_factory=Counter)  # what the queue does not count (replaced)
    rejected_by: Counter[str] = field(default_factory=Counter)
    problem: str = ""  # why its last frame gave no maps (reason: detail); cleared by published maps
    refused_at: float = 0.0  # monotonic; a refused source is listed until idle_s after its last refusal

    def note_problem(self, reason: str, detail: str) -> None:
        self.problem = f"{reason}: {detail}"[:300] if detail else reason

    def absorb(self, other: SourceStats) -> None:
        """Add a refused source's counts of another stretch (it was forgotten and came back)."""
        self.dropped += other.dropped
        self.rejected += other.rejected
        self.stale += other.stale
        self.credits += other.credits
        self.dropped_by.update(other.dropped_by)
        self.rejected_by.update(other.rejected_by)
        self.problem = other.problem or self.problem

    def bytes_per_s(self, now: float) -> float | None:
        while self.arrivals and self.arrivals[0][0] < now - RATE_WINDOW_S:
            self.arrivals.popleft()
        if not self.arrivals:
            return None
        # Over the window, or over what the capped deque still holds of it at high frame rates.
        span = RATE_WINDOW_S if len(self.arrivals) < LATENCY_WINDOW else max(now - self.arrivals[0][0], 1e-3)
        return round(sum(n for _, n in self.arrivals) / span, 1)


class FrameEvents(Protocol):
    """Timings observed as they happen (the metrics' histograms, service/runtime/metrics.py); counts are not
    here: they are read from the snapshot when asked."""

    def waited(self, wait_s: float) -> None:
        """A frame was taken for inference ``wait_s`` after its receipt."""

    def inferred(self, inference_s: float) -> None:
        """A frame's inference took ``inference_s``."""

    def published(self, source: str, map_age_s: float) -> None:
        """Maps of ``source`` went out, inferred or reused, ``map_age_s`` old as the freshness rule judged them."""

    def forget(self, source: str) -> None:
        """``source`` is forgotten: its series go."""


class NoEvents:
    """Timings observed by nobody."""

    def waited(self, wait_s: float) -> None:
        pass

    def inferred(self, inference_s: float) -> None:
        pass

    def published(self, source: str, map_age_s: float) -> None:
        pass

    def forget(self, source: str) -> None:
        pass


@dataclass(frozen=True)
class StatsSnapshot:
    """The status's counting part, read under one lock so its numbers agree with each other."""

    sources: dict[str, SourceStatus]
    rejected_by_reason: dict[str, int]
    dropped_by_reason: dict[str, int]
    last_errors: list[str]


class ServiceStats:
    """Thread-safe; written by the subscriber callbacks and the worker, read by the status query."""

    def __init__(self, log: logging.Logger, idle_s: float = 300.0, events: FrameEvents | None = None) -> None:
        self._lock = threading.Lock()
        self._log = log
        self.events: FrameEvents = events or NoEvents()  # the timings, told outside the lock
        self.idle_s = idle_s  # source_idle_s: refused sources are listed that long after their last frame
        self.sources: dict[str, SourceStats] = {}
        # Sources refused before they took a slot (every frame stale, or undecodable): their counts are kept,
        # bounded, so that the status shows them with why; an invented name costs one entry at most, briefly.
        self.refused: OrderedDict[str, SourceStats] = OrderedDict()
        self.rejected_by_reason: Counter[str] = Counter()
        self.dropped_by_reason: Counter[str] = Counter()
        self.last_errors: deque[str] = deque(maxlen=LAST_ERRORS)
        self._last_logged: dict[str, float] = {}
        self._suppressed: Counter[str] = Counter()

    def processed(
        self, name: str, seq: int, latency_ms: float, inference_ms: float, map_age_s: float | None = None
    ) -> None:
        """Inferred maps of ``name`` went out; ``map_age_s``: their age as judged before publishing."""
        self.events.inferred(inference_ms / 1e3)
        if map_age_s is not None:
            self.events.published(name, map_age_s)
        with self._lock:
            stats = self.sources.setdefault(name, SourceStats())
            stats.processed += 1
            stats.last_seq = seq
            stats.problem = ""
            self.refused.pop(name, None)  # served now: its refused stretch is history
            stats.latency_ms.append(latency_ms)
            stats.inference_ms.append(inference_ms)

    def unchanged(self, name: str, map_age_s: float | None = None) -> None:
        """A frame whose view had not changed: not inferred, the source's last maps published again."""
        if map_age_s is not None:
            self.events.published(name, map_age_s)
        with self._lock:
            stats = self.sources.setdefault(name, SourceStats())
            stats.unchanged += 1
            stats.problem = ""

    def dropped(self, name: str, reason: str, count: int = 1) -> None:
        """Count good frames that will never be published, by reason."""
        with self._lock:
            stats = self.sources.setdefault(name, SourceStats())
            stats.dropped += count
            stats.dropped_by[reason] += count
            stats.note_problem(reason, "")
            self.dropped_by_reason[reason] += count

    def intake(self, name: str, nbytes: int, age_s: float | None) -> None:
        """A frame of ``name`` reached the service: its bytes and, when stamped, its age at intake (its lag,
        service/runtime/intake/freshness.py)."""
        with self._lock:
            stats = self.sources.setdefault(name, SourceStats())
            stats.arrivals.append((time.monotonic(), nbytes))
            if len(stats.arrivals) > LATENCY_WINDOW:
                stats.arrivals.popleft()
            if age_s is not None:
                stats.age_ms.append(age_s * 1e3)

    def stale(self, name: str, detail: str = "") -> None:
        """A frame older than max_frame_age_s, dropped: counted stale and dropped (reason ``stale``), and
        logged at the rate limit: a robot whose clock is off would otherwise lose every frame in silence."""
        with self._lock:
            stats = self.sources.setdefault(name, SourceStats())
            stats.stale += 1
            stats.dropped += 1
            stats.dropped_by["stale"] += 1
            stats.note_problem("stale", detail)
            self.dropped_by_reason["stale"] += 1
        if detail:
            self._log_limited("stale", f"dropped {name}: stale: {detail}")

    def waited(self, wait_s: float) -> None:
        """A frame was taken for inference ``wait_s`` after its receipt."""
        self.events.waited(max(wait_s, 0.0))

    def credit(self, name: str) -> None:
        with self._lock:
            self.sources.setdefault(name, SourceStats()).credits += 1

    def forget(self, name: str) -> None:
        """The service lets the source go. One that never got maps but had frames dropped or rejected stays
        listed as refused (bounded), with its counts and why: else a camera whose every frame is stale, or
        undecodable, would be invisible."""
        with self._lock:
            stats = self.sources.pop(name, None)
            if stats is not None and stats.processed == 0 and stats.dropped + stats.rejected > 0:
                self._refused_entry(name).absorb(stats)
        self.events.forget(name)

    def _refused_entry(self, name: str) -> SourceStats:
        entry = self.refused.pop(name, None) or SourceStats()
        entry.refused_at = time.monotonic()
        self.refused[name] = entry  # the newest last
        while len(self.refused) > REFUSED_SOURCES:
            self.refused.popitem(last=False)
        return entry

    def _expire_refused(self) -> None:
        horizon = time.monotonic() - self.idle_s
        while self.refused and next(iter(self.refused.values())).refused_at < horizon:
            self.refused.popitem(last=False)

    def problem(self, name: str) -> str:
        """Why ``name``'s last frame gave no maps, or ''."""
        with self._lock:
            stats = self.sources.get(name)
            refused = self.refused.get(name)
        return (stats.problem if stats is not None else "") or (refused.problem if refused is not None else "")

    def rejected(
        self, name: str | None, reason: str, detail: str, error: BaseException | None = None, tracked: bool = True
    ) -> None:
        """Count a bad input and log it (with ``error``'s traceback), at most once per reason every few seconds.
        ``tracked`` False: ``name`` holds no slot (a refused new source); counted in the bounded refused list."""
        message = f"{name or '-'}: {reason}: {detail}"
        with self._lock:
            if name is not None:
                stats = self.sources.setdefault(name, SourceStats()) if tracked else self._refused_entry(name)
                stats.rejected += 1
                stats.rejected_by[reason] += 1
                stats.note_problem(reason, detail)
            self.rejected_by_reason[reason] += 1
            self.last_errors.append(f"{time.strftime('%H:%M:%S')} {message}")
        self._log_limited(reason, f"rejected {message}", error)

    def rejected_unread(self, reason: str, detail: Callable[[], str]) -> None:
        """Count a frame refused before anything of it was read, by reason only (a flood's cost stays a
        counter); ``detail`` is built only when it is logged."""
        with self._lock:
            self.rejected_by_reason[reason] += 1
            if time.monotonic() - self._last_logged.get(reason, -1e9) < ERROR_LOG_INTERVAL_S:
                self._suppressed[reason] += 1
                return
            message = f"-: {reason}: {detail()}"
            self.last_errors.append(f"{time.strftime('%H:%M:%S')} {message}")
        self._log_limited(reason, f"rejected {message}")

    def _log_limited(self, reason: str, message: str, error: BaseException | None = None) -> None:
        """Log at most once per reason every ERROR_LOG_INTERVAL_S, saying how many were suppressed."""
        with self._lock:
            now = time.monotonic()
            if now - self._last_logged.get(reason, -1e9) < ERROR_LOG_INTERVAL_S:
                self._suppressed[reason] += 1
                return
            self._last_logged[reason] = now
            suppressed = self._suppressed.pop(reason, 0)
        extra = f" (+{suppressed} similar since last report)" if suppressed else ""
        self._log.warning("%s%s", message, extra, exc_info=error)

    def snapshot(
        self,
        queued: Mapping[str, QueueCounters],
        clock_offsets: Mapping[str, float] | None = None,
        shares: Mapping[str, Share] | None = None,
    ) -> StatsSnapshot:
        """Per source: the queue's counts (received, dropped) with this object's (processed, rejected, latency),
        its clock's offset as learnt (service/runtime/intake/clock_offset.py) and the scheduler's weight and share."""
        offsets, shares = clock_offsets or {}, shares or {}
        with self._lock:
            sources = {
                name: self._source_status(queued.get(name), name, offsets.get(name), shares.get(name))
                for name in sorted(set(queued) | set(self.sources))
            }
            self._expire_refused()
            for name, refused in self.refused.items():
                if name not in sources:
                    sources[name] = self._refused_status(refused)
            sources = dict(sorted(sources.items()))
            replaced = sum(counters.dropped for counters in queued.values())
            dropped = {**({"replaced": replaced} if replaced else {}), **self.dropped_by_reason}
            return StatsSnapshot(sources, dict(self.rejected_by_reason), dropped, list(self.last_errors))

    def _source_status(
        self, queued: QueueCounters | None, name: str, clock_offset_s: float | None, share: Share | None
    ) -> SourceStatus:
        stats = self.sources.get(name, SourceStats())
        return SourceStatus(
            received=queued.received if queued else 0,
            dropped=(queued.dropped if queued else 0) + stats.dropped,
            processed=stats.processed,
            rejected=stats.rejected,
            last_seq=stats.last_seq,
            latency_ms=percentiles(stats.latency_ms),
            inference_ms=percentiles(stats.inference_ms),
            stale=stats.stale,
            bytes_per_s=stats.bytes_per_s(time.monotonic()),
            frame_age_ms=percentiles(stats.age_ms, (50, 95)),
            credits=stats.credits,
            clock_offset_s=None if clock_offset_s is None else round(clock_offset_s, 3),
            dropped_by_reason=self._dropped_by(stats, queued),
            rejected_by_reason=dict(stats.rejected_by),
            problem=stats.problem,
            unchanged=stats.unchanged,
            weight=share.weight if share is not None else None,
            share=share.share if share is not None else None,
        )

    @staticmethod
    def _dropped_by(stats: SourceStats, queued: QueueCounters | None) -> dict[str, int]:
        replaced = queued.dropped if queued is not None else 0
        return dict(stats.dropped_by) | ({"replaced": replaced} if replaced else {})

    @staticmethod
    def _refused_status(stats: SourceStats) -> SourceStatus:
        """A source without a slot: only the frames counted against it, every one dropped or rejected."""
        return SourceStatus(
            received=stats.dropped + stats.rejected,
            dropped=stats.dropped,
            rejected=stats.rejected,
            stale=stats.stale,
            credits=stats.credits,
            dropped_by_reason=dict(stats.dropped_by),
            rejected_by_reason=dict(stats.rejected_by),
            problem=stats.problem,
            refused=True,
        )
