"""Scenario sampling for the simulated room of README "The simulated world", as plain geometry (no PyBullet).

A :class:`Scenario` is everything random about one world: the doorway (width and which wall) and the
pose and size of the chair, box and desk. Keeping it pure numpy lets the labeller, the world builder and
the pictures share one description, and lets a scenario be written to ``scenarios.jsonl`` and rebuilt
exactly. Frames follow ROS REP-103: x forward/east, y left/north, yaw counter-clockwise in radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# Class ids of common.model_spec.CLASS_NAMES; the doorframe is a label only, never a body, and people
# are ray-cast in closed form (services.simulator.people).
CHAIR, BOX, DESK, DOORFRAME, PERSON = 0, 1, 2, 3, 4

ROOM_HALF_M = 2.0  # inner faces of the room walls
WALL_THICKNESS_M = 0.1
WALL_HEIGHT_M = 0.5
OUTER_HALF_M = 3.1  # inner faces of the outer enclosure
# An open-space room (``triscan dataset --open-space``) keeps the furniture and the robot where the
# paper's room has them but moves its walls out to a half-width drawn from this range: walls 2.3–7.8 m
# away leave much of a scan beyond the raster's 4 m full scale, or beyond a short-range sensor's
# reach, as halls and open-plan floors do, and people walk up to about 5 m from the robot.
OPEN_SPACE_HALF_M = (2.5, 6.0)
PLACEMENT_HALF_M = 1.8  # object centres and inflated footprints stay inside [-1.8, 1.8]^2
# The world inflates each footprint by 0.7 m before the containment and overlap tests. We read that as
# 0.7 m added to each dimension (0.35 m per side): two inflated footprints that do not overlap leave a
# 0.7 m corridor between the objects, wide enough for the robot. A 0.7 m margin per side cannot place
# three objects in the room at all for most desk sizes.
PLACEMENT_MARGIN_M = 0.35
MAX_PLACEMENT_TRIES = 10_000
PLACEMENT_DRAWS_PER_OBJECT = 200

ROBOT_GRID_STEP_M = 0.1
ROBOT_GRID_HALF_M = 1.75
LEG_CLEARANCE_M = 0.22
BOX_CLEARANCE_M = 0.175
MIN_POSITION_SPACING_M = 0.25


@dataclass(frozen=True)
class Rect:
    """An oriented rectangle on the floor: centre (m), size along its own x and y (m), yaw (rad)."""

    center: tuple[float, float]
    size: tuple[float, float]
    yaw: float

    def corners(self) -> np.ndarray:
        """Return the four corners, counter-clockwise, as float64[4, 2] in the world frame."""
        hx, hy = self.size[0] / 2.0, self.size[1] / 2.0
        local = np.array([[hx, hy], [-hx, hy], [-hx, -hy], [hx, -hy]])
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        rot = np.array([[c, -s], [s, c]])
        return local @ rot.T + np.asarray(self.center)

    def inflated(self, margin: float) -> Rect:
        return Rect(self.center, (self.size[0] + 2 * margin, self.size[1] + 2 * margin), self.yaw)

    def to_local(self, points: np.ndarray) -> np.ndarray:
        """Express world points float[..., 2] in the rectangle's own frame."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        d = np.asarray(points, dtype=np.float64) - np.asarray(self.center)
        return np.stack([d[..., 0] * c + d[..., 1] * s, -d[..., 0] * s + d[..., 1] * c], axis=-1)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Euclidean distance from each point float[..., 2] to the filled rectangle (0 inside)."""
        local = self.to_local(points)
        half = np.array(self.size) / 2.0
        outside = np.maximum(np.abs(local) - half, 0.0)
        return np.hypot(outside[..., 0], outside[..., 1])


@dataclass(frozen=True)
class Furniture:
    """One piece of furniture. Chairs and desks are four legs under a top; the box is solid."""

    class_id: int
    footprint: Rect
    height_m: float  # top height (chair, desk) or box height
    leg_size_m: float = 0.0  # square leg side; 0 for the solid box

    @property
    def has_legs(self) -> bool:
        return self.leg_size_m > 0.0

    def leg_rects(self) -> list[Rect]:
        """Legs flush in the footprint's corners (README, "The simulated world"), in the world frame."""
        if not self.has_legs:
            return []
        hx = (self.footprint.size[0] - self.leg_size_m) / 2.0
        hy = (self.footprint.size[1] - self.leg_size_m) / 2.0
        c, s = math.cos(self.footprint.yaw), math.sin(self.footprint.yaw)
        cx, cy = self.footprint.center
        legs = []
        for lx, ly in ((hx, hy), (-hx, hy), (-hx, -hy), (hx, -hy)):
            centre = (cx + lx * c - ly * s, cy + lx * s + ly * c)
            legs.append(Rect(centre, (self.leg_size_m, self.leg_size_m), self.footprint.yaw))
        return legs

    def solid_rects(self) -> list[Rect]:
        """What the scan plane can hit: the legs, or the whole footprint of a solid box."""
        return self.leg_rects() if self.has_legs else [self.footprint]


