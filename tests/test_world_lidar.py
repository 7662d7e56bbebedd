"""The PyBullet world and the LiDAR model against distances computed by hand and by a 2D ray caster.

The reference ray caster below is independent of ``world.py``: it intersects rays with the scenario's
``Rect`` footprints by the slab method and builds the door wall from ``Doorway.opening``, so a wrong
wall placement, a gap in a corner, a visible table top or a misplaced leg in the PyBullet scene all
show up as range mismatches.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest

from services.simulator.lidar import RAY_BATCH_LIMIT, Lidar, LidarReading, LidarSpec, lidar_pose
from services.simulator.scenario import (
    BOX,
    CHAIR,
    DESK,
    OUTER_HALF_M,
    ROOM_HALF_M,
    WALL_THICKNESS_M,
    Doorway,
    Furniture,
    Rect,
    Scenario,
)
from services.simulator.world import NO_HIT, WALL_OBJECT, World

EXACT = LidarSpec(noise_sigma_m=0.0)
OFFSET = -EXACT.mount_offset_x_m  # 0.03 m: the sensor sits behind the robot centre


def chair(center: tuple[float, float], yaw: float = 0.0, side: float = 0.4) -> Furniture:
    return Furniture(CHAIR, Rect(center, (side, side), yaw), 0.4, 0.03)


def desk(center: tuple[float, float], yaw: float = 0.0, size: tuple[float, float] = (0.8, 1.6)) -> Furniture:
    return Furniture(DESK, Rect(center, size, yaw), 0.74, 0.05)


def box(center: tuple[float, float], yaw: float = 0.0, size: tuple[float, float] = (0.4, 0.6)) -> Furniture:
    return Furniture(BOX, Rect(center, size, yaw), 0.4)


def scenario(door_k: int = 2, door_width: float = 0.8, objects: tuple[Furniture, ...] = ()) -> Scenario:
    return Scenario(index=0, seed=0, door=Doorway(door_k, door_width), objects=objects)


def scan_exact(world: World, robot_pose: tuple[float, float, float], spec: LidarSpec = EXACT) -> LidarReading:
    return Lidar(world, spec, rng=np.random.default_rng(0)).scan(robot_pose)


# --- an independent 2D reference ray caster --------------------------------------------------------


def ray_rect(origin: tuple[float, float], angles: np.ndarray, rect: Rect, grow: float = 0.0) -> np.ndarray:
    """Distance along each ray to a filled rectangle (slab method), inf on a miss; ``grow`` inflates it."""
    local_origin = rect.to_local(np.asarray(origin))
    rel = angles - rect.yaw
    d = np.stack([np.cos(rel), np.sin(rel)], axis=-1)
    half = np.asarray(rect.size) / 2.0 + grow
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - local_origin) / d
        t2 = (half - local_origin) / d
    near = np.nanmax(np.minimum(t1, t2), axis=-1)
    far = np.nanmin(np.maximum(t1, t2), axis=-1)
    return np.where((far >= near) & (near >= 0.0), near, np.inf)


def wall_rects(door: Doorway | None) -> list[Rect]:
    """Room and enclosure walls as floor rectangles; the door gap is taken from ``Doorway.opening``."""
    rects = []
    room = door.room_half_m if door is not None else ROOM_HALF_M
    for half, is_room in ((room, True), (room + OUTER_HALF_M - ROOM_HALF_M, False)):
        outer = half + WALL_THICKNESS_M
        for k in range(4):
            yaw = k * math.pi / 2
            c, s = math.cos(yaw), math.sin(yaw)
            r = half + WALL_THICKNESS_M / 2
            if is_room and door is not None and k == door.wall_k:
                a, b = door.opening
                gap = float(np.linalg.norm(b - a)) / 2
                for lo, hi in ((-outer, -gap), (gap, outer)):
                    mid = (lo + hi) / 2
                    rects.append(Rect((r * c - mid * s, r * s + mid * c), (WALL_THICKNESS_M, hi - lo), yaw))
            else:
                rects.append(Rect((r * c, r * s), (WALL_THICKNESS_M, 2 * outer), yaw))
    return rects


@dataclass(frozen=True)
class Reference:
    distance: np.ndarray  # float64[N], inf beyond range_max
    label: np.ndarray  # int[N], as LidarReading.hit_object
    solid: np.ndarray  # int[N], which rectangle was hit first (-1 none)


def reference_scan(
    sensor_pose: tuple[float, float, float], spec: LidarSpec, scene: Scenario | None, grow: float = 0.0
) -> Reference:
    """The first surface along each beam of ``spec`` from ``sensor_pose``."""
    angles = sensor_pose[2] + spec.bearings_rad
    origin = (sensor_pose[0], sensor_pose[1])
    solids: list[tuple[int, Rect]] = [(WALL_OBJECT, w) for w in wall_rects(scene.door if scene else None)]
    if scene is not None:
        solids += [(i, r) for i, obj in enumerate(scene.objects) for r in obj.solid_rects()]
    dists = np.stack([ray_rect(origin, angles, rect, grow) for _, rect in solids])
    labels = np.array([label for label, _ in solids])
    first = np.argmin(dists, axis=0)
    dist = dists[first, np.arange(len(angles))]
    out = dist > spec.range_max
    return Reference(
        np.where(out, np.inf, dist), np.where(out, NO_HIT, labels[first]), np.where(out, -1, first)
    )


def assert_matches_reference(
    reading: LidarReading, spec: LidarSpec, scene: Scenario | None, min_clear: float = 0.95
) -> None:
    """Every beam whose first surface is unambiguous matches the reference to 1 µm.

    A beam is ambiguous when shrinking or growing every rectangle by 0.1 mm changes which one it hits
    first (it grazes a corner) or whether it is in range; PyBullet's triangle test may go either way.
    """
    shrunk = reference_scan(reading.lidar_pose, spec, scene, grow=-1e-4)
    grown = reference_scan(reading.lidar_pose, spec, scene, grow=1e-4)
    exact = reference_scan(reading.lidar_pose, spec, scene)
    clear = (shrunk.solid == grown.solid) & (shrunk.solid == exact.solid)
    assert clear.mean() >= min_clear
    np.testing.assert_allclose(reading.true_ranges[clear], exact.distance[clear], atol=1e-6, rtol=0)
    np.testing.assert_array_equal(reading.hit_object[clear], exact.label[clear])


def assert_hits_lie_on(reading: LidarReading, rects: list[Rect], beams: np.ndarray) -> None:
    """The hit points of the selected beams lie on the boundary of one of ``rects`` (within 1 µm)."""
    assert np.any(beams)
    x, y, yaw = reading.lidar_pose
    angles = yaw + EXACT.bearings_rad[beams]
    r = reading.true_ranges[beams]
    points = np.stack([x + r * np.cos(angles), y + r * np.sin(angles)], axis=-1)
    gap = np.min([rect.distance(points) for rect in rects], axis=0)
    assert np.all(gap < 1e-6)


# --- geometry ----------------------------------------------------------------------------------------


def test_closed_room_walls_at_hand_computed_distances() -> None:
    with World() as world:
        reading = scan_exact(world, (0.0, 0.0, 0.0))
    # The sensor is at (-0.03, 0): 2.03 m ahead, 2.0 m to either side, 1.97 m behind.
    assert reading.lidar_pose == pytest.approx((-OFFSET, 0.0, 0.0))
    assert reading.true_ranges[0] == pytest.approx(ROOM_HALF_M + OFFSET, abs=1e-9)
    assert reading.true_ranges[90] == pytest.approx(ROOM_HALF_M, abs=1e-9)
    assert reading.true_ranges[180] == pytest.approx(ROOM_HALF_M - OFFSET, abs=1e-9)
    assert reading.true_ranges[270] == pytest.approx(ROOM_HALF_M, abs=1e-9)
    # The corner (2, 2) lies at 44.57° from the sensor, so beam 45 passes left of it onto the +y wall.
    assert reading.true_ranges[45] == pytest.approx(ROOM_HALF_M / math.sin(math.pi / 4), abs=1e-9)
    assert np.all(reading.hit_object == WALL_OBJECT)
    assert reading.ranges.dtype == np.float32
    assert reading.true_ranges.dtype == np.float64
    assert reading.hit_object.dtype == np.int16
    np.testing.assert_array_equal(reading.ranges, reading.true_ranges.astype(np.float32))


@pytest.mark.parametrize(
    "robot_pose", [(0.0, 0.0, 0.0), (1.9, 1.85, 0.3), (-1.8, 1.9, 2.0), (0.5, -1.9, -1.2)]
)
def test_closed_room_has_no_gaps(robot_pose: tuple[float, float, float]) -> None:
    """Near the corners every beam must return from the room walls at the reference distance.

    A gap where two walls meet would let beams through to the enclosure (or out of range), which the
    reference, whose walls overlap in the corners, would not.
    """
    with World() as world:
        reading = scan_exact(world, robot_pose)
    assert set(np.unique(reading.hit_object).tolist()) <= {WALL_OBJECT, NO_HIT}
    assert_matches_reference(reading, EXACT, None, min_clear=0.99)


@pytest.mark.parametrize("door_k", [0, 1, 2, 3])
def test_doorway_on_wall_k_matches_doorway_opening(door_k: int) -> None:
    scene = scenario(door_k=door_k, door_width=0.8)
    with World(scene) as world:
        # Sensor exactly at the origin, so beam k·90 runs down the middle of the door.
        reading = scan_exact(world, (OFFSET, 0.0, 0.0))
    assert reading.lidar_pose[:2] == pytest.approx((0.0, 0.0), abs=1e-12)
    door_beam = 90 * door_k
    assert reading.true_ranges[door_beam] == pytest.approx(OUTER_HALF_M, abs=1e-9)
    assert reading.true_ranges[(door_beam + 180) % 360] == pytest.approx(ROOM_HALF_M, abs=1e-9)
    # The opening spans ±atan(0.4 / 2) = ±11.3° at the inner face and ±10.8° at the outer face of the
    # wall: beams within 10° leave the room, beams from 12° on hit the wall beside the door.
    offsets = np.arange(-20, 21)
    ranges = reading.true_ranges[(door_beam + offsets) % 360]
    through = np.abs(offsets) <= 10
    expected_through = OUTER_HALF_M / np.cos(np.radians(offsets[through]))
    np.testing.assert_allclose(ranges[through], expected_through, atol=1e-6)
    beside = np.abs(offsets) >= 12
    np.testing.assert_allclose(ranges[beside], ROOM_HALF_M / np.cos(np.radians(offsets[beside])), atol=1e-6)
    # The doorframe proxy lies in the gap: its centre is seen straight through.
    frame_bearing = math.degrees(math.atan2(scene.door.frame.center[1], scene.door.frame.center[0])) % 360
    assert round(frame_bearing) == door_beam
    assert_matches_reference(reading, EXACT, scene)


def test_open_space_room_moves_the_walls_and_the_enclosure_out() -> None:
    room = 4.6
    scene = Scenario(0, 0, Doorway(1, 0.8, room), (chair((0.8, 0.5)), box((-1.0, -0.6))))
    far = LidarSpec(noise_sigma_m=0.0, range_max=12.0)
    with World(scene) as world:
        reading = scan_exact(world, (OFFSET, 0.0, 0.0), far)
        short = scan_exact(world, (OFFSET, 0.0, 0.0))  # the LDS-01 reaches 3.5 m: no wall returns
    assert reading.true_ranges[90] == pytest.approx(room + OUTER_HALF_M - ROOM_HALF_M, abs=1e-9)  # the door
    assert reading.true_ranges[270] == pytest.approx(room, abs=1e-9)
    assert_matches_reference(reading, far, scene)
    assert not np.any(short.hit_object == WALL_OBJECT)
    assert_matches_reference(short, EXACT, scene)


def test_chair_shows_only_its_legs() -> None:
    scene = scenario(door_k=2, objects=(chair((1.0, 0.0)),))
    with World(scene) as world:
        reading = scan_exact(world, (0.0, 0.0, 0.0))
    sensor_x = -OFFSET
    near_face = 1.0 - 0.2  # the legs' near faces are flush with the footprint edge x = 0.8
    # Beam ±12°: at x = 0.8 it is 0.83·tan 12° = 0.176 m off axis, inside the leg band [0.17, 0.20].
    for beam in (12, 348):
        assert reading.hit_object[beam] == 0
        expected = (near_face - sensor_x) / math.cos(math.radians(12))
        assert reading.true_ranges[beam] == pytest.approx(expected, abs=1e-9)
    # Beams within ±7° pass between the legs, under the top, to the +x wall.
    for beam in (*range(0, 8), *range(353, 360)):
        assert reading.hit_object[beam] == WALL_OBJECT
        bearing = math.radians(beam if beam < 180 else beam - 360)
        assert reading.true_ranges[beam] == pytest.approx(
            (ROOM_HALF_M - sensor_x) / math.cos(bearing), abs=1e-9
        )
    assert_matches_reference(reading, EXACT, scene)


def test_table_tops_exist_above_the_scan_plane() -> None:
    """A sensor raised into the chair's top slab (0.37–0.40 m) sees the top where the low one saw through."""
    scene = scenario(door_k=2, objects=(chair((1.0, 0.0)),))
    raised = LidarSpec(noise_sigma_m=0.0, mount_height_m=0.385)
    with World(scene) as world:
        low = scan_exact(world, (0.0, 0.0, 0.0))
        high = scan_exact(world, (0.0, 0.0, 0.0), raised)
    assert low.hit_object[0] == WALL_OBJECT
    assert high.hit_object[0] == 0
    assert high.true_ranges[0] == pytest.approx(0.8 + OFFSET, abs=1e-9)


