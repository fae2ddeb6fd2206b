"""A synthetic world for the experience benchmark and tests: terrain tiles that look like one thing and are,
now and then, another; a camera that renders what it sees as colours; a backend whose logits follow the
colour under each pixel; a robot whose tracked speed follows the true traversability.

*Honest confusion.* Each tile has an appearance (what the camera sees: grassy, sandy, ...), and each of its
patches a true terrain drawn from ``CONFUSION[appearance]``: a patch of a grassy tile is grass 97 % of the time
and bush 3 %, a bushy one bush 90 % and grass 10 %, as bush and grass look alike to CLIP. The backend's
softmax over the concepts is that same row (with a little noise per pixel), so its weights are honest
probabilities of the terrain, which the GCD assumes: then the anchor positions that best explain the outcomes
are the terrains' true traversabilities, and a mixture with the right widths is calibrated.
Not in the wheel: tests and benchmarks import it from the checkout.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from gcdtrav.schemas.anchors import Anchor, AnchorSet
from gcdtrav.schemas.settings import CameraIntrinsics, CameraMountSettings, GridSettings
from gcdtrav.service.backends.base import BackendDescription
from gcdtrav.service.grid.geometry import CameraMount, PinholeCamera, ground_points, map_cell_pixels
from numpy.typing import NDArray

# The starting set (what an operator would guess, close to the paper's) and the world's truth.
START: dict[str, float] = {
    "water": 0.02, "mud": 0.1, "sand": 0.4, "bush": 0.45, "grass": 0.5, "gravel": 0.6, "dirt": 0.7, "asphalt": 0.98,
}  # fmt: skip
TRUTH: dict[str, float] = {**START, "sand": 0.15, "bush": 0.25, "grass": 0.8}
# appearance -> (its colour, P(true terrain | appearance))
CONFUSION: dict[str, tuple[tuple[int, int, int], dict[str, float]]] = {
    "grassy": ((40, 160, 60), {"grass": 0.97, "bush": 0.03}),
    "bushy": ((30, 90, 40), {"bush": 0.9, "grass": 0.1}),
    "sandy": ((210, 190, 130), {"sand": 0.96, "dirt": 0.04}),
    "paved": ((90, 90, 90), {"asphalt": 0.98, "gravel": 0.02}),
    "gravelly": ((150, 150, 140), {"gravel": 0.92, "dirt": 0.05, "asphalt": 0.03}),
    "dirty": ((120, 85, 50), {"dirt": 0.92, "gravel": 0.05, "mud": 0.03}),
    "muddy": ((80, 60, 40), {"mud": 0.9, "water": 0.07, "dirt": 0.03}),
    "wet": ((60, 80, 150), {"water": 0.95, "mud": 0.05}),
}
APPEARANCE_SHARE: dict[str, float] = {
    "grassy": 0.36, "bushy": 0.1, "sandy": 0.26, "paved": 0.06, "gravelly": 0.06, "dirty": 0.08, "muddy": 0.04,
    "wet": 0.04,
}  # fmt: skip
SKY = (200, 220, 250)
APPEARANCES = list(CONFUSION)
FLOOR_PROBABILITY = 1e-4  # a concept the appearance never is: a tiny weight, as a real softmax gives


def start_anchors() -> AnchorSet:
    ordered = sorted(START.items(), key=lambda item: item[1])
    return AnchorSet(name="start", anchors=[Anchor(concept=c, position=p) for c, p in ordered])


def palette() -> NDArray[np.int32]:
    return np.array([CONFUSION[a][0] for a in APPEARANCES] + [SKY], np.int32)


class SceneBackend:
    """A SegmentationBackend whose logits follow the colour of each pixel: the nearest appearance's row of
    CONFUSION (log-probabilities) plus Gaussian noise of ``noise`` per logit; the sky is uniform."""

    model_id = "synthetic-scene"

    def __init__(self, noise: float = 0.1, seed: int = 0) -> None:
        self.noise = noise
        self.rng = np.random.default_rng(seed)

    def describe(self) -> BackendDescription:
        return BackendDescription(self.model_id)

    def prepare(self, concepts: Sequence[str]) -> object:
        table = np.full((len(APPEARANCES) + 1, len(concepts)), math.log(FLOOR_PROBABILITY), np.float32)
        for a, appearance in enumerate(APPEARANCES):
            for k, concept in enumerate(concepts):
                share = CONFUSION[appearance][1].get(concept)
                if share is not None:
                    table[a, k] = math.log(share)
        table[-1] = 0.0  # the sky: every concept alike
        return table

    def logits(self, image_rgb: NDArray[np.uint8], prepared: object) -> NDArray[np.float32]:
        table = np.asarray(prepared)
        colours = image_rgb.reshape(-1, 3).astype(np.int32)
        distance = ((colours[:, None, :] - palette()[None, :, :]) ** 2).sum(axis=2)
        appearance = distance.argmin(axis=1)
        logits = table[appearance] + self.rng.normal(0, self.noise, (len(appearance), table.shape[1]))
        return logits.T.reshape(table.shape[1], image_rgb.shape[0], image_rgb.shape[1]).astype(np.float32)


@dataclass(frozen=True)
class World:
    tile_m: float
    appearance: NDArray[np.int64]  # (tiles, tiles): index into APPEARANCES
    terrain: NDArray[np.int64]  # (tiles * split, tiles * split): index into the concepts of TRUTH (list order)
    origin: float  # the world covers [origin, origin + tiles * tile_m) in x and y

    @property
    def split(self) -> int:
        """Patches of true terrain per tile side: a grassy tile holds patches of bush."""
        return self.terrain.shape[0] // self.appearance.shape[0]

    @property
    def size_m(self) -> float:
        return self.appearance.shape[0] * self.tile_m

    def tile_of(
        self, x: NDArray[np.floating], y: NDArray[np.floating], split: int = 1
    ) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        n, side = self.appearance.shape[0] * split, self.tile_m / split
        i = np.clip(np.floor((np.asarray(y) - self.origin) / side).astype(np.intp), 0, n - 1)
        j = np.clip(np.floor((np.asarray(x) - self.origin) / side).astype(np.intp), 0, n - 1)
        return i, j

    def true_traversability(self, x: float, y: float) -> float:
        i, j = self.tile_of(np.array(x), np.array(y), self.split)
        return TRUTH[list(TRUTH)[int(self.terrain[i, j])]]


def make_world(tiles: int = 24, tile_m: float = 8.0, split: int = 4, seed: int = 0) -> World:
    """Tiles of one appearance each, every tile split into split x split patches of true terrain drawn from
    its appearance's row of CONFUSION."""
    rng = np.random.default_rng(seed)
    shares = np.array([APPEARANCE_SHARE[a] for a in APPEARANCES])
    appearance = rng.choice(len(APPEARANCES), size=(tiles, tiles), p=shares / shares.sum())
    patches = np.kron(appearance, np.ones((split, split), np.int64))
    concepts = list(TRUTH)
    terrain = np.empty_like(patches)
    for index, name in enumerate(APPEARANCES):
        rows = CONFUSION[name][1]
        where = patches == index
        # Stratified: the world's patches of this appearance hold each terrain in the row's proportion exactly.
        counts = np.floor(np.array(list(rows.values())) * int(where.sum())).astype(int)
        counts[0] += int(where.sum()) - counts.sum()
        drawn = rng.permutation(np.repeat(np.arange(len(rows)), counts))
        terrain[where] = [concepts.index(list(rows)[d]) for d in drawn]
    return World(tile_m, appearance, terrain, -tiles * tile_m / 2)


