"""Pictures of one data-set sample: its RGB raster with label boxes, and the world it came from.

``triscan show`` draws two PNGs per sample, for eyeballing a data set and for the README:

* the **raster picture** (the paper's Figure 3): the 64 × 384 three-channel image the detector reads,
  magnified, with bearing/range axes, the label boxes in per-class colours and a legend for the
  channels (R = scan t-2, G = t-1, B = t);
* the **top-down map** (the paper's Figure 1): the scenario's room, objects and robot in metres, with
  the LiDAR hits of the three scans *decoded back from the PNG* and drawn in their channel colours.

Decoding the hits from the PNG rather than re-simulating them is deliberate: the map then shows what
the network actually gets (quantised to 1° × 4/63 m pixels), so a wrong channel order, a mirrored
bearing or a label box that misses its object is visible at a glance. Only Pillow and numpy are used,
and only Pillow's embedded font, so the pictures are the same on every machine.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from common.encoding import (
    ANGLE_COLUMNS,
    IMAGE_WIDTH,
    PAD_COLUMNS,
    R_MAX_M,
    RANGE_ROWS,
    SENTINEL_ROW,
    STACK_DEPTH,
    bearing_to_pixel_x,
    pixel_x_to_bearing_deg,
    pixel_y_to_range_m,
    polar_to_xy,
    range_to_pixel_y,
)
from common.model_spec import CLASS_COLOURS, CLASS_NAMES
from services.simulator.scenario import (
    DOORFRAME,
    Rect,
    Scenario,
    enclosure_rects,
    room_wall_rects,
)

log = logging.getLogger(__name__)

Colour = tuple[int, int, int]
Pose = tuple[float, float, float]
Font = ImageFont.FreeTypeFont | ImageFont.ImageFont

CHANNEL_COLOURS: tuple[Colour, ...] = ((255, 0, 0), (0, 255, 0), (0, 0, 255))
CHANNEL_NAMES: tuple[str, ...] = ("t-2 (oldest)", "t-1 (middle, labelled)", "t (newest)")
BACKGROUND: Colour = (0, 0, 0)
GRID: Colour = (48, 48, 48)
AXIS: Colour = (170, 170, 170)
TEXT: Colour = (235, 235, 235)
MUTED: Colour = (150, 150, 150)
WALL: Colour = (105, 105, 110)
ROBOT: Colour = (255, 255, 255)

MAX_SCALE = 16  # 384 · 16 = 6144 px wide; beyond that the picture is just big, not clearer

# Raster picture layout (pixels). Fixed margins: the raster's top-left corner is always RASTER_ORIGIN.
RASTER_ORIGIN: tuple[int, int] = (58, 50)
RASTER_RIGHT_MARGIN = 24
RANGE_TICKS_M = (0, 1, 2, 3, 4)
BEARING_TICKS_DEG = tuple(range(0, ANGLE_COLUMNS, 45))

# Top-down map layout: 100 px per metre over [-3.3, 3.3]^2, y up, x right (world frame, REP-103).
MAP_PX_PER_M = 100.0
MAP_HALF_M = 3.3
MAP_ORIGIN: tuple[int, int] = (48, 44)  # image pixel of the map's top-left corner (-3.3, +3.3)
MAP_PANEL_WIDTH = 320
MAP_BOTTOM_MARGIN = 64
HIT_RADIUS_PX = 2

# Robot geometry (TurtleBot3 Burger, README "The simulated world"): the LDS-01 sits 3 cm behind the centre.
ROBOT_RADIUS_M = 0.105
LIDAR_BEHIND_CENTRE_M = 0.03


@dataclass(frozen=True)
class LabelBox:
    """One YOLO label line in raster pixels (continuous coordinates, x2/y2 exclusive)."""

    class_id: int
    x1: float
    y1: float
    x2: float
    y2: float


@dataclass(frozen=True)
class Sample:
    """Everything the two pictures need about one sample, read and checked from the data set."""

    name: str
    image_path: Path
    split: str
    tensor: np.ndarray  # uint8[64, 384, 3]: channel 0 = t-2, 1 = t-1, 2 = t
    boxes: tuple[LabelBox, ...]
    lidar_pose: Pose  # of the middle scan t-1, world frame
    scenario: Scenario
    position: int
    frame: int
    padding: str


# --------------------------------------------------------------------------------------------------
# Reading a sample
# --------------------------------------------------------------------------------------------------


def _read_jsonl(path: Path) -> list[dict[str, Any]]:
    """Every record of a JSON-lines file; a bad line is named (file:line), as sets get hand-edited."""
    if not path.is_file():
        raise FileNotFoundError(f"data set file {path} is missing (is this a `triscan dataset` output?)")
    records = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}:{number}: not valid JSON ({exc.msg})") from exc
    return records


def _select_record(
    records: list[dict[str, Any]], samples_path: Path, sample: str | None, index: int
) -> dict[str, Any]:
    """Find the sample by image path (``images/train/x.png``), file name or stem; else by line index."""
    if not records:
        raise ValueError(f"{samples_path} lists no samples")
    if sample is None:
        if not 0 <= index < len(records):
            raise ValueError(
                f"sample index {index} is out of range: {samples_path} has {len(records)} samples "
                f"(valid: 0..{len(records) - 1})"
            )
        return records[index]
    wanted = sample.strip().replace("\\", "/")
    for record in records:
        image = str(record.get("image", ""))
        if wanted in (image, Path(image).name, Path(image).stem):
            return record
    examples = ", ".join(Path(str(r.get("image", ""))).stem for r in records[:3])
    raise ValueError(
        f"sample {sample!r} is not in {samples_path} ({len(records)} samples, e.g. {examples}); "
        "give an image path like images/train/<name>.png, a file name or a stem"
    )


def _read_tensor(image_path: Path) -> np.ndarray:
    """The PNG as the uint8[64, 384, 3] tensor, in file channel order (R = t-2, as written)."""
    if not image_path.is_file():
        raise FileNotFoundError(f"sample image {image_path} is missing")
    with Image.open(image_path) as image:
        if image.mode != "RGB" or image.size != (IMAGE_WIDTH, RANGE_ROWS):
            raise ValueError(
                f"{image_path} is {image.mode} {image.size[0]}x{image.size[1]}, "
                f"expected RGB {IMAGE_WIDTH}x{RANGE_ROWS}"
            )
        return np.asarray(image, dtype=np.uint8).copy()


def _read_boxes(label_path: Path) -> tuple[LabelBox, ...]:
    """YOLO lines ``cls xc yc w h`` (normalised by 384 and 64) back to raster-pixel boxes."""
    if not label_path.is_file():
        raise FileNotFoundError(f"label file {label_path} is missing")
    boxes = []
    for number, line in enumerate(label_path.read_text().splitlines(), start=1):
        fields = line.split()
        if not fields:
            continue
        try:
            if len(fields) != 5:
                raise ValueError(f"{len(fields)} fields")
            class_id = int(fields[0])
            xc, yc, w, h = (float(v) for v in fields[1:])
        except ValueError as exc:
            raise ValueError(f"{label_path}:{number}: expected 'cls xc yc w h', got {line!r}") from exc
        if not 0 <= class_id < len(CLASS_NAMES):
            raise ValueError(
                f"{label_path}:{number}: class {class_id} is not one of 0..{len(CLASS_NAMES) - 1}"
            )
        boxes.append(
            LabelBox(
                class_id,
                (xc - w / 2) * IMAGE_WIDTH,
                (yc - h / 2) * RANGE_ROWS,
                (xc + w / 2) * IMAGE_WIDTH,
                (yc + h / 2) * RANGE_ROWS,
            )
        )
    return tuple(boxes)


def _padding_of(dataset_dir: Path, tensor: np.ndarray) -> str:
    """The set's padding mode from summary.json; an old set without one is judged from its pixels."""
    summary = dataset_dir / "summary.json"
    if summary.is_file():
        padding = json.loads(summary.read_text()).get("config", {}).get("padding")
        if isinstance(padding, str):
            return padding
    pad = tensor[:, ANGLE_COLUMNS:]
    if not pad.any():
        return "zero"
    return "wrap" if np.array_equal(pad, tensor[:, :PAD_COLUMNS]) else "unknown"