def test_desk_legs_and_box_in_a_full_scene() -> None:
    # Objects deliberately not in class-id order: hit_object indexes scenario.objects.
    objects = (desk((-0.9, 0.2), yaw=0.4), box((1.0, -0.9), yaw=-0.7), chair((0.8, 1.0), yaw=2.1, side=0.45))
    scene = scenario(door_k=1, door_width=0.9, objects=objects)
    with World(scene) as world:
        for pose in [(0.0, 0.0, 0.0), (0.3, -0.2, 1.1), (-0.1, 1.5, -2.5), (1.2, 0.3, 3.0)]:
            reading = scan_exact(world, pose)
            assert_matches_reference(reading, EXACT, scene)
        reading = scan_exact(world, (0.0, 0.0, 0.0))
    seen = set(np.unique(reading.hit_object).tolist())
    assert seen == {WALL_OBJECT, 0, 1, 2}
    # Desk and chair returns all lie on a leg, never under the top between the legs.
    for index in (0, 2):
        assert_hits_lie_on(reading, objects[index].leg_rects(), reading.hit_object == index)
    # The box is solid: every beam between its silhouette edges stops on it.
    box_beams = np.flatnonzero(reading.hit_object == 1)
    assert np.all(np.diff(box_beams) == 1) and len(box_beams) >= 10


