"""The relay's decisions, without zenoh: when a camera may send, what the link's clock offset is, how many
bytes pass, how large a frame goes out. client/relay/relay.py wires them to the bus."""

from __future__ import annotations

import math
import statistics
import threading
import time
from collections import deque
from collections.abc import Callable

import cv2
import numpy as np
from gcdtrav.schemas.delay_window import SmallestDelay
from gcdtrav.schemas.messages import CreditGrant
from numpy.typing import NDArray

MAX_CREDIT_TIMEOUT_S = 30.0
TIMEOUT_STRETCH = 3.0  # times the usual wait for a credit before it counts as lost
RATE_WINDOW_S = 10.0


class CreditWindow:
    """One camera's permission to send: a credit (the owner freed the source's slot), or a timeout.

    The first frame goes without a credit. Then each frame spends the credit, and the next waits for the
    owner's grant, or for the timeout when a grant was lost (a dropped message, a restarted or replaced
    service). The timeout stretches to ``TIMEOUT_STRETCH`` times the recent send-to-grant wait, so a busy
    service that grants slowly is not flooded with frames it must drop.
    """

    def __init__(self, timeout_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.base_timeout_s = timeout_s
        self._clock = clock
        self._credit = True
        self._last_sent = -math.inf
        self._waits: deque[float] = deque(maxlen=16)
        self.timeouts = 0
        self.unanswered = 0  # frames sent without a credit since the last grant: no owner answers
        self.owner: str | None = None

    @property
    def timeout_s(self) -> float:
        usual = statistics.median(self._waits) if self._waits else 0.0
        return min(max(self.base_timeout_s, TIMEOUT_STRETCH * usual), max(MAX_CREDIT_TIMEOUT_S, self.base_timeout_s))

    def wait_s(self) -> float:
        """Seconds until a frame may go without a credit; 0 when one may go now."""
        if self._credit:
            return 0.0
        return max(0.0, self._last_sent + self.timeout_s - self._clock())

    def ready(self) -> bool:
        return self.wait_s() == 0.0

    def spend(self) -> None:
        """A frame went out: with the credit, or (counted) after the timeout."""
        if not self._credit:
            self.timeouts += 1
            self.unanswered += 1
        self._credit = False
        self._last_sent = self._clock()

    def grant(self, grant: CreditGrant) -> None:
        """The owner is ready for the next frame."""
        if not self._credit and math.isfinite(self._last_sent):
            self._waits.append(self._clock() - self._last_sent)
        self._credit = True
        self.unanswered = 0
        self.owner = grant.instance


class CameraClock:
    """This host's clock minus the camera's, learnt as the service learns a robot's (the one smallest-delay
    window, schemas/delay_window.py): the smallest delay (arrival here minus capture stamp) of the recent
    frames. A camera stamping from another clock (a PTP-synced sensor, a board without NTP) then does not make
    every map look hours old: a map's stamp plus this offset is its capture time on this host's clock, within
    the camera's smallest delivery delay."""

    def __init__(self) -> None:
        self._delays = SmallestDelay()
        self._lock = threading.Lock()

    def add(self, stamp: float, arrived_at: float) -> None:
        with self._lock:
            self._delays.add(arrived_at, arrived_at - stamp)

    def offset_s(self) -> float | None:
        """Host minus camera clock (plus the smallest delivery delay); None before any frame."""
        with self._lock:
            return self._delays.smallest

    def on_host_clock(self, stamp: float) -> float:
        """A camera stamp on this host's clock (unchanged before any frame taught the offset)."""
        offset = self.offset_s()
        return stamp if offset is None else stamp + offset


class ClockEstimate:
    """Service clock minus this clock, from credit round trips (NTP's four stamps): the frame's sent_at
    (here) and received_at (there), the grant's granted_at (there) and arrival (here). The sample with the
    shortest round trip of the recent ones wins; its error is at most half the round trip's asymmetry (a
    frame's upload time on a slow link: 30 kB at 2 Mbit/s, 60 ms)."""

    def __init__(self, keep: int = 16) -> None:
        self._samples: deque[tuple[float, float]] = deque(maxlen=keep)  # (round trip, offset)
        self._lock = threading.Lock()

    def add(self, grant: CreditGrant, arrived_at: float) -> None:
        sent, received = grant.frame_sent_at, grant.frame_received_at
        if sent is None or received is None:
            return
        round_trip = (arrived_at - sent) - (grant.granted_at - received)
        offset = ((received - sent) + (grant.granted_at - arrived_at)) / 2
        if math.isfinite(round_trip) and math.isfinite(offset) and round_trip >= 0:
            with self._lock:
                self._samples.append((round_trip, offset))

    def best(self) -> tuple[float, float] | None:
        """(round trip s, offset s) of the best recent sample; None before any."""
        with self._lock:
            return min(self._samples) if self._samples else None


class RateWindow:
    """Bytes per second over the last ``window_s``."""

    def __init__(self, window_s: float = RATE_WINDOW_S, clock: Callable[[], float] = time.monotonic) -> None:
        self.window_s = window_s
        self._clock = clock
        self._events: deque[tuple[float, int]] = deque()
        self._lock = threading.Lock()
        self.total = 0

    def add(self, nbytes: int) -> None:
        with self._lock:
            self._events.append((self._clock(), nbytes))
            self.total += nbytes

    def per_s(self) -> float:
        now = self._clock()
        with self._lock:
            while self._events and self._events[0][0] < now - self.window_s:
                self._events.popleft()
            return sum(n for _, n in self._events) / self.window_s


def target_size(width: int, height: int, max_side: int | str, model_input: tuple[int, int]) -> tuple[int, int]:
    """The size a frame is sent at, aspect kept, never enlarged.

    ``auto``: every side at least the model's (it resizes to a fixed size, ignoring aspect, so fewer pixels
    would lose detail and more are wasted on the link): 1920x1200 -> 563x352 for a 352x352 model. An integer:
    the longer side at most that.
    """
    if max_side == "auto":
        scale = max(model_input[0] / width, model_input[1] / height)
    else:
        scale = int(max_side) / max(width, height)
    if scale >= 1.0:
        return width, height
    return max(1, round(width * scale)), max(1, round(height * scale))


def downsized(image: NDArray[np.uint8], max_side: int | str, model_input: tuple[int, int]) -> NDArray[np.uint8]:
    """``image`` at ``target_size`` (area interpolation: no aliasing)."""
    height, width = image.shape[:2]
    size = target_size(width, height, max_side, model_input)
    if size == (width, height):
        return image
    return np.asarray(cv2.resize(image, size, interpolation=cv2.INTER_AREA), np.uint8)
