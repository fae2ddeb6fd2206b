"""Does the speed layer slow the robot where it should? A closed loop on the synthetic world (issue 48 item 4).

    python -m benchmarks.speed                       # 5 seeds x 3 routes; prints a Markdown table
    python -m benchmarks.speed --out benchmarks/speed-mine.json
    python -m benchmarks.speed --quick               # 1 seed, 1 short route: a smoke check
    python -m benchmarks.speed --link-loss           # the link dies at a random moment (issue 55)

The world (tools/synthetic_scene.py's concepts, anchors and camera): clear ground (paved or grassy, which the
start anchor set knows well: U < 0.06) with patches of ambiguous ground, whose softmax is split between grass,
asphalt and mud (U 0.28, P(T < 0.3) 0.2: the mixture cannot say which), and inside half of those patches a
hazard (a hidden rock or hole) the camera cannot tell from the rest of the patch: the backend's weights are the
same there. The robot must cross: a straight route of ROUTE_M through the patches, no planner to go around.

The loop, in simulated time: the robot (max speed V_MAX, accelerating at ACCEL and braking at DECEL) publishes its
pose at 50 Hz; its camera takes a frame at 5 Hz that reaches fusion LATENCY_S later (uniform; 2-3 s in the
last row: a slow box or link); the grid
(GridOutputs, no zenoh) fuses it at the pose of its capture and hands out a speed mask at most ``rate_hz``; the
mask reaches Nav2's SpeedFilter LINK_S after that, decoded from its nav_msgs/OccupancyGrid CDR; the SpeedFilter
looks up the robot's cell in the last mask it has at 10 Hz, as nav2_costmap_2d's does (a cell off the mask
keeps the last limit), and caps the controller's speed at that percent. Without the layer: V_MAX all the way.

Link loss (``--link-loss``): the link dies at a random moment of the drive, after which nothing crosses it: no
frame is fused, no mask reaches the robot. Three ways the robot's mask can end: none (the last live mask stays,
as for a killed service), the service's own safe mask (sent when its grid goes stale, into the dead link: what
a robot had before issue 55), and the relay's (client/relay/mask_guard.py, on the robot: the floor everywhere
``after_s`` after the last message of the service). Off the mask, SpeedFilter gives no limit: Nav2's with a path
(path lookahead, navigation2 main) does; without one it keeps its last limit. Run on hazards and on clear ground.

A hazard contact: the robot enters a hazard's square faster than V_SAFE (a rock it rolls over at walking pace
but not at full speed); each hazard counts once per drive. A stall: the robot slower than 0.05 m/s for more than
a second before its goal (a floor above 0 never stops it; counted to show it).
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from gcdtrav.client.relay.mask_guard import MaskGuard
from gcdtrav.schemas.anchors import AnchorSet
from gcdtrav.schemas.messages import Pose2D
from gcdtrav.schemas.relay import SafeMaskSettings
from gcdtrav.schemas.settings import GridSettings
from gcdtrav.service.backends.cpus import cpu_name
from gcdtrav.service.grid.geometry import ground_points, map_cell_pixels
from gcdtrav.service.grid.speed import NO_LIMIT
from gcdtrav.service.ros import cdr
from gcdtrav.service.runtime.grids import GridOutputs
from gcdtrav.service.runtime.history import FrameRecord
from numpy.typing import NDArray

from tools.synthetic_scene import FLOOR_PROBABILITY, SceneCamera, default_camera, start_anchors

CAMERA = "robot/cam"
V_MAX, V_SAFE = 1.5, 0.6  # m/s: the robot's maximum, and the fastest a hazard is entered without harm
ACCEL, DECEL = 1.0, 1.5  # m/s^2
FLOOR = 0.3  # the speed layer's floor: 0.45 m/s at V_MAX, under V_SAFE
POSE_HZ, FRAME_HZ, FILTER_HZ = 50.0, 5.0, 10.0
# lead_m as docs/grid.md sizes it: braking from V_MAX to the floor, plus one SpeedFilter period at V_MAX (0.8 m)
LEAD_M = round((V_MAX**2 - (FLOOR * V_MAX) ** 2) / (2 * DECEL) + V_MAX / FILTER_HZ, 1)
LATENCY_S = (0.3, 0.6)  # capture to fusion: inference on the offboard box plus the link
LINK_S = 0.05  # the mask's way back to the robot
ROUTE_M, QUICK_ROUTE_M, CLEAR_START_M = 40.0, 14.0, 5.0
PATCH_M, HAZARD_M = 2.0, 0.5  # an ambiguous patch's side; a hazard's, inside a patch, on the route
PATCHES_PER_10_M = 1
STALL_MPS, STALL_S = 0.05, 1.0
SAFE_AFTER_S, STALE_S = 2.0, 3.0  # the relay's safe_mask.after_s, the service's speed.stale_s
HORIZON_S = 30.0  # the relay's safe mask reaches 2 x V_MAX x HORIZON_S = 90 m each way: never left on a route
GUARDS = ("none", "service", "robot")
NOISE = 0.1  # per logit, as SceneBackend

ROWS = {  # what the backend's softmax says of each kind of ground (over the start set's concepts)
    "paved": {"asphalt": 0.98, "gravel": 0.02},
    "grassy": {"grass": 0.97, "bush": 0.03},
    "ambiguous": {"grass": 0.6, "asphalt": 0.2, "mud": 0.2},  # a hazard inside looks the same
}


@dataclass(frozen=True)
class Ground:
    """A route's world: clear ground (paved or grassy halves), ambiguous squares, hazards inside some of them."""

    patches: list[tuple[float, float]]  # centres of the ambiguous squares
    hazards: list[tuple[float, float]]  # centres of the hazards

    def kind(self, x: NDArray[np.floating], y: NDArray[np.floating]) -> NDArray[np.intp]:
        """0 paved, 1 grassy, 2 ambiguous, per point."""
        kinds = np.where(np.asarray(y) >= 0.0, 0, 1)
        for px, py in self.patches:
            inside = (np.abs(np.asarray(x) - px) <= PATCH_M / 2) & (np.abs(np.asarray(y) - py) <= PATCH_M / 2)
            kinds = np.where(inside, 2, kinds)
        return np.asarray(kinds, np.intp)

    def hazard_at(self, x: float, y: float) -> int | None:
        for index, (hx, hy) in enumerate(self.hazards):
            if abs(x - hx) <= HAZARD_M / 2 and abs(y - hy) <= HAZARD_M / 2:
                return index
        return None


