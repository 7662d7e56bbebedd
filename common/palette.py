"""One fixed colour per detection class, shared by every view (the rerun visualizer, RViz markers).

Kept apart from the viewers so that a process drawing for ROS does not have to import rerun to agree
with the visualizer on what colour a chair is.
"""

from __future__ import annotations

from typing import Final

Rgb = tuple[int, int, int]

CLASS_COLORS: Final[dict[int, Rgb]] = {
    0: (255, 127, 14),  # chair: orange
    1: (31, 119, 180),  # box: blue
    2: (44, 160, 44),  # desk: green
    3: (214, 39, 40),  # doorframe: red
}
"""One fixed colour per class (index = class id), the same in every view and every run."""

UNKNOWN_CLASS_COLOR: Final[Rgb] = (128, 128, 128)


def class_color(class_id: int) -> Rgb:
    return CLASS_COLORS.get(class_id, UNKNOWN_CLASS_COLOR)
