"""A robot streaming a folder of images to the gcdtrav service, and printing the maps it gets back.

    python examples/robot_stream_folder.py IMAGES_DIR --source r1/front --fps 5 [-e tcp/HOST:7447]

Zenoh flags are those of zenoh-python's examples (-m, -e, -l, -c, --no-multicast-scouting, --cfg).
"""

from __future__ import annotations

import argparse
import itertools
import threading
import time
from pathlib import Path

from gcdtrav.client import Maps, TraversabilityClient, add_zenoh_arguments, zenoh_config_from_args

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", type=Path, help="folder of JPEG/PNG images, sent in name order")
    parser.add_argument("--source", default="r1/front", help="source name: published on gcdtrav/in/SOURCE")
    parser.add_argument("--fps", type=float, default=5.0, help="frames per second to send")
    parser.add_argument("--loop", action="store_true", help="start over at the end of the folder")
    parser.add_argument("--count", type=int, default=None, help="stop after this many frames")
    parser.add_argument("--frame-id", default="camera", help="the camera's frame id")
    add_zenoh_arguments(parser)
    args = parser.parse_args()

    images = sorted(p for p in args.folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not images:
        parser.error(f"no .jpg/.jpeg/.png files in {args.folder}")
    lock = threading.Lock()

    def show(maps: Maps) -> None:
        h = maps.header
        latency = (h.published_at - h.received_at) * 1e3
        with lock:
            print(
                f"maps {h.source} seq={h.seq} T mean={maps.traversability.mean():.2f} "
                f"U mean={maps.uncertainty.mean():.3f} inference={h.inference_ms:.0f} ms "
                f"in-service={latency:.0f} ms anchors={h.anchor_set_version}"
            )

    with TraversabilityClient(config=zenoh_config_from_args(args)) as client:
        subscriber = client.subscribe_maps(args.source, show)
        frames = itertools.cycle(images) if args.loop else iter(images)
        period = 1.0 / args.fps
        for index, path in enumerate(itertools.islice(frames, args.count)):
            began = time.monotonic()
            client.publish_image(args.source, path.read_bytes(), frame_id=args.frame_id)
            with lock:
                print(f"sent {index}: {path.name}")
            time.sleep(max(0.0, period - (time.monotonic() - began)))
        time.sleep(2.0)  # the last maps
        subscriber.undeclare()


if __name__ == "__main__":
    main()