def make_ground(route_m: float, rng: np.random.Generator) -> Ground:
    """Ambiguous squares along the route (y = 0) after a clear start, half of them holding a hazard on the route."""
    count = max(2, round(route_m / 10 * PATCHES_PER_10_M))
    slots = np.linspace(CLEAR_START_M + PATCH_M, route_m - PATCH_M, count)
    patches = [(float(x + rng.uniform(-0.5, 0.5)), float(rng.uniform(-0.4, 0.4))) for x in slots]
    chosen = rng.permutation(count)[: count // 2]
    hazards = [(patches[i][0] + float(rng.uniform(-0.5, 0.5)), 0.0) for i in sorted(chosen)]
    return Ground(patches, hazards)


class Eyes:
    """The camera's frames as the backend's softmax weights: each pixel's ground point's kind's row, with noise."""

    def __init__(self, scene: SceneCamera, anchors: AnchorSet, rng: np.random.Generator) -> None:
        self.scene, self.rng = scene, rng
        shape = (scene.camera.height, scene.camera.width)
        u, v = map_cell_pixels(shape, (scene.camera.width, scene.camera.height))
        self.base, self.valid = ground_points(scene.camera, scene.mount, u, v, scene.max_range_m)
        rows = [[ROWS[kind].get(c, FLOOR_PROBABILITY) for c in anchors.concepts] for kind in ROWS]
        self.logits = np.log(np.array(rows, np.float64))

    def weights(self, ground: Ground, pose: tuple[float, float, float]) -> NDArray[np.float16]:
        x, y, yaw = pose
        c, s = math.cos(yaw), math.sin(yaw)
        wx = x + c * self.base[:, 0] - s * self.base[:, 1]
        wy = y + s * self.base[:, 0] + c * self.base[:, 1]
        logits = self.logits[ground.kind(np.nan_to_num(wx), np.nan_to_num(wy))]
        logits = logits + self.rng.normal(0, NOISE, logits.shape)
        logits[~self.valid] = 0.0  # sky or beyond range: every concept alike
        weights = np.exp(logits - logits.max(axis=1, keepdims=True))
        weights /= weights.sum(axis=1, keepdims=True)
        camera = self.scene.camera
        return np.ascontiguousarray(weights.T.reshape(-1, camera.height, camera.width)).astype(np.float16)


@dataclass
class Mask:
    """The speed mask as Nav2's SpeedFilter holds it: percent values, origin, resolution; when it arrived."""

    values: NDArray[np.int8]
    origin: tuple[float, float]
    resolution: float
    arrives_at: float

    @staticmethod
    def decoded(payload: bytes, arrives_at: float) -> Mask:
        message = cdr.typestore().deserialize_cdr(payload, cdr.OCCUPANCY_GRID)
        info = message.info
        values = np.asarray(message.data, np.int8).reshape(info.height, info.width)
        origin = (float(info.origin.position.x), float(info.origin.position.y))
        return Mask(values, origin, float(info.resolution), arrives_at)

    def percent_at(self, x: float, y: float) -> int | None:
        """The mask's value in the robot's cell; None off the mask (SpeedFilter then keeps its last limit)."""
        j = math.floor((x - self.origin[0]) / self.resolution)
        i = math.floor((y - self.origin[1]) / self.resolution)
        rows, columns = self.values.shape
        return int(self.values[i, j]) if 0 <= i < rows and 0 <= j < columns else None


@dataclass(frozen=True)
class Layer:
    """How the speed layer runs in a drive: the mask's rate and lead_m."""

    rate_hz: float
    lead_m: float
    latency_s: tuple[float, float] = LATENCY_S  # capture to fusion, uniform

    @property
    def name(self) -> str:
        slow = "" if self.latency_s == LATENCY_S else f", fused {self.latency_s[0]:g}-{self.latency_s[1]:g} s late"
        return f"mask at {self.rate_hz:g} Hz, lead_m {self.lead_m:g}{slow}"


# the default speed.rate_hz is 1 Hz; the last: a slow box or link, frames fused 2-3 s after capture
LAYERS = (Layer(1.0, 0.0), Layer(1.0, LEAD_M), Layer(5.0, LEAD_M), Layer(1.0, LEAD_M, (2.0, 3.0)))


@dataclass(frozen=True)
class LinkLoss:
    """The link dies at ``at_s`` (simulated); ``guard``: which safe mask may follow (GUARDS)."""

    at_s: float
    guard: str


class LinkSide:
    """What the link and the robot's relay make of the masks and frames, before and after a loss."""

    def __init__(self, loss: LinkLoss | None) -> None:
        self.loss = loss
        settings = SafeMaskSettings(after_s=SAFE_AFTER_S, floor=FLOOR, max_speed_m_s=V_MAX, horizon_s=HORIZON_S)
        self.now = 0.0
        self.guard = MaskGuard("robot/cam", settings, clock=lambda: self.now)
        self.last_fused = 0.0
        self.service_safe_sent = False

    def up(self, t: float) -> bool:
        return self.loss is None or t < self.loss.at_s

    def crossing(self, masks: list[Mask]) -> list[Mask]:
        """The masks that reach the robot: those arriving while the link is up; each tells the relay's guard."""
        arrived = [mask for mask in masks if self.up(mask.arrives_at)]
        for mask in arrived:
            self.last_fused = mask.arrives_at
        return arrived

    def safe_masks(self, t: float, robot: Robot) -> list[Mask]:
        """The safe masks handed out at ``t``: the service's (its grid stale for STALE_S; it crosses only a live
        link) and the relay's guard's (on the robot: always arrives)."""
        if self.loss is None or self.loss.guard == "none":
            return []
        found = []
        if not self.service_safe_sent and t - self.last_fused > STALE_S:
            self.service_safe_sent = True  # put once, as the service does; a dead link loses it
            if self.up(t):
                found.append(uniform_mask(robot.x, 16.0, 0.2, t + LINK_S))
        if self.loss.guard == "robot":
            self.now = t
            if t - self.last_fused < 1.0 / FRAME_HZ + 0.1:  # credits and maps at the frames' rate while up
                self.guard.heard()
            self.guard.pose(robot.x, 0.0, "odom")
            safe = self.guard.due()
            if safe is not None:
                found.append(Mask(safe.values(), safe.origin, safe.resolution, t))
        return found


def uniform_mask(x: float, size_m: float, resolution: float, arrives_at: float) -> Mask:
    """The floor everywhere on a square of ``size_m`` centred at (x, 0): the service's safe mask of its grid."""
    cells = round(size_m / resolution)
    values = np.full((cells, cells), round(FLOOR * 100), np.int8)
    return Mask(values, (x - size_m / 2, -size_m / 2), resolution, arrives_at)


@dataclass
class Drive:
    """One drive's outcome."""

    layer: str  # "off" or the Layer's name
    seed: int
    route: int
    time_to_goal_s: float
    contacts: int
    hazards: int
    entry_speeds: list[float]  # the robot's speed as it first entered each hazard it reached, m/s
    stalls: int
    mean_speed_ambiguous: float
    mean_speed_clear: float
    reached: bool
    loss_at_s: float | None = None  # when the link died, if it did
    fast_after_loss_m: float = 0.0  # metres driven above the floor's speed after the loss


@dataclass
class Robot:
    x: float = 0.0
    v: float = 0.0
    limit: float = 1.0  # the fraction of V_MAX the SpeedFilter allows now
    samples: dict[int, list[float]] = field(default_factory=lambda: {0: [], 1: [], 2: []})  # kind -> speeds

    def step(self, dt: float) -> None:
        wanted = V_MAX * self.limit
        change = ACCEL * dt if wanted > self.v else -DECEL * dt
        self.v = min(wanted, self.v + change) if change > 0 else max(wanted, self.v + change)
        self.x += self.v * dt


def grid_settings(scene: SceneCamera, layer: Layer) -> GridSettings:
    speed = {"floor": FLOOR, "rate_hz": layer.rate_hz, "lead_m": layer.lead_m, "stale_s": 3.0}
    return scene.grid_settings(
        source=CAMERA, pose_key="robot/pose", size_m=16.0, resolution_m=0.2, half_life_s=2.0, max_age_s=None,
        speed=speed, poses={"wait_s": 0.0, "span_s": 10.0},
    )  # fmt: skip


def drive(
    ground: Ground, route_m: float, layer: Layer | None, seed: int, route: int, loss: LinkLoss | None = None
) -> Drive:
    """The robot along y = 0 to x = route_m; ``layer`` None: without the speed layer; ``loss``: the link dies."""
    rng = np.random.default_rng(seed * 1000 + route)
    scene, anchors = default_camera(), start_anchors()
    eyes = Eyes(scene, anchors, rng)
    clock = [0.0]
    settings = grid_settings(scene, layer or LAYERS[0])
    grids = GridOutputs([settings], len(anchors), "speed", clock=lambda: clock[0])
    robot = Robot(limit=1.0)
    frames: list[tuple[float, float, tuple[float, float, float]]] = []  # (fused at, captured at, pose then)
    masks: list[Mask] = []
    dt, t, slow_since, stalls = 1.0 / POSE_HZ, 0.0, None, 0
    entered: dict[int, float] = {}  # hazard -> the speed it was entered at
    limit_deadline = 120.0 + route_m / (V_MAX * FLOOR)
    link, fast_m = LinkSide(loss), 0.0
    off_mask = "keep" if loss is None else "no_limit"
    while robot.x < route_m and t < limit_deadline:
        step = round(t * POSE_HZ)
        grids.add_pose(CAMERA, Pose2D(stamp=t, frame_id="odom", x=robot.x, y=0.0, yaw=0.0))
        if layer is not None:
            if step % round(POSE_HZ / FRAME_HZ) == 0 and link.up(t):
                frames.append((t + float(rng.uniform(*layer.latency_s)), t, (robot.x, 0.0, 0.0)))
            masks += link.crossing(fuse_due(grids, eyes, ground, frames, t, anchors, clock))
            masks += link.safe_masks(t, robot)
            if step % round(POSE_HZ / FILTER_HZ) == 0:
                robot.limit = filter_limit(masks, robot, t, off_mask)
        if loss is not None and t >= loss.at_s and robot.v > FLOOR * V_MAX + 1e-6:
            fast_m += robot.v * dt
        kind = int(ground.kind(np.array(robot.x), np.array(0.0)))
        robot.samples[kind].append(robot.v)
        hazard = ground.hazard_at(robot.x, 0.0)
        if hazard is not None and hazard not in entered:
            entered[hazard] = robot.v
        slow_since, stalls = stall_watch(robot.v, t, slow_since, stalls)
        robot.step(dt)
        t += dt
    clear = robot.samples[0] + robot.samples[1]
    return Drive(
        "off" if layer is None else layer.name, seed, route, t, sum(v > V_SAFE for v in entered.values()),
        len(ground.hazards), list(entered.values()), stalls, _mean(robot.samples[2]), _mean(clear), robot.x >= route_m,
        None if loss is None else loss.at_s, fast_m,
    )  # fmt: skip


def fuse_due(
    grids: GridOutputs,
    eyes: Eyes,
    ground: Ground,
    frames: list[tuple[float, float, tuple[float, float, float]]],
    t: float,
    anchors: AnchorSet,
    clock: list[float],
) -> list[Mask]:
    """Fuse every frame whose fusion time has come (in that order); the masks they hand out, as they arrive."""
    masks = []
    for frame in sorted(f for f in frames if f[0] <= t):
        frames.remove(frame)
        fused_at, captured, pose = frame
        clock[0] = fused_at
        weights = eyes.weights(ground, pose)
        size = (eyes.scene.camera.width, eyes.scene.camera.height)
        fused = grids.fuse(CAMERA, FrameRecord(0, captured, "", weights, anchors, size), weights)
        update = fused.encode() if fused is not None else None
        if update is not None and update.speed is not None and update.speed.mask is not None:
            masks.append(Mask.decoded(update.speed.mask, fused_at + LINK_S))
    return masks


def filter_limit(masks: list[Mask], robot: Robot, t: float, off_mask: str = "keep") -> float:
    """Nav2's SpeedFilter: the newest mask arrived by ``t``, at the robot's cell; none yet, the last limit stays
    (the robot starts with none: full speed, as Nav2 before its first mask); off the mask, ``off_mask``: "keep"
    the last limit (Jazzy, Kilted, or main without a path) or "no_limit" (main's path lookahead)."""
    arrived = [mask for mask in masks if mask.arrives_at <= t]
    if not arrived:
        return robot.limit
    percent = arrived[-1].percent_at(robot.x, 0.0)
    if percent is None:
        return robot.limit if off_mask == "keep" else 1.0
    return 1.0 if percent == NO_LIMIT else percent / 100.0


def stall_watch(v: float, t: float, slow_since: float | None, stalls: int) -> tuple[float | None, int]:
    """A stall: slower than STALL_MPS for STALL_S (each stretch counted once); the robot's start is no stall."""
    if v >= STALL_MPS or t < STALL_S:
        return None, stalls
    if slow_since is None:
        return t, stalls
    return (math.inf, stalls + 1) if t - slow_since >= STALL_S else (slow_since, stalls)


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else math.nan


def run(seeds: int, routes: int, route_m: float, layers: tuple[Layer, ...]) -> list[Drive]:
    """Every seed's routes, driven without the layer and with each of ``layers`` (the same ground, frames'
    latencies and noise)."""
    drives = []
    for seed in range(seeds):
        for route in range(routes):
            ground = make_ground(route_m, np.random.default_rng(seed * 100 + route))
            for layer in (None, *layers):
                drives.append(drive(ground, route_m, layer, seed, route))
    return drives


def run_link_loss(seeds: int, routes: int, route_m: float) -> list[Drive]:
    """Every seed's routes with the default layer, the link dying at a random moment while the robot approaches
    the hazards (after the clear start, before the last third), once per guard; and the same on clear ground."""
    layer, drives = LAYERS[1], []
    for seed in range(seeds):
        for route in range(routes):
            rng = np.random.default_rng(seed * 100 + route + 7)
            hazards = make_ground(route_m, np.random.default_rng(seed * 100 + route))
            at_s = float(rng.uniform(CLEAR_START_M / V_MAX, 0.6 * route_m / V_MAX))
            for name, ground in (("hazards", hazards), ("clear", Ground([], []))):
                for guard in GUARDS:
                    done = drive(ground, route_m, layer, seed, route, LinkLoss(at_s, guard))
                    done.layer = f"{name}, safe mask: {guard}"
                    drives.append(done)
    return drives


def link_loss_table(drives: list[Drive]) -> str:
    lines = [
        "| ground, safe mask after the loss | drives (reached) | time to goal, s (median) | hazard contacts / hazards "
        "| m driven above the floor's speed after the loss (median / max) |",
        "|---|---|---|---|---|",
    ]
    for layer in dict.fromkeys(d.layer for d in drives):
        mine = [d for d in drives if d.layer == layer]
        fast = [d.fast_after_loss_m for d in mine]
        lines.append(
            f"| {layer} | {len(mine)} ({sum(d.reached for d in mine)}) | "
            f"{statistics.median(d.time_to_goal_s for d in mine):.1f} | {sum(d.contacts for d in mine)} / "
            f"{sum(d.hazards for d in mine)} | {statistics.median(fast):.1f} / {max(fast):.1f} |"
        )
    return "\n".join(lines)


def summary(drives: list[Drive]) -> list[dict[str, float | str | int]]:
    """Per way to drive: sums of contacts and hazards, medians of time and speeds, over every seed and route."""
    rows: list[dict[str, float | str | int]] = []
    for layer in dict.fromkeys(d.layer for d in drives):
        mine = [d for d in drives if d.layer == layer]
        rows.append({
            "layer": layer, "drives": len(mine), "reached": sum(d.reached for d in mine),
            "time_to_goal_s_median": statistics.median(d.time_to_goal_s for d in mine),
            "contacts": sum(d.contacts for d in mine), "hazards": sum(d.hazards for d in mine),
            "entry_speed_median": statistics.median(v for d in mine for v in d.entry_speeds),
            "entry_speed_max": max(v for d in mine for v in d.entry_speeds),
            "stalls": sum(d.stalls for d in mine),
            "mean_speed_ambiguous_median": statistics.median(d.mean_speed_ambiguous for d in mine),
            "mean_speed_clear_median": statistics.median(d.mean_speed_clear for d in mine),
        })  # fmt: skip
    return rows


def table(rows: list[dict[str, float | str | int]]) -> str:
    lines = [
        "| speed layer | drives (reached) | time to goal, s (median) | hazard contacts / hazards | "
        "speed entering a hazard, m/s (median / max) | stalls | mean speed m/s on ambiguous / clear ground (median) |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        lines.append(
            f"| {row['layer']} | {row['drives']} ({row['reached']}) | {row['time_to_goal_s_median']:.1f} | "
            f"{row['contacts']} / {row['hazards']} | {row['entry_speed_median']:.2f} / {row['entry_speed_max']:.2f} | "
            f"{row['stalls']} | "
            f"{row['mean_speed_ambiguous_median']:.2f} / {row['mean_speed_clear_median']:.2f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.speed", description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=5, help="worlds [5]")
    parser.add_argument("--routes", type=int, default=3, help="routes per world [3]")
    parser.add_argument("--quick", action="store_true", help="1 seed, 1 short route, the default layer: a smoke check")
    parser.add_argument("--link-loss", action="store_true", help="the link dies at a random moment (issue 55)")
    parser.add_argument("--out", type=Path, help="write the drives, the summary and the machine as JSON")
    args = parser.parse_args(argv)
    if args.link_loss:
        seeds, routes, route_m = (1, 1, QUICK_ROUTE_M) if args.quick else (args.seeds, args.routes, ROUTE_M)
        drives = run_link_loss(seeds, routes, route_m)
        print(f"cpu: {cpu_name()}, python {platform.python_version()}")
        print(link_loss_table(drives))
        if args.out is not None:
            document = {"cpu": cpu_name(), "drives": [asdict(d) for d in drives]}
            args.out.write_text(json.dumps(document, indent=1) + "\n")
        return 0
    quick = (1, 1, QUICK_ROUTE_M, (LAYERS[1],))
    drives = run(*quick) if args.quick else run(args.seeds, args.routes, ROUTE_M, LAYERS)
    rows = summary(drives)
    print(f"cpu: {cpu_name()}, python {platform.python_version()}")
    print(table(rows))
    if args.out is not None:
        document = {"cpu": cpu_name(), "summary": rows, "drives": [asdict(d) for d in drives]}
        args.out.write_text(json.dumps(document, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
