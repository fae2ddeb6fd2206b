"""Two routers, a service session and a user's session on loopback, connected BY THE CLUSTER'S NAMES, each
config given as JSON5 text; run by tests/deploy/test_zenoh_cluster.py in a process whose resolver answers
those names with 127.0.0.1 (nss_wrapper, LD_PRELOAD), since zenoh's TLS takes the server name it verifies
from the endpoint's host and resolves that host itself.

    python zenoh_fleet_by_name.py SPEC.json   ->   one JSON line: the keys the service saw, the sessions refused

SPEC: {"routers": [json5, ...], "service": json5, "users": {name: json5}, "puts": [[user, key], ...],
       "subscribe": key expression, "timeout_s": float}. Routers open first, in order; then the service, which
subscribes; then each user puts on its keys until the service has seen them or the time is up.
"""

from __future__ import annotations

import json
import sys
import threading
import time
from pathlib import Path

import zenoh


def main() -> None:
    spec = json.loads(Path(sys.argv[1]).read_text("utf-8"))
    zenoh.init_log_from_env_or("error")
    routers = [zenoh.open(zenoh.Config.from_json5(text)) for text in spec["routers"]]
    refused: list[str] = []  # the client sessions that could not connect (zenoh.open raises)

    def client(name: str, text: str) -> zenoh.Session | None:
        try:
            return zenoh.open(zenoh.Config.from_json5(text))
        except zenoh.ZError:
            refused.append(name)
            return None

    seen: set[str] = set()
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            seen.add(str(sample.key_expr))

    service = client("service", spec["service"])
    subscriber = service.declare_subscriber(spec["subscribe"], on_sample) if service is not None else None
    opened = {name: client(name, text) for name, text in spec["users"].items()}
    users = {name: session for name, session in opened.items() if session is not None}
    expected = {key for _, key in spec["puts"]}
    deadline = time.monotonic() + spec["timeout_s"]
    while time.monotonic() < deadline:
        for user, key in spec["puts"]:
            if user in users:
                users[user].put(key, b"x")
        with lock:
            if seen >= expected:
                break
        time.sleep(0.2)
    time.sleep(0.5)  # puts that were to be dropped have had the time to arrive, if they were not
    with lock:
        print(json.dumps({"seen": sorted(seen), "refused": sorted(refused)}), flush=True)
    if subscriber is not None:
        subscriber.undeclare()
    for session in [*users.values(), *([service] if service is not None else []), *routers]:
        session.close()


if __name__ == "__main__":
    main()
