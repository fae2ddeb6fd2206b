"""The smallest-delay window (schemas/delay_window.py) at its edges: none and one sample, a clock step either
way, samples out of order, the window rolling over, gaps and outages, receipts that go back, bad samples."""

from __future__ import annotations

import math

import pytest
from gcdtrav.schemas.delay_window import GAP_S, WINDOW_S, SmallestDelay, clock_difference


def fed(window: SmallestDelay, samples: list[tuple[float, float]]) -> list[float | None]:
    """The smallest delay after each (receipt, delay)."""
    return [window.add(received_at, delay) for received_at, delay in samples]


def test_no_sample_knows_nothing_and_one_sample_is_the_clock() -> None:
    window = SmallestDelay()
    assert window.smallest is None
    assert window.add(5.0, 100.2) == window.smallest == 100.2
    assert window.add(5.0, 100.2) == 100.2  # the same sample again: no time passes


def test_a_clock_stepping_forward_is_learnt_at_once_and_back_as_the_window_rolls_over() -> None:
    window = SmallestDelay(window_s=10.0)
    fed(window, [(float(t), 100.0) for t in range(20)])
    assert window.add(20.0, 95.0) == 95.0  # stepped forward by 5 s: smaller delays, at once
    learnt = fed(window, [(20.0 + t, 97.0) for t in range(1, 12)])  # back by 2 s: larger delays
    assert learnt[:9] == [95.0] * 9  # the 95 s sample (t = 20) is held for window_s
    assert learnt[10] == 97.0  # ... and gone at t = 31, over 10 s of streaming later


def test_samples_out_of_order_count_by_their_delays() -> None:
    """Stamps out of order (a frame overtaken on the link) only change delays: the smallest wins; a sample
    behind a smaller one is never the smallest while that one is in the window."""
    window = SmallestDelay(window_s=10.0)
    assert fed(window, [(0.0, 0.3), (0.25, 0.1), (0.5, 0.4), (0.75, 0.2)]) == [0.3, 0.1, 0.1, 0.1]
    learnt = dict(zip([t / 4 for t in range(4, 45)], fed(window, [(t / 4, 0.5) for t in range(4, 45)]), strict=True))
    assert [learnt[10.25], learnt[10.5], learnt[10.75], learnt[11.0]] == [0.1, 0.2, 0.2, 0.5]  # 0.4: never


def test_the_window_rolls_over_after_window_s_of_streaming() -> None:
    window = SmallestDelay()
    window.add(0.0, 1.0)
    learnt = fed(window, [(t / 4, 2.0) for t in range(1, round(WINDOW_S * 4) + 2)])  # quarters: exact sums
    assert learnt[round(WINDOW_S * 4) - 1] == 1.0  # at WINDOW_S exactly: still in
    assert learnt[-1] == 2.0  # a quarter past it: gone


def test_an_outage_counts_gap_s_at_most_and_a_receipt_that_goes_back_counts_nothing() -> None:
    """The window's time runs only while samples come: a backlog after an outage of any length is judged
    against the clock learnt before it, and this host's clock stepping back ages nothing."""
    window = SmallestDelay(window_s=10.0)
    window.add(0.0, 1.0)
    assert window.add(3600.0, 2.0) == 1.0  # an hour later: the hour counts GAP_S
    learnt = fed(window, [(3600.0 + t, 2.0) for t in range(1, 12)])
    assert learnt.index(2.0) == round(10.0 - GAP_S)  # 1 s (the outage) + 9 s of streaming = the window
    other = SmallestDelay(window_s=10.0)
    other.add(100.0, 1.0)
    assert fed(other, [(50.0, 2.0), (51.0, 2.0)]) == [1.0, 1.0]  # back 50 s: counted 0 s, then 1 s


def test_a_bad_sample_teaches_nothing_and_restart_learns_afresh() -> None:
    window = SmallestDelay()
    assert window.add(1.0, math.inf) is None and window.add(math.nan, 1.0) is None
    window.add(1.0, 0.5)
    assert window.add(2.0, -math.inf) == 0.5
    window.restart(3.0, 7.0)  # a step confirmed by the caller
    assert window.smallest == 7.0 and window.add(3.5, 8.0) == 7.0


def test_clock_difference_of_two_learnt_clocks() -> None:
    camera, poses = SmallestDelay(), SmallestDelay()
    camera.add(10.0, 100.05)  # service minus camera clock 100 s, link 0.05 s
    assert clock_difference(camera.smallest, poses.smallest) is None
    poses.add(10.0, 97.01)  # service minus pose clock 97 s: the pose clock is 3 s ahead; link 0.01 s
    assert clock_difference(camera.smallest, poses.smallest) == pytest.approx(3.04)
