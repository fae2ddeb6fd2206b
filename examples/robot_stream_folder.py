"""A robot streaming a folder of images to the gcdtrav service, and printing the maps it gets back.

    python examples/robot_stream_folder.py IMAGES_DIR --source r1/front --fps 5 [-e tcp/HOST:7447]

Zenoh flags are those of zenoh-python's examples (-m, -e, -l, -c, --no-multicast-scouting, --cfg).
After the last image it waits, at most --wait seconds, for that image's maps. Exit status: 0 when they
came, 1 when they did not, 2 for a folder that is missing or holds no images (one line on stderr).
"""

from __future__ import annotations

import argparse
import itertools
import sys
import threading
import time
from pathlib import Path

from gcdtrav.client import Maps, TraversabilityClient, add_zenoh_arguments, zenoh_config_from_args

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png"}
EXIT_NO_MAPS, EXIT_USAGE = 1, 2


def images_in(folder: Path) -> list[Path] | str:
    """The folder's images in name order, or what is wrong with it."""
    if not folder.is_dir():
        return f"{folder}: no such folder" if not folder.exists() else f"{folder}: not a folder"
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    return images or f"{folder}: no .jpg/.jpeg/.png files"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", type=Path, help="folder of JPEG/PNG images, sent in name order")
    parser.add_argument("--source", default="r1/front", help="source name: published on gcdtrav/in/SOURCE")
    parser.add_argument("--fps", type=float, default=5.0, help="frames per second to send")
    parser.add_argument("--loop", action="store_true", help="start over at the end of the folder")
    parser.add_argument("--count", type=int, default=None, help="stop after this many frames")
    parser.add_argument("--frame-id", default="camera", help="the camera's frame id")
    parser.add_argument("--wait", type=float, default=10.0, help="seconds to wait for the last image's maps")
    add_zenoh_arguments(parser)
    args = parser.parse_args()

    images = images_in(args.folder)
    if isinstance(images, str):
        print(f"robot_stream_folder: {images}", file=sys.stderr)
        return EXIT_USAGE
    lock = threading.Lock()
    newest_stamp = [float("-inf")]  # input stamp of the newest maps received
    arrived = threading.Event()

    def show(maps: Maps) -> None:
        h = maps.header
        latency = (h.published_at - h.received_at) * 1e3
        with lock:
            print(
                f"maps {h.source} seq={h.seq} T mean={maps.traversability.mean():.2f} "
                f"U mean={maps.uncertainty.mean():.3f} inference={h.inference_ms:.0f} ms "
                f"in-service={latency:.0f} ms anchors={h.anchor_set_version}"
            )
            newest_stamp[0] = max(newest_stamp[0], h.stamp)
        arrived.set()

    with TraversabilityClient(config=zenoh_config_from_args(args)) as client:
        subscriber = client.subscribe_maps(args.source, show)
        frames = itertools.cycle(images) if args.loop else iter(images)
        period = 1.0 / args.fps
        last_stamp = None
        for index, path in enumerate(itertools.islice(frames, args.count)):
            began = time.monotonic()
            last_stamp = time.time()
            client.publish_image(args.source, path.read_bytes(), stamp=last_stamp, frame_id=args.frame_id)
            with lock:
                print(f"sent {index}: {path.name}")
            time.sleep(max(0.0, period - (time.monotonic() - began)))
        came = last_stamp is None or wait_for_maps(newest_stamp, last_stamp, arrived, args.wait)
        subscriber.undeclare()
    if not came:
        print(f"robot_stream_folder: no maps for the last image within {args.wait:g} s", file=sys.stderr)
        return EXIT_NO_MAPS
    return 0


def wait_for_maps(newest_stamp: list[float], last_stamp: float, arrived: threading.Event, timeout: float) -> bool:
    """Whether maps of the image stamped ``last_stamp`` (or a later one) arrive within ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while newest_stamp[0] < last_stamp:
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            return False
        arrived.wait(remaining)
        arrived.clear()
    return True


if __name__ == "__main__":
    sys.exit(main())
