"""Outcomes measured on the robot while the service is away (killed, restarted, its router gone) wait on the
robot and reach the service once it is back, each once. Before, the relay put them into a link that no
subscriber matched: zenoh dropped them at the writer, and the relay counted them sent."""

from __future__ import annotations

import zenoh
from gcdtrav.client.relay.relay import Relay
from gcdtrav.client.session.zenoh_args import zenoh_config
from gcdtrav.schemas.experience import OutcomeBatch, TraversalOutcome
from gcdtrav.schemas.relay import RelaySettings
from zenoh_helpers import connecting_config, free_port, subscribed_elsewhere, wait_until

SOURCE, OUTCOME_KEY = "r1/front", "robot/outcome"


def test_outcomes_measured_while_the_service_is_away_reach_it_once_it_is_back() -> None:
    port, robot_port = free_port(), free_port()
    stamps: list[float] = []

    def service() -> tuple[zenoh.Session, zenoh.Subscriber]:
        session = zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False))
        batches = session.declare_subscriber(
            "gcdtrav/in/**/outcomes",
            lambda sample: stamps.extend(o.stamp for o in OutcomeBatch.unpack(sample.payload.to_bytes()).outcomes),
        )
        return session, batches

    bus = zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{robot_port}"], multicast_scouting=False))
    local = zenoh.open(connecting_config(robot_port, mode="client"))
    up, subscriber = service()
    link = zenoh.open(connecting_config(port, mode="client"))  # a client's first connection must succeed
    settings = RelaySettings.model_validate(
        {
            "cameras": [{"camera": "robot/unused", "source": SOURCE, "frames": False}],
            "safe_mask": {"enabled": False},
            "outcomes": {"cmd_vel": None, "outcome": OUTCOME_KEY, "batch_period_s": 0.1},
        }
    )
    relay = Relay(settings, link, local).start()
    outcomes = relay.outcomes
    assert outcomes is not None

    def measure(first: int, count: int) -> None:
        for stamp in range(first, first + count):
            bus.put(OUTCOME_KEY, TraversalOutcome(stamp=stamp, x=0.0, y=0.0, score=0.5, kind="velocity").pack())
        assert wait_until(lambda: outcomes.measured == first + count, 10)

    try:
        assert subscribed_elsewhere(bus, OUTCOME_KEY, 30)
        measure(0, 5)
        assert wait_until(lambda: len(stamps) == 5, 10), stamps
        subscriber.undeclare()
        up.close()  # the service is gone
        assert wait_until(lambda: outcomes.holding, 10)
        measure(5, 7)
        up, subscriber = service()  # back, on the same endpoint: the relay's session reconnects
        assert wait_until(lambda: len(stamps) == 12, 30), stamps
        assert sorted(stamps) == [float(stamp) for stamp in range(12)]  # each once
        assert outcomes.sent == outcomes.measured == 12 and not outcomes.holding
    finally:
        relay.close()
        subscriber.undeclare()
        for session in (link, local, bus, up):
            session.close()


def test_outcomes_measured_since_the_last_batch_leave_when_the_relay_stops() -> None:
    port, robot_port = free_port(), free_port()
    stamps: list[float] = []
    service = zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False))
    subscriber = service.declare_subscriber(
        "gcdtrav/in/**/outcomes",
        lambda sample: stamps.extend(o.stamp for o in OutcomeBatch.unpack(sample.payload.to_bytes()).outcomes),
    )
    bus = zenoh.open(zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{robot_port}"], multicast_scouting=False))
    local = zenoh.open(connecting_config(robot_port, mode="client"))
    link = zenoh.open(connecting_config(port, mode="client"))
    settings = RelaySettings.model_validate(
        {
            "cameras": [{"camera": "robot/unused", "source": SOURCE, "frames": False}],
            "safe_mask": {"enabled": False},
            "outcomes": {"cmd_vel": None, "outcome": OUTCOME_KEY, "batch_period_s": 60},
        }
    )
    relay = Relay(settings, link, local).start()
    try:
        outcomes = relay.outcomes
        assert outcomes is not None and subscribed_elsewhere(bus, OUTCOME_KEY, 30)
        assert wait_until(lambda: outcomes.batches == 0 and outcomes.receiving(), 10)
        for stamp in range(3):
            bus.put(OUTCOME_KEY, TraversalOutcome(stamp=stamp, x=0.0, y=0.0, score=0.5, kind="velocity").pack())
        assert wait_until(lambda: outcomes.measured == 3, 10)
        relay.close()  # the next batch was due in a minute: before, the three were lost
        assert wait_until(lambda: len(stamps) == 3, 10), stamps
    finally:
        relay.close()
        subscriber.undeclare()
        for session in (link, local, bus, service):
            session.close()
