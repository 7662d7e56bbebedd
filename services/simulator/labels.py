"""Ground-truth boxes for one sample, by README "Labels".

A sample's labels describe its middle scan (t−1), seen from the true LiDAR pose at that scan. Each
object's footprint is projected into (bearing, range): the box spans the arc that covers its corners
and the range interval from its nearest boundary point to its farthest corner, snapped outward to
whole raster pixels — exactly the pixels a return from that object can light. An object is a target
only if the sensor saw it: at least two beams of scan t−1 hit it (for the doorway: pass through it).
A person's footprint is a disc about the midpoint of their legs (:data:`PERSON_FOOTPRINT_RADIUS_M`).
A model with a raster yaw sees its scans turned (:mod:`common.encoding`): its labels are made in that
turned frame, where its seam lies, with the same rules.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from common.encoding import ANGLE_COLUMNS, IMAGE_WIDTH, RANGE_ROWS, Padding, arc_pixel_boxes, disc_polar
from common.model_spec import PERSON_FOOTPRINT_RADIUS_M
from services.simulator.people import leg_object
from services.simulator.scenario import DOORFRAME, PERSON, Rect, Scenario

MIN_BEAMS_ON_OBJECT = 2
Box = tuple[float, float, float, float]


@dataclass(frozen=True)
class ObjectLabel:
    """How one object looks from one sensor pose; ``boxes_px`` is empty when it is no target."""

    class_id: int
    beams_on_object: int
    visible: bool
    # Bearings in the raster's frame: the laser frame turned by the raster yaw (0: the laser frame).
    bearing_center_deg: float  # in [0, 360)
    bearing_min_deg: float  # arc ends, unwrapped around the centre: min may be < 0, max may be > 360
    bearing_max_deg: float
    range_min_m: float
    range_max_m: float
    boxes_px: tuple[Box, ...]  # (x1, y1, x2, y2) in raster pixels, one per copy in the image


def _to_sensor_frame(points: np.ndarray, lidar_pose: tuple[float, float, float]) -> np.ndarray:
    x, y, yaw = lidar_pose
    c, s = math.cos(yaw), math.sin(yaw)
    d = np.asarray(points, dtype=np.float64) - np.array([x, y])
    return np.stack([d[..., 0] * c + d[..., 1] * s, -d[..., 0] * s + d[..., 1] * c], axis=-1)


def footprint_polar(
    rect: Rect, lidar_pose: tuple[float, float, float]
) -> tuple[float, float, float, float, float]:
    """(centre bearing in [0, 360), arc min, arc max, range min, range max) of a footprint.

    The arc is measured around the centre bearing so it never breaks at 0°/360°; its ends are
    unwrapped (e.g. −12° … 15°). A sensor inside the footprint sees it all around: the full circle.
    """
    sensor_xy = np.array(lidar_pose[:2])
    local = _to_sensor_frame(np.vstack([rect.corners(), [rect.center]]), lidar_pose)
    bearings = np.degrees(np.arctan2(local[:, 1], local[:, 0]))
    center = float(np.mod(bearings[-1], 360.0))
    range_min = float(rect.distance(sensor_xy))
    range_max = float(np.hypot(local[:4, 0], local[:4, 1]).max())
    if range_min == 0.0:
        return center, 0.0, 360.0, 0.0, range_max
    offsets = np.mod(bearings[:4] - center + 180.0, 360.0) - 180.0
    return center, center + float(offsets.min()), center + float(offsets.max()), range_min, range_max


def arc_crosses_seam(center_deg: float, lo_deg: float, hi_deg: float) -> bool:
    """Whether an object's arc spans the 0°/360° column seam (where ``zero`` padding clips its box).

    Uses the column arithmetic of the labels, so it is true exactly when the ``zero`` box is clipped.
    """
    shift = -ANGLE_COLUMNS * math.floor(math.floor(center_deg + 0.5) / ANGLE_COLUMNS)
    first = math.floor(lo_deg + 0.5) + shift
    past_last = min(math.floor(hi_deg + 0.5) + 1, math.floor(lo_deg + 0.5) + ANGLE_COLUMNS) + shift
    return first < 0 or past_last > ANGLE_COLUMNS


def turned_arc(center: float, lo: float, hi: float, yaw_deg: float) -> tuple[float, float, float]:
    """An arc (centre in [0, 360), ends unwrapped around it) turned by a raster yaw: the centre taken
    mod 360 again and the ends kept around it. A yaw of 0 returns the arc as it is, bit for bit."""
    if yaw_deg == 0.0:
        return center, lo, hi
    turned = float(np.mod(center + yaw_deg, 360.0))
    return turned, lo + (turned - center), hi + (turned - center)


def beams_through_segment(
    segment: np.ndarray,
    lidar_pose: tuple[float, float, float],
    bearings_rad: np.ndarray,
    true_ranges: np.ndarray,
    range_max: float,
) -> int:
    """How many beams cross ``segment`` before their first hit and within the sensor's reach."""
    x, y, yaw = lidar_pose
    angles = yaw + np.asarray(bearings_rad, dtype=np.float64)
    direction = np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    p, q = np.asarray(segment[0], dtype=np.float64), np.asarray(segment[1], dtype=np.float64)
    edge = q - p
    origin_to_p = p - np.array([x, y])
    denom = direction[:, 0] * edge[1] - direction[:, 1] * edge[0]  # cross(direction, edge)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (origin_to_p[0] * edge[1] - origin_to_p[1] * edge[0]) / denom  # distance along the beam
        u = (origin_to_p[0] * direction[:, 1] - origin_to_p[1] * direction[:, 0]) / denom  # along segment
    reach = np.minimum(np.where(np.isfinite(true_ranges), true_ranges, np.inf), range_max)
    crossing = (denom != 0) & (t > 0) & (u >= 0) & (u <= 1) & (t <= reach)
    return int(np.count_nonzero(crossing))