def test_reload_replaces_the_previous_scenario() -> None:
    with World(scenario(door_k=2, objects=(box((1.0, 0.0)),))) as world:
        before = scan_exact(world, (0.0, 0.0, 0.0))
        world.load(scenario(door_k=0, objects=(chair((-1.0, 0.0)), box((0.0, 1.0)))))
        after = scan_exact(world, (0.0, 0.0, 0.0))
        assert world.scenario is not None and world.scenario.door.wall_k == 0
    assert before.hit_object[0] == 0 and before.true_ranges[0] == pytest.approx(0.8 + OFFSET, abs=1e-9)
    assert after.true_ranges[0] == pytest.approx(OUTER_HALF_M + OFFSET, abs=1e-9)  # old box gone, door there
    assert after.hit_object[90] == 1 and after.true_ranges[90] == pytest.approx(0.7, abs=1e-9)
    # Beam 180 runs between the new chair's legs to the -x wall.
    assert after.hit_object[180] == WALL_OBJECT
    assert after.true_ranges[180] == pytest.approx(ROOM_HALF_M - OFFSET, abs=1e-9)


def test_out_of_range_and_too_close_are_inf() -> None:
    scene = scenario(door_k=0, door_width=1.0)
    with World(scene) as world:
        # Through the door the enclosure is 3.1 + 1.53 = 4.63 m away: beyond range_max.
        far = scan_exact(world, (-1.5, 0.0, 0.0))
        # Facing away from the +y wall, 7 cm from it: beam 180 returns at 0.07 m < range_min.
        close = scan_exact(world, (0.0, 1.9, -math.pi / 2))
    assert np.isinf(far.ranges[0]) and np.isinf(far.true_ranges[0])
    assert far.hit_object[0] == NO_HIT
    assert np.isfinite(far.ranges[180])
    assert close.lidar_pose[1] == pytest.approx(1.93)
    assert close.true_ranges[180] == pytest.approx(0.07, abs=1e-9)
    assert close.hit_object[180] == WALL_OBJECT
    assert np.isinf(close.ranges[180])


