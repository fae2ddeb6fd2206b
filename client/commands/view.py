"""`gcdtrav view`: the command line of the live Foxglove view (torch-free; needs the ``view`` extra).

Exit codes: 0 stopped by Ctrl-C or SIGTERM (every MCAP file closed), 1 failed (one line on stderr), 2 usage
or a missing extra.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import signal
import sys
import threading
from pathlib import Path
from types import FrameType

from gcdtrav.client.session.zenoh_args import add_zenoh_arguments, zenoh_config_from_args

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2
RECORD_MAX_MB = 4096  # by default: about an hour of one source at full rate, and never more than this
INSTALL = "pip install 'gcdtrav[view]'"


def add_view_command(commands: argparse._SubParsersAction) -> None:
    view = commands.add_parser(
        "view",
        help="live view in Foxglove: images, T, U, grid, status; anchor set as parameters; MCAP recording",
        description="Serve the service's outputs to Foxglove (WebSocket, default ws://localhost:8765) and, with "
        "--record, into MCAP files. Open Foxglove, 'Open connection', 'Foxglove WebSocket', that URL, then import "
        "the layout that `gcdtrav view --layout my-layout.json` writes for the service's sources (one tab per "
        "source, docs/view.md). Torch-free; needs " + INSTALL + ".",
    )
    view.add_argument("--port", type=int, default=8765, help="WebSocket port [8765; 0 = any free port]")
    view.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to bind [127.0.0.1: this machine only]. Another address (e.g. 0.0.0.0) lets anyone who "
        "reaches it watch and change the anchor set",
    )
    view.add_argument("--sources", default="**", help="which sources, as a key expression of names ['**' = all]")
    view.add_argument("--prefix", default="gcdtrav", help="the service's key prefix [gcdtrav]")
    view.add_argument(
        "--input-prefix",
        default="gcdtrav/in",
        help="where robots publish images, for the camera channel [gcdtrav/in]; '' to not subscribe to inputs",
    )
    view.add_argument("--record", type=Path, metavar="DIR", help="also record every channel to MCAP files in DIR")
    view.add_argument("--record-file-mb", type=float, default=256, help="start a new MCAP file beyond this [256]")
    view.add_argument(
        "--record-max-mb",
        type=float,
        default=RECORD_MAX_MB,
        help="total size of the recording: the oldest files are deleted to stay under it, and files are at most "
        f"a quarter of it [{RECORD_MAX_MB}: a day of recording fits a small disk; 0: no limit]",
    )
    view.add_argument(
        "--record-camera-every",
        type=int,
        default=1,
        metavar="N",
        help="record one camera frame in N (the live view keeps every frame) [1; 0: leave the camera out]",
    )
    view.add_argument(
        "--settings",
        type=Path,
        metavar="FILE",
        help="the service's settings file: its grid cameras' mounts and intrinsics place the cameras and their "
        "frustums in the 3D panel",
    )
    view.add_argument(
        "--layout",
        type=Path,
        metavar="FILE",
        help="write a Lichtblick/Foxglove layout for the sources the service has (one tab per source) and exit",
    )
    view.add_argument("--max-sources", type=int, default=32, help="sources shown at most [32]")
    view.add_argument("--status-period", type=float, default=1.0, help="seconds between status queries [1]")
    view.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the service's answers [5]")
    add_zenoh_arguments(view)


def run(args: argparse.Namespace) -> int:
    needed = (("foxglove", "foxglove-sdk"), ("mcap", "mcap"), ("matplotlib", "matplotlib"))
    missing = [package for module, package in needed if not _has(module)]
    if missing:
        print(f"gcdtrav view: needs {', '.join(missing)}; install the view extra: {INSTALL}", file=sys.stderr)
        return EXIT_USAGE
    problem = usage_problem(args)
    if problem:
        print(f"gcdtrav view: {problem}", file=sys.stderr)
        return EXIT_USAGE
    from gcdtrav.client.client import TraversabilityClient
    from gcdtrav.client.view.viewer import Viewer, ViewOptions

    if args.layout is not None:
        return write_layout(args)

    options = ViewOptions(
        host=args.host,
        port=args.port,
        prefix=args.prefix,
        sources=args.sources,
        input_prefix=args.input_prefix,
        max_sources=args.max_sources,
        status_period_s=args.status_period,
        timeout_s=args.timeout,
        record=args.record,
        record_file_bytes=megabytes(args.record_file_mb),
        record_max_bytes=megabytes(args.record_max_mb) if args.record_max_mb else None,
        record_camera_every=args.record_camera_every,
        settings=args.settings,
    )
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda number, frame: _stop(stop, number, frame))
    try:
        config = zenoh_config_from_args(args)
        with TraversabilityClient(config=config, prefix=args.prefix, timeout=args.timeout) as client:
            with Viewer(client, options) as viewer:
                print(f"gcdtrav view: Foxglove WebSocket at {viewer.url} (Ctrl-C stops)", flush=True)
                print(f"gcdtrav view: or open {viewer.server.app_url()}", flush=True)
                if viewer.recorder is not None:
                    print(f"gcdtrav view: recording to {viewer.recorder.directory}", flush=True)
                while not stop.wait(0.5):
                    pass
            if viewer.recorder is not None:
                print(recording_summary(viewer.recorder.files), flush=True)
                if viewer.recorder.deleted:
                    deleted = len(viewer.recorder.deleted)
                    print(f"gcdtrav view: {deleted} oldest files deleted (--record-max-mb {args.record_max_mb:g})")
    except Exception as err:  # zenoh errors, a port in use, an unwritable directory: one line
        print(f"gcdtrav view: {type(err).__name__}: {' '.join(str(err).split())}", file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK


def usage_problem(args: argparse.Namespace) -> str | None:
    if args.record_file_mb <= 0 or args.max_sources < 1 or args.status_period <= 0 or not 0 <= args.port < 65536:
        return "--record-file-mb, --max-sources and --status-period must be positive, and --port 0..65535"
    if args.record_max_mb < 0:
        return "--record-max-mb must be positive (or 0: no limit)"
    if args.record_camera_every < 0:
        return "--record-camera-every must be 1 or more (or 0: no camera in recordings)"
    return None


def write_layout(args: argparse.Namespace) -> int:
    """Ask the service which sources it has and write a layout with one tab per source."""
    from gcdtrav.client.client import TraversabilityClient
    from gcdtrav.client.view.layout import layout, service_sources
    from gcdtrav.schemas.settings import load_settings

    try:
        grids = load_settings(args.settings).grids if args.settings else []
        config = zenoh_config_from_args(args)
        with TraversabilityClient(config=config, prefix=args.prefix, timeout=args.timeout) as client:
            sources = service_sources(client.statuses(timeout=args.timeout), [grid.source for grid in grids])
        if not sources:
            print("gcdtrav view: the service has no sources yet: send it images first", file=sys.stderr)
            return EXIT_FAILED
        args.layout.write_text(json.dumps(layout(sources, args.prefix), indent=1) + "\n")
    except Exception as err:  # no answer, an unwritable file: one line
        print(f"gcdtrav view: {type(err).__name__}: {' '.join(str(err).split())}", file=sys.stderr)
        return EXIT_FAILED
    print(f"gcdtrav view: layout for {', '.join(sources)} written to {args.layout}")
    return EXIT_OK


def megabytes(value: float) -> int:
    return int(value * 1024 * 1024)


def _has(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except ValueError:  # in sys.modules as None: blocked
        return False


def _stop(stop: threading.Event, number: int, frame: FrameType | None) -> None:
    stop.set()


def recording_summary(files: list[Path]) -> str:
    """One line per MCAP file, read back with the mcap library: its messages and channels."""
    from mcap.reader import make_reader

    lines = []
    for path in files:
        with path.open("rb") as stream:
            summary = make_reader(stream).get_summary()
        if summary is None or summary.statistics is None:
            lines.append(f"{path}: no summary (not closed cleanly)")
        else:
            stats = summary.statistics
            lines.append(f"{path}: {stats.message_count} messages on {stats.channel_count} channels")
    return "\n".join(lines)
