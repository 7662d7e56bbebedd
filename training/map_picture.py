"""The top-down map (the paper's Figure 1): a sample's room, objects and robot in metres, hits decoded.

The LiDAR hits of the three scans are *decoded back from the PNG* (:func:`decode_hits`) rather than
re-simulated, and drawn in their channel colours: the map then shows what the network actually gets
(quantised to 1° × 4/63 m pixels), so a wrong channel order, a mirrored bearing or a label box that
misses its object is visible at a glance. All three scans are placed with the one stored pose, that
of t-1, so the motion between scans shows as the same colour fringes the detector reads.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from common.encoding import (
    ANGLE_COLUMNS,
    SENTINEL_ROW,
    STACK_DEPTH,
    pixel_x_to_bearing_deg,
    pixel_y_to_range_m,
    polar_to_xy,
    raster_to_laser_bearing_deg,
)
from common.model_spec import CLASS_COLOURS, CLASS_NAMES
from services.simulator.scenario import (
    DOORFRAME,
    OUTER_HALF_M,
    PERSON,
    ROOM_HALF_M,
    Rect,
    Scenario,
    enclosure_rects,
    room_wall_rects,
)
from training.dataset_sample import Pose, Sample
from training.picture_style import (
    AXIS,
    BACKGROUND,
    CHANNEL_COLOURS,
    CHANNEL_NAMES,
    GRID,
    MUTED,
    TEXT,
    Colour,
    Font,
    load_font,
    text_width,
    wrap,
)

WALL: Colour = (105, 105, 110)
ROBOT: Colour = (255, 255, 255)

# Layout: 100 px per metre over [-3.3, 3.3]^2, y up, x right (world frame, REP-103).
MAP_PX_PER_M = 100.0
MAP_HALF_M = 3.3
MAP_SIZE_PX = round(2 * MAP_HALF_M * MAP_PX_PER_M)
MAP_ORIGIN: tuple[int, int] = (48, 44)  # image pixel of the map's top-left corner (-3.3, +3.3)
MAP_PANEL_WIDTH = 320
MAP_BOTTOM_MARGIN = 64
HIT_RADIUS_PX = 2

# Robot geometry (TurtleBot3 Burger, README "The simulated world"): the LDS-01 sits 3 cm behind the centre.
ROBOT_RADIUS_M = 0.105
LIDAR_BEHIND_CENTRE_M = 0.03


# --------------------------------------------------------------------------------------------------
# Geometry shared with the tests
# --------------------------------------------------------------------------------------------------


def decode_hits(tensor: np.ndarray, lidar_pose: Pose, raster_yaw_deg: float = 0.0) -> list[np.ndarray]:
    """World points float64[K, 2] of the lit pixels of each channel (t-2, t-1, t), via ``lidar_pose``.

    Each pixel is taken at its centre (bearing = column turned back by the set's ``raster_yaw_deg``,
    range = (row + 0.5) · 4/63 m). The sentinel
    row means "no return", not an object at 4 m, so it is skipped; padding columns repeat or blank
    real columns, so they are skipped too. All channels use the *one* stored pose (that of t-1): the
    scans t-2 and t were taken from slightly different poses, so their points land slightly off —
    the same smear the detector sees as colour fringes.
    """
    x, y, yaw = lidar_pose
    c, s = math.cos(yaw), math.sin(yaw)
    rotation = np.array([[c, -s], [s, c]])
    points = []
    for channel in range(STACK_DEPTH):
        rows, cols = np.nonzero(tensor[:SENTINEL_ROW, :ANGLE_COLUMNS, channel])
        bearings = raster_to_laser_bearing_deg(pixel_x_to_bearing_deg(cols + 0.5), raster_yaw_deg)
        ranges = pixel_y_to_range_m(rows + 0.5)
        points.append(polar_to_xy(bearings, ranges) @ rotation.T + np.array([x, y]))
    return points


def world_to_map_px(points: np.ndarray) -> np.ndarray:
    """Image pixel (u right, v down) of world points (x right/east, y up/north), float64[..., 2]."""
    pts = np.asarray(points, dtype=np.float64)
    u = MAP_ORIGIN[0] + (pts[..., 0] + MAP_HALF_M) * MAP_PX_PER_M
    v = MAP_ORIGIN[1] + (MAP_HALF_M - pts[..., 1]) * MAP_PX_PER_M
    return np.stack([u, v], axis=-1)


def robot_centre(lidar_pose: Pose) -> tuple[float, float]:
    """The robot centre: the LiDAR sits 3 cm behind it, so the centre is 3 cm ahead along the yaw."""
    x, y, yaw = lidar_pose
    return x + LIDAR_BEHIND_CENTRE_M * math.cos(yaw), y + LIDAR_BEHIND_CENTRE_M * math.sin(yaw)


# --------------------------------------------------------------------------------------------------
# The picture, layer by layer
# --------------------------------------------------------------------------------------------------


def draw_map_picture(sample: Sample) -> Image.Image:
    """The sample's world from above, in metres, with the three scans' hits decoded from the PNG."""
    ox, oy = MAP_ORIGIN
    canvas_w = ox + MAP_SIZE_PX + MAP_PANEL_WIDTH
    canvas_h = oy + MAP_SIZE_PX + MAP_BOTTOM_MARGIN
    image = Image.new("RGB", (canvas_w, canvas_h), BACKGROUND)
    draw = ImageDraw.Draw(image)
    small, font, title_font = load_font(12), load_font(13), load_font(16)
    _draw_metre_grid(draw, small)
    _draw_scene(draw, sample)
    image = _stamp_hits(image, sample)
    draw = ImageDraw.Draw(image)
    _draw_name_tags(draw, sample.scenario, small)
    _draw_people_tags(draw, sample, small)
    _draw_robot(draw, sample.lidar_pose)
    _draw_scale_bar(draw, font)
    title = (
        f"scenario {sample.scenario.index} ({sample.split})   sample {sample.name}   top-down, world frame"
    )
    draw.text((ox, 12), title, font=title_font, fill=TEXT)
    _map_legend(draw, sample, (ox + MAP_SIZE_PX + 20, oy), MAP_PANEL_WIDTH - 36, font)
    return image


def _draw_metre_grid(draw: ImageDraw.ImageDraw, small: Font) -> None:
    """Metre grid with axis labels, the map's frame and the axis names."""
    ox, oy = MAP_ORIGIN
    map_px = MAP_SIZE_PX
    for metres in range(-math.floor(MAP_HALF_M), math.floor(MAP_HALF_M) + 1):
        u, v = world_to_map_px(np.array([metres, metres], dtype=np.float64))
        draw.line([u, oy, u, oy + map_px - 1], fill=GRID)
        draw.line([ox, v, ox + map_px - 1, v], fill=GRID)
        label = f"{metres}"
        draw.text((u - text_width(small, label) / 2, oy + map_px + 4), label, font=small, fill=AXIS)
        draw.text((ox - 8 - text_width(small, label), v - 7), label, font=small, fill=AXIS)
    draw.rectangle([ox - 1, oy - 1, ox + map_px, oy + map_px], outline=AXIS)
    draw.text((ox + map_px - 40, oy + map_px + 18), "x (m)", font=small, fill=MUTED)
    draw.text((4, oy - 18), "y (m)", font=small, fill=MUTED)


