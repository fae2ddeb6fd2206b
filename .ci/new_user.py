"""A new user's first hour, as CI: the README's quick start run as written, in an empty folder with an empty HOME.

    python .ci/new_user.py --wheel dist/gcdtrav-*.whl --venv .venv-newuser   # CI: a fresh venv from the wheel
    python .ci/new_user.py                                                   # locally: the gcdtrav on PATH

The commands are the bash blocks of README.md between the markers ``<!-- new-user: begin`` and
``<!-- new-user: end -->``, so the document and this test cannot drift. Each line runs in bash as it is,
with two substitutions that the README states beside the block:
  * a ``pip install`` line installs the built wheel into the venv (deploy/install-wheel.sh, as the Docker
    image does; without --wheel, locally, it is skipped and the gcdtrav already on PATH is used);
  * ``hf download REPO --local-dir DIR`` writes a tiny random checkpoint into DIR (tools/random_clipseg.py):
    no download, and the commands after it run on a real, small, checkpoint in DIR.
A line that runs ``gcdtrav serve`` starts in the background, as in its own terminal; the next lines run
once it logs that it is serving; at the end it gets SIGINT (Ctrl-C) and must exit 0. Every other line must
exit 0. Afterwards nothing may have been written outside the state and cache directories: the working
directory holds only the checkpoint, HOME only .local/state/gcdtrav and .cache/gcdtrav.

Before the service stops, a PNG camera (issue 36: bare PNGs were rejected as malformed envelopes): the
user's Python puts a 640x480 PNG, bare and without an encoding, on gcdtrav/in/png_camera, as a camera on
zenoh would, and the README's `gcdtrav probe SOURCE 320 400` must answer for it (the other cameras and the
README's other examples are tests: tests/client/test_first_contact.py).

Bounded: each command at most COMMAND_TIMEOUT_S, the service's start at most SERVE_START_S.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # the repository's tools/, not in the wheel
COMMAND_TIMEOUT_S = 240
SERVE_START_S = 120
SERVE_PORT = 7447  # gcdtrav serve's default listen port (service/commands/cli.py DEFAULT_SERVE_LISTEN)
ALLOWED_IN_HOME = (".cache/gcdtrav/", ".local/state/gcdtrav/")
CAMERA_S = 90  # the PNG camera's frames until the probe answers (the service may still measure the modes)
PNG_CAMERA = f"""
import sys, time
import cv2, numpy as np, zenoh
config = zenoh.Config()
config.insert_json5("mode", '"client"')
config.insert_json5("connect/endpoints", '["tcp/localhost:{SERVE_PORT}"]')
image = np.random.default_rng(0).integers(0, 256, (480, 640, 3), np.uint8)
png = cv2.imencode(".png", image)[1].tobytes()
with zenoh.open(config) as session:
    deadline = time.monotonic() + float(sys.argv[1])
    while time.monotonic() < deadline:
        session.put("gcdtrav/in/png_camera", png)  # no encoding: zenoh/bytes
        time.sleep(0.5)
