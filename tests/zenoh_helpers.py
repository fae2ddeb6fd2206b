"""Real zenoh sessions on loopback for tests: multicast scouting off, ports picked by the test."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable

import zenoh
from gcdtrav.client.zenoh_args import zenoh_config


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def listening_config(port: int, mode: str = "peer") -> zenoh.Config:
    return zenoh_config(mode=mode, listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)


def connecting_config(port: int, mode: str = "peer") -> zenoh.Config:
    conf = zenoh_config(mode=mode, connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
    conf.insert_json5("scouting/gossip/enabled", "false")
    return conf


def wait_until(condition: Callable[[], object], timeout: float = 10.0, interval: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(interval)
    return bool(condition())
