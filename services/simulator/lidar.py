"""A 2D LiDAR (ROBOTIS LDS-01 by default, README "The simulated world") ray-cast in a ``World``.

The reading mirrors ROS ``sensor_msgs/LaserScan``: beam i has bearing ``angle_min + i·angle_increment``,
counter-clockwise from the sensor's forward axis (REP-103), and a return that is missing or outside
[range_min, range_max] is published as ``inf``, as real drivers do; the encoder maps those to its
sentinel row. Besides the noisy ranges the reading keeps the noise-free ranges and the id of the object
each beam hit, which the labeller needs ("at least 2 beams hit it", README "Labels").

All beams of one scan go to PyBullet in one ``rayTestBatch`` call; noise comes from the caller's seeded
generator and is drawn for every beam on every scan, so the random stream advances identically
whatever the scene and the same seed reproduces the same ranges byte for byte.

Real sensors are worse than Gaussian noise, and a model trained on clean scans is fragile exactly
there: dark or shiny surfaces return nothing (``dropout_rate``: a beam comes back invalid), dust and
mixed pixels return something short (``spurious_rate``: a beam comes back at a random range before
its true hit). Both are drawn from a second stream spawned from the caller's generator, so turning
them on leaves the Gaussian noise of every beam exactly as it was: the same world under several
imperfection settings differs only by the imperfections.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pybullet as p

from services.simulator.clutter import CLUTTER_OBJECT, Clutter, clutter_distances
from services.simulator.people import Person, people_distances
from services.simulator.robot import Pose
from services.simulator.sensors import DEFAULT_SPEC, LidarSpec
from services.simulator.world import World

# PyBullet rejects batches above MAX_RAY_INTERSECTION_BATCH_SIZE (16384 in 3.2.7) and, in 3.2.7,
# silently returns no results for a batch of exactly that size; one ray less is always safe.
RAY_BATCH_LIMIT = int(getattr(p, "MAX_RAY_INTERSECTION_BATCH_SIZE", 1024)) - 1


# The LiDAR imperfections ``triscan eval --noise`` measures a model under (the model card's conditions):
# a name here, or the same ``key=value`` text directly.
IMPERFECTION_KEYS: dict[str, str] = {
    "sigma": "noise_sigma_m",
    "dropout": "dropout_rate",
    "spurious": "spurious_rate",
}
NAMED_IMPERFECTIONS: dict[str, str] = {
    "clean": "",
    "sigma3": "sigma=0.03",
    "drop5": "dropout=0.05",
    "drop5+sigma3": "sigma=0.03,dropout=0.05",
    "drop10+sigma3+spur1": "sigma=0.03,dropout=0.10,spurious=0.01",
}


def with_imperfections(text: str, spec: LidarSpec = DEFAULT_SPEC) -> LidarSpec:
    """``spec`` with the imperfections of ``text``: a name of :data:`NAMED_IMPERFECTIONS` or
    ``sigma=0.03,dropout=0.05,spurious=0.01`` (any subset; σ in metres, rates as shares)."""
    text = NAMED_IMPERFECTIONS.get(text, text)
    changes: dict[str, Any] = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        key, sep, value = item.partition("=")
        if not sep or key.strip() not in IMPERFECTION_KEYS:
            raise ValueError(
                f"imperfection {item!r}: use one of {sorted(NAMED_IMPERFECTIONS)} or "
                f"key=value with keys {sorted(IMPERFECTION_KEYS)} (e.g. sigma=0.03,dropout=0.05)"
            )
        try:
            changes[IMPERFECTION_KEYS[key.strip()]] = float(value)
        except ValueError:
            raise ValueError(f"imperfection {item!r}: {value!r} is not a number") from None
    return replace(spec, **changes)  # LidarSpec checks the ranges


@dataclass(frozen=True)
class LidarReading:
    """One scan with its ground truth.

    ``ranges`` is what the sensor publishes; ``true_ranges`` and ``hit_object`` describe the first
    surface along each beam without noise, so a beam whose noisy range fell out of bounds still records
    what it hit. ``hit_object``: furniture index in ``scenario.objects``, -1 wall, -2 nothing within
    ``range_max``.
    """

    ranges: np.ndarray  # float32[N], noisy, inf where invalid
    true_ranges: np.ndarray  # float64[N], inf where nothing within range_max
    hit_object: np.ndarray  # int16[N]
    lidar_pose: Pose
    people_legs: tuple[tuple[tuple[float, float, float], ...], ...] = ()  # each person's leg circles


def lidar_pose(robot_pose: Pose, spec: LidarSpec = DEFAULT_SPEC) -> Pose:
    """Sensor pose in the world: the mount offset is along the robot's forward axis, yaw unchanged.

    The 3 cm offset matters for labels: bearings and ranges are measured from here, not from the robot
    centre, and a rotation in place moves the sensor on a small circle.
    """
    x, y, yaw = robot_pose
    c, s = math.cos(yaw), math.sin(yaw)
    return (x + spec.mount_offset_x_m * c, y + spec.mount_offset_x_m * s, yaw)


class Lidar:
    """Ray-casts a :class:`LidarSpec` in a :class:`World` and adds seeded Gaussian range noise.

    The generator is required rather than defaulted: every scan of the dataset must be reproducible
    from its seed, and a hidden default seed would make two sensors silently share one noise stream.
    """

    def __init__(self, world: World, spec: LidarSpec = DEFAULT_SPEC, *, rng: np.random.Generator) -> None:
        self.world = world
        self.spec = spec
        self.rng = rng
        self.fault_rng = rng.spawn(1)[0]  # dropouts and spurious returns: never shifts the noise stream
        bearings = spec.bearings_rad
        self._cos_b = np.cos(bearings)
        self._sin_b = np.sin(bearings)

    def pose_of(self, robot_pose: Pose) -> Pose:
        """Sensor pose for a robot pose under this sensor's mount offset."""
        return lidar_pose(robot_pose, self.spec)

    def cast(self, sensor_pose: Pose) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free first hits from a sensor pose: (true ranges float64[N] with inf, body ids int64[N]).

        Rays start at the sensor origin and end at ``range_max``; PyBullet's hit fraction times
        ``range_max`` is then the distance. Batches above PyBullet's limit are split (only a
        >16k-beam sensor would need it).
        """
        self.world.require_open()
        spec = self.spec
        x, y, yaw = sensor_pose
        c, s = math.cos(yaw), math.sin(yaw)
        starts = np.empty((spec.beams, 3))
        starts[:] = (x, y, spec.mount_height_m)
        ends = starts.copy()
        ends[:, 0] += spec.range_max * (c * self._cos_b - s * self._sin_b)
        ends[:, 1] += spec.range_max * (s * self._cos_b + c * self._sin_b)
        body_ids: list[int] = []
        fractions: list[float] = []
        for first in range(0, spec.beams, RAY_BATCH_LIMIT):
            last = first + RAY_BATCH_LIMIT
            results = p.rayTestBatch(
                starts[first:last], ends[first:last], numThreads=1, physicsClientId=self.world.client_id
            )
            # Transpose the per-ray tuples in C: (ids, links, fractions, positions, normals).
            ids, _links, fracs, _positions, _normals = zip(*results, strict=True)
            body_ids.extend(ids)
            fractions.extend(fracs)
        bodies = np.asarray(body_ids, dtype=np.int64)
        true_ranges = np.where(bodies >= 0, np.asarray(fractions, dtype=np.float64) * spec.range_max, np.inf)
        return true_ranges, bodies

    def scan(
        self,
        robot_pose: Pose,
        clutter: tuple[Clutter, ...] = (),
        t_s: float = 0.0,
        people: tuple[Person, ...] = (),
    ) -> LidarReading:
        """One scan from a robot pose (the sensor offset is applied here), with ``clutter`` and
        ``people`` as they stand at ``t_s``.

        Both are merged with the world's first hits before any noise: a beam stopped by clutter has
        the clutter's true range and object index ``CLUTTER_OBJECT``, so it counts for no label; a
        beam stopped by a leg of person k has :func:`services.simulator.people.leg_object` of it.
        """
        spec = self.spec
        sensor_pose = self.pose_of(robot_pose)
        true_ranges, bodies = self.cast(sensor_pose)
        hit_object = self.world.hit_object(bodies)
        if clutter or people:
            angles = sensor_pose[2] + spec.bearings_rad
            directions = np.stack([np.cos(angles), np.sin(angles)], axis=1)
        if clutter:
            blocked = clutter_distances(clutter, sensor_pose[:2], directions, t_s)
            closer = blocked < np.minimum(true_ranges, spec.range_max)
            true_ranges = np.where(closer, blocked, true_ranges)
            hit_object = np.where(closer, CLUTTER_OBJECT, hit_object).astype(hit_object.dtype)
        if people:
            blocked, legs = people_distances(people, sensor_pose[:2], directions, t_s)
            closer = blocked < np.minimum(true_ranges, spec.range_max)
            true_ranges = np.where(closer, blocked, true_ranges)
            hit_object = np.where(closer, legs, hit_object).astype(hit_object.dtype)
        # Always draw N samples, even where there is no return, so the stream does not depend on the scene.
        noisy = true_ranges + self.rng.normal(0.0, spec.noise_sigma_m, size=spec.beams)
        if spec.dropout_rate > 0.0 or spec.spurious_rate > 0.0:
            draws = self.fault_rng.random((3, spec.beams))  # all three every scan, whatever the rates
            reach = np.minimum(true_ranges, spec.range_max)
            spurious = draws[0] < spec.spurious_rate
            noisy = np.where(spurious, spec.range_min + draws[1] * (reach - spec.range_min), noisy)
            noisy = np.where(draws[2] < spec.dropout_rate, np.inf, noisy)
        valid = (noisy >= spec.range_min) & (noisy <= spec.range_max)  # inf and NaN fail both
        ranges = np.where(valid, noisy, np.inf).astype(np.float32)
        return LidarReading(
            ranges=ranges,
            true_ranges=true_ranges,
            hit_object=hit_object,
            lidar_pose=sensor_pose,
            people_legs=tuple(tuple(person.legs(t_s)) for person in people),
        )