def load_sample(dataset_dir: Path, *, sample: str | None = None, index: int = 0) -> Sample:
    """Read one sample (image, labels, pose, scenario) from a data set written by ``training.dataset``.

    Raises ``FileNotFoundError`` naming the missing file and ``ValueError`` for an unknown sample, an
    index out of range or a malformed file: ``triscan show`` reports both as one clear line.
    """
    dataset_dir = Path(dataset_dir)
    if not dataset_dir.is_dir():
        raise FileNotFoundError(f"data set directory {dataset_dir} does not exist")
    samples_path = dataset_dir / "samples.jsonl"
    scenarios_path = dataset_dir / "scenarios.jsonl"
    record = _select_record(_read_jsonl(samples_path), samples_path, sample, index)
    try:
        image_rel = Path(str(record["image"]))
        scenario_index = int(record["scenario"])
        pose = tuple(float(v) for v in record["lidar_pose"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{samples_path}: malformed sample record {record!r}") from exc
    if len(pose) != 3:
        raise ValueError(f"{samples_path}: lidar_pose of {image_rel} must be [x, y, yaw], got {pose}")
    scenario_record = next(
        (r for r in _read_jsonl(scenarios_path) if int(r.get("index", -1)) == scenario_index), None
    )
    if scenario_record is None:
        raise ValueError(f"scenario {scenario_index} of sample {image_rel} is not in {scenarios_path}")
    if len(image_rel.parts) < 3 or image_rel.parts[0] != "images":
        raise ValueError(f"{samples_path}: image path {image_rel} is not images/<split>/<name>.png")
    split = image_rel.parts[1]
    label_path = dataset_dir / "labels" / Path(*image_rel.parts[1:]).with_suffix(".txt")
    tensor = _read_tensor(dataset_dir / image_rel)
    return Sample(
        name=image_rel.stem,
        image_path=dataset_dir / image_rel,
        split=str(scenario_record.get("split", split)),
        tensor=tensor,
        boxes=_read_boxes(label_path),
        lidar_pose=(pose[0], pose[1], pose[2]),
        scenario=Scenario.from_json(scenario_record),
        position=int(record.get("position", -1)),
        frame=int(record.get("frame", -1)),
        padding=_padding_of(dataset_dir, tensor),
    )


# --------------------------------------------------------------------------------------------------
# Geometry shared with the tests
# --------------------------------------------------------------------------------------------------


def decode_hits(tensor: np.ndarray, lidar_pose: Pose) -> list[np.ndarray]:
    """World points float64[K, 2] of the lit pixels of each channel (t-2, t-1, t), via ``lidar_pose``.

    Each pixel is taken at its centre (bearing = column, range = (row + 0.5) · 4/63 m). The sentinel
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
        bearings = pixel_x_to_bearing_deg(cols + 0.5)
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
# Drawing helpers
# --------------------------------------------------------------------------------------------------


def _font(size: int) -> Font:
    """Pillow's embedded font (no file on disk, no download), so pictures render the same everywhere."""
    return ImageFont.load_default(size=size)


def _text_width(font: Font, text: str) -> float:
    return float(font.getlength(text))


def _wrap(text: str, font: Font, width: float) -> list[str]:
    """Greedy word wrap to ``width`` pixels: legends are prose and the panel is narrow."""
    lines: list[str] = []
    current = ""
    for word in text.split():
        candidate = f"{current} {word}".strip()
        if current and _text_width(font, candidate) > width:
            lines.append(current)
            current = word
        else:
            current = candidate
    if current:
        lines.append(current)
    return lines


def _dim(colour: Colour, factor: float) -> Colour:
    return (round(colour[0] * factor), round(colour[1] * factor), round(colour[2] * factor))


def _dilate(image: np.ndarray) -> np.ndarray:
    """Per-channel 3 × 3 maximum: lit pixels grow by one display pixel, mixed colours stay mixed."""
    padded = np.pad(image, ((1, 1), (1, 1), (0, 0)))
    h, w = image.shape[:2]
    shifts = [padded[dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3)]
    return np.max(np.stack(shifts), axis=0)


def _disk_offsets(radius: int) -> np.ndarray:
    """int[K, 2] (du, dv) offsets of a filled disk, to stamp hit dots with numpy indexing."""
    d = np.arange(-radius, radius + 1)
    du, dv = np.meshgrid(d, d, indexing="xy")
    inside = du**2 + dv**2 <= radius**2 + radius  # "+ radius": rounder small disks
    return np.stack([du[inside], dv[inside]], axis=-1)


def _legend_flow(
    draw: ImageDraw.ImageDraw,
    items: list[tuple[Colour | None, str]],
    origin: tuple[int, int],
    width: int,
    font: Font,
    line_height: int,
) -> int:
    """Draw (swatch, text) items left to right, wrapping at ``width``; return the y below the last row."""
    x0, y = origin
    x = x0
    swatch = line_height - 6
    for colour, text in items:
        item_width = (swatch + 6 if colour else 0) + _text_width(font, text) + 18
        if x > x0 and x + item_width > x0 + width:
            x, y = x0, y + line_height
        if colour is not None:
            draw.rectangle([x, y + 3, x + swatch - 1, y + 3 + swatch - 1], fill=colour)
            x += swatch + 6
        draw.text((x, y + 1), text, font=font, fill=TEXT)
        x += round(_text_width(font, text)) + 18
    return y + line_height


# --------------------------------------------------------------------------------------------------
# The raster picture
# --------------------------------------------------------------------------------------------------


def draw_raster_picture(sample: Sample, scale: int) -> Image.Image:
    """The network's input as a picture: magnified RGB raster, axes, label boxes and a legend.

    Pixels are magnified by ``scale`` (nearest neighbour) and, for display only, grown by one screen
    pixel: a single lit raster pixel is otherwise hard to see at any sensible size. Boxes are drawn on
    top with their exact pixel bounds, so a box that misses its object's pixels shows it.
    """
    ox, oy = RASTER_ORIGIN
    width_px, height_px = IMAGE_WIDTH * scale, RANGE_ROWS * scale
    small, font, title_font = _font(12), _font(13), _font(16)
    seam_label = f"360° | {sample.padding} padding"
    seam_label_right = (
        ox + ANGLE_COLUMNS * scale + _text_width(small, seam_label) - _text_width(small, "360°") / 2
    )
    title = (
        f"scenario {sample.scenario.index} ({sample.split})   sample {sample.name}   "
        f"raster 64 x 384 x 3, shown x{scale}"
    )
    caption = (
        "x: bearing (degrees, counter-clockwise from forward)    y: range (rows of 4/63 m, row 0 nearest)"
    )
    canvas_w = max(
        ox + width_px + RASTER_RIGHT_MARGIN,
        round(seam_label_right) + 12,
        ox + 420,  # room for a readable legend even at scale 1
        ox + round(_text_width(title_font, title)) + 12,
        ox + round(_text_width(small, caption)) + 12,
    )
    legend_width = canvas_w - ox - 16
    # Lay the legend out once off-screen to learn its height, then draw it for real.
    legend_items = _raster_legend_items(sample)
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    legend_bottom = _legend_flow(probe, legend_items, (0, 0), legend_width, font, 20)
    canvas_h = oy + height_px + 46 + legend_bottom + 16
    image = Image.new("RGB", (canvas_w, canvas_h), BACKGROUND)
    draw = ImageDraw.Draw(image)

    # Grid first, so lit pixels paint over it.
    for metres in RANGE_TICKS_M:
        y = oy + round(float(range_to_pixel_y(metres)) * scale)
        draw.line([ox, y, ox + width_px - 1, y], fill=GRID)
        draw.line([ox - 6, y, ox - 1, y], fill=AXIS)
        label = f"{metres} m"
        draw.text((ox - 9 - _text_width(small, label), y - 7), label, font=small, fill=AXIS)
    for degrees in BEARING_TICKS_DEG:
        x = ox + round(float(bearing_to_pixel_x(degrees)) * scale)
        draw.line([x, oy, x, oy + height_px - 1], fill=GRID)
        draw.line([x, oy + height_px, x, oy + height_px + 5], fill=AXIS)
        label = f"{degrees}°"
        draw.text((x - _text_width(small, label) / 2, oy + height_px + 7), label, font=small, fill=AXIS)
    seam_x = ox + ANGLE_COLUMNS * scale
    for y in range(oy, oy + height_px, 6):  # dashed: a boundary, not data
        draw.line([seam_x, y, seam_x, min(y + 3, oy + height_px - 1)], fill=AXIS)
    draw.text(
        (seam_x - _text_width(small, "360°") / 2, oy + height_px + 7), seam_label, font=small, fill=AXIS
    )
    draw.rectangle([ox - 1, oy - 1, ox + width_px, oy + height_px], outline=AXIS)

    # Lit pixels by numpy: magnify, grow by one display pixel, paste where any channel is lit.
    magnified = np.repeat(np.repeat(sample.tensor, scale, axis=0), scale, axis=1)
    shown = _dilate(magnified) if scale >= 2 else magnified
    canvas = np.asarray(image).copy()
    region = canvas[oy : oy + height_px, ox : ox + width_px]
    lit = shown.any(axis=-1)
    region[lit] = shown[lit]
    image = Image.fromarray(canvas)
    draw = ImageDraw.Draw(image)

    line_width = 2 if scale >= 3 else 1
    for box in sample.boxes:
        colour = CLASS_COLOURS[box.class_id]
        left, top = ox + round(box.x1 * scale), oy + round(box.y1 * scale)
        right, bottom = ox + round(box.x2 * scale) - 1, oy + round(box.y2 * scale) - 1
        draw.rectangle([left, top, right, bottom], outline=colour, width=line_width)
        name = CLASS_NAMES[box.class_id]
        tag_w = round(_text_width(small, name)) + 6
        # The tag sits on the box's top edge, outside it, so it hides none of the pixels it labels;
        # a box at the right border gets its tag shifted left rather than cut off.
        tag_left = min(left, canvas_w - tag_w - 2)
        draw.rectangle([tag_left, top - 15, tag_left + tag_w, top - 1], fill=colour)
        draw.text((tag_left + 3, top - 15), name, font=small, fill=BACKGROUND)

    draw.text((ox, 12), title, font=title_font, fill=TEXT)
    draw.text((ox, oy + height_px + 24), caption, font=small, fill=MUTED)
    _legend_flow(draw, legend_items, (ox, oy + height_px + 46), legend_width, font, 20)
    return image


def _raster_legend_items(sample: Sample) -> list[tuple[Colour | None, str]]:
    labelled = sorted({b.class_id for b in sample.boxes})
    items: list[tuple[Colour | None, str]] = [
        (CHANNEL_COLOURS[i], f"{'RGB'[i]} = scan {CHANNEL_NAMES[i]}") for i in range(STACK_DEPTH)
    ]
    items.append((None, "(mixed colour: pixel lit in several scans; white = all three)"))
    items.append((None, "label boxes of scan t-1:" if labelled else "no labelled object in this sample"))
    items += [(CLASS_COLOURS[c], CLASS_NAMES[c]) for c in labelled]
    items.append((None, f"bottom row {SENTINEL_ROW}: no return (sentinel, {R_MAX_M:g} m)"))
    return items


# --------------------------------------------------------------------------------------------------
# The top-down map
# --------------------------------------------------------------------------------------------------


def _polygon(draw: ImageDraw.ImageDraw, rect: Rect, **style: Any) -> None:
    corners = world_to_map_px(rect.corners())
    draw.polygon([(float(u), float(v)) for u, v in corners], **style)


def draw_map_picture(sample: Sample) -> Image.Image:
    """The sample's world from above, in metres, with the three scans' hits decoded from the PNG."""
    map_px = round(2 * MAP_HALF_M * MAP_PX_PER_M)
    ox, oy = MAP_ORIGIN
    canvas_w = ox + map_px + MAP_PANEL_WIDTH
    canvas_h = oy + map_px + MAP_BOTTOM_MARGIN
    image = Image.new("RGB", (canvas_w, canvas_h), BACKGROUND)
    draw = ImageDraw.Draw(image)
    small, font, title_font = _font(12), _font(13), _font(16)

    # Metre grid with axis labels.
    for metres in range(-math.floor(MAP_HALF_M), math.floor(MAP_HALF_M) + 1):
        u, v = world_to_map_px(np.array([metres, metres], dtype=np.float64))
        draw.line([u, oy, u, oy + map_px - 1], fill=GRID)
        draw.line([ox, v, ox + map_px - 1, v], fill=GRID)
        label = f"{metres}"
        draw.text((u - _text_width(small, label) / 2, oy + map_px + 4), label, font=small, fill=AXIS)
        draw.text((ox - 8 - _text_width(small, label), v - 7), label, font=small, fill=AXIS)
    draw.rectangle([ox - 1, oy - 1, ox + map_px, oy + map_px], outline=AXIS)
    draw.text((ox + map_px - 40, oy + map_px + 18), "x (m)", font=small, fill=MUTED)
    draw.text((4, oy - 18), "y (m)", font=small, fill=MUTED)

    for rect in enclosure_rects() + room_wall_rects(sample.scenario.door):
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

    # Hits by numpy: one plane per channel, disks stamped by fancy indexing, channels combined by max,
    # so a spot hit by t-2 and t-1 shows yellow exactly as the raster does.
    canvas = np.asarray(image).copy()
    offsets = _disk_offsets(HIT_RADIUS_PX)
    planes = np.zeros((canvas_h, canvas_w, STACK_DEPTH), dtype=np.uint8)
    for channel, points in enumerate(decode_hits(sample.tensor, sample.lidar_pose)):
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
    image = Image.fromarray(canvas)
    draw = ImageDraw.Draw(image)

    # Name tags after the hits so they stay readable, just above each footprint so they hide none of
    # its own hits; the doorframe's goes inside the room, where the wall cannot hide it.
    door_tag = np.asarray(door.frame.center) - 0.35 * np.array([math.cos(door.yaw), math.sin(door.yaw)])
    _name_tag(draw, world_to_map_px(door_tag), CLASS_NAMES[DOORFRAME], small, door_colour)
    for obj in sample.scenario.objects:
        corners = world_to_map_px(obj.footprint.corners())
        anchor = np.array([corners[:, 0].mean(), corners[:, 1].min() - 10.0])
        _name_tag(draw, anchor, CLASS_NAMES[obj.class_id], small, CLASS_COLOURS[obj.class_id])

    # Robot on top: outline only, so hits under it stay visible.
    cx, cy = robot_centre(sample.lidar_pose)
    yaw = sample.lidar_pose[2]
    (cu, cv), (lu, lv) = world_to_map_px(np.array([[cx, cy], sample.lidar_pose[:2]]))
    r = ROBOT_RADIUS_M * MAP_PX_PER_M
    draw.ellipse([cu - r, cv - r, cu + r, cv + r], outline=ROBOT, width=2)
    nose = world_to_map_px(np.array([cx + 0.2 * math.cos(yaw), cy + 0.2 * math.sin(yaw)]))
    draw.line([cu, cv, float(nose[0]), float(nose[1])], fill=ROBOT, width=2)
    draw.ellipse([lu - 2, lv - 2, lu + 2, lv + 2], fill=ROBOT)

    # Scale bar under the map, left.
    bar_y = oy + map_px + 40
    draw.line([ox, bar_y, ox + MAP_PX_PER_M, bar_y], fill=TEXT, width=3)
    for end in (ox, ox + MAP_PX_PER_M):
        draw.line([end, bar_y - 5, end, bar_y + 5], fill=TEXT, width=1)
    draw.text((ox + MAP_PX_PER_M + 8, bar_y - 8), "1 m", font=font, fill=TEXT)

    title = (
        f"scenario {sample.scenario.index} ({sample.split})   sample {sample.name}   top-down, world frame"
    )
    draw.text((ox, 12), title, font=title_font, fill=TEXT)
    _map_legend(draw, sample, (ox + map_px + 20, oy), MAP_PANEL_WIDTH - 36, font)
    return image


def _name_tag(draw: ImageDraw.ImageDraw, centre: np.ndarray, text: str, font: Font, colour: Colour) -> None:
    """Black text on a class-coloured tag centred on ``centre``: legible over walls, grid and hits."""
    half = _text_width(font, text) / 2 + 3
    u, v = float(centre[0]), float(centre[1])
    draw.rectangle([u - half, v - 8, u + half, v + 7], fill=colour)
    draw.text((u - half + 3, v - 8), text, font=font, fill=BACKGROUND)


def _map_legend(
    draw: ImageDraw.ImageDraw, sample: Sample, origin: tuple[int, int], width: int, font: Font
) -> None:
    """The map's key: hits per scan, the smear they show, objects, walls, robot and pose."""
    x, y = origin
    heading = _font(14)
    line = 18

    def paragraph(text: str, colour: Colour = MUTED, indent: int = 0) -> None:
        nonlocal y
        for row in _wrap(text, font, width - indent):
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
        state = "labelled" if class_id in labelled else "not labelled (< 2 beams)"
        swatch_row(CLASS_COLOURS[class_id], f"{name}: {state}")
    paragraph("Thick outline: labelled in this sample. Filled: legs, or the solid box.")
    swatch_row(WALL, "walls: 4 x 4 m room, enclosure at 3.1 m")
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


# --------------------------------------------------------------------------------------------------
# Entry point of `triscan show`
# --------------------------------------------------------------------------------------------------


def render_sample(
    dataset_dir: Path, out_dir: Path, *, sample: str | None, index: int, scale: int
) -> tuple[Path, Path]:
    """Write ``<name>_raster.png`` and ``<name>_map.png`` for one sample; return their paths.

    ``sample`` (image path, file name or stem) wins over ``index`` (line of samples.jsonl).
    """
    if not 1 <= scale <= MAX_SCALE:
        raise ValueError(f"scale must be between 1 and {MAX_SCALE}, got {scale}")
    chosen = load_sample(Path(dataset_dir), sample=sample, index=index)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    raster_png = out_dir / f"{chosen.name}_raster.png"
    map_png = out_dir / f"{chosen.name}_map.png"
    # Draw both before writing either, so a failure never leaves half a pair behind.
    raster_picture, map_picture = draw_raster_picture(chosen, scale), draw_map_picture(chosen)
    raster_picture.save(raster_png)
    map_picture.save(map_png)
    log.info(
        "sample %s (scenario %d, %s, %d boxes): wrote %s and %s",
        chosen.name,
        chosen.scenario.index,
        chosen.split,
        len(chosen.boxes),
        raster_png,
        map_png,
    )
    return raster_png, map_png
