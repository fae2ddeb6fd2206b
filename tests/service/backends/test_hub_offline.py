"""Offline, a hub id fails at once with the instructions instead of after the hub's retries (46 s)."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import pytest
from gcdtrav.service.backends import hub

HUB_ID = "CIDAS/clipseg-rd64-refined"


def test_offline_by_setting_reads_hf_hub_offline() -> None:
    assert hub.offline_by_setting({"HF_HUB_OFFLINE": "1"}) and hub.offline_by_setting({"HF_HUB_OFFLINE": "True"})
    assert not hub.offline_by_setting({"HF_HUB_OFFLINE": "0"}) and not hub.offline_by_setting({})


def test_hub_address_follows_hf_endpoint() -> None:
    assert hub.hub_address({}) == ("huggingface.co", 443)
    assert hub.hub_address({"HF_ENDPOINT": "http://mirror.local:8080"}) == ("mirror.local", 8080)
    assert hub.hub_address({"HF_ENDPOINT": "http://mirror.local"}) == ("mirror.local", 80)


def test_a_probe_that_hangs_counts_as_unreachable_after_its_timeout() -> None:
    """A resolver that never answers (DNS without a network) costs the probe's timeout, not its own."""
    release = threading.Event()

    def hanging(address: tuple[str, int], timeout: float) -> object:
        release.wait(30)
        return True

    try:
        began = time.monotonic()
        assert not hub.hub_reachable(("hub.invalid", 443), timeout=0.2, connect=hanging)
        assert time.monotonic() - began < 10  # bounded by the probe's timeout, whatever the resolver does
    finally:
        release.set()


def test_probe_outcomes() -> None:
    def refused(address: tuple[str, int], timeout: float) -> object:
        raise ConnectionRefusedError("no")

    assert not hub.hub_reachable(("x", 1), timeout=1, connect=refused)
    assert hub.hub_reachable(("x", 1), timeout=1, connect=lambda address, timeout: True)
    with socket.socket() as listener:  # a real connection on loopback
        listener.bind(("127.0.0.1", 0))
        listener.listen(1)
        assert hub.hub_reachable(listener.getsockname(), timeout=2)


def test_hub_offline_says_why_and_trusts_a_proxy() -> None:
    assert hub.hub_offline({"HF_HUB_OFFLINE": "1"}, reachable=lambda: True) == "HF_HUB_OFFLINE is set"
    assert hub.hub_offline({}, reachable=lambda: True) is None
    assert "cannot reach huggingface.co:443" in (hub.hub_offline({}, reachable=lambda: False) or "")
    assert hub.hub_offline({"HTTPS_PROXY": "http://proxy:3128"}, reachable=lambda: False) is None


def test_an_unreachable_hub_fails_at_once_without_touching_the_network(monkeypatch: pytest.MonkeyPatch) -> None:
    """No HF_HUB_OFFLINE, the hub unreachable: the error comes from the probe, and nothing ever connects (so
    no retries): every socket connection is refused by this test."""
    pytest.importorskip("torch")
    from gcdtrav.service.backends import ModelUnavailableError
    from gcdtrav.service.backends.clipseg import ClipSegBackend

    connections: list[object] = []

    def no_connection(self: socket.socket, address: object) -> None:
        connections.append(address)
        raise AssertionError(f"a connection to {address}")

    for name in ("HF_HUB_OFFLINE", "HTTPS_PROXY", "https_proxy", "ALL_PROXY", "all_proxy"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(hub, "hub_reachable", lambda: False)
    monkeypatch.setattr(socket.socket, "connect", no_connection)
    with pytest.raises(ModelUnavailableError, match=r"cannot reach huggingface.co:443.*not in the hub's local cache"):
        ClipSegBackend(HUB_ID)
    assert connections == []


def test_an_offline_hub_id_in_the_cache_loads_from_it(
    tiny_model_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A hub id whose files are in the Hugging Face cache loads offline, local files only."""
    pytest.importorskip("torch")
    from gcdtrav.service.backends.clipseg import ClipSegBackend

    snapshot = tmp_path / "hub" / "models--someone--tiny" / "snapshots" / ("0" * 40)
    snapshot.mkdir(parents=True)
    for path in tiny_model_dir.iterdir():
        (snapshot / path.name).symlink_to(path)
    (tmp_path / "hub" / "models--someone--tiny" / "refs").mkdir()
    (tmp_path / "hub" / "models--someone--tiny" / "refs" / "main").write_text("0" * 40)
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path / "hub"))
    monkeypatch.setattr("huggingface_hub.constants.HF_HUB_CACHE", str(tmp_path / "hub"))
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    backend = ClipSegBackend("someone/tiny")
    assert backend.checkpoint_dir == snapshot
