"""`gcdtrav serve`'s metrics port as a process: off by default (nothing but zenoh listens), on where asked
(GET /metrics in Prometheus's text format), a taken port refused at start in one line."""

from __future__ import annotations

import os
import socket
import subprocess
import urllib.request
from pathlib import Path

import pytest
from conftest import textured_image
from zenoh_helpers import connecting_config, free_port, input_subscribed, serve_args, service_reachable, wait_until

pytest.importorskip("torch")

from gcdtrav.client import Maps, TraversabilityClient

ROBOTS = ["r1/front", "r2/front"]


def listening_ports(pid: int) -> set[int]:
    """The TCP ports process ``pid`` listens on: its sockets' inodes found in /proc/net/tcp*, state LISTEN."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    ports = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            fields = line.split()
            if fields[3] == "0A" and fields[9] in inodes:  # 0A: LISTEN
                ports.add(int(fields[1].rsplit(":", 1)[1], 16))
    return ports


def scrape(port: int) -> tuple[str, str]:
    """GET /metrics: its content type and text."""
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10) as response:
        return response.headers["Content-Type"], response.read().decode()


def mine(maps: list[Maps], robot: str) -> int:
    """How many of ``maps`` are ``robot``'s."""
    return sum(m.header.source == robot for m in maps)


def counted(text: str, robot: str) -> float:
    """The robot's frames processed or reused, by the metrics' ``text``."""
    labels = f'{{gcdtrav_instance="on",source="{robot}"}}'
    series = tuple(f"gcdtrav_frames_{kind}_total{labels}" for kind in ("processed", "reused"))
    return sum(float(line.split()[-1]) for line in text.splitlines() if line.startswith(series))


def serve(model: Path, state: Path, zenoh_port: int, *extra: str) -> subprocess.Popen[str]:
    args = serve_args(model, "-l", f"tcp/127.0.0.1:{zenoh_port}", "--state-dir", str(state), *extra)
    environ = {k: v for k, v in os.environ.items() if not k.startswith("GCDTRAV_")}  # the defaults, not the shell's
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=environ)


@pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="reads the listening sockets from Linux's /proc")
def test_metrics_are_off_by_default_and_served_where_asked(tiny_model_dir: Path, tmp_path: Path) -> None:
    off_port, on_port, metrics_port = free_port(), free_port(), free_port()
    off = serve(tiny_model_dir, tmp_path / "off", off_port, "--instance", "off")
    on = serve(
        tiny_model_dir, tmp_path / "on", on_port, "--instance", "on", "--metrics-port", str(metrics_port),
        "--metrics-address", "127.0.0.1",
    )  # fmt: skip
    try:
        with TraversabilityClient(config=connecting_config(off_port), timeout=5.0) as client:
            assert wait_until(lambda: service_reachable(client), 90), "the service did not come up"
        with TraversabilityClient(config=connecting_config(on_port), timeout=5.0) as client:
            assert wait_until(lambda: service_reachable(client), 90), "the service did not come up"
            maps: list[Maps] = []
            client.subscribe_maps("**", maps.append)  # declared before the images: it reaches the service first
            for robot in ROBOTS:
                assert input_subscribed(client, robot), "the service's input subscription"
            for k in range(2):  # two robots, two frames each: established, so the fleet's table holds them
                for robot in ROBOTS:
                    client.publish_image(robot, textured_image(48, 64, seed=k))
                # A round's maps before the next round's images: a frame still queued would be replaced.
                assert wait_until(lambda k=k: len(maps) == 2 * (k + 1), 60), len(maps)
            # The maps go out just before their frames are counted: wait for the counts to catch up.
            assert wait_until(lambda: all(counted(scrape(metrics_port)[1], r) == mine(maps, r) for r in ROBOTS), 30)
        assert wait_until(lambda: listening_ports(on.pid) == {on_port, metrics_port}, 30), listening_ports(on.pid)
        assert listening_ports(off.pid) == {off_port}  # metrics_port 0: nothing listens but zenoh
        content_type, text = scrape(metrics_port)
        assert content_type.startswith("text/plain") and "version=" in content_type
        named = '{gcdtrav_instance="on"}'  # every series names the instance
        assert f"gcdtrav_healthy{named} 1.0" in text and 'gcdtrav_service_info{anchor_set_version="' in text
        assert 'name="on"' in text and f"gcdtrav_instances_live{named} 1.0" in text
        assert f"gcdtrav_sources_owned{named} 2.0" in text  # one instance: every robot is its own
        assert len(maps) == 4
        for robot in ROBOTS:  # processed or reused, one map each
            assert mine(maps, robot) == counted(text, robot)
    finally:
        for process in (off, on):
            process.terminate()
        for process in (off, on):
            output, _ = process.communicate(timeout=30)
            assert process.returncode == 0, output
    assert f"metrics on http://127.0.0.1:{metrics_port}/metrics" in output


def test_a_taken_metrics_port_stops_serve_at_start_in_one_line(tiny_model_dir: Path, tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        process = serve(
            tiny_model_dir, tmp_path, free_port(), "--metrics-port", str(port), "--metrics-address", "127.0.0.1"
        )
        output, _ = process.communicate(timeout=120)
    assert process.returncode == 2, output
    assert f"cannot serve metrics on 127.0.0.1:{port} (metrics_port)" in output