def _draw_scene(draw: ImageDraw.ImageDraw, sample: Sample) -> None:
    """Walls, the doorframe and the objects; a labelled class gets a thick outline."""
    for rect in enclosure_rects(sample.scenario.room_half_m) + room_wall_rects(sample.scenario.door):
        _polygon(draw, rect, fill=WALL)
    labelled = {b.class_id for b in sample.boxes}
    door = sample.scenario.door
    door_colour = CLASS_COLOURS[DOORFRAME]
    _polygon(draw, door.frame, outline=door_colour, width=3 if DOORFRAME in labelled else 1)
    opening = world_to_map_px(door.opening)
    draw.line([tuple(opening[0]), tuple(opening[1])], fill=door_colour, width=1)
    for obj in sample.scenario.objects:
        colour = CLASS_COLOURS[obj.class_id]
        width = 3 if obj.class_id in labelled else 1
        if obj.has_legs:
            _polygon(draw, obj.footprint, outline=colour, width=width)
            for leg in obj.leg_rects():
                _polygon(draw, leg, fill=colour, outline=colour)
        else:
            _polygon(draw, obj.footprint, fill=_dim(colour, 0.35), outline=colour, width=width)
    person_colour = CLASS_COLOURS[PERSON]
    for legs in sample.people_legs:
        for x, y, r in legs:
            u, v = world_to_map_px(np.array([x, y], dtype=np.float64))
            radius = r * MAP_SIZE_PX / (2 * MAP_HALF_M)
            draw.ellipse([u - radius, v - radius, u + radius, v + radius], outline=person_colour, width=2)


