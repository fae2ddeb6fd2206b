"""A simulated robot for the experience loop, without ROS: it drives a synthetic world and publishes what a real
robot would, the documented way (docs/calibration.md): its pose (Pose2D on robot/pose) and camera images (on
robot/cam) for the ground grid; velocity commands (Twist2D on robot/cmd_vel) and odometry (Odometry2D on
robot/odom), from which the service makes velocity outcomes; and, where it bogs down in water, a bumper's
outcome (TraversalOutcome, kind contact, through client.publish_outcome). Then calibration and proposals
have data:

    gcdtrav serve --settings examples/experience_drive.yaml --model ./clipseg-rd64-refined  # terminal 1
    python examples/experience_drive.py -e tcp/127.0.0.1:7447                                 # terminal 2
    gcdtrav calibration -e tcp/127.0.0.1:7447        # the active set graded, a verdict, what next
    gcdtrav anchors propose -e tcp/127.0.0.1:7447    # a fitted set, judged on the later pairs

The world (tools/synthetic_scene.py, so run this from a checkout) is tiles of plain colour whose true
traversability differs from what an operator would guess (grass 0.8, sand 0.15); the camera renders 64 x 48
images of them. CLIPSeg sees plain colours: the figures show the loop at work, not CLIPSeg on real ground.
Simulated time starts now and runs as fast as the service answers: each image waits for its maps (about 120
images a simulated minute; with the real model on a CPU, a few minutes of driving for 100 s simulated).
"""

from __future__ import annotations

import argparse
import re
import sys
import time
from pathlib import Path

import zenoh
from gcdtrav.client import ServiceError, TraversabilityClient, add_zenoh_arguments, zenoh_config_from_args
from gcdtrav.schemas.experience import TraversalOutcome

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the checkout: tools/ is not in the wheel
from tools.robot_drive import CAMERA_SOURCE, BusRobot
from tools.synthetic_scene import Robot, make_world

STALL_BELOW = 0.05  # true traversability under which the robot's bumper reports a stall (water)
CONTACT_SPACING_M = 1.0  # at most one contact outcome per metre
REPORT_EVERY_S = 10.0  # simulated seconds between progress lines


class Reporter:
    """After every odometry sample: a contact outcome where the robot stalls, and now and then a progress line
    with the service's counts."""

    def __init__(self, client: TraversabilityClient) -> None:
        self.client = client
        self.last_contact: tuple[float, float] | None = None
        self.next_report = 0.0

    def __call__(self, robot: Robot, stamp: float) -> None:
        far = self.last_contact is None or (
            (robot.x - self.last_contact[0]) ** 2 + (robot.y - self.last_contact[1]) ** 2 >= CONTACT_SPACING_M**2
        )
        if robot.world.true_traversability(robot.x, robot.y) < STALL_BELOW and far:
            stall = TraversalOutcome(stamp=stamp, x=robot.x, y=robot.y, score=0.0, kind="contact", radius_m=0.3)
            self.client.publish_outcome(CAMERA_SOURCE, stall)
            self.last_contact = (robot.x, robot.y)
        if stamp >= self.next_report:
            self.next_report = stamp + REPORT_EVERY_S
            print(f"at ({robot.x:6.1f}, {robot.y:6.1f}) m: {self.counts()}", flush=True)

    def counts(self) -> str:
        experience = self.client.status().experience
        if experience is None:
            return "the service has no experience: start it with --settings examples/experience_drive.yaml"
        counts = experience.counts
        return f"{counts.get('outcomes', 0)} outcomes, {experience.pairs} pairs, {counts.get('ask_asked', 0)} questions"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=120.0, help="simulated seconds to drive [120]")
    parser.add_argument("--seed", type=int, default=2, help="the route [2: through water within 20 s]")
    parser.add_argument("--world-seed", type=int, default=0, help="the world [0]")
    parser.add_argument("--timeout", type=float, default=30.0, help="seconds to wait for an image's maps [30]")
    add_zenoh_arguments(parser)
    args = parser.parse_args()
    if args.seconds <= 0:
        parser.error("--seconds must be positive")
    try:
        with TraversabilityClient(config=zenoh_config_from_args(args)) as client:
            reporter = Reporter(client)
            robot = BusRobot(client, make_world(seed=args.world_seed), timeout_s=args.timeout, after_step=reporter)
            time.sleep(0.5)  # let the maps subscription reach the service
            try:
                end = robot.drive(args.seconds, seed=args.seed, start_stamp=time.time())
            finally:
                robot.close()
            time.sleep(0.5)  # the last outcomes reach the service
            print(f"drove {args.seconds:g} s (simulated, last stamp {end:.2f}): {reporter.counts()}")
    except (TimeoutError, ServiceError, zenoh.ZError) as err:
        said = re.sub(r"\s+at \S+\.rs:\d+\.?$", "", " ".join(str(err).split()))  # zenoh names its Rust source
        print(f"experience_drive: {said}", file=sys.stderr)
        print("is `gcdtrav serve --settings examples/experience_drive.yaml` running, and reachable?", file=sys.stderr)
        return 1
    print("next: gcdtrav calibration, then gcdtrav anchors propose (with this script's zenoh flags)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
