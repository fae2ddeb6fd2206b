"""Remake docs/view-3d.png: Lichtblick's 3D panel connected to `gcdtrav view`, with the robot, its camera's
frustum and the CVaR layer of its ground grid. Not a test (CI never runs it): it needs a Lichtblick web build
and a headless Chromium driven by Playwright from a separate virtual environment.

    python -m venv /tmp/pw-venv && /tmp/pw-venv/bin/pip install playwright   # not in the project's env
    apt-get install chromium
    python -m tools.view_screenshot --lichtblick /tmp/lbsrc/web/.webpack --playwright-python /tmp/pw-venv/bin/python

Everything runs on 127.0.0.1 with multicast scouting off: an in-process service with the synthetic scene's
backend (tools/synthetic_scene.py: colours stand for terrains, so the pattern is not a real model's) and its
ground grid, the simulated robot of tools/robot_drive.py driving in it (pose and camera over zenoh),
`gcdtrav view --layout` then `gcdtrav view` with the service's settings, a static HTTP server for the
Lichtblick build and the layout, and tools/view_screenshot_browser.py, which opens Lichtblick on
``?ds=foxglove-websocket&ds.url=...&layoutUrl=...`` (the layout goes through the same validation as
**Import from file…**) and screenshots the 3D panel.

A Lichtblick web build with only the npm registry at hand (how docs/view-3d.png was made, v1.28.1):
``git archive v1.28.1`` of lichtblick-suite/lichtblick; in package.json's ``resolutions`` the five packages
the registry lacked at their pinned versions set to ones it has (``@lichtblick/rosbag2`` and
``@lichtblick/rosbag2-web`` 1.0.0, ``@lichtblick/eslint-plugin`` 1.0.4, ``@lichtblick/tsconfig`` 1.0.0,
``flatbuffers_reflection`` 0.0.7: bag files and flatbuffer schemas, not used here); ``YARN_ENABLE_SCRIPTS=false
corepack yarn install --mode=skip-build``; ``"ignoreDeprecations": "6.0"`` and a ``rootDir`` in
node_modules/@lichtblick/tsconfig/base.json (TypeScript 6 refuses the older base config); the
ForkTsCheckerWebpackPlugin taken out of packages/suite-base/webpack.ts (the older pins do not type-check);
``TS_NODE_TRANSPILE_ONLY=true corepack yarn run web:build:dev``, which writes web/.webpack.
"""

from __future__ import annotations

import argparse
import functools
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import yaml
from gcdtrav.client import TraversabilityClient, zenoh_config
from gcdtrav.schemas.settings import ServiceSettings

from tools.loopback import free_port, in_process_service
from tools.robot_drive import CAMERA_EVERY, ODOMETRY_DT, START_STAMP, BusRobot, grid_settings
from tools.synthetic_scene import SceneBackend, make_world, start_anchors

BROWSER_SCRIPT = Path(__file__).with_name("view_screenshot_browser.py")
LAYOUT_NAME = "gcdtrav-layout.json"
WARM_UP_S = 90.0  # simulated seconds driven before the viewer starts: a grid with some cells to show
DRIVE_S = 3600.0  # the route's length in simulated seconds: longer than any screenshot takes


def service_settings(state: Path) -> ServiceSettings:
    """The robot's grid, simulated time from a stamp in the past like a replayed bag (no age or skew checks)."""
    return ServiceSettings(
        state_dir=state, instance="shot", preview=False, max_frame_age_s=None, max_stamp_skew_s=None,
        grids=[grid_settings()],
    )  # fmt: skip


def write_view_settings(path: Path) -> None:
    """The part of the service's settings `gcdtrav view --settings` reads: the grid camera's mount and intrinsics."""
    grids = [grid_settings().model_dump(mode="json", exclude_defaults=True)]
    path.write_text(yaml.safe_dump({"grids": grids}))


def gcdtrav_command(*arguments: str) -> list[str]:
    return [sys.executable, "-m", "gcdtrav.service.commands.cli", *arguments]


class Stopped(Exception):
    """Raised inside the robot's loop to end its drive."""


