"""Is the Hugging Face hub reachable, and is a hub id in the local cache? Answered in about a second.

Offline, transformers' ``from_pretrained`` of a hub id retries the hub several times with back-off (46 s on
a box without a network) before failing. So before loading a hub id: if ``HF_HUB_OFFLINE`` is set or a TCP
connection to the hub cannot be opened within ``PROBE_TIMEOUT_S``, the model is loaded from the local
cache only, and one that is not cached fails at once with the instructions.
"""

from __future__ import annotations

import os
import socket
import threading
from collections.abc import Callable, Mapping
from urllib.parse import urlsplit

PROBE_TIMEOUT_S = 1.5
DEFAULT_ENDPOINT = "https://huggingface.co"
PROXY_VARIABLES = ("HTTPS_PROXY", "https_proxy", "ALL_PROXY", "all_proxy")
TRUE_VALUES = ("1", "on", "yes", "true")

Connect = Callable[[tuple[str, int], float], object]


def offline_by_setting(environ: Mapping[str, str] | None = None) -> bool:
    env = os.environ if environ is None else environ
    return env.get("HF_HUB_OFFLINE", "").strip().lower() in TRUE_VALUES


def hub_address(environ: Mapping[str, str] | None = None) -> tuple[str, int]:
    env = os.environ if environ is None else environ
    url = urlsplit(env.get("HF_ENDPOINT") or DEFAULT_ENDPOINT)
    return url.hostname or "huggingface.co", url.port or (80 if url.scheme == "http" else 443)


def _open_and_close(address: tuple[str, int], timeout: float) -> object:
    socket.create_connection(address, timeout=timeout).close()
    return True


def hub_reachable(
    address: tuple[str, int] | None = None, timeout: float = PROBE_TIMEOUT_S, connect: Connect = _open_and_close
) -> bool:
    """A TCP connection to the hub opens within ``timeout`` (DNS included: the probe runs in a thread that is
    abandoned when the time is up, so a resolver that hangs costs ``timeout``, not its own minutes)."""
    target = address or hub_address()
    outcome: list[bool] = []

    def probe() -> None:
        try:
            connect(target, timeout)
            outcome.append(True)
        except OSError:
            outcome.append(False)

    thread = threading.Thread(target=probe, name="hub-probe", daemon=True)
    thread.start()
    thread.join(timeout)
    return bool(outcome and outcome[0])


def hub_offline(environ: Mapping[str, str] | None = None, reachable: Callable[[], bool] = hub_reachable) -> str | None:
    """Why the hub cannot be used ('HF_HUB_OFFLINE is set', 'cannot reach huggingface.co:443'), or None.
    Behind a proxy a direct connection says nothing: the hub is then assumed reachable."""
    env = os.environ if environ is None else environ
    if offline_by_setting(env):
        return "HF_HUB_OFFLINE is set"
    if any(env.get(name) for name in PROXY_VARIABLES):
        return None
    if reachable():
        return None
    host, port = hub_address(env)
    return f"cannot reach {host}:{port} within {PROBE_TIMEOUT_S:g} s"


def cached_in_hub_cache(model_id: str, filename: str = "config.json") -> bool:
    """The hub id's file is in the local Hugging Face cache (no network)."""
    from huggingface_hub import try_to_load_from_cache

    try:
        found = try_to_load_from_cache(model_id, filename)
    except ValueError:  # not a valid repo id
        return False
    return isinstance(found, str)
