"""`gcdtrav serve` as a process: its one HTTP port is open from the first second, answering 503 "starting"
while the model loads and warms up (a kubelet sees a pod starting, not a closed port), then the service's
probes and metrics on the same port, as the Kubernetes manifests configure it."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

import pytest
from zenoh_helpers import free_port, wait_until

pytest.importorskip("torch")

ROOT = Path(__file__).resolve().parents[2]


def get(port: int, path: str) -> tuple[int, str]:
    """Status and body; 0 when nothing listens."""
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=30) as reply:  # bounds a failure
            return reply.status, reply.read().decode()
    except urllib.error.HTTPError as err:
        return err.code, err.read().decode()
    except urllib.error.URLError:
        return 0, ""


def test_the_probe_port_answers_503_starting_before_the_model_has_warmed_up(
    tiny_model_dir: Path, tmp_path: Path
) -> None:
    """The warm-up inference is held (tools/faulty_serve.py: inference blocks while a flag file exists), so
    the service is still starting; before, nothing listened until the service ran."""
    port, hold = free_port(), tmp_path / "hold-inference"
    hold.touch()
    environ = {k: v for k, v in os.environ.items() if not k.startswith("GCDTRAV_")}
    environ |= {"FAULTY_SERVE_HANG_FLAG": str(hold), "GCDTRAV_HEALTH_PORT": str(port)}
    environ |= {"GCDTRAV_METRICS_PORT": str(port), "GCDTRAV_HEALTH_ADDRESS": "127.0.0.1"}
    environ["GCDTRAV_METRICS_ADDRESS"] = "127.0.0.1"
    command = [sys.executable, "-m", "tools.faulty_serve", "serve", "--model", str(tiny_model_dir)]
    command += ["--no-multicast-scouting", "-l", f"tcp/127.0.0.1:{free_port()}", "--state-dir", str(tmp_path)]
    process = subprocess.Popen(
        command, cwd=ROOT, env=environ, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    try:
        assert wait_until(lambda: get(port, "/livez")[0] != 0, 60), "the port never opened"
        assert get(port, "/readyz")[1].startswith("starting: "), "loading the model, then warming up"
        assert wait_until(lambda: get(port, "/livez")[1] == "starting: warming up\n", 60)
        for path in ("/livez", "/readyz", "/metrics"):  # held in the warm-up: nothing is served yet
            assert get(port, path) == (503, "starting: warming up\n"), path
        hold.unlink()
        assert wait_until(lambda: get(port, "/readyz") == (200, "ok\n"), 60)
        assert get(port, "/livez") == (200, "ok\n")
        status, text = get(port, "/metrics")
        assert status == 200 and re.search(r"^gcdtrav_healthy(\{[^}]*\})? 1\.0$", text, re.MULTILINE), text[-400:]
    finally:
        hold.unlink(missing_ok=True)
        process.terminate()
        output, _ = process.communicate(timeout=30)
    assert process.returncode == 0, output