class Driving:
    """One robot drives one route in a thread until stopped: first as fast as the service answers (to fill its
    grid), then, once ``pace`` is called, at the wall clock's rate (the simulation alone runs many times
    faster: Lichtblick then warns of topics above 60 Hz, foxglove-sdk drops messages, and software WebGL
    cannot keep up)."""

    def __init__(self, robot: BusRobot, seed: int) -> None:
        self.robot, self.seed = robot, seed
        self.frame_period_s = 0.0
        self.next_frame = 0.0
        self.stop = threading.Event()
        self.error: BaseException | None = None
        publish_image = robot.client.publish_image

        def paced(*args: Any, **kwargs: Any) -> Any:
            time.sleep(max(0.0, self.next_frame - time.monotonic()))
            if self.stop.is_set():
                raise Stopped
            self.next_frame = time.monotonic() + self.frame_period_s
            return publish_image(*args, **kwargs)

        setattr(robot.client, "publish_image", paced)  # noqa: B010 (an instance's method, on purpose)
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def pace(self, warm_up_s: float, timeout_s: float = 120.0) -> None:
        """Once ``warm_up_s`` of simulated time has been driven, drive in real time."""
        self.robot.maps.wait_for(START_STAMP + warm_up_s, timeout_s)
        self.frame_period_s = CAMERA_EVERY * ODOMETRY_DT

    def _run(self) -> None:
        try:
            self.robot.drive(DRIVE_S, seed=self.seed)
        except Stopped:
            pass
        except BaseException as err:  # reported by the main thread
            self.error = err


@contextmanager
def http_server(build: Path, layout: Path) -> Iterator[int]:
    """The Lichtblick build at /, the layout at /LAYOUT_NAME; yields the port."""

    class Handler(SimpleHTTPRequestHandler):
        def translate_path(self, path: str) -> str:
            return str(layout) if path.split("?")[0] == f"/{LAYOUT_NAME}" else super().translate_path(path)

        def log_message(self, format: str, *args: object) -> None:  # quiet
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Handler, directory=str(build)))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield int(server.server_address[1])
    finally:
        server.shutdown()
        server.server_close()


@contextmanager
def viewer(flags: list[str], settings: Path, port: int) -> Iterator[None]:
    """`gcdtrav view` on ``port`` until the context ends (SIGTERM)."""
    process = subprocess.Popen(
        gcdtrav_command("view", "--port", str(port), "--settings", str(settings), *flags),
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert process.stdout is not None
        line = process.stdout.readline()
        if "Foxglove WebSocket at" not in line:
            raise RuntimeError(f"gcdtrav view did not start: {line!r}")
        print(line.strip(), flush=True)
        yield
    finally:
        process.terminate()
        process.wait(timeout=30)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--lichtblick", type=Path, required=True, help="a Lichtblick web build (web/.webpack)")
    parser.add_argument("--playwright-python", default="/tmp/pw-venv/bin/python", help="Python with playwright")
    parser.add_argument("--chromium", default="/usr/bin/chromium")
    parser.add_argument("--out", type=Path, default=Path("docs/view-3d.png"))
    parser.add_argument("--wait", type=float, default=25.0, help="seconds of live data before the screenshot")
    parser.add_argument("--seed", type=int, default=3, help="the robot's route [3]")
    parser.add_argument("--zoom-steps", type=int, default=8, help="mouse-wheel steps towards the robot [8]")
    parser.add_argument("--page-out", type=Path, help="also a screenshot of the whole page (the whole layout)")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as temporary:
        work = Path(temporary)
        view_settings, layout = work / "settings.yaml", work / LAYOUT_NAME
        write_view_settings(view_settings)
        settings = service_settings(work / "state")
        with (
            in_process_service(SceneBackend(), settings, start_anchors()) as (_, port),
            TraversabilityClient(
                config=zenoh_config(mode="peer", connect=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False)
            ) as client,
        ):
            flags = ["-m", "client", "-e", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"]
            driving = Driving(BusRobot(client, make_world(seed=0)), args.seed)
            driving.pace(WARM_UP_S)
            subprocess.run(
                gcdtrav_command("view", "--layout", str(layout), "--settings", str(view_settings), *flags), check=True
            )
            ws_port = free_port()
            try:
                with viewer(flags, view_settings, ws_port), http_server(args.lichtblick, layout) as http_port:
                    base = f"http://127.0.0.1:{http_port}"
                    url = (
                        f"{base}/?ds=foxglove-websocket&ds.url=ws://127.0.0.1:{ws_port}&layoutUrl={base}/{LAYOUT_NAME}"
                    )
                    subprocess.run(
                        [args.playwright_python, str(BROWSER_SCRIPT), "--url", url, "--chromium", args.chromium,
                         "--out", str(args.out), "--wait", str(args.wait),
                         "--zoom-steps", str(args.zoom_steps),
                         *(["--page-out", str(args.page_out)] if args.page_out else [])],
                        check=True,
                    )  # fmt: skip
            finally:
                driving.stop.set()
                driving.thread.join(timeout=60)
            if driving.error is not None:
                raise RuntimeError("the robot stopped driving") from driving.error
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
