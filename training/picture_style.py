"""What the two ``triscan show`` pictures share so they read as one figure: palette, font and legend text.

The raster picture and the top-down map are looked at side by side, so a scan's channel has one
colour and one name in both, and so does the background, the grid and the text. Text uses only
Pillow's embedded font (no file on disk, no download), so the pictures come out the same on every
machine; the few layout helpers here (width, wrapping, a flowing legend) work in that font's pixels.
Class colours are not here: they are :data:`common.model_spec.CLASS_COLOURS`, shared with the viewer.
"""

from __future__ import annotations

from PIL import ImageDraw, ImageFont

Colour = tuple[int, int, int]
Font = ImageFont.FreeTypeFont | ImageFont.ImageFont

CHANNEL_COLOURS: tuple[Colour, ...] = ((255, 0, 0), (0, 255, 0), (0, 0, 255))
CHANNEL_NAMES: tuple[str, ...] = ("t-2 (oldest)", "t-1 (middle, labelled)", "t (newest)")
BACKGROUND: Colour = (0, 0, 0)
GRID: Colour = (48, 48, 48)
AXIS: Colour = (170, 170, 170)
TEXT: Colour = (235, 235, 235)
MUTED: Colour = (150, 150, 150)


def load_font(size: int) -> Font:
    """Pillow's embedded font (no file on disk, no download), so pictures render the same everywhere."""
    return ImageFont.load_default(size=size)


def text_width(font: Font, text: str) -> float:
    return float(font.getlength(text))


def wrap(text: str, font: Font, width: float) -> list[str]:
    """Greedy word wrap to ``width`` pixels: legends are prose and the panel is narrow."""
    lines: list[str] = []
    current = ""
    for word in text.split():
        candidate = f"{current} {word}".strip()
        if current and text_width(font, candidate) > width:
            lines.append(current)
            current = word
        else:
            current = candidate
    if current:
        lines.append(current)
    return lines


def legend_flow(
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
        item_width = (swatch + 6 if colour else 0) + text_width(font, text) + 18
        if x > x0 and x + item_width > x0 + width:
            x, y = x0, y + line_height
        if colour is not None:
            draw.rectangle([x, y + 3, x + swatch - 1, y + 3 + swatch - 1], fill=colour)
            x += swatch + 6
        draw.text((x, y + 1), text, font=font, fill=TEXT)
        x += round(text_width(font, text)) + 18
    return y + line_height
