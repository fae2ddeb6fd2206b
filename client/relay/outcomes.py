"""Outcomes measured on the robot and sent over the link in a few bytes (docs/calibration.md, "Which robots teach").

The robot has everything an outcome needs: its own velocity commands and odometry at their full rate, its bumper,
its planned path. Sending those streams would cost more than the frames the relay shrinks; the outcomes they
make cost a few bytes each. So the relay grades them here, by the service's own rules (schemas/outcomes.py),
and sends what they make: every ``batch_period_s`` at most one ``OutcomeBatch`` on ``{prefix}/in/{source}/outcomes``
(each outcome with its stamp, on the odometry's clock, which is the pose stream's and so the grid's, and the robot's
position), and the planned path, when it changed, as a ``PlannedPath`` on ``{prefix}/in/{source}/planned_path``,
shortened to ``path_length_m``. The service pairs them exactly as a robot's on its own bus. The robot sides
(the zenoh bus, client/relay/relay.py; the ROS 2 graph, ros2_node.py) only decode and hand over.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from gcdtrav.client.relay.state import RateWindow
from gcdtrav.schemas.experience import (
    MAX_BATCH_OUTCOMES,
    Odometry2D,
    OutcomeBatch,
    PlannedPath,
    TraversalOutcome,
    Twist2D,
)
from gcdtrav.schemas.messages import MessageError
from gcdtrav.schemas.outcomes import ContactWatch, VelocityTracker
from gcdtrav.schemas.relay import RelayOutcomes

log = logging.getLogger("gcdtrav.relay")
PATH_SPACING_M = 0.5  # the path's vertices sent at least this far apart (a few grid cells: segments between)
PATH_TOLERANCE_M = 0.5  # a new path whose nearer half keeps this close to the last one sent is the same path
ROS_TYPES = {  # the rmw_zenoh key chunk of each type a zenoh relay reads as a ROS topic
    "cmd_vel": "geometry_msgs::msg::dds_::Twist_",
    "cmd_vel_stamped": "geometry_msgs::msg::dds_::TwistStamped_",
    "odometry": "nav_msgs::msg::dds_::Odometry_",
    "contact": "std_msgs::msg::dds_::Bool_",
    "planned_path": "nav_msgs::msg::dds_::Path_",
}


def robot_key(name: str, kind: str) -> str:
    """The key a zenoh relay reads an input on: a plain key as it is, a ROS topic ('/...') as its rmw_zenoh keys
    (any domain, any type hash); ValueError for a topic of an input that has no ROS type (``outcome``)."""
    if not name.startswith("/"):
        return name
    if kind not in ROS_TYPES:
        raise ValueError(f"outcomes.{kind} '{name}' is a ROS topic, but {kind} is read from a zenoh key only")
    return f"*/{name.strip('/')}/{ROS_TYPES[kind]}/*"


INPUT_ERRORS = (MessageError,)  # a bad input of the outcomes (RosNavError is a MessageError)


class OutcomeLink:
    """One robot's outcomes: fed by the robot side's callbacks, sent by the relay's control thread (``send_due``).
    Thread-safe."""

    def __init__(
        self,
        settings: RelayOutcomes,
        source: str,
        publisher: Any,
        path_publisher: Any,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """``publisher``, ``path_publisher``: the link's (Guarded) publishers of the grid ``source``'s outcomes and
        planned path (``Keys.outcomes``, ``Keys.planned_path``), each with ``put`` and ``matching`` (whether anyone
        across the link subscribes now); ``clock``: the relay's monotonic clock."""
        self.settings, self.source, self.clock = settings, source, clock
        self.velocity, self.contacts = VelocityTracker(settings), ContactWatch(settings)
        self._publisher, self._path_publisher = publisher, path_publisher
        self._pending: list[TraversalOutcome] = []
        self._path: PlannedPath | None = None  # the newest path, not yet sent
        self._path_sent: list[tuple[float, float]] | None = None
        self._path_sent_at = -math.inf
        self._dropped = 0
        self._next_send = -math.inf
        self._lock = threading.Lock()
        self.uplink = RateWindow()
        self.measured = self.sent = self.batches = self.bytes_sent = self.rejected = 0
        self.holding = False  # nobody received at the last send: the outcomes wait (the newest MAX_BATCH_OUTCOMES)

    # ---- from the robot side ---------------------------------------------------------------------------
    def on_command(self, command: Twist2D) -> None:
        self.velocity.on_command(command, self.clock())  # the command's age on this clock, as the service's

    def on_odometry(self, odometry: Odometry2D) -> None:
        self.contacts.on_odometry(odometry)
        self._add(self.velocity.on_odometry(odometry, self.clock()))

    def on_contact(self, pressed: bool) -> None:
        self._add(self.contacts.on_contact(pressed))

    def on_outcome(self, outcome: TraversalOutcome) -> None:
        """An outcome the robot's own code measured."""
        self._add(outcome)

    def on_path(self, frame_id: str, stamp: float, points: Sequence[tuple[float, float]]) -> None:
        """The robot's planned path (the grid's frame), shortened: kept to send if it changed (its nearer half left
        the last one sent: a new plan, or the robot drove half of it) or the last was sent ``path_renew_s`` ago
        (the service forgets a path not renewed within its ask.path_timeout_s). MessageError for a path that is
        not one the service takes (a frame id too long, a point out of reach)."""
        kept = shortened(points, self.settings.path_length_m)
        path = PlannedPath.validated({"stamp": stamp, "frame_id": frame_id, "points": kept})
        with self._lock:
            due = self.clock() - self._path_sent_at >= self.settings.path_renew_s
            if due or not follows(kept, self._path_sent, self.settings.path_length_m / 2):
                self._path = path

    def _add(self, outcome: TraversalOutcome | None) -> None:
        if outcome is None:
            return
        with self._lock:
            self.measured += 1
            self._pending.append(outcome)
            if len(self._pending) > MAX_BATCH_OUTCOMES:  # the link could not take them: keep the newest
                self._pending.pop(0)
                self._dropped += 1

    # ---- to the link -----------------------------------------------------------------------------------
    def send_due(self, force: bool = False) -> float:
        """Send what waits if ``batch_period_s`` has passed since the last send (``force``: now, the relay stopping);
        when to be asked next (``clock``). While nobody across the link receives the outcomes (the link, its router
        or the service down: a put would be lost, and was counted sent), they wait, the newest MAX_BATCH_OUTCOMES,
        the rest counted dropped, and leave in the first batch once someone receives again; the newest path waits
        for its own receiver alike."""
        now = self.clock()
        if now < self._next_send and not force:
            return self._next_send
        outcomes_heard, path_heard = self.receiving(), receives(self._path_publisher)
        with self._lock:
            self._next_send = now + self.settings.batch_period_s
            self._hold(not outcomes_heard)
            outcomes, dropped, path = [], 0, None
            if outcomes_heard:
                outcomes, self._pending, dropped, self._dropped = self._pending, [], self._dropped, 0
            if path_heard and self._path is not None:
                path, self._path = self._path, None
                self._path_sent = [(float(x), float(y)) for x, y in path.points]
                self._path_sent_at = now
        if outcomes or dropped:
            payload = OutcomeBatch(outcomes=outcomes, sent_at=time.time(), dropped=dropped).pack()
            self._put(self._publisher, payload)
            self.sent += len(outcomes)
            self.batches += 1
        if path is not None:
            self._put(self._path_publisher, path.pack())
        return self._next_send

    def receiving(self) -> bool:
        """Whether anyone across the link subscribes to the outcomes now."""
        return receives(self._publisher)

    def _hold(self, holding: bool) -> None:
        """Under the lock: whether the outcomes wait now; a change said once (loudly only with outcomes waiting:
        not at every start, before the link is up)."""
        if holding == self.holding:
            return
        self.holding, waiting = holding, len(self._pending)
        if holding:
            level = logging.WARNING if waiting else logging.INFO
            log.log(level, "nobody receives the outcomes of %s across the link: holding them", self.source)
        else:
            log.info("the outcomes of %s are received again: sending the %d held", self.source, waiting)

    def _put(self, publisher: Any, payload: bytes) -> None:
        publisher.put(payload)
        self.uplink.add(len(payload))
        self.bytes_sent += len(payload)