def clip_to_field_of_view(
    center: float, lo: float, hi: float, bearings_rad: np.ndarray
) -> tuple[float, float] | None:
    """The part of the arc ``lo``…``hi`` (degrees, unwrapped around ``center``) that the beams cover.

    A sensor that sees all around leaves the arc as it is. One with a narrower field of view keeps the
    largest piece inside it, so a box never claims columns the sensor leaves dark; ``None`` when the
    arc lies wholly outside.
    """
    bearings = np.asarray(bearings_rad, dtype=np.float64)
    step = float(bearings[1] - bearings[0]) if len(bearings) > 1 else 2.0 * math.pi
    if len(bearings) * step >= 2.0 * math.pi - 1e-9:
        return lo, hi
    first, last = math.degrees(float(bearings[0])), math.degrees(float(bearings[-1]))
    best: tuple[float, float] | None = None
    for turn in (-720.0, -360.0, 0.0, 360.0, 720.0):
        a, b = max(lo, first + turn), min(hi, last + turn)
        if b > a and (best is None or b - a > best[1] - best[0]):
            best = (a, b)
    return best


def person_footprint_polar(
    legs: Sequence[tuple[float, float, float]], lidar_pose: tuple[float, float, float]
) -> tuple[float, float, float, float, float]:
    """(centre bearing, arc min, arc max, range min, range max) of a person's footprint.

    The footprint is the disc of :data:`PERSON_FOOTPRINT_RADIUS_M` about the midpoint of the legs (the
    person's position), not the legs themselves: a leg shows the sensor only its near side, a few
    centimetres deep, so leg-sized boxes are one to three rows tall, and at that size the row or two no
    scan can place (a leg's far side, a hidden leg) decides whether a box reaches IoU 0.5. A box about
    the person is as big as a chair's, and its centre is where the person stands.
    """
    centres = np.array([leg[:2] for leg in legs], dtype=np.float64)
    return disc_polar(_to_sensor_frame(centres.mean(axis=0), lidar_pose), PERSON_FOOTPRINT_RADIUS_M)


def label_scan(
    scenario: Scenario,
    lidar_pose: tuple[float, float, float],
    bearings_rad: np.ndarray,
    true_ranges: np.ndarray,
    hit_object: np.ndarray,
    range_max: float,
    padding: Padding = "zero",
    people_legs: Sequence[Sequence[tuple[float, float, float]]] = (),
    raster_yaw_deg: float = 0.0,
) -> list[ObjectLabel]:
    """Labels of every object of ``scenario`` (chair, box, desk, doorframe) and every person for one scan.

    ``true_ranges`` and ``hit_object`` are the noise-free first hit of each beam and the index in
    ``scenario.objects`` of what it hit (−1 wall, −2 nothing within range, a person's legs
    :func:`services.simulator.people.leg_object`). ``people_legs`` holds each person's two leg
    circles (x, y, r) at this scan: a person's box spans their footprint (:func:`person_footprint_polar`), and
    the person is a target when at least two beams hit their legs. ``range_max`` is the labelling range: the
    sensor's reach within the raster's full scale. Boxes keep to the sensor's field of view.
    ``raster_yaw_deg`` is the model's raster yaw (a checked value in [0, 360)): bearings, the field of
    view and the boxes are turned by it, and the seam rule applies in the turned frame.
    """
    labels: list[ObjectLabel] = []
    hits = np.asarray(hit_object)
    candidates: list[tuple[int, Rect, int]] = [
        (obj.class_id, obj.footprint, int(np.count_nonzero(hits == index)))
        for index, obj in enumerate(scenario.objects)
    ]
    door_beams = beams_through_segment(
        scenario.door.opening, lidar_pose, bearings_rad, true_ranges, range_max
    )
    candidates.append((DOORFRAME, scenario.door.frame, door_beams))
    polar = [(class_id, footprint_polar(rect, lidar_pose), beams) for class_id, rect, beams in candidates]
    for person, legs in enumerate(people_legs):
        beams = int(np.count_nonzero(np.isin(hits, [leg_object(person, leg) for leg in range(len(legs))])))
        polar.append((PERSON, person_footprint_polar(legs, lidar_pose), beams))
    seen_bearings = np.asarray(bearings_rad, dtype=np.float64) + math.radians(raster_yaw_deg)
    for class_id, (laser_center, laser_lo, laser_hi, rmin, rmax), beams in polar:
        center, lo, hi = turned_arc(laser_center, laser_lo, laser_hi, raster_yaw_deg)
        arc = clip_to_field_of_view(center, lo, hi, seen_bearings)
        visible = beams >= MIN_BEAMS_ON_OBJECT and rmin <= range_max and arc is not None
        boxes = arc_pixel_boxes(center, *arc, rmin, rmax, padding) if visible and arc is not None else ()
        labels.append(
            ObjectLabel(class_id, beams, visible and bool(boxes), center, lo, hi, rmin, rmax, boxes)
        )
    return labels


def yolo_lines(labels: list[ObjectLabel]) -> list[str]:
    """YOLO text lines (class, x-centre, y-centre, width, height; normalised by 384 and 64)."""
    lines = []
    for label in labels:
        for x1, y1, x2, y2 in label.boxes_px:
            lines.append(
                f"{label.class_id} {(x1 + x2) / 2 / IMAGE_WIDTH:.6f} {(y1 + y2) / 2 / RANGE_ROWS:.6f} "
                f"{(x2 - x1) / IMAGE_WIDTH:.6f} {(y2 - y1) / RANGE_ROWS:.6f}"
            )
    return lines
