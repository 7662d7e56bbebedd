"""Label rules of README "Labels" on hand-computed geometry (no simulator: the beams are given)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from services.simulator.labels import (
    ObjectLabel,
    arc_crosses_seam,
    beams_through_segment,
    footprint_polar,
    label_scan,
    yolo_lines,
)
from services.simulator.scenario import BOX, CHAIR, DESK, DOORFRAME, Doorway, Furniture, Rect, Scenario

BEARINGS = np.radians(np.arange(360.0))
NO_HIT = np.full(360, -2, dtype=np.int16)
FAR = np.full(360, np.inf)


def scenario_with(box: Rect, door_k: int = 0, door_width: float = 0.8) -> Scenario:
    """A box where the test wants it; chair and desk parked in a far corner (never hit in these tests)."""
    return Scenario(
        index=0,
        seed=0,
        door=Doorway(door_k, door_width),
        objects=(
            Furniture(CHAIR, Rect((-1.5, -1.5), (0.4, 0.4), 0.0), 0.4, 0.03),
            Furniture(BOX, box, 0.4),
            Furniture(DESK, Rect((-1.3, 1.2), (0.8, 1.6), 0.0), 0.74, 0.05),
        ),
    )


def hits_on(box_beams: list[int]) -> np.ndarray:
    hit = NO_HIT.copy()
    hit[box_beams] = 1  # index of the box in scenario.objects
    return hit


def box_label(scenario: Scenario, pose: tuple[float, float, float], beams: list[int], padding: str = "zero"):
    labels = label_scan(scenario, pose, BEARINGS, FAR, hits_on(beams), 3.5, padding)  # type: ignore[arg-type]
    return next(label for label in labels if label.class_id == BOX)


def test_known_object_gives_the_hand_computed_box() -> None:
    # Box 0.4 × 0.4 centred 1.5 m to the left of the sensor. Corner bearings: atan2(1.3, ±0.2) and
    # atan2(1.7, ±0.2) → arc 81.25°…98.75°; columns 81…99 → x 81…100. Nearest point 1.3 m → row 20
    # (20.475); farthest corner hypot(0.2, 1.7) = 1.712 m → row 26 (26.96) → y 20…27.
    scenario = scenario_with(Rect((0.0, 1.5), (0.4, 0.4), 0.0))
    label = box_label(scenario, (0.0, 0.0, 0.0), [85, 90, 95])
    assert label.visible and label.beams_on_object == 3
    assert label.boxes_px == ((81.0, 20.0, 100.0, 27.0),)
    assert label.bearing_center_deg == pytest.approx(90.0)
    assert label.range_min_m == pytest.approx(1.3)
    # Seen from a sensor turned 30° to the left, the box sits 30° further clockwise: 30 columns lower.
    turned = box_label(scenario, (0.0, 0.0, math.radians(30.0)), [60])
    assert turned.boxes_px == () and not turned.visible  # one beam is not enough
    turned = box_label(scenario, (0.0, 0.0, math.radians(30.0)), [55, 60])
    assert turned.boxes_px == ((51.0, 20.0, 70.0, 27.0),)


def test_yolo_line_is_normalised_by_384_and_64() -> None:
    scenario = scenario_with(Rect((0.0, 1.5), (0.4, 0.4), 0.0))
    labels = label_scan(scenario, (0.0, 0.0, 0.0), BEARINGS, FAR, hits_on([85, 90]), 3.5, "zero")
    (line,) = [line for line in yolo_lines(labels) if line.startswith("1 ")]
    cls, xc, yc, w, h = line.split()
    assert cls == "1"
    assert float(xc) == pytest.approx(90.5 / 384, abs=1e-6) and float(w) == pytest.approx(19 / 384, abs=1e-6)
    assert float(yc) == pytest.approx(23.5 / 64, abs=1e-6) and float(h) == pytest.approx(7 / 64, abs=1e-6)


def test_seam_crossing_box_zero_padding_keeps_the_centre_side() -> None:
    # Box 1.5 m straight ahead: arc −8.75°…8.75° → columns −9…9.
    scenario = scenario_with(Rect((1.5, 0.0), (0.4, 0.4), 0.0))
    ahead = box_label(scenario, (0.0, 0.0, 0.0), [0, 1])
    assert ahead.boxes_px == ((0.0, 20.0, 10.0, 27.0),)  # centre column 0: the [0°, 9°] side is kept
    # Turn the sensor so the centre is at 355°: arc 346.25°…363.75° → columns 346…364; centre side is high.
    pose = (0.0, 0.0, math.radians(5.0))
    assert box_label(scenario, pose, [350, 351]).boxes_px == ((346.0, 20.0, 360.0, 27.0),)
    # Centre at 4°: arc −4.75°…12.75° → columns −5…13; the low side [0, 14) is kept.
    pose = (0.0, 0.0, math.radians(-4.0))
    assert box_label(scenario, pose, [3, 4]).boxes_px == ((0.0, 20.0, 14.0, 27.0),)


def test_seam_crossing_box_wrap_padding_extends_whole_into_the_padding() -> None:
    scenario = scenario_with(Rect((1.5, 0.0), (0.4, 0.4), 0.0))
    pose = (0.0, 0.0, math.radians(5.0))  # arc 346.25°…363.75° → columns 346…364
    label = box_label(scenario, pose, [350, 351], padding="wrap")
    # The whole object in columns 346…364 (360–364 are the repeated 0–4), and the part of it that the
    # image also shows in columns 0–4. Both copies are really in the padded image.
    assert label.boxes_px == ((0.0, 20.0, 5.0, 27.0), (346.0, 20.0, 365.0, 27.0))
    # An object within 0°–23° appears twice in a wrap image, and is labelled twice.
    pose = (0.0, 0.0, math.radians(-12.0))  # arc 3.25°…20.75° → columns 3…21
    twice = box_label(scenario, pose, [10, 12], padding="wrap")
    assert twice.boxes_px == ((3.0, 20.0, 22.0, 27.0), (363.0, 20.0, 382.0, 27.0))
    assert box_label(scenario, pose, [10, 12], padding="zero").boxes_px == ((3.0, 20.0, 22.0, 27.0),)


@pytest.mark.parametrize(
    ("yaw_deg", "crosses"),
    [(0.0, True), (5.0, True), (-4.0, True), (-12.0, False), (12.0, False), (180.0, False)],
)
def test_seam_crossing_is_exactly_where_zero_padding_clips(yaw_deg: float, crosses: bool) -> None:
    scenario = scenario_with(Rect((1.5, 0.0), (0.4, 0.4), 0.0))  # arc ±8.75° around the box centre
    pose = (0.0, 0.0, math.radians(yaw_deg))
    label = box_label(scenario, pose, [0, 1])
    assert arc_crosses_seam(label.bearing_center_deg, label.bearing_min_deg, label.bearing_max_deg) is crosses
    wrap = box_label(scenario, pose, [0, 1], padding="wrap")
    whole = max(wrap.boxes_px, key=lambda box: box[2] - box[0])
    assert (whole[0] < 360.0 < whole[2]) is crosses  # wrap shows it whole across column 360


def test_far_object_is_not_a_target_even_with_hits() -> None:
    scenario = scenario_with(Rect((3.8, 0.0), (0.2, 0.2), 0.0))
    assert not box_label(scenario, (0.0, 0.0, 0.0), [0, 1, 359]).visible


def test_footprint_polar_from_inside_is_the_full_circle() -> None:
    _, lo, hi, rmin, rmax = footprint_polar(Rect((0.0, 0.0), (1.0, 1.0), 0.3), (0.1, 0.0, 0.0))
    assert (lo, hi, rmin) == (0.0, 360.0, 0.0) and rmax > 0.5


def test_footprint_polar_range_interval_uses_nearest_boundary_point() -> None:
    # A long wall-like rectangle broadside: nearest point is straight ahead, not a corner.
    _, lo, hi, rmin, rmax = footprint_polar(Rect((2.0, 0.0), (0.1, 2.0), 0.0), (0.0, 0.0, 0.0))
    assert rmin == pytest.approx(1.95)
    assert rmax == pytest.approx(math.hypot(2.05, 1.0))
    assert lo == pytest.approx(-math.degrees(math.atan2(1.0, 1.95)))
    assert hi == pytest.approx(math.degrees(math.atan2(1.0, 1.95)))


def test_doorway_counts_beams_passing_through_it() -> None:
    door = Doorway(wall_k=0, width_m=0.8)  # opening on x = 2.0, y in [−0.4, 0.4]
    # From the origin the opening spans ±atan(0.4 / 2) = ±11.3°: beams 0…11 and 349…359 → 23 beams.
    assert beams_through_segment(door.opening, (0.0, 0.0, 0.0), BEARINGS, FAR, 3.5) == 23
    # Beams stopped before the doorway (something 1 m ahead) do not pass it.
    blocked = FAR.copy()
    blocked[:12] = 1.0
    assert beams_through_segment(door.opening, (0.0, 0.0, 0.0), BEARINGS, blocked, 3.5) == 11
    # Out of the sensor's reach (opening 2.5 m away, reach 2.0 m): nothing passes.
    assert beams_through_segment(door.opening, (-0.5, 0.0, 0.0), BEARINGS, FAR, 2.0) == 0
    # The sensor turned away: a door behind it is crossed by the beams pointing backwards.
    assert beams_through_segment(door.opening, (0.0, 0.0, math.pi), BEARINGS, FAR, 3.5) == 23


def test_doorframe_label_uses_the_proxy_rectangle() -> None:
    scenario = scenario_with(Rect((-1.0, -1.0), (0.4, 0.4), 0.0), door_k=1, door_width=0.8)
    labels = label_scan(scenario, (0.0, 0.0, 0.0), BEARINGS, FAR, NO_HIT, 3.5, "zero")
    door = next(label for label in labels if label.class_id == DOORFRAME)
    # Door on the +y wall: the proxy spans x ±0.4 at y 2.0…2.1 → centre bearing 90°.
    assert door.visible and door.beams_on_object == 23
    assert door.bearing_center_deg == pytest.approx(90.0)
    assert door.range_min_m == pytest.approx(2.0)
    x1, y1, x2, y2 = door.boxes_px[0]
    assert (x1, x2) == (79.0, 102.0)  # arc ±atan(0.4/2.0) = ±11.31° → columns 79…101
    assert (y1, y2) == (31.0, 34.0)  # 2.0 m → row 31 (31.5); hypot(0.4, 2.1) = 2.138 m → row 33 (33.67) → 34


def test_occluded_object_gets_no_label_in_the_simulated_world() -> None:
    """A chair hidden behind the solid box (seen through real PyBullet beams) is no target."""
    from services.simulator.lidar import Lidar, LidarSpec
    from services.simulator.world import World

    spec = LidarSpec(noise_sigma_m=0.0)
    chair = Furniture(CHAIR, Rect((1.6, 0.0), (0.4, 0.4), 0.0), 0.4, 0.03)  # legs within ±7.5° from origin
    desk = Furniture(DESK, Rect((-1.0, 1.0), (0.8, 1.6), 0.0), 0.74, 0.05)
    robot_pose = (0.03, 0.0, 0.0)  # puts the LiDAR (0.03 m behind the centre) at the origin

    def labels_with_box_at(box_center: tuple[float, float]) -> dict[int, object]:
        box = Furniture(BOX, Rect(box_center, (0.4, 0.6), 0.0), 0.4)  # at (0.8, 0): hides ±26°
        scenario = Scenario(0, 0, Doorway(2, 0.8), (chair, box, desk))
        with World(scenario) as world:
            reading = Lidar(world, spec, rng=np.random.default_rng(0)).scan(robot_pose)
        labels = label_scan(
            scenario,
            reading.lidar_pose,
            spec.bearings_rad,
            reading.true_ranges,
            reading.hit_object,
            spec.range_max,
            "zero",
        )
        return {label.class_id: label for label in labels}

    hidden = labels_with_box_at((0.8, 0.0))
    assert hidden[CHAIR].beams_on_object == 0 and not hidden[CHAIR].visible and hidden[CHAIR].boxes_px == ()
    assert hidden[BOX].visible and hidden[DESK].visible
    in_view = labels_with_box_at((0.8, -1.2))
    assert in_view[CHAIR].visible and in_view[CHAIR].beams_on_object >= 2
    assert len(in_view[CHAIR].boxes_px) == 1


def test_with_a_raster_yaw_of_180_ahead_is_the_middle_and_behind_is_the_seam() -> None:
    """Labels of a model with raster yaw 180 (common.encoding): made in the turned frame, where its
    tensors put the lit pixels, with the seam rule applied there."""
    from common.encoding import ANGLE_COLUMNS, encode_scan
    from services.simulator.lidar import Lidar, LidarSpec
    from services.simulator.world import World

    spec = LidarSpec(noise_sigma_m=0.0)
    ahead = Furniture(BOX, Rect((1.2, 0.0), (0.4, 0.4), 0.0), 0.4)  # straight ahead of the sensor
    behind = Furniture(CHAIR, Rect((-1.4, 0.0), (0.4, 0.4), 0.0), 0.4, 0.03)  # straight behind it
    desk = Furniture(DESK, Rect((0.0, 1.4), (0.8, 1.6), 0.0), 0.74, 0.05)
    scenario = Scenario(0, 0, Doorway(2, 0.8), (behind, ahead, desk))
    with World(scenario) as world:
        reading = Lidar(world, spec, rng=np.random.default_rng(0)).scan((0.03, 0.0, 0.0))  # LiDAR at origin

    def labelled(yaw: float) -> dict[int, ObjectLabel]:
        labels = label_scan(
            scenario, reading.lidar_pose, spec.bearings_rad, reading.true_ranges, reading.hit_object,
            spec.range_max, "zero", raster_yaw_deg=yaw,
        )  # fmt: skip
        return {label.class_id: label for label in labels}

    plain, turned = labelled(0.0), labelled(180.0)
    (box,) = turned[BOX].boxes_px
    assert box[0] < 180.0 < box[2] and abs((box[0] + box[2]) / 2 - 180.5) <= 1.0
    assert turned[BOX].bearing_center_deg == pytest.approx(180.0, abs=1e-6)
    # Every pixel the box lights in the turned raster lies in its box.
    raster = encode_scan(
        reading.ranges, spec.angle_min, spec.angle_increment, spec.range_min, spec.range_max,
        raster_yaw_deg=180.0,
    )  # fmt: skip
    beams = np.flatnonzero(reading.hit_object == 1)
    cols = np.floor(np.degrees(spec.bearings_rad[beams]) + 180.0 + 0.5).astype(int) % ANGLE_COLUMNS
    rows = np.floor(reading.ranges[beams] * 63 / 4.0).astype(int)
    assert len(beams) >= 2 and (raster[rows, cols] == 255).all()
    assert ((cols >= box[0]) & (cols < box[2]) & (rows >= box[1]) & (rows < box[3])).all()

    # The object behind the robot is split by the turned raster's seam, as the one ahead is by the paper's.
    def crosses(label: ObjectLabel) -> bool:
        return arc_crosses_seam(label.bearing_center_deg, label.bearing_min_deg, label.bearing_max_deg)

    assert crosses(turned[CHAIR]) and not crosses(turned[BOX])
    assert crosses(plain[BOX]) and not crosses(plain[CHAIR])
    (chair,) = turned[CHAIR].boxes_px
    assert chair[0] == 0.0 or chair[2] == ANGLE_COLUMNS  # clipped at the seam, as SPEC's rule says
    assert (box[1], box[3]) == plain[BOX].boxes_px[0][1::2]  # ranges do not turn