def receives(publisher: Any) -> bool:
    """Whether anyone across the link subscribes to what ``publisher`` puts (zenoh drops a put nobody matches, at
    the writer); False when it cannot tell (closing)."""
    try:
        return bool(publisher.matching())
    except Exception:  # zenoh's own error types
        return False


def follows(path: list[tuple[float, float]], sent: list[tuple[float, float]] | None, length_m: float) -> bool:
    """Whether ``path``'s vertices within ``length_m`` of its start keep within PATH_TOLERANCE_M of the polyline
    ``sent``."""
    if not sent or not path:
        return not sent and not path
    points = np.asarray(path, np.float64)
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(points, axis=0).T))])
    near = points[travelled <= length_m]
    line = np.asarray(sent, np.float64)
    if len(line) == 1:
        return bool(np.all(np.hypot(*(near - line[0]).T) <= PATH_TOLERANCE_M))
    start, end = line[:-1], line[1:]
    segment = end - start
    lengths = np.maximum((segment**2).sum(axis=1), 1e-12)
    along = np.clip(((near[:, None, :] - start[None]) * segment[None]).sum(axis=2) / lengths[None], 0.0, 1.0)
    closest = start[None] + along[..., None] * segment[None]
    return bool(np.all(np.hypot(*(near[:, None, :] - closest).transpose(2, 0, 1)).min(axis=1) <= PATH_TOLERANCE_M))


def shortened(points: Sequence[tuple[float, float]], length_m: float) -> list[tuple[float, float]]:
    """The path's first ``length_m`` (from its start: the robot), vertices at least PATH_SPACING_M apart."""
    kept: list[tuple[float, float]] = []
    travelled = 0.0
    for x, y in points:
        point = (float(x), float(y))
        if kept:
            step = math.hypot(point[0] - kept[-1][0], point[1] - kept[-1][1])
            if step < PATH_SPACING_M:
                continue
            travelled += step
        kept.append(point)
        if travelled >= length_m:
            break
    return kept