def test_hit_object_lookup() -> None:
    with World(scenario(objects=(box((1.0, 0.0)), chair((-1.0, 0.0))))) as world:
        lookup = world.object_index_of_body
        furniture_bodies = np.flatnonzero(lookup >= 0)
        wall_bodies = np.flatnonzero(lookup == WALL_OBJECT)
        assert lookup[furniture_bodies].tolist() == [0, 1]
        ids = np.array([-1, wall_bodies[0], furniture_bodies[1], furniture_bodies[0], -1])
        assert world.hit_object(ids).tolist() == [NO_HIT, WALL_OBJECT, 1, 0, NO_HIT]
        assert world.hit_object(ids).dtype == np.int16


# --- the sensor model --------------------------------------------------------------------------------


def test_lidar_pose_applies_rear_offset() -> None:
    assert lidar_pose((1.0, 2.0, 0.0)) == pytest.approx((0.97, 2.0, 0.0))
    assert lidar_pose((1.0, 2.0, math.pi / 2)) == pytest.approx((1.0, 1.97, math.pi / 2))
    assert lidar_pose((0.0, 0.0, math.pi)) == pytest.approx((0.03, 0.0, math.pi))


def test_default_spec_is_lds01() -> None:
    spec = LidarSpec()
    assert (spec.beams, spec.range_min, spec.range_max, spec.noise_sigma_m) == (360, 0.12, 3.5, 0.015)
    assert spec.bearings_rad[1] == pytest.approx(math.radians(1.0))
    assert spec.bearings_rad[0] == 0.0
    assert spec.angle_max == pytest.approx(math.radians(359.0))
    with pytest.raises(ValueError):
        LidarSpec(range_min=4.0)


