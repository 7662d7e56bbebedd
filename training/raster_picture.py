"""The raster picture (the paper's Figure 3): the 64 × 384 × 3 image the detector reads, made legible.

The raster is magnified, given bearing and range axes, the dashed 0°/360° seam with the padding mode
beside it, the label boxes in per-class colours and a legend for the channels (R = scan t-2, G = t-1,
B = t). Boxes are drawn with their exact pixel bounds, so a box that misses its object's pixels, a
wrong channel order or a mirrored bearing shows at a glance.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from PIL import Image, ImageDraw

from common.encoding import (
    ANGLE_COLUMNS,
    IMAGE_WIDTH,
    R_MAX_M,
    RANGE_ROWS,
    SENTINEL_ROW,
    STACK_DEPTH,
    bearing_to_pixel_x,
    range_to_pixel_y,
)
from common.model_spec import CLASS_COLOURS, CLASS_NAMES
from training.dataset_sample import LabelBox, Sample
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
    legend_flow,
    load_font,
    text_width,
)

# Layout (pixels). Fixed margins: the raster's top-left corner is always RASTER_ORIGIN.
RASTER_ORIGIN: tuple[int, int] = (58, 50)
RASTER_RIGHT_MARGIN = 24
RANGE_TICKS_M = (0, 1, 2, 3, 4)
BEARING_TICKS_DEG = tuple(range(0, ANGLE_COLUMNS, 45))
LEGEND_LINE_PX = 20
DASH_PX = 6  # the model's boxes are dashed, the labels solid


@dataclass(frozen=True)
class DetectedBox:
    """One box the model found, in raster pixels (as ``Detection.box_px``), with its score."""

    class_id: int
    x1: float
    y1: float
    x2: float
    y2: float
    score: float


def draw_raster_picture(sample: Sample, scale: int, detections: Sequence[DetectedBox] = ()) -> Image.Image:
    """The network's input as a picture: magnified RGB raster, axes, label boxes and a legend.

    ``detections`` (the model's boxes) are drawn dashed beside the solid labels, tagged under the box
    with class and score, so the two never hide each other's tags.

    Pixels are magnified by ``scale`` (nearest neighbour) and, for display only, grown by one screen
    pixel: a single lit raster pixel is otherwise hard to see at any sensible size. Boxes are drawn on
    top with their exact pixel bounds, so a box that misses its object's pixels shows it.
    """
    ox, oy = RASTER_ORIGIN
    height_px = RANGE_ROWS * scale
    small, font, title_font = load_font(12), load_font(13), load_font(16)
    seam_label = f"360° | {sample.padding} padding"
    title = (
        f"scenario {sample.scenario.index} ({sample.split})   sample {sample.name}   "
        f"raster 64 x 384 x 3, shown x{scale}"
    )
    caption = (
        "x: bearing (degrees, counter-clockwise from forward)    y: range (rows of 4/63 m, row 0 nearest)"
    )
    canvas_w = max(
        ox + IMAGE_WIDTH * scale + RASTER_RIGHT_MARGIN,
        round(_seam_label_right(seam_label, scale, small)) + 12,
        ox + 420,  # room for a readable legend even at scale 1
        ox + round(text_width(title_font, title)) + 12,
        ox + round(text_width(small, caption)) + 12,
    )
    legend_width = canvas_w - ox - 16
    # Lay the legend out once off-screen to learn its height, then draw it for real.
    legend_items = _raster_legend_items(sample)
    if detections:
        legend_items.append(
            (None, f"dashed: the model's {len(detections)} boxes, tagged under them with their score")
        )
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    legend_bottom = legend_flow(probe, legend_items, (0, 0), legend_width, font, LEGEND_LINE_PX)
    canvas_h = oy + height_px + 46 + legend_bottom + 16
    image = Image.new("RGB", (canvas_w, canvas_h), BACKGROUND)
    _draw_axes(ImageDraw.Draw(image), scale, seam_label, small)  # grid first, so lit pixels paint over it
    image = _paste_lit_pixels(image, sample.tensor, scale)
    draw = ImageDraw.Draw(image)
    _draw_label_boxes(draw, sample.boxes, scale, small, canvas_w)
    _draw_detected_boxes(draw, detections, scale, small, canvas_w)
    draw.text((ox, 12), title, font=title_font, fill=TEXT)
    draw.text((ox, oy + height_px + 24), caption, font=small, fill=MUTED)
    legend_flow(draw, legend_items, (ox, oy + height_px + 46), legend_width, font, LEGEND_LINE_PX)
    return image


def _seam_label_right(seam_label: str, scale: int, font: Font) -> float:
    """Right end of the seam's label, which starts centred under the 360° column and may overhang."""
    ox = RASTER_ORIGIN[0]
    return ox + ANGLE_COLUMNS * scale + text_width(font, seam_label) - text_width(font, "360°") / 2


def _draw_axes(draw: ImageDraw.ImageDraw, scale: int, seam_label: str, small: Font) -> None:
    """Range and bearing grid with tick labels, the dashed 0°/360° seam and the raster's frame."""
    ox, oy = RASTER_ORIGIN
    width_px, height_px = IMAGE_WIDTH * scale, RANGE_ROWS * scale
    for metres in RANGE_TICKS_M:
        y = oy + round(float(range_to_pixel_y(metres)) * scale)
        draw.line([ox, y, ox + width_px - 1, y], fill=GRID)
        draw.line([ox - 6, y, ox - 1, y], fill=AXIS)
        label = f"{metres} m"
        draw.text((ox - 9 - text_width(small, label), y - 7), label, font=small, fill=AXIS)
    for degrees in BEARING_TICKS_DEG:
        x = ox + round(float(bearing_to_pixel_x(degrees)) * scale)
        draw.line([x, oy, x, oy + height_px - 1], fill=GRID)
        draw.line([x, oy + height_px, x, oy + height_px + 5], fill=AXIS)
        label = f"{degrees}°"
        draw.text((x - text_width(small, label) / 2, oy + height_px + 7), label, font=small, fill=AXIS)
    seam_x = ox + ANGLE_COLUMNS * scale
    for y in range(oy, oy + height_px, 6):  # dashed: a boundary, not data
        draw.line([seam_x, y, seam_x, min(y + 3, oy + height_px - 1)], fill=AXIS)
    draw.text((seam_x - text_width(small, "360°") / 2, oy + height_px + 7), seam_label, font=small, fill=AXIS)
    draw.rectangle([ox - 1, oy - 1, ox + width_px, oy + height_px], outline=AXIS)


def _paste_lit_pixels(image: Image.Image, tensor: np.ndarray, scale: int) -> Image.Image:
    """The raster by numpy: magnify, grow by one display pixel, paste where any channel is lit."""
    ox, oy = RASTER_ORIGIN
    width_px, height_px = IMAGE_WIDTH * scale, RANGE_ROWS * scale
    magnified = np.repeat(np.repeat(tensor, scale, axis=0), scale, axis=1)
    shown = _dilate(magnified) if scale >= 2 else magnified
    canvas = np.asarray(image).copy()
    region = canvas[oy : oy + height_px, ox : ox + width_px]
    lit = shown.any(axis=-1)
    region[lit] = shown[lit]
    return Image.fromarray(canvas)


def _dilate(image: np.ndarray) -> np.ndarray:
    """Per-channel 3 × 3 maximum: lit pixels grow by one display pixel, mixed colours stay mixed."""
    padded = np.pad(image, ((1, 1), (1, 1), (0, 0)))
    h, w = image.shape[:2]
    shifts = [padded[dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3)]
    return np.max(np.stack(shifts), axis=0)


def _draw_label_boxes(
    draw: ImageDraw.ImageDraw, boxes: tuple[LabelBox, ...], scale: int, small: Font, canvas_w: int
) -> None:
    """Each label box at its exact pixel bounds, in its class colour, with a name tag on its top edge."""
    ox, oy = RASTER_ORIGIN
    line_width = 2 if scale >= 3 else 1
    for box in boxes:
        colour = CLASS_COLOURS[box.class_id]
        left, top = ox + round(box.x1 * scale), oy + round(box.y1 * scale)
        right, bottom = ox + round(box.x2 * scale) - 1, oy + round(box.y2 * scale) - 1
        draw.rectangle([left, top, right, bottom], outline=colour, width=line_width)
        name = CLASS_NAMES[box.class_id]
        tag_w = round(text_width(small, name)) + 6
        # The tag sits on the box's top edge, outside it, so it hides none of the pixels it labels;
        # a box at the right border gets its tag shifted left rather than cut off.
        tag_left = min(left, canvas_w - tag_w - 2)
        draw.rectangle([tag_left, top - 15, tag_left + tag_w, top - 1], fill=colour)
        draw.text((tag_left + 3, top - 15), name, font=small, fill=BACKGROUND)


def _draw_detected_boxes(
    draw: ImageDraw.ImageDraw, boxes: Sequence[DetectedBox], scale: int, small: Font, canvas_w: int
) -> None:
    """Each of the model's boxes dashed in its class colour, tagged with class and score under it."""
    line_width = 2 if scale >= 3 else 1
    for box in boxes:
        colour = CLASS_COLOURS[box.class_id]
        left, top, right, bottom = _screen_rect(box, scale)
        for x in range(left, right + 1, 2 * DASH_PX):
            draw.line([x, top, min(x + DASH_PX - 1, right), top], fill=colour, width=line_width)
            draw.line([x, bottom, min(x + DASH_PX - 1, right), bottom], fill=colour, width=line_width)
        for y in range(top, bottom + 1, 2 * DASH_PX):
            draw.line([left, y, left, min(y + DASH_PX - 1, bottom)], fill=colour, width=line_width)
            draw.line([right, y, right, min(y + DASH_PX - 1, bottom)], fill=colour, width=line_width)
        tag = f"{CLASS_NAMES[box.class_id]} {box.score:.2f}"
        tag_left = min(left, canvas_w - round(text_width(small, tag)) - 8)  # kept inside the canvas
        draw.rectangle(
            [tag_left, bottom + 1, tag_left + text_width(small, tag) + 6, bottom + 15], fill=BACKGROUND
        )
        draw.text((tag_left + 3, bottom + 1), tag, font=small, fill=colour)


def _screen_rect(box: DetectedBox, scale: int) -> tuple[int, int, int, int]:
    """A raster box's (left, top, right, bottom) picture pixels: its exact bounds, magnified."""
    ox, oy = RASTER_ORIGIN
    return (
        ox + round(box.x1 * scale),
        oy + round(box.y1 * scale),
        ox + round(box.x2 * scale) - 1,
        oy + round(box.y2 * scale) - 1,
    )


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
