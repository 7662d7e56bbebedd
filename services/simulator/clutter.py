"""Non-target clutter for domain-randomised data: thin poles and short wall stubs.

Real rooms hold things that are none of the classes, and the ones that fool a scan detector look like
them: a lone pole is one chair leg (or one person's leg), a wall stub is a box side. Clutter appears in
the scans and is never labelled, so the network learns to tell them apart. People are not clutter:
they are labelled (:mod:`services.simulator.people`).

Clutter is ray-cast in closed form here rather than added to the PyBullet world: it changes with every
robot motion and legs move with every scan, and PyBullet leaks memory on every body removed or
collision shape created (see :mod:`services.simulator.world`). Circles and oriented rectangles are
intersected with all beams at once in numpy, exactly, and merged with the world's first hits by the
LiDAR (:meth:`services.simulator.lidar.Lidar.scan`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from services.simulator.scenario import Rect, Scenario

CLUTTER_OBJECT = -3  # object index of a beam that hit clutter (-1 wall, -2 nothing: world.py)
FURNITURE_CLEARANCE_M = 0.08  # clutter never touches furniture (a pole against a leg would change its shape)
ROBOT_CLEARANCE_M = 0.35  # nor comes near the robot's own path
ROOM_MARGIN_M = 0.1  # and stays inside the room, off the walls
PLACEMENT_TRIES = 30
KINDS = ("pole", "stub")


@dataclass(frozen=True)
class Pole:
    """A thin vertical cylinder (lamp stand, coat rack, table base): one chair-leg-like return."""

    center: tuple[float, float]
    radius_m: float

    def circles(self, t_s: float) -> list[tuple[float, float, float]]:
        return [(self.center[0], self.center[1], self.radius_m)]

    def rects(self, t_s: float) -> list[Rect]:
        return []

    def path(self, duration_s: float) -> np.ndarray:
        return np.array([self.center])

    @property
    def extent_m(self) -> float:
        return self.radius_m


@dataclass(frozen=True)
class WallStub:
    """A short free-standing wall piece (partition, shelf side): a straight return like a box face."""

    rect: Rect

    def circles(self, t_s: float) -> list[tuple[float, float, float]]:
        return []

    def rects(self, t_s: float) -> list[Rect]:
        return [self.rect]

    def path(self, duration_s: float) -> np.ndarray:
        return np.array([self.rect.center])

    @property
    def extent_m(self) -> float:
        return math.hypot(*self.rect.size) / 2.0


Clutter = Pole | WallStub


def ray_circle_distances(
    origin: tuple[float, float], directions: np.ndarray, circles: np.ndarray
) -> np.ndarray:
    """Distance along each unit ray ``float64[N, 2]`` to its first circle ``float64[K, 3]`` (x, y, r).

    ``inf`` where a ray meets none. The sensor is never inside a circle (placement keeps clear).
    """
    if len(circles) == 0:
        return np.full(len(directions), np.inf)
    to_centre = circles[:, :2] - np.asarray(origin)  # [K, 2]
    along = directions @ to_centre.T  # [N, K]: projection of the centre on the ray
    closest_sq = (to_centre**2).sum(axis=1)[None, :] - along**2
    inside = circles[:, 2][None, :] ** 2 - closest_sq
    with np.errstate(invalid="ignore"):
        t = along - np.sqrt(inside)
    hit = (inside >= 0.0) & (t > 0.0)
    return np.where(hit, t, np.inf).min(axis=1)


def ray_rect_distances(
    origin: tuple[float, float], directions: np.ndarray, rects: Sequence[Rect]
) -> np.ndarray:
    """Distance along each unit ray ``float64[N, 2]`` to its first oriented rectangle (slab method)."""
    best = np.full(len(directions), np.inf)
    for rect in rects:
        c, s = math.cos(rect.yaw), math.sin(rect.yaw)
        local_origin = rect.to_local(np.asarray(origin))
        local_dir = np.stack(
            [directions[:, 0] * c + directions[:, 1] * s, -directions[:, 0] * s + directions[:, 1] * c],
            axis=1,
        )
        half = np.asarray(rect.size) / 2.0
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-half - local_origin) / local_dir
            t2 = (half - local_origin) / local_dir
        # A ray parallel to a slab is inside it for all t (or never): the ±inf/NaN of 0-division say so.
        parallel = local_dir == 0.0
        inside_slab = np.abs(local_origin) <= half
        t_lo = np.where(parallel, np.where(inside_slab, -np.inf, np.inf), np.minimum(t1, t2))
        t_hi = np.where(parallel, np.where(inside_slab, np.inf, -np.inf), np.maximum(t1, t2))
        enter, leave = t_lo.max(axis=1), t_hi.min(axis=1)
        hit = (enter <= leave) & (enter > 0.0)
        best = np.minimum(best, np.where(hit, enter, np.inf))
    return best


def clutter_distances(
    clutter: Sequence[Clutter], sensor_xy: tuple[float, float], directions: np.ndarray, t_s: float
) -> np.ndarray:
    """First-hit distance of every beam on the clutter at time ``t_s`` (``inf`` where none)."""
    circles = np.array([c for item in clutter for c in item.circles(t_s)], dtype=np.float64).reshape(-1, 3)
    rects = [r for item in clutter for r in item.rects(t_s)]
    return np.minimum(
        ray_circle_distances(sensor_xy, directions, circles), ray_rect_distances(sensor_xy, directions, rects)
    )


def _draw_item(kind: str, rng: np.random.Generator, room_half_m: float) -> Clutter:
    lim = room_half_m - ROOM_MARGIN_M
    centre = (float(rng.uniform(-lim, lim)), float(rng.uniform(-lim, lim)))
    if kind == "pole":
        return Pole(centre, float(rng.uniform(0.01, 0.03)))
    size = (float(rng.uniform(0.1, 0.5)), float(rng.uniform(0.02, 0.12)))
    return WallStub(Rect(centre, size, float(rng.uniform(0.0, math.pi))))


def _fits(item: Clutter, scenario: Scenario, robot_path: np.ndarray, duration_s: float) -> bool:
    path = item.path(duration_s)
    extent = item.extent_m
    if np.any(np.abs(path) > scenario.room_half_m - ROOM_MARGIN_M - extent):
        return False
    for obj in scenario.objects:
        if np.any(obj.footprint.distance(path) < FURNITURE_CLEARANCE_M + extent):
            return False
    gaps = np.hypot(*(path[:, None, :] - robot_path[None, :, :2]).transpose(2, 0, 1))
    return bool(np.all(gaps >= ROBOT_CLEARANCE_M + extent))


def sample_clutter(
    scenario: Scenario,
    robot_path: np.ndarray,
    duration_s: float,
    max_items: int,
    rng: np.random.Generator,
) -> list[Clutter]:
    """Between 0 and ``max_items`` clutter items for one robot motion, none touching furniture or robot.

    ``robot_path`` is float64[T, ≥2] of the robot's positions over the motion. An item that does not
    fit after a few draws is left out, so a crowded room simply gets less clutter.
    """
    if max_items <= 0:
        return []
    placed: list[Clutter] = []
    for _ in range(int(rng.integers(0, max_items + 1))):
        kind = KINDS[int(rng.integers(0, len(KINDS)))]
        for _ in range(PLACEMENT_TRIES):
            item = _draw_item(kind, rng, scenario.room_half_m)
            if _fits(item, scenario, robot_path, duration_s):
                placed.append(item)
                break
    return placed
