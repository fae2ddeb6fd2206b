"""The client's per-source order: a map older than one already shown (a previous owner's) is held back."""

from __future__ import annotations

from gcdtrav.client.client import MapsOrder
from gcdtrav.schemas.config import Method
from gcdtrav.schemas.messages import MapsHeader


def header(source: str, stamp: float, received_at: float, instance: str, order: bool = True) -> MapsHeader:
    return MapsHeader(
        source=source,
        key=f"gcdtrav/in/{source}",
        seq=0,
        stamp=stamp,
        received_at=received_at,
        published_at=received_at + 0.1,
        inference_ms=1.0,
        model="m",
        instance=instance,
        anchor_set_version="v",
        method=Method.GCD,
        map_shape=(8, 8),
        image_size=(64, 48),
        scale=(8.0, 6.0),
        order=(stamp, received_at) if order else None,
    )


def test_maps_interleaved_from_two_instances_come_out_in_order() -> None:
    order = MapsOrder()
    arrivals = [
        header("r1", 10.0, 10.1, "new"),
        header("r1", 9.0, 9.1, "old"),  # the old owner, resumed after a SIGSTOP, publishes late
        header("r1", 11.0, 11.1, "new"),
        header("r1", 11.0, 11.2, "old"),  # the same frame, done by both during the hand-over
        header("r1", 10.5, 10.6, "old"),
        header("r2", 1.0, 1.1, "old"),  # another source has its own order
        header("r1", 12.0, 12.1, "new", order=False),  # a 1.1 service: stamp and received_at order it
    ]
    shown = [(h.source, h.stamp, h.instance) for h in arrivals if order.is_newer(h)]
    assert shown == [
        ("r1", 10.0, "new"),
        ("r1", 11.0, "new"),
        ("r1", 11.0, "old"),
        ("r2", 1.0, "old"),
        ("r1", 12.0, "new"),
    ]
    assert order.held_back == 2


def test_an_equal_order_is_the_same_frame_again() -> None:
    order = MapsOrder()
    assert order.is_newer(header("r1", 5.0, 5.0, "a"))
    assert not order.is_newer(header("r1", 5.0, 5.0, "a"))


def test_a_robot_clock_stepped_back_starts_its_order_again_but_a_late_map_does_not() -> None:
    order = MapsOrder()
    assert order.is_newer(header("r1", 5000.0, 100.0, "a"))  # a robot clock an hour ahead
    assert not order.is_newer(header("r1", 4995.0, 99.0, "b"))  # a previous owner's late map: received earlier
    assert not order.is_newer(header("r1", 4991.0, 100.5, "a"))  # 9 s older, received later: held back
    assert order.is_newer(header("r1", 1400.0, 101.0, "a"))  # the clock set right: shown, and ordered from it
    assert order.is_newer(header("r1", 1400.25, 101.25, "a"))
    assert not order.is_newer(header("r1", 4999.0, 100.2, "b"))  # a late map of before the step
    assert order.held_back == 3