@dataclass(frozen=True)
class SceneCamera:
    camera: PinholeCamera
    mount: CameraMount
    max_range_m: float = 8.0

    def render(self, world: World, x: float, y: float, yaw: float) -> tuple[NDArray[np.uint8], NDArray[np.float64]]:
        """The image the camera sees from pose (x, y, yaw): one pixel per patch, each the colour of the tile its
        ray meets (sky above the horizon or beyond range); and each pixel's ground point in the base frame
        (NaN where none)."""
        shape = (self.camera.height, self.camera.width)
        u, v = map_cell_pixels(shape, (self.camera.width, self.camera.height))
        base, valid = ground_points(self.camera, self.mount, u, v, self.max_range_m)
        c, s = math.cos(yaw), math.sin(yaw)
        world_x = x + c * base[:, 0] - s * base[:, 1]
        world_y = y + s * base[:, 0] + c * base[:, 1]
        i, j = world.tile_of(np.nan_to_num(world_x), np.nan_to_num(world_y))
        colours = palette()[np.where(valid, world.appearance[i, j], len(APPEARANCES))]
        return colours.reshape(*shape, 3).astype(np.uint8), base

    def grid_settings(self, **fields: Any) -> GridSettings:
        """A ground grid of this camera (its intrinsics, mount and range) with ``fields`` (source, pose_key, ...)."""
        camera, mount = self.camera, self.mount
        intrinsics = CameraIntrinsics(
            fx=camera.fx, fy=camera.fy, cx=camera.cx, cy=camera.cy, width=camera.width, height=camera.height
        )
        mounted = CameraMountSettings(
            x=mount.x, y=mount.y, z=mount.z, roll=mount.roll, pitch=mount.pitch, yaw=mount.yaw
        )
        return GridSettings(intrinsics=intrinsics, mount=mounted, max_range_m=self.max_range_m, **fields)


def default_camera() -> SceneCamera:
    return SceneCamera(PinholeCamera(50.0, 50.0, 32.0, 24.0, 64, 48), CameraMount(z=1.0, pitch=0.5))


# ---- the robot -------------------------------------------------------------------------------------------

