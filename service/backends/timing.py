"""How long calls take, timed in rounds of one call each: a busy machine's drift hits every call alike.

Stdlib only, so the backends (choosing fused ops), ``precision: auto``, ``gcdtrav bench`` and the benchmarks share it.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping


def interleaved_ms(calls: Mapping[str, Callable[[], object]], rounds: int, warmup: int = 1) -> dict[str, list[float]]:
    """Each call's ``rounds`` times in ms, the calls taking turns; ``warmup`` untimed rounds first
    (first-call allocations, caches)."""
    times: dict[str, list[float]] = {name: [] for name in calls}
    for round_ in range(warmup + rounds):
        for name, call in calls.items():
            began = time.perf_counter()
            call()
            if round_ >= warmup:
                times[name].append((time.perf_counter() - began) * 1e3)
    return times
