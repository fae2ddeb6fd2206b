"""One anchor set per fleet: instances converge to the newest accepted set, a new one adopts it, rollback is a
fleet action, and a swap some instances refuse says exactly which instance holds what."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import zenoh
from zenoh_helpers import client_config, free_port, start_router, wait_until

pytest.importorskip("torch")

from conftest import three_anchor_set
from gcdtrav.client import PartialSwap, TraversabilityClient
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.schemas.config import EngineSettings
from gcdtrav.schemas.settings import ServiceSettings
from gcdtrav.service.bus.node import TraversabilityService
from gcdtrav.service.pipeline import Pipeline
from gcdtrav.service.store import StoreUnavailable


class Fleet:
    def __init__(self, backend: Any, port: int, root: Path) -> None:
        self.backend, self.port, self.root = backend, port, root
        self.running: dict[str, tuple[TraversabilityService, zenoh.Session]] = {}

    def start(self, instance: str) -> TraversabilityService:
        session = zenoh.open(client_config(self.port))
        settings = ServiceSettings(state_dir=self.root / instance, instance=instance, preview=False)
        pipeline = Pipeline(self.backend, default_anchor_set(), EngineSettings())
        service = TraversabilityService(session, pipeline, settings)
        service.start()
        self.running[instance] = (service, session)
        return service

    def versions(self) -> dict[str, str]:
        return {name: service.pipeline.anchors.version for name, (service, _) in self.running.items()}

    def converged_on(self, version: str) -> bool:
        return set(self.versions().values()) == {version}

    def stop(self) -> None:
        for service, session in self.running.values():
            service.stop()
            session.close()


def test_instances_converge_new_ones_adopt_and_rollback_ends_everywhere_on_one_set(
    tiny_backend: Any, tmp_path: Path
) -> None:
    port = free_port()
    router = start_router(port)
    fleet = Fleet(tiny_backend, port, tmp_path)
    client = TraversabilityClient(config=client_config(port), timeout=5.0)
    try:
        a, b = fleet.start("box-a"), fleet.start("box-b")
        assert wait_until(lambda: len(client.statuses(timeout=1.0)) == 2, 60)
        first = three_anchor_set("first")
        a.runtime.anchor_switch.swap(first)  # a swap that reached one instance only
        assert wait_until(lambda: fleet.converged_on(first.version), 60), fleet.versions()
        accepted = a.runtime.anchor_switch.head().accepted_at
        assert b.runtime.anchor_switch.head().accepted_at == accepted  # adopted, not re-accepted
        c = fleet.start("box-c")  # starts with the default set and an empty state dir
        assert wait_until(lambda: fleet.converged_on(first.version), 60), fleet.versions()
        assert wait_until(lambda: c.status().anchor_sets == dict.fromkeys(fleet.running, first.version), 60)

        second = three_anchor_set("second")
        assert client.set_anchors(second) == second.version
        assert fleet.converged_on(second.version)
        assert client.rollback_anchors(1) == first.version
        assert wait_until(lambda: fleet.converged_on(first.version), 60), fleet.versions()
        assert {s.anchor_set_version for s in client.statuses()} == {first.version}
    finally:
        client.close()
        fleet.stop()
        router.terminate()
        router.communicate(timeout=20)


def test_a_swap_one_instance_refuses_names_each_instance_and_the_status_shows_the_divergence(
    tiny_backend: Any, tmp_path: Path
) -> None:
    port = free_port()
    router = start_router(port)
    fleet = Fleet(tiny_backend, port, tmp_path)
    client = TraversabilityClient(config=client_config(port), timeout=5.0)
    try:
        a, b = fleet.start("box-a"), fleet.start("box-b")
        assert wait_until(lambda: len(client.statuses(timeout=1.0)) == 2, 60)

        def unwritable(*_: object, **__: object) -> None:
            raise StoreUnavailable("the store b.sqlite3: disk I/O error")

        b.runtime.anchor_switch.store.activate = unwritable  # type: ignore[method-assign]  # b's store refuses
        new = three_anchor_set("new")
        with pytest.raises(PartialSwap) as partial:
            client.set_anchors(new)
        assert partial.value.swapped == {"box-a": new.version} and set(partial.value.failed) == {"box-b"}
        assert f"anchor set {new.version} active on box-a; not on the others: box-b:" in str(partial.value)
        assert fleet.versions() == {"box-a": new.version, "box-b": default_anchor_set().version}
        status = a.status()
        assert wait_until(lambda: a.status().anchor_sets == fleet.versions(), 60), status.anchor_sets
    finally:
        client.close()
        fleet.stop()
        router.terminate()
        router.communicate(timeout=20)