@dataclass(frozen=True)
class Doorway:
    """The opening in one room wall. ``wall_k`` rotates the +x wall by k·90° (k = 0: door faces +x).

    ``room_half_m`` is where that wall's inner face lies: the room is square about the origin.
    """

    wall_k: int
    width_m: float
    room_half_m: float = ROOM_HALF_M

    @property
    def yaw(self) -> float:
        return self.wall_k * math.pi / 2.0

    @property
    def axes(self) -> tuple[np.ndarray, np.ndarray]:
        """The door wall's outward normal and its direction along the wall, in the world frame."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([c, s]), np.array([-s, c])

    @property
    def frame(self) -> Rect:
        """The doorframe label proxy: centred in the doorway, wall-thick across, door-wide along."""
        r = self.room_half_m + WALL_THICKNESS_M / 2.0
        return Rect(
            (r * math.cos(self.yaw), r * math.sin(self.yaw)), (WALL_THICKNESS_M, self.width_m), self.yaw
        )

    @property
    def opening(self) -> np.ndarray:
        """The opening on the inner wall face, float64[2, 2] endpoints: a beam crossing it leaves the room."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        half = self.width_m / 2.0
        local = np.array([[self.room_half_m, -half], [self.room_half_m, half]])
        return local @ np.array([[c, -s], [s, c]]).T


