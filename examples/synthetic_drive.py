"""A synthetic drive for the ground grid: a robot moving along x sends poses and camera images.

gcdtrav serve --settings examples/grid.yaml -l tcp/127.0.0.1:7447          # terminal 1
python examples/synthetic_drive.py -e tcp/127.0.0.1:7447                     # terminal 2
python examples/planner_path.py --source cam --path "0,0;4,0" -e tcp/127.0.0.1:7447
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from gcdtrav.client import Grid, TraversabilityClient, add_zenoh_arguments, zenoh_config_from_args
from gcdtrav.schemas.messages import Pose2D
from gcdtrav.service.commands.bench import bench_image


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=5)
    parser.add_argument("--step", type=float, default=0.5, help="metres driven between frames")
    add_zenoh_arguments(parser)
    args = parser.parse_args()
    grids: list[Grid] = []
    with TraversabilityClient(config=zenoh_config_from_args(args)) as client:
        subscriber = client.subscribe_grid("cam", grids.append)
        time.sleep(0.5)
        for k in range(args.frames):
            stamp = time.time()
            client.session.put("robot/pose", Pose2D(stamp=stamp, x=args.step * k, y=0.0, yaw=0.0).pack())
            time.sleep(0.1)
            client.publish_image("cam", bench_image(480, 640, seed=k), stamp=stamp)
            began = time.monotonic()
            while len(grids) <= k and time.monotonic() - began < 30:
                time.sleep(0.05)
            if len(grids) > k:
                h = grids[-1].header
                known = grids[-1].count > 0
                print(
                    f"grid seq {h.seq}: robot {h.robot}, origin {h.origin}, {h.known_cells} known cells, "
                    f"T mean {np.nanmean(grids[-1].traversability[known]):.3f}"
                )
        subscriber.undeclare()


if __name__ == "__main__":
    main()
