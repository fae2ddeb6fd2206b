"""`gcdtrav serve` opens the store once, before the model loads: a store it must refuse stops it before the
model is loaded; the store's active set is the pipeline's first and the service keeps that same store."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import three_anchor_set
from gcdtrav.client.session.zenoh_args import zenoh_config
from gcdtrav.schemas.anchors import default_anchor_set
from gcdtrav.schemas.settings import ServiceSettings, SettingsError
from gcdtrav.service.commands import serve
from gcdtrav.service.store import Store, StoreUnavailable, open_store
from gcdtrav.service.store import opening as store_opening
from gcdtrav.service.store.sqlite import SqliteStore
from zenoh_helpers import free_port


class Http:
    """The probes' starting messages, recorded (the HTTP endpoints themselves are tested elsewhere)."""

    def __init__(self) -> None:
        self.said: list[str] = []

    def starting(self, message: str) -> None:
        self.said.append(message)


def test_a_store_of_a_newer_schema_stops_serve_before_the_model_loads(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    settings = ServiceSettings(state_dir=tmp_path, model=str(tmp_path / "no-model"))
    newer = SqliteStore(store_opening.sqlite_file(tmp_path, settings.prefix))
    with newer._transaction("schema") as cursor:
        cursor.execute("UPDATE schema_version SET version = 99")  # as a newer gcdtrav would leave it
    newer.close()

    def load_model(*args: object) -> None:
        raise AssertionError("the model was loaded before the store was refused")

    monkeypatch.setattr(serve, "build_service_pipeline", load_model)
    with pytest.raises(SettingsError, match="schema version 99"):
        serve.serve_with(Http(), settings, zenoh_config(mode="peer", multicast_scouting=False), None)  # type: ignore[arg-type]


def test_the_store_is_opened_once_and_its_active_set_starts_the_pipeline(
    tiny_model_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    settings = ServiceSettings(state_dir=tmp_path, model=str(tiny_model_dir), precision="fp32")
    active = three_anchor_set("fleet")
    seeded = open_store(settings.store, tmp_path, settings.prefix)
    seeded.seed(active, "box-a")
    seeded.close()
    opened: list[Store] = []

    def counted(*args: object) -> Store:
        opened.append(open_store(*args))  # type: ignore[arg-type]
        return opened[-1]

    monkeypatch.setattr(store_opening, "open_store", counted)  # the one place the service opens its store
    config = zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{free_port()}"], multicast_scouting=False)
    store = serve.store_at_start(settings)
    service, session, pipeline = serve.start_serving(Http(), settings, config, None, store)  # type: ignore[arg-type]
    try:
        assert pipeline.anchors.version == active.version
        assert len(opened) == 1 and service.store.store is opened[0]
    finally:
        service.stop()
        session.close()


def test_a_store_not_reached_at_start_is_tried_once_and_the_configured_set_starts(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An unreachable PostgreSQL costs serve one connect timeout before the model loads, not one per reader."""
    tries: list[object] = []

    def unreachable(*args: object) -> Store:
        tries.append(args)
        raise StoreUnavailable("connection refused")

    monkeypatch.setattr(store_opening, "open_store", unreachable)
    settings = ServiceSettings(state_dir=tmp_path)
    store = serve.store_at_start(settings)
    assert store is None
    assert serve.starting_anchor_set(settings, store).version == default_anchor_set().version
    assert len(tries) == 1