@dataclass(frozen=True)
class Scenario:
    """One randomised world: a doorway and exactly one chair, box and desk."""

    index: int
    seed: int
    door: Doorway
    objects: tuple[Furniture, ...]
    axis_aligned: bool = field(default=False)

    @property
    def room_half_m(self) -> float:
        """Where the room walls' inner faces lie (the paper's room: 2 m)."""
        return self.door.room_half_m

    def footprint_of(self, class_id: int) -> Rect:
        if class_id == DOORFRAME:
            return self.door.frame
        return next(o.footprint for o in self.objects if o.class_id == class_id)

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready description, enough to rebuild the scenario with :meth:`from_json`."""
        door: dict[str, Any] = {"wall_k": self.door.wall_k, "width_m": self.door.width_m}
        if self.door.room_half_m != ROOM_HALF_M:  # the paper's rooms keep their records unchanged
            door["room_half_m"] = self.door.room_half_m
        return {
            "index": self.index,
            "seed": self.seed,
            "axis_aligned": self.axis_aligned,
            "door": door,
            "objects": [
                {
                    "class_id": o.class_id,
                    "center": list(o.footprint.center),
                    "size": list(o.footprint.size),
                    "yaw": o.footprint.yaw,
                    "height_m": o.height_m,
                    "leg_size_m": o.leg_size_m,
                }
                for o in self.objects
            ],
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Scenario:
        objects = tuple(
            Furniture(
                class_id=int(o["class_id"]),
                footprint=Rect(tuple(o["center"]), tuple(o["size"]), float(o["yaw"])),
                height_m=float(o["height_m"]),
                leg_size_m=float(o["leg_size_m"]),
            )
            for o in data["objects"]
        )
        door = Doorway(
            int(data["door"]["wall_k"]),
            float(data["door"]["width_m"]),
            float(data["door"].get("room_half_m", ROOM_HALF_M)),
        )
        return cls(
            int(data["index"]), int(data["seed"]), door, objects, bool(data.get("axis_aligned", False))
        )


# --- walls: the room with its doorway and the outer enclosure, as floor rectangles -----------------

# Exact quarter-turn rotations (cos, sin) so that rotated walls keep bit-exact coordinates.
_QUARTER_TURNS: tuple[tuple[int, int], ...] = ((1, 0), (0, 1), (-1, 0), (0, -1))


def _axis_rect(x_min: float, x_max: float, y_min: float, y_max: float, k: int = 0) -> Rect:
    """An axis-aligned rectangle given by its extents, then turned by k quarter turns about the origin.

    Quarter turns are applied with integer cos/sin and a swap of the sizes, so walls on every side keep
    exact coordinates (a float rotation by ``k·π/2`` would leave 1e-16 m crumbs in the geometry).
    """
    c, s = _QUARTER_TURNS[k % 4]
    cx, cy = (x_min + x_max) / 2.0, (y_min + y_max) / 2.0
    sx, sy = x_max - x_min, y_max - y_min
    size = (sx, sy) if k % 2 == 0 else (sy, sx)
    return Rect((c * cx - s * cy, s * cx + c * cy), size, 0.0)


def ring_of_walls(inner_half_m: float) -> list[Rect]:
    """Four walls whose inner faces are at ±inner_half_m; each spans the full outer width.

    Spanning the outer width makes neighbouring walls overlap in the corner squares, so a beam aimed at
    a corner can never slip through a gap.
    """
    outer = inner_half_m + WALL_THICKNESS_M
    return [_axis_rect(inner_half_m, outer, -outer, outer, k) for k in range(4)]


def room_wall_rects(door: Doorway) -> list[Rect]:
    """Floor rectangles of the inner room walls with the doorway cut out.

    The door is cut, centred, from the +x wall and that wall is turned by ``door.wall_k`` quarter turns,
    which is exactly how :attr:`Doorway.opening` and :attr:`Doorway.frame` place the opening.
    """
    half = door.room_half_m
    outer = half + WALL_THICKNESS_M
    half_door = door.width_m / 2.0
    if not 0.0 < half_door < half:
        raise ValueError(f"door width {door.width_m} m does not fit in a {2 * half} m wall")
    k = door.wall_k % 4
    walls = [
        _axis_rect(half, outer, -outer, -half_door, k),
        _axis_rect(half, outer, half_door, outer, k),
    ]
    walls += [_axis_rect(half, outer, -outer, outer, k + j) for j in (1, 2, 3)]
    return walls


def enclosure_rects(room_half_m: float = ROOM_HALF_M) -> list[Rect]:
    """Floor rectangles of the closed outer enclosure, seen through the doorway: as far outside the
    room's walls as the paper's enclosure is outside its room."""
    return ring_of_walls(room_half_m + OUTER_HALF_M - ROOM_HALF_M)


def _rects_overlap(a: Rect, b: Rect) -> bool:
    """Separating-axis test for two oriented rectangles (touching counts as overlapping)."""
    ca, cb = a.corners(), b.corners()
    for yaw in (a.yaw, a.yaw + math.pi / 2, b.yaw, b.yaw + math.pi / 2):
        axis = np.array([math.cos(yaw), math.sin(yaw)])
        pa, pb = ca @ axis, cb @ axis
        if pa.max() < pb.min() or pb.max() < pa.min():
            return False
    return True


def _inside_placement_area(rect: Rect) -> bool:
    return bool(np.all(np.abs(rect.corners()) <= PLACEMENT_HALF_M))


def _sample_yaw(rng: np.random.Generator, axis_aligned: bool) -> float:
    if axis_aligned:
        return float(rng.integers(0, 4)) * math.pi / 2.0
    return float(rng.uniform(0.0, 2.0 * math.pi))


def _sample_furniture(rng: np.random.Generator, class_id: int, yaw: float) -> Furniture:
    """Draw one object's size at a random centre; placement is checked by the caller."""
    center = (
        float(rng.uniform(-PLACEMENT_HALF_M, PLACEMENT_HALF_M)),
        float(rng.uniform(-PLACEMENT_HALF_M, PLACEMENT_HALF_M)),
    )
    if class_id == CHAIR:
        s = float(rng.uniform(0.8, 1.2))  # one factor: chairs stay square
        return Furniture(CHAIR, Rect(center, (0.4 * s, 0.4 * s), yaw), height_m=0.4, leg_size_m=0.03)
    if class_id == DESK:
        size = (0.8 * float(rng.uniform(0.8, 1.2)), 1.6 * float(rng.uniform(0.8, 1.2)))
        return Furniture(DESK, Rect(center, size, yaw), height_m=0.74, leg_size_m=0.05)
    if class_id == BOX:
        size = (0.4 * float(rng.uniform(0.8, 1.2)), 0.6 * float(rng.uniform(0.8, 1.2)))
        return Furniture(BOX, Rect(center, size, yaw), height_m=0.4)
    raise ValueError(f"class {class_id} is not a piece of furniture")


