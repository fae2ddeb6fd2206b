"""Outcomes measured where the robot is: how well it kept the speed it was commanded, and what it hit. One
implementation, with the inputs' decoders, for the service (commands and odometry on its bus) and for the relay on
the robot (its own cmd_vel and odometry, client/relay/outcomes.py), so a relayed robot's
outcomes are graded exactly as a robot's on the service's bus (docs/calibration.md, "Which robots teach").

**Velocity.** While the command in force asks for more than ``min_command_mps``, each odometry sample scores
achieved / commanded speed, clipped to [0, 1]; every ``outcome_spacing_m`` driven (or after
``outcome_period_s`` by odometry stamps, for a robot that barely moves) the mean score becomes one
``TraversalOutcome`` of kind ``velocity`` at the mean of the window's positions (where the score was earned),
over the robot's footprint (radius footprint_m / 2). A command is in force for ``command_timeout_s`` after it
was *received* (a Twist carries no stamp, and the robot's clock need not agree with the receiver's), so the
command's age is judged on the receiving clock for both streams. The outcome's stamp is the odometry's: the
pose stream's clock, which is the grid's.

Outcomes are spaced by distance, not time: a robot is slow exactly where the ground is bad, so outcomes per
second would sample bad ground more densely than good ground within the same-looking terrain (a bush patch
in a grassy field), and pull the fitted positions down (benchmarks/experience.py measured grass 0.75 and
bush 0.15 for true 0.8 and 0.25 that way).

**Contact.** A bumper (or any signal the robot's code raises) going from clear to pressed is one outcome of
kind ``contact``, score 0, at the robot's newest pose, over its footprint; held pressed, nothing more.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

from gcdtrav.schemas.experience import Odometry2D, TraversalOutcome, Twist2D
from gcdtrav.schemas.messages import check_size
from gcdtrav.schemas.ros_nav import RosNavError, bool_value, odometry_motion, twist_command
from gcdtrav.schemas.settings.experience import TrackingSettings

MAX_INPUT_BYTES = 64 * 1024  # an Odometry CDR with its covariances is about 700 bytes
CDR = (b"\x00\x00", b"\x00\x01")  # an encapsulation header's first bytes; msgpack and JSON start otherwise


def decode_command(payload: bytes, stamped: bool = False) -> Twist2D:
    """A velocity command: a geometry_msgs Twist (``stamped``: TwistStamped) in CDR, or a Twist2D in msgpack or
    JSON, told apart by their first bytes; MessageError (RosNavError is one) when unusable."""
    check_size("a velocity command", payload, MAX_INPUT_BYTES)
    return twist_command(payload, stamped) if payload[:2] in CDR else Twist2D.decode(payload)


def decode_odometry(payload: bytes) -> Odometry2D:
    """Odometry: a nav_msgs Odometry in CDR, or an Odometry2D in msgpack or JSON; MessageError when unusable."""
    check_size("odometry", payload, MAX_INPUT_BYTES)
    return odometry_motion(payload) if payload[:2] in CDR else Odometry2D.decode(payload)


def decode_contact(payload: bytes) -> bool:
    """A bumper: a std_msgs Bool in CDR, or JSON true / false; RosNavError if neither."""
    if payload[:2] in CDR:
        return bool_value(payload)
    text = payload.strip().lower()
    if text not in (b"true", b"false"):
        raise RosNavError(f"a contact is a std_msgs/Bool CDR or JSON true/false, not {payload[:20]!r}")
    return text == b"true"


@dataclass
class _Window:
    start: float  # odometry stamp of the window's first sample
    total: float = 0.0
    x: float = 0.0  # sums of the samples' positions: the outcome sits at their mean
    y: float = 0.0
    samples: int = 0
    travelled: float = 0.0  # metres since the window's first sample
    last: tuple[float, float] | None = None


class VelocityTracker:
    """One robot's commands and odometry in, velocity outcomes out. Thread-safe (two subscribers feed it)."""

    def __init__(self, settings: TrackingSettings) -> None:
        self.settings = settings
        self._command: Twist2D | None = None
        self._command_received = -math.inf
        self._window: _Window | None = None
        self._lock = threading.Lock()
        self.counts: dict[str, int] = {}

    def _count(self, name: str) -> None:
        self.counts[name] = self.counts.get(name, 0) + 1

    def on_command(self, command: Twist2D, received_at: float) -> None:
        with self._lock:
            self._command, self._command_received = command, received_at

    def on_odometry(self, odometry: Odometry2D, received_at: float) -> TraversalOutcome | None:
        """Score this sample; the outcome of the period it closes, if any."""
        s = self.settings
        with self._lock:
            command = self._command
            # A command recorded after this sample's receipt is in force too: zenoh runs each subscriber's
            # callback on its own thread, so a newer command can land between the sample's receipt and here.
            fresh = command is not None and received_at - self._command_received <= s.command_timeout_s
            commanded = math.hypot(command.vx, command.vy) if command is not None and fresh else 0.0
            if commanded <= s.min_command_mps:
                self._window = None  # a stop, a turn on the spot or no command: nothing to grade
                self._count("not_commanded")
                return None
            score = min(max(math.hypot(odometry.vx, odometry.vy) / commanded, 0.0), 1.0)
            window = self._window
            if window is None or odometry.stamp < window.start:  # a replayed bag jumped back: start again
                window = self._window = _Window(odometry.stamp)
            window.total += score
            window.x += odometry.x
            window.y += odometry.y
            window.samples += 1
            if window.last is not None:
                window.travelled += math.hypot(odometry.x - window.last[0], odometry.y - window.last[1])
            window.last = (odometry.x, odometry.y)
            if window.travelled < s.outcome_spacing_m and odometry.stamp - window.start < s.outcome_period_s:
                return None
            self._window = _Window(odometry.stamp, last=(odometry.x, odometry.y))  # the next starts here
            self._count("outcomes")
        return TraversalOutcome(
            stamp=odometry.stamp,
            x=window.x / window.samples,
            y=window.y / window.samples,
            score=window.total / window.samples,
            kind="velocity",
            radius_m=s.footprint_m / 2,
        )


class ContactWatch:
    """A bumper's edges: clear -> pressed is one contact outcome at the newest pose. Thread-safe."""

    def __init__(self, settings: TrackingSettings) -> None:
        self.settings = settings
        self._pressed = False
        self._pose: tuple[float, float, float] | None = None  # stamp, x, y of the newest odometry
        self._lock = threading.Lock()
        self.contacts = self.without_pose = 0

    def on_odometry(self, odometry: Odometry2D) -> None:
        with self._lock:
            self._pose = (odometry.stamp, odometry.x, odometry.y)

    def on_contact(self, pressed: bool) -> TraversalOutcome | None:
        """The bumper's state; the outcome of a new press, if any (none before the first pose: counted)."""
        with self._lock:
            new_press, self._pressed = pressed and not self._pressed, pressed
            if not new_press:
                return None
            if self._pose is None:
                self.without_pose += 1
                return None
            self.contacts += 1
            stamp, x, y = self._pose
        return TraversalOutcome(
            stamp=stamp, x=x, y=y, score=0.0, kind="contact", radius_m=self.settings.footprint_m / 2
        )
