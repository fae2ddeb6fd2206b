"""A pod's first start, measured (issue 47 item 3): peak RSS and the bytes written to TMPDIR and the cache.

Runs `gcdtrav serve` with the Kubernetes ConfigMap's settings (deploy/kubernetes/base/config/service.yaml,
or --settings) on an empty state and cache directory, under `/usr/bin/time -v` (its "Maximum resident set
size" is the peak RSS of the process), and samples the size of TMPDIR and of the cache directory every
0.2 s until /readyz answers 200 (the pod would then be ready), then stops it with SIGTERM. Without a
checkpoint it builds random weights of the real architecture (tools/random_clipseg.py, rd64-refined): the
memory and the exports are those of the real model.

    python -m benchmarks.first_start [--model DIR] [--settings FILE] [--out benchmarks/first-start-DATE.json]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path

from tools.random_clipseg import checkpoint_or_random

ROOT = Path(__file__).resolve().parents[1]
CONFIGMAP_SETTINGS = ROOT / "deploy" / "kubernetes" / "base" / "config" / "service.yaml"
READY_TIMEOUT_S = 1800.0


def tree_bytes(folder: Path) -> int:
    total = 0
    for path, _dirs, files in os.walk(folder):
        for name in files:
            with contextlib.suppress(FileNotFoundError):  # removed while we walked: a temporary file
                total += os.lstat(os.path.join(path, name)).st_size
    return total


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def ready(port: int) -> bool:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/readyz", timeout=1) as reply:
            return bool(reply.status == 200)
    except (urllib.error.URLError, OSError):
        return False


def cpu_name() -> str:
    lscpu = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
    found = re.search(r"Model name:\s*(.+)", lscpu)
    return found.group(1).strip() if found else platform.processor()


def measure(model: Path, settings: Path, scratch: Path) -> dict[str, object]:
    health_port = free_port()
    tmpdir, cache, state = scratch / "tmp", scratch / "cache", scratch / "state"
    for folder in (tmpdir, cache, state):
        folder.mkdir()
    environ = {
        **os.environ,
        "TMPDIR": str(tmpdir),
        "GCDTRAV_MODEL": str(model),
        "GCDTRAV_CACHE_DIR": str(cache),
        "GCDTRAV_STATE_DIR": str(state),
        "GCDTRAV_HEALTH_PORT": str(health_port),
        "GCDTRAV_HEALTH_ADDRESS": "127.0.0.1",
    }
    anchors = ROOT / "deploy" / "kubernetes" / "base" / "config" / "anchors.yaml"
    environ["GCDTRAV_ANCHORS_FILE"] = str(anchors)
    rusage = scratch / "time.txt"
    gcdtrav = shutil.which("gcdtrav") or sys.exit("the gcdtrav command is not installed")
    command = ["/usr/bin/time", "-v", "-o", str(rusage), gcdtrav, "serve", "--settings", str(settings)]
    command += ["--listen", "tcp/127.0.0.1:0", "--no-multicast-scouting"]
    began = time.monotonic()
    process = subprocess.Popen(
        command, env=environ, stdout=subprocess.DEVNULL, stderr=scratch.joinpath("log").open("w")
    )
    peak_tmp = peak_cache = 0
    ready_after_s = None
    while time.monotonic() - began < READY_TIMEOUT_S and process.poll() is None:
        peak_tmp = max(peak_tmp, tree_bytes(tmpdir))
        peak_cache = max(peak_cache, tree_bytes(cache))
        if ready(health_port):
            ready_after_s = time.monotonic() - began
            break
        time.sleep(0.2)
    children = Path(f"/proc/{process.pid}/task/{process.pid}/children")
    for child in children.read_text().split() if process.poll() is None else []:
        os.kill(int(child), signal.SIGTERM)  # gcdtrav serve, not /usr/bin/time: time then writes its report
    process.wait(60)
    usage = re.search(r"Maximum resident set size \(kbytes\): (\d+)", rusage.read_text("utf-8"))
    if usage is None:
        sys.exit(
            f"no resource usage from /usr/bin/time:\n{rusage.read_text('utf-8')}"
            + scratch.joinpath("log").read_text("utf-8")
        )
    peak_rss_kib = int(usage.group(1))
    return {
        "cpu": cpu_name(),
        "cpus": os.cpu_count(),
        "settings": str(settings.relative_to(ROOT)) if settings.is_relative_to(ROOT) else str(settings),
        "ready_after_s": None if ready_after_s is None else round(ready_after_s, 1),
        "peak_rss_mib": round(peak_rss_kib / 1024, 1),
        "peak_tmpdir_mib": round(peak_tmp / 2**20, 1),
        "peak_cache_mib": round(peak_cache / 2**20, 1),
        "cache_after_mib": round(tree_bytes(cache) / 2**20, 1),
        "log_tail": scratch.joinpath("log").read_text("utf-8").splitlines()[-8:],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", help="checkpoint directory (default: random weights of rd64-refined)")
    parser.add_argument("--settings", type=Path, default=CONFIGMAP_SETTINGS)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        model = checkpoint_or_random(args.model, Path(scratch))
        run = Path(scratch) / "run"
        run.mkdir()
        result = measure(model, args.settings.resolve(), run)
    print(json.dumps(result, indent=2))
    if args.out:
        args.out.write_text(json.dumps(result, indent=2) + "\n", "utf-8")


if __name__ == "__main__":
    main()