def _try_arrangement(rng: np.random.Generator, axis_aligned: bool) -> list[Furniture] | None:
    """Place desk, box and chair (hardest first) with a few draws each; None when one does not fit."""
    placed: list[Furniture] = []
    for class_id in (DESK, BOX, CHAIR):
        for _ in range(PLACEMENT_DRAWS_PER_OBJECT):
            candidate = _sample_furniture(rng, class_id, _sample_yaw(rng, axis_aligned))
            grown = candidate.footprint.inflated(PLACEMENT_MARGIN_M)
            if _inside_placement_area(grown) and not any(
                _rects_overlap(grown, other.footprint.inflated(PLACEMENT_MARGIN_M)) for other in placed
            ):
                placed.append(candidate)
                break
        else:
            return None
    return placed


def sample_scenario(index: int, seed: int, room_half_m: float = ROOM_HALF_M) -> Scenario:
    """Draw scenario ``index`` of the data set seeded ``seed``; the same pair always gives the same world.

    Each scenario owns its random stream (``SeedSequence([seed, index])``), so scenarios can be made
    in any order, by any number of workers, and still come out identical. ``room_half_m`` moves the
    walls out (an open-space room) and changes nothing else the stream draws.
    """
    if room_half_m < ROOM_HALF_M:
        raise ValueError(f"a room's half-width must be at least {ROOM_HALF_M} m, got {room_half_m}")
    rng = np.random.default_rng(np.random.SeedSequence([seed, index]))
    door = Doorway(int(rng.integers(0, 4)), float(rng.uniform(0.5, 1.0)), room_half_m)
    axis_aligned = bool(rng.random() < 0.25)
    # Rejection sampling of the whole arrangement: a desk placed in the middle can leave no room for
    # the others, so a stuck arrangement is dropped and drawn again rather than retried object by object.
    for _ in range(MAX_PLACEMENT_TRIES):
        placed = _try_arrangement(rng, axis_aligned)
        if placed is not None:
            break
    else:  # pragma: no cover - only a broken configuration of the constants gets here
        raise RuntimeError(f"scenario {index}: no arrangement found in {MAX_PLACEMENT_TRIES} tries")
    placed.sort(key=lambda o: o.class_id)
    return Scenario(index, seed, door, tuple(placed), axis_aligned)


def free_grid_cells(scenario: Scenario) -> np.ndarray:
    """Robot centres on the 0.1 m grid over [-1.75, 1.75]^2 that keep the world's clearances.

    Besides 0.22 m from every leg and 0.175 m from the box, the robot also stays out from under the
    chair and desk tops: from inside a footprint the object surrounds the sensor and its label box
    would be the whole image, which is no detection target.
    """
    n = round(2 * ROBOT_GRID_HALF_M / ROBOT_GRID_STEP_M) + 1
    axis = np.linspace(-ROBOT_GRID_HALF_M, ROBOT_GRID_HALF_M, n)
    cells = np.stack(np.meshgrid(axis, axis, indexing="xy"), axis=-1).reshape(-1, 2)
    return free_of_objects(scenario, cells)


