"""`gcdtrav serve` as a process: starts, serves, stops cleanly on signals, keeps the accepted set."""

from __future__ import annotations

import signal
import subprocess
import time
from pathlib import Path

import pytest
from conftest import textured_image
from zenoh_helpers import (
    MapsInbox,
    connecting_config,
    free_port,
    input_subscribed,
    serve_args,
    service_reachable,
    wait_until,
)

pytest.importorskip("torch")

from gcdtrav.client import TraversabilityClient

NEW_SET = {
    "anchors": [
        {"concept": "lake", "position": 0.0},
        {"concept": "trail", "position": 0.7},
        {"concept": "road", "position": 1.0},
    ]
}


def start(model: Path, state: Path, port: int) -> subprocess.Popen[str]:
    args = serve_args(model, "-l", f"tcp/127.0.0.1:{port}", "--state-dir", str(state), "--instance", "cli-test")
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def stop(process: subprocess.Popen[str], signum: int) -> tuple[int, float, str]:
    began = time.monotonic()
    process.send_signal(signum)
    output, _ = process.communicate(timeout=30)
    return process.returncode, time.monotonic() - began, output


def test_serve_stops_cleanly_and_restart_keeps_the_accepted_set(tiny_model_dir: Path, tmp_path: Path) -> None:
    port = free_port()
    process = start(tiny_model_dir, tmp_path, port)
    try:
        with TraversabilityClient(config=connecting_config(port), timeout=5.0) as client:
            assert wait_until(lambda: service_reachable(client), 60), "service did not come up"
            maps = MapsInbox(client)  # subscribed before the image (iter_maps subscribed only at its next())
            assert input_subscribed(client, "cam"), "the service's input subscription"
            client.publish_image("cam", textured_image(64, 64))
            first = maps.next()
            assert first.header.instance == "cli-test"
            version = client.set_anchors(NEW_SET)
        code, seconds, output = stop(process, signal.SIGTERM)
        assert code == 0, output
        assert seconds < 10 + 5  # shutdown_grace_s (the exit's bound once the signal is seen), and slack
        assert "SIGTERM received" in output and "stopped" in output
    finally:
        if process.poll() is None:
            process.kill()

    process = start(tiny_model_dir, tmp_path, port)
    try:
        with TraversabilityClient(config=connecting_config(port), timeout=5.0) as client:
            assert wait_until(lambda: service_reachable(client), 60)
            reply = client.anchors()
            assert reply.version == version and [a.concept for a in reply.anchor_set.anchors] == [
                "lake",
                "trail",
                "road",
            ]
        code, _, output = stop(process, signal.SIGINT)
        assert code == 0, output
    finally:
        if process.poll() is None:
            process.kill()


def test_serve_with_missing_model_exits_2(tmp_path: Path) -> None:
    args = serve_args(tmp_path / "none", "-l", f"tcp/127.0.0.1:{free_port()}")
    result = subprocess.run(args, capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert "does not exist" in result.stderr and "Traceback" not in result.stderr


def test_serve_rejects_inputs_that_overlap_outputs(tiny_model_dir: Path, tmp_path: Path) -> None:
    args = serve_args(
        tiny_model_dir, "--input", "**", "-l", f"tcp/127.0.0.1:{free_port()}", "--state-dir", str(tmp_path)
    )
    result = subprocess.run(args, capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert "overlaps the service's outputs" in result.stderr


def test_serve_listens_on_7447_unless_told_where() -> None:
    from gcdtrav.service.commands.cli import DEFAULT_SERVE_LISTEN, build_parser, listens_by_choice

    assert DEFAULT_SERVE_LISTEN == "tcp/0.0.0.0:7447"
    parse = build_parser().parse_args
    assert not listens_by_choice(parse(["serve"]))
    assert not listens_by_choice(parse(["serve", "-e", "tcp/robot:7447", "--cfg", "scouting/gossip/enabled:false"]))
    for told in (["-l", "tcp/127.0.0.1:9000"], ["-c", "zenoh.json5"], ["--cfg", "listen/endpoints:[]"]):
        assert listens_by_choice(parse(["serve", *told]))


def test_a_taken_default_port_falls_back_to_zenohs_pick(caplog: pytest.LogCaptureFixture) -> None:
    import socket

    from gcdtrav.client.session.zenoh_args import zenoh_config
    from gcdtrav.schemas.settings import SettingsError
    from gcdtrav.service.commands.serve import open_session

    with socket.socket() as taken:
        taken.bind(("0.0.0.0", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        busy = zenoh_config(mode="peer", listen=[f"tcp/0.0.0.0:{port}"], multicast_scouting=False)
        with pytest.raises(SettingsError, match="cannot open the zenoh session"):
            open_session(busy)
        free = free_port()
        fallback = zenoh_config(mode="peer", listen=[f"tcp/127.0.0.1:{free}"], multicast_scouting=False)
        session = open_session(busy, fallback)
        try:
            socket.create_connection(("127.0.0.1", free), timeout=5).close()  # the fallback listens
        finally:
            session.close()
    assert "cannot listen on serve's default endpoint" in caplog.text and "give -l ENDPOINT" in caplog.text
