"""The PyBullet scene of README "The simulated world": room, doorway, enclosure, one chair, box and desk.

PyBullet is used here only as a ray caster: every body is static (mass 0), there is no floor, no
gravity and no robot body, so the scan plane at 0.173 m sees exactly the wall faces, the chair and
desk legs, and the box. Each body is a *static triangle mesh* of closed cuboids rather than a
``GEOM_BOX``: Bullet ray-casts convex boxes with an iterative GJK cast that is off by up to centimetres
near edges and corners (measured on 100k random rays: 99.9th percentile 2 mm, worst 6 cm, and
hit/miss disagreements for rays passing centimetres from a corner), whereas triangle meshes are
intersected in closed form (worst 0.15 mm, only on rays grazing an edge within 0.2 mm). Legs are 3 cm
wide, so that difference decides which beams see them.

Each :class:`World` owns its own physics client, so several worlds can live in one process (dataset
workers each build one); every PyBullet call therefore names ``physicsClientId``. Frames follow ROS
REP-103: x forward, y left, z up, yaw counter-clockwise in radians.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from types import TracebackType

import numpy as np
import pybullet as p

from services.simulator.scenario import (
    ROOM_HALF_M,
    WALL_HEIGHT_M,
    Furniture,
    Rect,
    Scenario,
    enclosure_rects,
    ring_of_walls,
    room_wall_rects,
)

log = logging.getLogger(__name__)

TOP_THICKNESS_M = 0.03  # chair and desk top slab; it lies above the scan plane but exists
WALL_OBJECT = -1  # object index of a room wall or the enclosure
NO_HIT = -2  # object index of a beam that hit nothing (PyBullet reports body id -1)


# Twelve outward-facing triangles of a cuboid whose corners are numbered bottom 0-3 then top 4-7,
# each ring counter-clockwise seen from above (the order Rect.corners returns).
_CUBOID_TRIANGLES = np.array(
    [
        [0, 2, 1], [0, 3, 2],  # bottom
        [4, 5, 6], [4, 6, 7],  # top
        [0, 1, 5], [0, 5, 4],
        [1, 2, 6], [1, 6, 5],
        [2, 3, 7], [2, 7, 6],
        [3, 0, 4], [3, 4, 7],
    ],
    dtype=np.int32,
)  # fmt: skip


@dataclass(frozen=True)
class Cuboid:
    """A vertical prism: an oriented floor rectangle extruded from ``z_min_m`` to ``z_max_m``."""

    footprint: Rect
    z_min_m: float
    z_max_m: float

    def vertices(self) -> np.ndarray:
        """The eight corners as float64[8, 3], bottom ring then top ring (see ``_CUBOID_TRIANGLES``)."""
        xy = self.footprint.corners()
        bottom = np.column_stack([xy, np.full(4, self.z_min_m)])
        top = np.column_stack([xy, np.full(4, self.z_max_m)])
        return np.concatenate([bottom, top])


def furniture_cuboids(obj: Furniture) -> list[Cuboid]:
    """The solid parts of one object in 3D.

    Legs run from the floor to the underside of a top slab, so the scan plane at 0.173 m meets only the
    legs while the slab still exists (a future tilted or higher sensor would see it). The box is one
    solid cuboid of its full height.
    """
    if not obj.has_legs:
        return [Cuboid(obj.footprint, 0.0, obj.height_m)]
    leg_top = obj.height_m - TOP_THICKNESS_M
    if leg_top <= 0.0:
        raise ValueError(f"top at {obj.height_m} m is not above its {TOP_THICKNESS_M} m slab")
    parts = [Cuboid(leg, 0.0, leg_top) for leg in obj.solid_rects()]
    parts.append(Cuboid(obj.footprint, leg_top, obj.height_m))
    return parts


def _wall_cuboids(rects: Iterable[Rect]) -> list[Cuboid]:
    return [Cuboid(r, 0.0, WALL_HEIGHT_M) for r in rects]


class World:
    """One PyBullet client holding the static scene of one scenario at a time.

    :meth:`load` rebuilds the whole scene after ``resetSimulation``. Removing and re-adding only the
    changed bodies was faster (1.7 ms against 2.3 ms a load) but in PyBullet 3.2.7 ``removeBody`` never
    frees a body's native memory (measured 14 KB per box body, 16 KB per mesh body), which a dataset
    worker loading thousands of scenarios cannot afford. A reset also restarts body ids at 0, so one
    scenario always gets the same ids whatever was loaded before.

    Known residue: ``createCollisionShape`` keeps an extra reference to every vertex row and coordinate
    it is given, so about 38 KB of Python floats stay alive per load whatever we do (also across
    ``disconnect``); a long-running process that loads many thousands of scenarios should be recycled.
    """

    def __init__(self, scenario: Scenario | None = None) -> None:
        self.client_id: int = p.connect(p.DIRECT)
        if self.client_id < 0:
            raise RuntimeError("could not start a PyBullet DIRECT client")
        self.scenario: Scenario | None = None
        # Indexed by PyBullet body unique id: furniture index, or WALL_OBJECT for the walls and enclosure.
        self.object_index_of_body: np.ndarray = np.zeros(0, dtype=np.int16)
        try:
            self.load(scenario)
        except Exception:
            self.close()  # a half-built world would otherwise hold its client until the process ends
            raise

    def __enter__(self) -> World:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        """Disconnect the client; safe to call twice so ``with`` and explicit close can be mixed."""
        if self.client_id >= 0:
            p.disconnect(physicsClientId=self.client_id)
            self.client_id = -1

    def load(self, scenario: Scenario | None) -> None:
        """Replace the scene with ``scenario``'s; ``None`` builds the room without doorway or furniture.

        The empty closed room is for tools and tests that want every beam from inside to return.
        """
        self.require_open()
        p.resetSimulation(physicsClientId=self.client_id)
        wall_rects = (
            enclosure_rects(scenario.room_half_m) + room_wall_rects(scenario.door)
            if scenario
            else enclosure_rects() + ring_of_walls(ROOM_HALF_M)
        )
        walls = self._add_static_mesh(_wall_cuboids(wall_rects))
        objects = scenario.objects if scenario else ()
        furniture = [self._add_static_mesh(furniture_cuboids(obj)) for obj in objects]
        lookup = np.full(max([walls, *furniture]) + 1, WALL_OBJECT, dtype=np.int16)
        lookup[furniture] = np.arange(len(furniture), dtype=np.int16)
        self.object_index_of_body = lookup
        self.scenario = scenario
        if scenario is not None:
            log.debug("loaded scenario %d (door on wall %d)", scenario.index, scenario.door.wall_k)

    def hit_object(self, body_ids: np.ndarray) -> np.ndarray:
        """Map ray-result body ids to furniture indices: ≥0 furniture, -1 wall, -2 no hit (id -1)."""
        ids = np.asarray(body_ids, dtype=np.int64)
        out = np.full(ids.shape, NO_HIT, dtype=np.int16)
        hit = ids >= 0
        out[hit] = self.object_index_of_body[ids[hit]]
        return out

    def require_open(self) -> None:
        """Fail loudly: PyBullet calls on a closed client raise an unhelpful "not connected" error."""
        if self.client_id < 0:
            raise RuntimeError("this World is closed")

    def _add_static_mesh(self, parts: Sequence[Cuboid]) -> int:
        """One static body made of closed cuboids, as a concave triangle mesh (see module docstring)."""
        vertices = np.concatenate([part.vertices() for part in parts])
        triangles = np.concatenate([_CUBOID_TRIANGLES + 8 * i for i in range(len(parts))])
        shape = p.createCollisionShape(
            p.GEOM_MESH,
            vertices=vertices.tolist(),
            indices=triangles.ravel().tolist(),
            flags=p.GEOM_FORCE_CONCAVE_TRIMESH,
            physicsClientId=self.client_id,
        )
        if shape < 0:
            raise RuntimeError("PyBullet refused a collision mesh")
        body = p.createMultiBody(baseMass=0.0, baseCollisionShapeIndex=shape, physicsClientId=self.client_id)
        if body < 0:
            raise RuntimeError("PyBullet refused a static body")
        return body