def door_watch_cells(scenario: Scenario, nearest_m: float = 0.6, farthest_m: float = 1.6) -> np.ndarray:
    """Free robot centres in front of the doorway, inside the room, ``nearest_m``–``farthest_m`` from
    the door wall and at most 0.5 m to either side of the door's centre line (any room size).

    From there a robot looks out through the doorway at close range, as robots parked by a door or a
    gap in a partition do: people beyond it show only through the opening.
    """
    half = scenario.door.room_half_m
    outs = np.arange(half - farthest_m, half - nearest_m + 1e-9, ROBOT_GRID_STEP_M)
    sides = np.arange(-0.5, 0.5 + 1e-9, ROBOT_GRID_STEP_M)
    grid = np.stack(np.meshgrid(outs, sides, indexing="xy"), axis=-1).reshape(-1, 2)
    normal, along = scenario.door.axes
    return free_of_objects(scenario, grid[:, :1] * normal + grid[:, 1:] * along)


def free_of_objects(scenario: Scenario, cells: np.ndarray) -> np.ndarray:
    """The robot centres among ``cells`` (float64[N, 2]) that keep the clearances of
    :func:`free_grid_cells` from every object."""
    free = np.ones(len(cells), dtype=bool)
    for obj in scenario.objects:
        if obj.has_legs:
            free &= obj.footprint.distance(cells) > 0.0
            for leg in obj.leg_rects():
                free &= leg.distance(cells) >= LEG_CLEARANCE_M
        else:
            free &= obj.footprint.distance(cells) >= BOX_CLEARANCE_M
    return cells[free]


def check_share(share: float, what: str) -> float:
    """``share`` back when it is a share (of scenarios, of motions), in [0, 1]; else a one-line
    ``ValueError`` naming ``what`` it is the share of."""
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"the {what} share must lie in [0, 1], got {share}")
    return share


def check_open_space(share: float) -> float:
    """``share`` back when it is a share of scenarios, in [0, 1]; else a one-line ``ValueError``."""
    return check_share(share, "open-space")


def room_half_of(seed: int, index: int, open_space: float) -> float:
    """Scenario ``index``'s room half-width: an open-space one (:data:`OPEN_SPACE_HALF_M`) for a share
    ``open_space`` of scenarios, else the paper's, drawn from the scenario's own stream
    (``[seed, index, 6]``) so that the rest of its world, motions and noise stay as they were."""
    if check_open_space(open_space) == 0.0:
        return ROOM_HALF_M
    rng = np.random.default_rng(np.random.SeedSequence([seed, index, 6]))
    if rng.random() >= open_space:
        return ROOM_HALF_M
    return float(rng.uniform(*OPEN_SPACE_HALF_M))


def sample_robot_positions(scenario: Scenario, count: int, rng: np.random.Generator) -> np.ndarray:
    """Up to ``count`` free cells at least 0.25 m apart, in random order, as float64[K, 2].

    Greedy acceptance over a shuffled candidate list: cheap, deterministic for a seed, and it spreads
    the positions over the whole free space.
    """
    cells = free_grid_cells(scenario)
    chosen: list[np.ndarray] = []
    for cell in cells[rng.permutation(len(cells))]:
        if all(np.hypot(*(cell - c)) >= MIN_POSITION_SPACING_M - 1e-9 for c in chosen):
            chosen.append(cell)
            if len(chosen) == count:
                break
    return np.array(chosen, dtype=np.float64).reshape(-1, 2)


def sample_waypoints(
    scenario: Scenario,
    start: np.ndarray,
    rng: np.random.Generator,
    count: int = 2,
    min_step_m: float = 0.1,
    max_step_m: float = 0.2,
) -> list[tuple[float, float]]:
    """``count`` waypoints, each a free cell 0.1–0.2 m from the previous one (the data set's short motion)."""
    cells = free_grid_cells(scenario)
    points: list[tuple[float, float]] = []
    current = np.asarray(start, dtype=np.float64)
    for _ in range(count):
        d = np.hypot(*(cells - current).T)
        near = cells[(d >= min_step_m - 1e-9) & (d <= max_step_m + 1e-9)]
        if len(near) == 0:
            break
        current = near[rng.integers(0, len(near))]
        points.append((float(current[0]), float(current[1])))
    return points
