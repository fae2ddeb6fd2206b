"""`gcdtrav relay`: the command line of the robot's relay (torch-free, the base install).

    gcdtrav relay --camera /camera/front/image_raw --source r1/front -e tcp/OFFBOARD:7447
    gcdtrav relay --ros -e tcp/OFFBOARD:7447 --ros-args -p camera:=/camera/front/image_raw -p source:=r1/front

Exit codes: 0 stopped by Ctrl-C or SIGTERM, 1 failed (one line on stderr), 2 usage.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from types import FrameType
from typing import Any

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2


def max_side(text: str) -> int | str:
    if text == "auto":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--max-side takes a number of pixels or 'auto', not '{text}'") from None


def add_relay_command(commands: argparse._SubParsersAction) -> None:
    from gcdtrav.client.session.zenoh_args import add_zenoh_arguments

    relay = commands.add_parser(
        "relay",
        help="on the robot: send camera frames to the service only when it is ready, sized for the model (no torch)",
        description="Relay the robot's cameras to the service over a slow link: only the newest frame, only when "
        "the service grants a credit, shrunk to the model's input and JPEG-encoded; outputs come back to the "
        "robot's bus only while a consumer there subscribes. The zenoh flags are the link's (to the service); "
        "--local-connect is the robot's own router, where the cameras are.",
    )
    relay.add_argument("--settings", metavar="FILE", help="relay settings (YAML), e.g. several cameras")
    relay.add_argument(
        "--camera",
        action="append",
        metavar="KEY|/TOPIC",
        help="a zenoh key of images, or a ROS topic (starting with '/'); repeatable, paired with --source",
    )
    relay.add_argument("--source", action="append", metavar="NAME", help="the source name at the service")
    relay.add_argument("--prefix", help="the service's key prefix [gcdtrav]")
    relay.add_argument("--input-prefix", help="where the service takes images [gcdtrav/in]")
    relay.add_argument("--jpeg-quality", type=int, help="JPEG quality of the frames sent [80]")
    relay.add_argument(
        "--max-side", type=max_side, help="longest side sent, pixels, or 'auto': the model's input [auto]"
    )
    from gcdtrav.schemas.relay import RelaySettings

    timeout = RelaySettings.model_fields["credit_timeout_s"].default
    relay.add_argument("--credit-timeout", type=float, help=f"send without a credit after this long, s [{timeout:g}]")
    relay.add_argument("--stale-after", type=float, help="report maps older than this as stale, s [3]")
    relay.add_argument(
        "--no-frames",
        action="store_true",
        help="send no frames (they reach the service another way, e.g. rmw_zenoh): only bring the outputs back and "
        "guard the speed mask",
    )
    relay.add_argument(
        "--safe-after", type=float, metavar="S", help="the safe speed mask after this long without the service [2]"
    )
    relay.add_argument("--safe-floor", type=float, metavar="F", help="the safe mask's fraction of max speed [0.3]")
    relay.add_argument("--max-speed", type=float, metavar="M_S", help="the robot's maximum speed, m/s [1.5]")
    relay.add_argument(
        "--pose-key", metavar="KEY", help="the robot's pose on its bus (Pose2D or Odometry CDR): the safe mask's centre"
    )
    relay.add_argument(
        "--local-connect", action="append", metavar="ENDPOINT", help="the robot's router [tcp/127.0.0.1:7447]"
    )
    relay.add_argument("--local-mode", choices=["client", "peer"], help="the robot-side session's mode [client]")
    relay.add_argument(
        "--ros",
        action="store_true",
        help="run as a ROS 2 node (rclpy: the robot's own, on any RMW): cameras, CameraInfo and odometry from the "
        "ROS graph, T, U, the costmap and /diagnostics back into it (docs/ros2.md)",
    )
    add_zenoh_arguments(relay)
    relay.add_argument(
        "--ros-args",
        nargs=argparse.REMAINDER,
        help="the rest goes to ROS 2 (implies --ros): -p name:=value, -r from:=to, -r __ns:=/robot1, ...",
    )


def relay_settings(args: argparse.Namespace) -> Any:
    """The settings file with the flags on top; --camera/--source pairs replace its cameras."""
    from gcdtrav.schemas.relay import load_relay_settings

    return load_relay_settings(args.settings, flag_overrides(args))


def flag_overrides(args: argparse.Namespace) -> dict[str, object]:
    from gcdtrav.schemas.relay import RelaySettingsError

    cameras, sources = args.camera or [], args.source or []
    if len(cameras) != len(sources):
        raise RelaySettingsError(f"{len(cameras)} --camera but {len(sources)} --source: give them in pairs")
    overrides: dict[str, object] = {
        "prefix": args.prefix,
        "input_prefix": args.input_prefix,
        "jpeg_quality": args.jpeg_quality,
        "max_side": args.max_side,
        "credit_timeout_s": args.credit_timeout,
        "stale_after_s": args.stale_after,
        "local_connect": args.local_connect,
        "local_mode": args.local_mode,
        "pose_key": args.pose_key,
    }
    safe = {"after_s": args.safe_after, "floor": args.safe_floor, "max_speed_m_s": args.max_speed}
    if any(value is not None for value in safe.values()):
        overrides["safe_mask"] = {name: value for name, value in safe.items() if value is not None}
    frames = {"frames": False} if args.no_frames else {}
    if cameras:
        overrides["cameras"] = [{"camera": c, "source": s} | frames for c, s in zip(cameras, sources, strict=True)]
    return overrides


def run(args: argparse.Namespace) -> int:
    import zenoh
    from gcdtrav.client.relay.relay import Relay
    from gcdtrav.client.session.zenoh_args import zenoh_config, zenoh_config_from_args
    from gcdtrav.schemas.relay import RelaySettingsError

    ros = args.ros or args.ros_args is not None
    try:
        overrides = flag_overrides(args)
        settings = None if ros else relay_settings(args)
        link_config = zenoh_config_from_args(args)
        if args.mode is None:
            link_config.insert_json5("mode", '"client"')
    except RelaySettingsError as err:
        print(f"gcdtrav relay: {err}", file=sys.stderr)
        return EXIT_USAGE
    except Exception as err:  # zenoh raises its own error type for bad config files and values
        print(f"gcdtrav relay: invalid zenoh configuration: {err}", file=sys.stderr)
        return EXIT_USAGE
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda number, frame: _stop(stop, number, frame))
    if ros:
        return run_ros(args, overrides, link_config, stop)
    assert settings is not None
    local_config = zenoh_config(
        mode=settings.local_mode,
        connect=settings.local_connect,
        listen=settings.local_listen,
        multicast_scouting=False,  # never find the service's side through the robot session
    )
    try:
        with zenoh.open(link_config) as link, zenoh.open(local_config) as local:
            relay = Relay(settings, link, local).start()
            try:
                stop.wait()
            finally:
                relay.close()
    except zenoh.ZError as err:
        print(f"gcdtrav relay: zenoh: {' '.join(str(err).split())}", file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK


def run_ros(args: argparse.Namespace, overrides: dict[str, object], link_config: Any, stop: threading.Event) -> int:
    """The ROS 2 node: rclpy is imported only here, so the base install needs no ROS."""
    import zenoh

    try:
        from gcdtrav.client.relay.ros2_node import run_node
    except ImportError as err:
        print(
            f"gcdtrav relay --ros: needs ROS 2's rclpy and message packages ({err}): source "
            "/opt/ros/<distro>/setup.bash on the robot",
            file=sys.stderr,
        )
        return EXIT_FAILED
    try:
        return run_node(args.ros_args or [], args.settings, overrides, link_config, stop)
    except zenoh.ZError as err:
        print(f"gcdtrav relay: zenoh: {' '.join(str(err).split())}", file=sys.stderr)
        return EXIT_FAILED


def _stop(stop: threading.Event, number: int, frame: FrameType | None) -> None:
    stop.set()
