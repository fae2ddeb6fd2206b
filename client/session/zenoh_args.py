"""The command-line flags of zenoh-python's examples, so Zenoh users feel at home.

-m/--mode, -e/--connect, -l/--listen, -c/--config, --no-multicast-scouting, --cfg KEY:VALUE.
"""

from __future__ import annotations

import argparse
import json

import zenoh


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("zenoh")
    group.add_argument(
        "--mode", "-m", choices=["peer", "client", "router"], help="The zenoh session mode [default: peer]."
    )
    group.add_argument(
        "--connect",
        "-e",
        metavar="ENDPOINT",
        action="append",
        help="Endpoints to connect to, e.g. tcp/192.168.1.10:7447.",
    )
    group.add_argument(
        "--listen", "-l", metavar="ENDPOINT", action="append", help="Endpoints to listen on, e.g. tcp/0.0.0.0:7447."
    )
    group.add_argument("--config", "-c", metavar="FILE", help="A zenoh configuration file (JSON5).")
    group.add_argument("--no-multicast-scouting", action="store_true", help="Disable multicast scouting.")
    group.add_argument(
        "--cfg",
        metavar="CFG",
        default=[],
        action="append",
        help="Arbitrary configuration changes as KEY:VALUE pairs, where KEY is a config path and "
        "VALUE a JSON5 value. Example: --cfg='transport/unicast/max_links:2'.",
    )


def zenoh_config(
    config_file: str | None = None,
    mode: str | None = None,
    connect: list[str] | None = None,
    listen: list[str] | None = None,
    multicast_scouting: bool = True,
    cfg: list[str] | None = None,
) -> zenoh.Config:
    conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    if mode is not None:
        conf.insert_json5("mode", json.dumps(mode))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if not multicast_scouting:
        conf.insert_json5("scouting/multicast/enabled", json.dumps(False))
    for item in cfg or []:
        key, sep, value = item.partition(":")
        if not sep or not key:
            raise ValueError(f"--cfg expects KEY:VALUE, got '{item}'")
        conf.insert_json5(key, value)
    return conf


def zenoh_config_from_args(args: argparse.Namespace) -> zenoh.Config:
    return zenoh_config(
        config_file=args.config,
        mode=args.mode,
        connect=args.connect,
        listen=args.listen,
        multicast_scouting=not args.no_multicast_scouting,
        cfg=args.cfg,
    )
