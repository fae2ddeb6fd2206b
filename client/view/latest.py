"""Latest-only buffers between zenoh's callbacks and the viewer's worker: one slot per key, a newer value
replaces an older one, a bounded number of keys. A put never blocks, so a slow viewer (or browser) costs
zenoh nothing but the newest payload per key."""

from __future__ import annotations

import threading
from collections.abc import Hashable
from typing import Generic, TypeVar

K = TypeVar("K", bound=Hashable)
V = TypeVar("V")


class LatestSlots(Generic[K, V]):
    def __init__(self, max_keys: int) -> None:
        self.max_keys = max_keys
        self.replaced = 0  # values overwritten before the worker took them
        self.refused = 0  # values of new keys while max_keys were waiting
        self._items: dict[K, V] = {}
        self._lock = threading.Lock()
        self._ready = threading.Event()

    def put(self, key: K, value: V) -> bool:
        """Keep ``value`` as ``key``'s newest; False when it was refused (too many keys waiting)."""
        with self._lock:
            if key in self._items:
                self.replaced += 1
            elif len(self._items) >= self.max_keys:
                self.refused += 1
                return False
            self._items[key] = value
            self._ready.set()
        return True

    def take_all(self, timeout: float) -> dict[K, V]:
        """Everything waiting (oldest key first), after at most ``timeout`` s; {} if nothing came."""
        self._ready.wait(timeout)
        with self._lock:
            items, self._items = self._items, {}
            self._ready.clear()
        return items

    def wake(self) -> None:
        """Let a waiting take_all return now (to stop)."""
        self._ready.set()
