"""What a relayed robot's outcomes cost on its link (issue 56): bytes per second of OutcomeBatches and planned
paths, beside the frames, from the relay's own OutcomeLink (client/relay/outcomes.py) on a simulated drive.

    python -m benchmarks.relay_outcomes [--minutes 30] [--seed 0]

The drive, in simulated time: odometry at 20 Hz and commands at 10 Hz (1.5 m/s told), the robot's speed a
random walk between 0.2 and 1.5 m/s (rough ground slows it), a bumper pressed about once a minute, a 20 m
planned path renewed every second (Nav2's default replanning rate) that changes as the robot moves. Each batch
is what goes on the link: its payload's bytes. The frames' cost for comparison is measured in
benchmarks/ros_relay.py (benchmarks/README.md, "A ROS 2 robot through gcdtrav relay --ros").
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import sys
from pathlib import Path

import numpy as np
from gcdtrav.client.relay.outcomes import OutcomeLink
from gcdtrav.schemas.experience import Odometry2D, Twist2D
from gcdtrav.schemas.relay import RelayOutcomes
from gcdtrav.service.backends.cpus import cpu_name

ODOMETRY_HZ, COMMAND_HZ, PATH_HZ = 20.0, 10.0, 1.0
COMMAND_MPS, SLOWEST_MPS = 1.5, 0.2
FRAMES_BYTES_PER_S = 33_000  # benchmarks/README.md: the ROS relay's uplink for a 1280x720 camera at 15 Hz


class Counter:
    """A link publisher that counts what is put on it."""

    def __init__(self) -> None:
        self.puts = 0
        self.bytes = 0

    def put(self, payload: bytes) -> None:
        self.puts += 1
        self.bytes += len(payload)


def drive(minutes: float, seed: int, batch_period_s: float) -> dict[str, float]:
    rng = np.random.default_rng(seed)
    outcomes, paths = Counter(), Counter()
    clock = [0.0]
    link = OutcomeLink(RelayOutcomes(batch_period_s=batch_period_s), "r1/front", outcomes, paths, lambda: clock[0])
    dt, x, y, heading, speed = 1.0 / ODOMETRY_HZ, 0.0, 0.0, 0.0, 1.0
    steps = int(minutes * 60 * ODOMETRY_HZ)
    for step in range(steps):
        t = clock[0] = step * dt
        if step % round(ODOMETRY_HZ / COMMAND_HZ) == 0:
            link.on_command(Twist2D(vx=COMMAND_MPS))
        speed = float(np.clip(speed + rng.normal(0, 0.05), SLOWEST_MPS, COMMAND_MPS))
        heading += rng.normal(0, 0.01)
        x, y = x + speed * math.cos(heading) * dt, y + speed * math.sin(heading) * dt
        link.on_odometry(Odometry2D(stamp=1.7e9 + t, x=x, y=y, yaw=heading, vx=speed))
        if rng.random() < dt / 60:  # about one press a minute
            link.on_contact(True)
            link.on_contact(False)
        if step % round(ODOMETRY_HZ / PATH_HZ) == 0:
            ahead = [(x + d * math.cos(heading), y + d * math.sin(heading)) for d in np.arange(0, 30, 0.05)]
            link.on_path("odom", 1.7e9 + t, ahead)
        link.send_due()
    seconds = minutes * 60
    return {
        "batch_period_s": batch_period_s,
        "outcomes": link.measured,
        "outcomes_per_s": link.measured / seconds,
        "batches": outcomes.puts,
        "bytes_per_outcome": outcomes.bytes / max(link.sent, 1),
        "outcome_bytes_per_s": outcomes.bytes / seconds,
        "path_bytes_per_s": paths.bytes / seconds,
        "total_bytes_per_s": (outcomes.bytes + paths.bytes) / seconds,
        "share_of_frames": (outcomes.bytes + paths.bytes) / seconds / FRAMES_BYTES_PER_S,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.relay_outcomes", description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=30.0, help="simulated driving [30]")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, help="write the rows and the machine as JSON")
    args = parser.parse_args(argv)
    rows = [drive(args.minutes, args.seed, period) for period in (0.5, 1.0, 5.0)]
    print(f"cpu: {cpu_name()}, python {platform.python_version()}; {args.minutes:g} min of simulated driving")
    print("| batch_period_s | outcomes/s | bytes an outcome | outcomes B/s | path B/s | total B/s | of the frames |")
    print("|---|---|---|---|---|---|---|")
    for row in rows:
        print(
            f"| {row['batch_period_s']:g} | {row['outcomes_per_s']:.2f} | {row['bytes_per_outcome']:.0f} | "
            f"{row['outcome_bytes_per_s']:.0f} | {row['path_bytes_per_s']:.0f} | {row['total_bytes_per_s']:.0f} | "
            f"{100 * row['share_of_frames']:.1f} % |"
        )
    if args.out is not None:
        args.out.write_text(json.dumps({"cpu": cpu_name(), "minutes": args.minutes, "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