COMMAND_MPS = 1.0
MIN_PACE = 0.35  # the route never stalls, so it visits every terrain; only odometry reports how slow it was
SPEED_NOISE = 0.05  # per odometry sample, on the ratio achieved / commanded


@dataclass
class Robot:
    world: World
    rng: np.random.Generator
    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    goal: tuple[float, float] = (0.0, 0.0)
    turns: list[float] = field(default_factory=list)

    def next_goal(self) -> None:
        half = self.world.size_m / 2 - 8.0
        self.goal = (float(self.rng.uniform(-half, half)), float(self.rng.uniform(-half, half)))

    def step(self, dt: float) -> tuple[float, float]:
        """Move one step toward the goal; (speed odometry reports, yaw rate)."""
        if math.hypot(self.goal[0] - self.x, self.goal[1] - self.y) < 1.0:
            self.next_goal()
        wanted = math.atan2(self.goal[1] - self.y, self.goal[0] - self.x)
        turn = math.atan2(math.sin(wanted - self.yaw), math.cos(wanted - self.yaw))
        rate = max(-1.0, min(1.0, 2.0 * turn))
        truth = self.world.true_traversability(self.x, self.y)
        ratio = min(max(truth + float(self.rng.normal(0, SPEED_NOISE)), 0.0), 1.0)
        pace = COMMAND_MPS * max(truth, MIN_PACE)
        self.yaw += rate * dt
        self.x += pace * math.cos(self.yaw) * dt
        self.y += pace * math.sin(self.yaw) * dt
        return COMMAND_MPS * ratio, rate


# ---- a hazard at known coordinates (benchmarks/placement.py) ---------------------------------------------

HAZARD_ROW = {"water": 0.95, "mud": 0.05}  # what the backend would say of the hazard's patches
GROUND_ROW = {"asphalt": 0.98, "gravel": 0.02}  # ... and of the paved ground around it


@dataclass(frozen=True)
class Hazard:
    """A square of water on paved ground, centred at (x, y) in the world (the odometry frame), axis-aligned."""

    x: float
    y: float
    side_m: float = 1.0

    def covers(self, x: NDArray[np.floating], y: NDArray[np.floating]) -> NDArray[np.bool_]:
        half = self.side_m / 2
        return (np.abs(np.asarray(x) - self.x) <= half) & (np.abs(np.asarray(y) - self.y) <= half)


def hazard_pixels(
    scene: SceneCamera, hazard: Hazard, pose: tuple[float, float, float]
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Per pixel (flattened, one patch per pixel) of the camera at ``pose`` (x, y, yaw): whether its ray meets
    the hazard, and whether it meets the ground at all (not sky, within range)."""
    shape = (scene.camera.height, scene.camera.width)
    u, v = map_cell_pixels(shape, (scene.camera.width, scene.camera.height))
    base, valid = ground_points(scene.camera, scene.mount, u, v, scene.max_range_m)
    x, y, yaw = pose
    c, s = math.cos(yaw), math.sin(yaw)
    inside = hazard.covers(x + c * base[:, 0] - s * base[:, 1], y + s * base[:, 0] + c * base[:, 1])
    return inside & valid, valid


def hazard_image(scene: SceneCamera, hazard: Hazard, pose: tuple[float, float, float]) -> NDArray[np.uint8]:
    """What the camera at ``pose`` sees of the hazard on paved ground, as the colours ``SceneBackend`` reads
    (RGB, height x width): the wet appearance's in the hazard, the paved one's around it, sky elsewhere."""
    inside, valid = hazard_pixels(scene, hazard, pose)
    colours = np.where(inside, APPEARANCES.index("wet"), np.where(valid, APPEARANCES.index("paved"), len(APPEARANCES)))
    return palette()[colours].reshape(scene.camera.height, scene.camera.width, 3).astype(np.uint8)


def hazard_view(
    scene: SceneCamera, hazard: Hazard, pose: tuple[float, float, float], concepts: Sequence[str]
) -> NDArray[np.float32]:
    """The softmax weights (n, height, width) over ``concepts`` of what the camera sees from ``pose`` (x, y, yaw):
    one patch per pixel, the hazard's row where its ground point falls in the hazard, the ground's elsewhere,
    uniform where the ray meets no ground (sky, beyond range)."""
    shape = (scene.camera.height, scene.camera.width)
    inside, valid = hazard_pixels(scene, hazard, pose)
    rows = {
        name: np.array([table.get(concept, FLOOR_PROBABILITY) for concept in concepts], np.float32)
        for name, table in (("hazard", HAZARD_ROW), ("ground", GROUND_ROW))
    }
    weights = np.where(inside[:, None], rows["hazard"], rows["ground"])
    weights[~valid] = 1.0
    weights /= weights.sum(axis=1, keepdims=True)
    return np.ascontiguousarray(weights.T.reshape(len(concepts), *shape))