def _polygon(draw: ImageDraw.ImageDraw, rect: Rect, **style: Any) -> None:
    corners = world_to_map_px(rect.corners())
    draw.polygon([(float(u), float(v)) for u, v in corners], **style)


def _dim(colour: Colour, factor: float) -> Colour:
    return (round(colour[0] * factor), round(colour[1] * factor), round(colour[2] * factor))


def _stamp_hits(image: Image.Image, sample: Sample) -> Image.Image:
    """The decoded hits as dots in their channel colours, pasted over the scene.

    By numpy: one plane per channel, disks stamped by fancy indexing, channels combined by max, so a
    spot hit by t-2 and t-1 shows yellow exactly as the raster does.
    """
    ox, oy = MAP_ORIGIN
    map_px = MAP_SIZE_PX
    canvas = np.asarray(image).copy()
    canvas_h, canvas_w = canvas.shape[:2]
    offsets = _disk_offsets(HIT_RADIUS_PX)
    planes = np.zeros((canvas_h, canvas_w, STACK_DEPTH), dtype=np.uint8)
    for channel, points in enumerate(decode_hits(sample.tensor, sample.lidar_pose, sample.raster_yaw_deg)):
        centres = np.rint(world_to_map_px(points)).astype(np.int64)
        stamped = (centres[:, None, :] + offsets[None, :, :]).reshape(-1, 2)
        inside = (
            (stamped[:, 0] >= ox)
            & (stamped[:, 0] < ox + map_px)
            & (stamped[:, 1] >= oy)
            & (stamped[:, 1] < oy + map_px)
        )
        planes[stamped[inside, 1], stamped[inside, 0], channel] = 255
    lit = planes.any(axis=-1)
    canvas[lit] = planes[lit]
    return Image.fromarray(canvas)


def _disk_offsets(radius: int) -> np.ndarray:
    """int[K, 2] (du, dv) offsets of a filled disk, to stamp hit dots with numpy indexing."""
    d = np.arange(-radius, radius + 1)
    du, dv = np.meshgrid(d, d, indexing="xy")
    inside = du**2 + dv**2 <= radius**2 + radius  # "+ radius": rounder small disks
    return np.stack([du[inside], dv[inside]], axis=-1)


def _draw_people_tags(draw: ImageDraw.ImageDraw, sample: Sample, small: Font) -> None:
    """A "person" tag above each person's legs."""
    for legs in sample.people_legs:
        points = world_to_map_px(np.array([leg[:2] for leg in legs], dtype=np.float64))
        anchor = np.array([points[:, 0].mean(), points[:, 1].min() - 12.0])
        _name_tag(draw, anchor, CLASS_NAMES[PERSON], small, CLASS_COLOURS[PERSON])


def _draw_name_tags(draw: ImageDraw.ImageDraw, scenario: Scenario, small: Font) -> None:
    """A class-name tag per object, drawn after the hits so it stays readable.

    Each sits just above its footprint so it hides none of its own hits; the doorframe's goes inside
    the room, where the wall cannot hide it.
    """
    door = scenario.door
    door_tag = np.asarray(door.frame.center) - 0.35 * np.array([math.cos(door.yaw), math.sin(door.yaw)])
    _name_tag(draw, world_to_map_px(door_tag), CLASS_NAMES[DOORFRAME], small, CLASS_COLOURS[DOORFRAME])
    for obj in scenario.objects:
        corners = world_to_map_px(obj.footprint.corners())
        anchor = np.array([corners[:, 0].mean(), corners[:, 1].min() - 10.0])
        _name_tag(draw, anchor, CLASS_NAMES[obj.class_id], small, CLASS_COLOURS[obj.class_id])


def _name_tag(draw: ImageDraw.ImageDraw, centre: np.ndarray, text: str, font: Font, colour: Colour) -> None:
    """Black text on a class-coloured tag centred on ``centre``: legible over walls, grid and hits."""
    half = text_width(font, text) / 2 + 3
    u, v = float(centre[0]), float(centre[1])
    draw.rectangle([u - half, v - 8, u + half, v + 7], fill=colour)
    draw.text((u - half + 3, v - 8), text, font=font, fill=BACKGROUND)


