"""No store call on a zenoh callback thread (issue 59): with the store blocking every read for 5 s, a proposal,
its application, the anchor history and the calibration wait for it on the anchor switch's threads, while the
status, the active set and a second instance's questions are answered at once."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import pytest
from gcdtrav.client import ServiceError, TraversabilityClient
from gcdtrav.service.store.sqlite import SqliteStore
from zenoh_helpers import connecting_config, service_reachable, wait_until

from tests.service.bus.test_experience_e2e import running, settings
from tools.robot_drive import CAMERA_SOURCE

BLOCK_S = 5.0


def test_a_store_that_blocks_holds_up_no_other_query(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with running(settings(tmp_path / "state")) as (_, client, flags):
        port = int(flags[3].rsplit(":", 1)[1])  # -m client -e tcp/127.0.0.1:PORT
        release = threading.Event()
        entered: list[str] = []

        def blocking(name: str) -> Any:
            real = getattr(SqliteStore, name)

            def call(self: SqliteStore, *args: Any, **kwargs: Any) -> Any:
                entered.append(name)
                release.wait(BLOCK_S)
                return real(self, *args, **kwargs)

            return call

        for name in ("history", "pairs", "proposal"):
            monkeypatch.setattr(SqliteStore, name, blocking(name))
        slow: dict[str, float] = {}

        def ask(name: str, call: Any) -> None:
            began = time.monotonic()
            try:
                with TraversabilityClient(config=connecting_config(port), timeout=3 * BLOCK_S) as mine:
                    call(mine)
            except ServiceError:  # no pairs to propose from, no kept proposal: an answer all the same
                pass
            slow[name] = time.monotonic() - began

        waiting = [
            threading.Thread(target=ask, args=(name, call))
            for name, call in (
                ("proposal", lambda c: c.anchor_proposal()),
                ("apply", lambda c: c.apply_proposal("0123456789abcdef")),
                ("history", lambda c: c.anchor_history()),
                ("calibration", lambda c: c.calibration(CAMERA_SOURCE)),
            )
        ]
        for thread in waiting:
            thread.start()
        assert wait_until(lambda: len(entered) >= 2, 30), entered  # the reader and the worker each wait on the store
        fast = {}
        for name, call in (("status", lambda: client.status()), ("anchors", lambda: client.anchors())):
            began = time.monotonic()
            call()
            fast[name] = time.monotonic() - began
        answered_while_blocked = not release.is_set() and not slow
        release.set()
        for thread in waiting:
            thread.join(4 * BLOCK_S)
        print(f"\nwhile the store blocked: {fast}; the store's queries, answered once it answered: {slow}")
        assert answered_while_blocked, (fast, slow)  # the status and the set came while every store read waited
        assert set(slow) == {"proposal", "apply", "history", "calibration"}  # and those were answered after
        assert service_reachable(client)
