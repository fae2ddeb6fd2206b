"""The shared timing loop: calls take turns, warm-up rounds are run but not reported."""

from __future__ import annotations

from gcdtrav.service.backends.timing import interleaved_ms


def test_calls_take_turns_and_warmup_is_not_reported() -> None:
    order: list[str] = []
    times = interleaved_ms({"a": lambda: order.append("a"), "b": lambda: order.append("b")}, rounds=3, warmup=2)
    assert order == ["a", "b"] * 5
    assert {name: len(values) for name, values in times.items()} == {"a": 3, "b": 3}
    assert all(value >= 0 for values in times.values() for value in values)


def test_times_are_milliseconds() -> None:
    import time

    times = interleaved_ms({"sleep": lambda: time.sleep(0.01)}, rounds=2, warmup=0)
    assert all(9 <= value < 1000 for value in times["sleep"])