def _draw_robot(draw: ImageDraw.ImageDraw, lidar_pose: Pose) -> None:
    """The robot on top: outline and heading line only, so hits under it stay visible; a dot at the LiDAR."""
    cx, cy = robot_centre(lidar_pose)
    yaw = lidar_pose[2]
    (cu, cv), (lu, lv) = world_to_map_px(np.array([[cx, cy], lidar_pose[:2]]))
    r = ROBOT_RADIUS_M * MAP_PX_PER_M
    draw.ellipse([cu - r, cv - r, cu + r, cv + r], outline=ROBOT, width=2)
    nose = world_to_map_px(np.array([cx + 0.2 * math.cos(yaw), cy + 0.2 * math.sin(yaw)]))
    draw.line([cu, cv, float(nose[0]), float(nose[1])], fill=ROBOT, width=2)
    draw.ellipse([lu - 2, lv - 2, lu + 2, lv + 2], fill=ROBOT)


def _draw_scale_bar(draw: ImageDraw.ImageDraw, font: Font) -> None:
    """A 1 m scale bar under the map, left."""
    ox, oy = MAP_ORIGIN
    bar_y = oy + MAP_SIZE_PX + 40
    draw.line([ox, bar_y, ox + MAP_PX_PER_M, bar_y], fill=TEXT, width=3)
    for end in (ox, ox + MAP_PX_PER_M):
        draw.line([end, bar_y - 5, end, bar_y + 5], fill=TEXT, width=1)
    draw.text((ox + MAP_PX_PER_M + 8, bar_y - 8), "1 m", font=font, fill=TEXT)


def _map_legend(
    draw: ImageDraw.ImageDraw, sample: Sample, origin: tuple[int, int], width: int, font: Font
) -> None:
    """The map's key: hits per scan, the smear they show, objects, walls, robot and pose."""
    x, y = origin
    heading = load_font(14)
    line = 18

    def paragraph(text: str, colour: Colour = MUTED, indent: int = 0) -> None:
        nonlocal y
        for row in wrap(text, font, width - indent):
            draw.text((x + indent, y), row, font=font, fill=colour)
            y += line

    def swatch_row(colour: Colour, text: str, dot: bool = False) -> None:
        nonlocal y
        if dot:
            draw.ellipse([x + 2, y + 4, x + 10, y + 12], fill=colour)
        else:
            draw.rectangle([x, y + 3, x + 12, y + 13], fill=colour)
        draw.text((x + 20, y), text, font=font, fill=TEXT)
        y += line

    draw.text((x, y), "LiDAR hits, decoded from the PNG", font=heading, fill=TEXT)
    y += line + 4
    for channel in range(STACK_DEPTH):
        swatch_row(CHANNEL_COLOURS[channel], f"scan {CHANNEL_NAMES[channel]}", dot=True)
    paragraph("Mixed colours: the same spot in several scans.")
    y += 4
    paragraph(
        "All three scans are placed with the LiDAR pose of t-1, the only pose stored. "
        "Scans t-2 and t were taken from slightly different poses while the robot moved, "
        "so their hits smear around the objects: that offset is the motion cue the detector "
        "reads as colour fringes."
    )
    y += 10
    draw.text((x, y), "Objects", font=heading, fill=TEXT)
    y += line + 4
    labelled = {b.class_id for b in sample.boxes}
    for class_id, name in enumerate(CLASS_NAMES):
        if class_id == PERSON:
            if not sample.people_legs:
                continue  # a set without people
            count = sum(b.class_id == PERSON for b in sample.boxes)
            swatch_row(
                CLASS_COLOURS[class_id], f"{name}: {count} of {len(sample.people_legs)} labelled (legs)"
            )
            continue
        state = "labelled" if class_id in labelled else "not labelled (< 2 beams)"
        swatch_row(CLASS_COLOURS[class_id], f"{name}: {state}")
    paragraph("Thick outline: labelled in this sample. Filled: legs, or the solid box.")
    room = sample.scenario.room_half_m
    enclosure = room + OUTER_HALF_M - ROOM_HALF_M
    swatch_row(WALL, f"walls: {2 * room:.3g} x {2 * room:.3g} m room, enclosure at {enclosure:.3g} m")
    y += 10
    draw.text((x, y), "Robot", font=heading, fill=TEXT)
    y += line + 4
    paragraph(
        f"Circle r = {ROBOT_RADIUS_M} m with heading line; dot = LiDAR, "
        f"{LIDAR_BEHIND_CENTRE_M * 100:.0f} cm behind the centre.",
        colour=TEXT,
    )
    px, py, pyaw = sample.lidar_pose
    paragraph(f"LiDAR at t-1: x {px:+.2f} m, y {py:+.2f} m, yaw {math.degrees(pyaw) % 360:.0f}°")
    paragraph(f"position {sample.position}, frame {sample.frame}")
