"""What the subscriber callback checks before a frame takes any state, in order: the source's name, the
source cap, the payload's size (refused unread: never copied out of the middleware's buffer) and the pending
frames' byte budget. No middleware here: the bus hands over the source, the size and a way to read."""

from __future__ import annotations

import time
from collections.abc import Callable

from gcdtrav.schemas.limits import MAX_SOURCE_CHARS
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.ros.cdr import RosTopic
from gcdtrav.service.runtime.frames import PendingFrame
from gcdtrav.service.runtime.latest_queue import LatestFrameQueue, PendingBudgetExceeded
from gcdtrav.service.runtime.sources import SourceTracker
from gcdtrav.service.runtime.stats import ServiceStats


class Admission:
    def __init__(
        self,
        settings: ServiceSettings,
        sources: SourceTracker,
        queue: LatestFrameQueue[PendingFrame],
        stats: ServiceStats,
    ) -> None:
        self.settings, self.sources, self.queue, self.stats = settings, sources, queue, stats

    def offer(
        self, source: str, key: str, size: int, read: Callable[[], bytes], encoding: str, ros: RosTopic | None = None
    ) -> bool:
        """Queue the frame as the source's newest, or count why not; True if queued."""
        if len(source) > MAX_SOURCE_CHARS:
            self.stats.rejected(
                None, "source_name_too_long", f"'{source[:60]}...' is over {MAX_SOURCE_CHARS} characters"
            )
            return False
        if not self.sources.admit(source):
            self.stats.rejected(
                None, "too_many_sources", f"'{source[:200]}': already tracking {self.sources.max_sources} sources"
            )
            return False
        if size > self.settings.max_payload_bytes:
            self.queue.count_unqueued(source)
            self.stats.rejected(
                source, "oversized", f"{size} bytes exceeds the limit of {self.settings.max_payload_bytes}"
            )
            return False
        pending = PendingFrame(source, key, read(), encoding, time.time(), ros)
        try:
            self.queue.put(source, pending, size)
        except PendingBudgetExceeded as err:
            self.stats.rejected(source, "pending_budget", str(err))
            return False
        return True
