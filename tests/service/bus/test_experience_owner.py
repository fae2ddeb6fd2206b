"""Commands and odometry on the service's bus are paired by the instance that owns the experience's grid only.
Every instance hears them; before, one whose grid had moved to another kept pairing them against its snapshots
from before the move, each outcome a second time, with a prediction minutes or hours old."""

from __future__ import annotations

from dataclasses import dataclass, field

from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.bus.experience import ExperienceBus
from zenoh_helpers import fake_sample


@dataclass
class ExperienceStub:
    source: str = "r1/front"


@dataclass
class Stats:
    counted: list[str] = field(default_factory=list)

    def rejected(self, source: str | None, reason: str, detail: str) -> None:
        self.counted.append(reason)


def test_commands_and_odometry_are_taken_only_while_this_instance_owns_the_grid() -> None:
    owned = {"r1/front": True}
    stats, taken = Stats(), []
    bus = ExperienceBus(None, ServiceSettings(), ExperienceStub(), stats, owned.__getitem__, None)  # type: ignore[arg-type]
    handle = bus._input_handler(lambda payload, received_at: taken.append(payload), "bad_odometry")
    handle(fake_sample(b"first", "robot/odom"))  # type: ignore[arg-type]
    owned["r1/front"] = False  # the grid moved to another instance
    handle(fake_sample(b"second", "robot/odom"))  # type: ignore[arg-type]
    owned["r1/front"] = True  # and back
    handle(fake_sample(b"third", "robot/odom"))  # type: ignore[arg-type]
    assert taken == [b"first", b"third"] and stats.counted == []