def test_noise_statistics_and_seeding() -> None:
    spec = LidarSpec()
    with World() as world:
        lidar = Lidar(world, spec, rng=np.random.default_rng(7))
        readings = [lidar.scan((0.1, -0.2, 0.05 * i)) for i in range(60)]
        again = Lidar(world, spec, rng=np.random.default_rng(7)).scan((0.1, -0.2, 0.0))
        other = Lidar(world, spec, rng=np.random.default_rng(8)).scan((0.1, -0.2, 0.0))
    errors = np.concatenate([r.ranges.astype(np.float64) - r.true_ranges for r in readings])
    assert errors.size == 60 * 360 and np.all(np.isfinite(errors))
    # Mean within 5 standard errors of 0; sample std within 3 % of σ (n = 21600).
    assert abs(errors.mean()) < 5 * spec.noise_sigma_m / math.sqrt(errors.size)
    assert errors.std() == pytest.approx(spec.noise_sigma_m, rel=0.03)
    assert again.ranges.tobytes() == readings[0].ranges.tobytes()
    assert not np.array_equal(other.ranges, readings[0].ranges)
    np.testing.assert_array_equal(other.true_ranges, readings[0].true_ranges)


def test_noisy_returns_outside_limits_become_inf() -> None:
    noisy = LidarSpec(noise_sigma_m=0.8)
    with World() as world:
        reading = Lidar(world, noisy, rng=np.random.default_rng(3)).scan((0.0, 0.0, 0.0))
    finite = np.isfinite(reading.ranges)
    assert 0 < np.count_nonzero(~finite) < noisy.beams
    assert np.all(reading.ranges[finite] >= noisy.range_min)
    assert np.all(reading.ranges[finite] <= noisy.range_max)
    assert np.all(np.isfinite(reading.true_ranges))  # the truth is unaffected by noise


