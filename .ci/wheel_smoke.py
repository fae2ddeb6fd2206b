"""CI, after installing the built wheel: the installed `gcdtrav serve` runs the grid example end to end.

    python .ci/wheel_smoke.py examples/grid.yaml

Builds a tiny random-weight checkpoint, starts `gcdtrav serve --settings examples/grid.yaml` as its own
process on a loopback port, sends a pose and one frame through the client, and waits for the maps and the
ground grid; then stops the service with SIGTERM and expects exit status 0. Bounded: fails after 180 s.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import zenoh
from gcdtrav.client import Grid, Maps, ServiceError, TraversabilityClient, zenoh_config
from gcdtrav.schemas.messages import Pose2D

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository's tools/, not in the wheel
from tools.loopback import free_port
from tools.random_clipseg import save_random_clipseg

DEADLINE_S = 180.0


def wait_for(what: str, condition, deadline: float) -> None:  # type: ignore[no-untyped-def]
    while not condition():
        if time.monotonic() > deadline:
            raise SystemExit(f"wheel smoke: no {what} within {DEADLINE_S:.0f} s")
        time.sleep(0.1)


def answers(client: TraversabilityClient) -> bool:
    try:
        client.status(timeout=1.0)
        return True
    except ServiceError:
        return False


def connected_client(config: zenoh.Config, deadline: float) -> TraversabilityClient:
    """A client-mode session opens only once the service listens, which takes the model's loading time."""
    while True:
        try:
            return TraversabilityClient(config=config, timeout=5.0)
        except zenoh.ZError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def main() -> int:
    settings = Path(sys.argv[1]).resolve()
    deadline = time.monotonic() + DEADLINE_S
    with tempfile.TemporaryDirectory() as scratch:
        model = save_random_clipseg(Path(scratch) / "tiny", preset="tiny", input_size=96)
        port = free_port()
        command = ["gcdtrav", "serve", "--settings", str(settings), "--model", str(model), "--instance", "smoke"]
        command += ["-l", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting", "--state-dir", f"{scratch}/state"]
        service = subprocess.Popen(command, cwd=scratch)  # not the checkout: only the installed wheel
        config = zenoh_config(mode="client", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
        try:
            with connected_client(config, deadline) as client:
                wait_for("status reply", lambda: answers(client), deadline)
                maps: list[Maps] = []
                grids: list[Grid] = []
                subscribers = [client.subscribe_maps("cam", maps.append), client.subscribe_grid("cam", grids.append)]
                time.sleep(0.5)
                stamp = time.time()
                client.session.put("robot/pose", Pose2D(stamp=stamp, x=0.0, y=0.0, yaw=0.0).pack())
                time.sleep(0.2)
                image = np.random.default_rng(0).integers(0, 255, (480, 640, 3), dtype=np.uint8)
                client.publish_image("cam", image, stamp=stamp)
                wait_for("maps", lambda: bool(maps), deadline)
                wait_for("ground grid", lambda: bool(grids), deadline)
                for subscriber in subscribers:
                    subscriber.undeclare()
        finally:
            service.send_signal(signal.SIGTERM)
            code = service.wait(timeout=30)
    h = maps[0].header
    print(
        f"wheel smoke: maps seq {h.seq} {h.map_shape} from {h.instance}; grid with {grids[0].header.known_cells} "
        f"known cells; service exit status {code}"
    )
    return 0 if code == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