"""


def quick_start_lines(readme: str) -> list[str]:
    """The command lines of the bash blocks between the new-user markers, in order (blank lines dropped)."""
    found = re.search(r"<!-- new-user: begin.*?-->(.*?)<!-- new-user: end -->", readme, re.S)
    if found is None:
        raise SystemExit("README.md: no <!-- new-user: begin ... --> ... <!-- new-user: end --> section")
    blocks = re.findall(r"```bash\n(.*?)```", found.group(1), re.S)
    lines = [line.strip() for block in blocks for line in block.splitlines() if line.strip()]
    if not lines:
        raise SystemExit("README.md: the new-user section has no bash block")
    return lines


def download_target(line: str) -> Path | None:
    """DIR of a ``hf download REPO --local-dir DIR`` line, None for any other line."""
    words = shlex.split(line, comments=True)
    if words[:2] != ["hf", "download"]:
        return None
    if "--local-dir" not in words:
        raise SystemExit(f"README.md: '{line}' has no --local-dir: the commands after it cannot name the folder")
    return Path(words[words.index("--local-dir") + 1])


def is_install(line: str) -> bool:
    return shlex.split(line, comments=True)[:2] == ["pip", "install"]


def is_service(line: str) -> bool:
    return shlex.split(line, comments=True)[:2] == ["gcdtrav", "serve"]


def files_under(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) + ("/" if p.is_dir() else "") for p in folder.rglob("*") if p.is_file())


def port_free(port: int) -> bool:
    with socket.socket() as probe:
        try:
            probe.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True


class NewUser:
    def __init__(self, scratch: Path, venv: Path | None, wheel: Path | None) -> None:
        self.home, self.cwd, self.logs = scratch / "home", scratch / "work", scratch / "logs"
        for folder in (self.home, self.cwd, self.logs):
            folder.mkdir()
        self.venv, self.wheel = venv, wheel
        self.services: list[tuple[str, subprocess.Popen[bytes], Path]] = []
        self.env = self.user_environment()
        self.installed: set[str] = set()  # what the install step left in HOME (pip's and toolchains' files)

    def user_environment(self) -> dict[str, str]:
        """A user's shell: this HOME, no XDG or GCDTRAV variables, no PYTHONPATH (the installed gcdtrav, not the
        checkout), the venv first on PATH; the hub offline (nothing is ever downloaded)."""
        drop = ("XDG_", "GCDTRAV_", "PYTHONPATH", "ORT_", "HF_", "TRANSFORMERS_")
        env = {k: v for k, v in os.environ.items() if not k.startswith(drop)}
        if self.venv is None and os.environ.get("PYTHONPATH"):
            env["PYTHONPATH"] = os.environ["PYTHONPATH"]  # locally, the development checkout
        env |= {"HOME": str(self.home), "HF_HUB_OFFLINE": "1"}
        if self.venv is not None:
            env["PATH"] = f"{self.venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
            env["VIRTUAL_ENV"] = str(self.venv)
        return env

    def run(self, lines: list[str]) -> None:
        for number, line in enumerate(lines, 1):
            print(f"new user [{number}/{len(lines)}] $ {line}", flush=True)
            if is_install(line):
                self.install()
            elif (target := download_target(line)) is not None:
                self.write_tiny_checkpoint(self.cwd / target)
            elif is_service(line):
                self.start_service(line)
            else:
                self.command(line)
        if self.services:
            self.png_camera()
        self.stop_services()

    def png_camera(self) -> None:
        """A camera putting bare PNGs, and `gcdtrav probe` answering for it (see the module's docstring)."""
        print("new user: a PNG camera on gcdtrav/in/png_camera, then gcdtrav probe png_camera 320 400", flush=True)
        camera = subprocess.Popen(["python", "-c", PNG_CAMERA, str(CAMERA_S)], cwd=self.cwd, env=self.env)
        probe = ["gcdtrav", "probe", "png_camera", "320", "400", "-e", f"tcp/localhost:{SERVE_PORT}"]
        try:
            deadline = time.monotonic() + CAMERA_S
            while True:
                result = subprocess.run(probe, cwd=self.cwd, env=self.env, capture_output=True, text=True, timeout=60)
                if result.returncode == 0 or time.monotonic() > deadline:
                    break
                time.sleep(2)
        finally:
            camera.kill()
            camera.wait()
        print("  " + (result.stdout + result.stderr).strip().replace("\n", "\n  ")[-2000:])
        if result.returncode != 0 or "pixel (x=320, y=400)" not in result.stdout:
            raise SystemExit(f"new user: no answer for the PNG camera: {result.stderr.strip()[-500:]}")

    def install(self) -> None:
        if self.wheel is None or self.venv is None:
            print("  (local run: the gcdtrav on PATH is used, nothing installed)")
            return
        if not (self.venv / "bin" / "python").exists():
            subprocess.run([sys.executable, "-m", "venv", str(self.venv)], check=True)
        script = ROOT / "deploy" / "install-wheel.sh"
        subprocess.run(["sh", str(script), str(self.wheel)], env=self.env, check=True, timeout=COMMAND_TIMEOUT_S)
        # A package built from source on the way (a Rust build writes ~/.rustup/settings.toml) is pip's doing,
        # not gcdtrav's: only what the commands after the install write is checked.
        self.installed = set(files_under(self.home))
        if self.installed:
            print(f"  (the install left in HOME: {sorted(self.installed)[:5]}; not counted against gcdtrav)")

    def write_tiny_checkpoint(self, directory: Path) -> None:
        from tools.random_clipseg import save_random_clipseg

        save_random_clipseg(directory, preset="tiny", input_size=96)
        print(f"  (a tiny random checkpoint written to {directory.relative_to(self.cwd)}/ instead of the download)")

    def command(self, line: str) -> None:
        result = subprocess.run(
            ["bash", "-c", line], cwd=self.cwd, env=self.env, capture_output=True, text=True, timeout=COMMAND_TIMEOUT_S
        )
        output = (result.stdout + result.stderr).strip()
        print("  " + output.replace("\n", "\n  ")[-4000:] if output else "  (no output)")
        if result.returncode != 0:
            raise SystemExit(f"new user: '{line}' exited {result.returncode}")

    def start_service(self, line: str) -> None:
        if not port_free(SERVE_PORT):
            raise SystemExit(f"new user: port {SERVE_PORT} is taken here; the README's commands need it free")
        log = self.logs / f"service-{len(self.services)}.log"
        with log.open("wb") as output:
            process = subprocess.Popen(
                ["bash", "-c", f"exec {line}"], cwd=self.cwd, env=self.env, stdout=output, stderr=subprocess.STDOUT
            )
        self.services.append((line, process, log))
        deadline = time.monotonic() + SERVE_START_S
        while "serving:" not in log.read_text("utf-8", errors="replace"):
            if process.poll() is not None or time.monotonic() > deadline:
                self.stop_services()
                raise SystemExit(f"new user: '{line}' did not start serving:\n{log.read_text('utf-8', 'replace')}")
            time.sleep(0.2)
        print("  (serving; the next lines run as in another terminal)")

    def stop_services(self) -> None:
        failures = []
        while self.services:
            line, process, log = self.services.pop()
            if process.poll() is None:
                process.send_signal(signal.SIGINT)  # Ctrl-C
                try:
                    process.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    process.kill()
                    process.wait()
            text = log.read_text("utf-8", errors="replace")
            print("  " + "\n  ".join(text.strip().splitlines()[-12:]))
            if process.returncode != 0:
                failures.append(f"'{line}' exited {process.returncode} after Ctrl-C")
        if failures:
            raise SystemExit("new user: " + "; ".join(failures))

    def check_nothing_written_outside(self, checkpoint_dirs: list[Path]) -> None:
        kept = tuple(f"{d.as_posix()}/" for d in checkpoint_dirs)
        strays_in_cwd = [p for p in files_under(self.cwd) if not p.startswith(kept)]
        strays_in_home = [
            p for p in files_under(self.home) if not p.startswith(ALLOWED_IN_HOME) and p not in self.installed
        ]
        print(f"  HOME holds: {sorted({'/'.join(p.split('/')[:3]) for p in files_under(self.home)})}")
        if strays_in_cwd or strays_in_home:
            raise SystemExit(
                f"new user: files written outside the state and cache directories: working directory "
                f"{strays_in_cwd[:20]}, HOME {strays_in_home[:20]}"
            )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--wheel", type=Path, default=None, help="the built wheel to install [local: none]")
    parser.add_argument("--venv", type=Path, default=None, help="the fresh venv to install it in (with --wheel)")
    args = parser.parse_args(argv)
    if (args.wheel is None) != (args.venv is None):
        parser.error("--wheel and --venv go together")
    lines = quick_start_lines((ROOT / "README.md").read_text("utf-8"))
    checkpoints = [target for line in lines if (target := download_target(line)) is not None]
    began = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="gcdtrav-new-user-") as scratch:
        user = NewUser(Path(scratch), args.venv.resolve() if args.venv else None, args.wheel)
        try:
            user.run(lines)
        finally:
            user.stop_services()
        user.check_nothing_written_outside(checkpoints)
    print(
        f"new user: {len(lines)} README lines ran, each exited 0, nothing written outside the state and cache "
        f"directories ({time.monotonic() - began:.0f} s)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