def test_noise_stream_does_not_depend_on_the_scene() -> None:
    """Same seed, different scenes: the noise draws (ranges − truth where both finite) are identical."""
    with World() as closed, World(scenario(door_k=0, door_width=1.0)) as open_door:
        a = Lidar(closed, LidarSpec(), rng=np.random.default_rng(5)).scan((-1.0, 0.0, 0.0))
        b = Lidar(open_door, LidarSpec(), rng=np.random.default_rng(5)).scan((-1.0, 0.0, 0.0))
    both = np.isfinite(a.ranges) & np.isfinite(b.ranges) & (a.true_ranges == b.true_ranges)
    assert np.count_nonzero(both) > 300
    np.testing.assert_array_equal(a.ranges[both], b.ranges[both])
    assert np.isinf(b.ranges[0]) and np.isfinite(a.ranges[0])


def test_non_default_spec_720_beams_over_180_degrees() -> None:
    spec = LidarSpec(beams=720, angle_min=-math.pi / 2, angle_increment=math.pi / 720, noise_sigma_m=0.0)
    scene = scenario(door_k=2, objects=(box((1.0, 0.0)),))
    with World(scene) as world:
        reading = scan_exact(world, (0.2, -0.3, 0.4), spec)
        straight = scan_exact(world, (0.0, 0.0, 0.0), spec)
    assert reading.ranges.shape == reading.true_ranges.shape == reading.hit_object.shape == (720,)
    assert spec.angle_max == pytest.approx(math.pi / 2 - math.pi / 720)
    assert_matches_reference(reading, spec, scene)
    assert straight.true_ranges[0] == pytest.approx(ROOM_HALF_M, abs=1e-9)  # -90°: the -y wall
    assert straight.true_ranges[360] == pytest.approx(0.8 + OFFSET, abs=1e-9)  # 0°: the box face at x = 0.8


def test_more_beams_than_one_pybullet_batch() -> None:
    beams = RAY_BATCH_LIMIT + 1000
    spec = LidarSpec(beams=beams, angle_increment=2 * math.pi / beams, noise_sigma_m=0.0)
    scene = scenario(door_k=3, objects=(chair((0.5, 0.5)), box((-1.0, -0.5))))
    with World(scene) as world:
        reading = scan_exact(world, (0.1, 0.1, 0.2), spec)
    assert reading.ranges.shape == (beams,)
    assert_matches_reference(reading, spec, scene, min_clear=0.99)


def test_worlds_in_one_process_are_independent() -> None:
    with World(scenario(door_k=0)) as a, World(scenario(door_k=2, objects=(box((1.0, 0.0)),))) as b:
        assert a.client_id != b.client_id
        first_a = scan_exact(a, (0.0, 0.0, 0.0))
        first_b = scan_exact(b, (0.0, 0.0, 0.0))
        again_a = scan_exact(a, (0.0, 0.0, 0.0))
    assert first_a.true_ranges[0] == pytest.approx(OUTER_HALF_M + OFFSET)
    assert first_b.true_ranges[0] == pytest.approx(0.8 + OFFSET)
    np.testing.assert_array_equal(first_a.true_ranges, again_a.true_ranges)


def test_closed_world_refuses_to_scan() -> None:
    world = World()
    lidar = Lidar(world, EXACT, rng=np.random.default_rng(0))
    world.close()
    world.close()  # idempotent
    with pytest.raises(RuntimeError, match="closed"):
        lidar.scan((0.0, 0.0, 0.0))
    with pytest.raises(RuntimeError, match="closed"):
        world.load(scenario())
