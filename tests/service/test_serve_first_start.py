"""`gcdtrav serve` on a fresh box (empty HOME, state and cache): visible and answering status at once, while
precision auto measures the modes in the background; then it switches; nothing is written outside the
state and cache directories."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import zenoh
from conftest import textured_image
from zenoh_helpers import MapsInbox, connecting_config, free_port, input_subscribed, wait_until

pytest.importorskip("torch")

from gcdtrav.client import QueryTimeout, TraversabilityClient
from gcdtrav.schemas.messages import ServiceStatus

ROOT = Path(__file__).resolve().parents[2]
# The measurement waits for a file the test creates: however fast or slow the model, serve must already
# answer while it runs. Then int8 is reported fastest, so the switch is visible.
SLOW_MEASUREMENT = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from gcdtrav.service.backends import precision_choice
    from gcdtrav.service.backends.precision_choice import ModeMeasurement

    def measure_when_released(backend, modes, runs=3, **options):
        while not Path(sys.argv[1]).exists():
            time.sleep(0.05)
        return [ModeMeasurement("fp32", 100.0, 0.0), ModeMeasurement("int8", 40.0, 0.001)]

    precision_choice.measure_modes = measure_when_released
    from gcdtrav.service.commands.cli import main
    sys.exit(main(sys.argv[2:]))
    """
)


def status_or_none(client: TraversabilityClient) -> ServiceStatus | None:
    try:
        return client.status(timeout=5.0)  # a measuring, loaded service answers late
    except QueryTimeout:
        return None


def alive_tokens(session: zenoh.Session) -> list[str]:
    return [str(reply.ok.key_expr) for reply in session.liveliness().get("gcdtrav/alive/*", timeout=1.0) if reply.ok]


def files_under(folder: Path) -> list[str]:
    return sorted(str(path.relative_to(folder)) for path in folder.rglob("*") if path.is_file())


def test_serve_answers_at_once_while_auto_measures_then_switches(tiny_model_dir: Path, tmp_path: Path) -> None:
    home, cwd, release = tmp_path / "home", tmp_path / "cwd", tmp_path / "release-measurement"
    home.mkdir()
    cwd.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith(("XDG_", "GCDTRAV_"))}
    env |= {"HOME": str(home), "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))}
    port = free_port()
    serve = ["serve", "--model", str(tiny_model_dir), "-l", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]
    process = subprocess.Popen(
        [sys.executable, "-c", SLOW_MEASUREMENT, str(release), *serve, "--instance", "fresh"],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        with TraversabilityClient(config=connecting_config(port), timeout=5.0) as client:
            assert wait_until(lambda: status_or_none(client) is not None, 60), "no status while measuring"
            first = status_or_none(client)
            assert first is not None and first.measuring and first.precision == "fp32", first
            assert "measuring in the background" in first.precision_reason
            assert alive_tokens(client.session) == ["gcdtrav/alive/fresh"]
            maps = MapsInbox(client)  # subscribed before the image (iter_maps subscribed only at its next())
            assert input_subscribed(client, "cam"), "the service's input subscription"
            client.publish_image("cam", textured_image(64, 64))
            assert maps.next().header.instance == "fresh"  # frames are served while measuring

            release.touch()
            assert wait_until(lambda: not getattr(status_or_none(client), "measuring", True), 60)
            after = status_or_none(client)
            assert after is not None and after.precision == "int8", after
            client.publish_image("cam", textured_image(64, 64, seed=1)[::-1].copy())  # another view: inferred
            after_switch = maps.next()
            assert after_switch.header.seq >= 1 and not after_switch.reused  # and after the switch
        process.send_signal(signal.SIGTERM)
        output, _ = process.communicate(timeout=30)
        assert process.returncode == 0, output
    finally:
        if process.poll() is None:
            process.kill()
    assert "precision switched to int8" in output
    assert files_under(cwd) == []  # no folder named '~', no export in the working directory
    written = files_under(home)
    assert written and all(path.startswith((".cache/gcdtrav/", ".local/state/gcdtrav/")) for path in written), written
    assert any(path.startswith(".cache/gcdtrav/precision/") for path in written)


def test_serve_stops_cleanly_in_the_middle_of_the_measurement(tiny_model_dir: Path, tmp_path: Path) -> None:
    """SIGTERM while a mode is being measured (here: forever): exit status 0, no abort of a native thread."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("GCDTRAV_")}
    env |= {"PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))}
    env |= {"XDG_CACHE_HOME": str(tmp_path / "cache"), "XDG_STATE_HOME": str(tmp_path / "state")}
    port = free_port()
    serve = ["serve", "--model", str(tiny_model_dir), "-l", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]
    never = str(tmp_path / "never-released")
    process = subprocess.Popen(
        [sys.executable, "-c", SLOW_MEASUREMENT, never, *serve], env=env, stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    try:
        with TraversabilityClient(config=connecting_config(port), timeout=5.0) as client:
            assert wait_until(lambda: getattr(status_or_none(client), "measuring", False), 60)
        process.send_signal(signal.SIGTERM)
        output, _ = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 0, output
    assert "stopped" in output and "not waiting for it (nothing cached)" in output
    assert not (tmp_path / "cache" / "gcdtrav" / "precision").exists()
