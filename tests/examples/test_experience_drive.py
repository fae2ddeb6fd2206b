"""examples/experience_drive.py, briefly, against a service on loopback started from examples/experience_drive.yaml
(the scene's backend in place of CLIPSeg): the drive publishes poses, images, commands, odometry and contact
outcomes the documented way, and `gcdtrav calibration` and `gcdtrav anchors propose` then have data."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from conftest import torch_free_gcdtrav
from gcdtrav.client import TraversabilityClient
from gcdtrav.schemas.delay_window import WINDOW_S
from gcdtrav.schemas.settings import load_settings
from zenoh_helpers import connecting_config

from tools.loopback import in_process_service
from tools.robot_drive import CAMERA_SOURCE, experience_settings, grid_settings
from tools.synthetic_scene import SceneBackend, start_anchors

ROOT = Path(__file__).resolve().parents[2]
SETTINGS = ROOT / "examples" / "experience_drive.yaml"


def test_the_settings_are_the_simulated_robots() -> None:
    settings = load_settings(SETTINGS, environ={})
    assert settings.grids == [grid_settings()]  # the camera the robot renders, where it puts its pose
    expected = experience_settings()
    assert (settings.experience.cmd_vel, settings.experience.odometry) == (expected.cmd_vel, expected.odometry)
    assert settings.experience.enabled and settings.ask.enabled


def test_the_settings_keep_the_map_age_alert_on() -> None:
    """Without max_frame_age_s, gcdtrav_max_frame_age_seconds is absent and GcdtravMapAgeHigh never fires. The
    limit must exceed what the simulated clock's drift can make a frame's lag: the offset window (clock:
    estimated, the smallest delay of WINDOW_S), plus a margin for the frame's time in the service."""
    settings = load_settings(SETTINGS, environ={})
    assert settings.clock == "estimated"
    assert settings.max_frame_age_s is not None and settings.max_frame_age_s >= WINDOW_S + 5.0


def test_a_short_drive_gives_calibration_and_a_proposal_data(tmp_path: Path) -> None:
    settings = load_settings(SETTINGS, {"state_dir": str(tmp_path), "instance": "sim-1"}, environ={})
    with (
        in_process_service(SceneBackend(), settings, start_anchors()) as (_, port),
        TraversabilityClient(config=connecting_config(port), timeout=5.0) as client,
    ):
        flags = ["-m", "client", "-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]
        script = [sys.executable, str(ROOT / "examples" / "experience_drive.py"), "--seconds", "40", *flags]
        drive = subprocess.run(script, capture_output=True, text=True, timeout=300, cwd=tmp_path)
        assert drive.returncode == 0, drive.stderr
        lines = drive.stdout.splitlines()
        assert lines[0].endswith(" m: 0 outcomes, 0 pairs, 0 questions") and len(lines) >= 5  # every 10 s
        assert lines[-2].startswith("drove 40 s (simulated, last stamp ") and lines[-1].startswith("next: ")

        report = client.calibration(CAMERA_SOURCE)
        assert report.figures.pairs > 100 and report.pairs_by_kind["velocity"] > 100
        assert report.pairs_by_kind.get("contact", 0) > 0  # the bumper's stalls in water, as TraversalOutcome
        calibration = subprocess.run(torch_free_gcdtrav("calibration", *flags), capture_output=True, text=True)
        assert calibration.returncode == 0 and "\nverdict: " in calibration.stdout, calibration.stderr
        proposal = subprocess.run(torch_free_gcdtrav("anchors", "propose", *flags), capture_output=True, text=True)
        assert proposal.returncode == 0 and "\nverdict: " in proposal.stdout, proposal.stderr


def test_without_a_service_it_says_what_to_start(tmp_path: Path) -> None:
    from tools.loopback import free_port

    flags = ["-m", "client", "-e", f"tcp/127.0.0.1:{free_port()}", "--no-multicast-scouting"]
    script = [sys.executable, str(ROOT / "examples" / "experience_drive.py"), "--seconds", "1", "--timeout", "1"]
    done = subprocess.run([*script, *flags], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert done.returncode == 1 and "Traceback" not in done.stderr and ".rs:" not in done.stderr
    assert done.stderr.splitlines()[-1].endswith("examples/experience_drive.yaml` running, and reachable?")
