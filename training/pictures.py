"""``triscan show``: two pictures of one data-set sample, for eyeballing a data set and for the README.

* the **raster picture** (the paper's Figure 3, :mod:`training.raster_picture`): the 64 × 384
  three-channel image the detector reads, magnified, with bearing/range axes, the label boxes in
  per-class colours and a legend for the channels (R = scan t-2, G = t-1, B = t);
* the **top-down map** (the paper's Figure 1, :mod:`training.map_picture`): the scenario's room,
  objects and robot in metres, with the LiDAR hits of the three scans *decoded back from the PNG* and
  drawn in their channel colours.

Decoding the hits from the PNG rather than re-simulating them is deliberate: the map then shows what
the network actually gets (quantised to 1° × 4/63 m pixels), so a wrong channel order, a mirrored
bearing or a label box that misses its object is visible at a glance. Only Pillow and numpy are used,
and only Pillow's embedded font (:mod:`training.picture_style`), so the pictures are the same on every
machine. The sample itself is read and checked by :mod:`training.dataset_sample`.
"""

from __future__ import annotations

import logging
from pathlib import Path

from training.dataset_sample import load_sample
from training.map_picture import draw_map_picture
from training.raster_picture import DetectedBox, draw_raster_picture

log = logging.getLogger(__name__)

MAX_SCALE = 16  # 384 · 16 = 6144 px wide; beyond that the picture is just big, not clearer


def render_sample(
    dataset_dir: Path,
    out_dir: Path,
    *,
    sample: str | None,
    index: int,
    scale: int,
    model: Path | None = None,
) -> tuple[Path, Path]:
    """Write ``<name>_raster.png`` and ``<name>_map.png`` for one sample; return their paths.

    ``sample`` (image path, file name or stem) wins over ``index`` (line of samples.jsonl). With
    ``model`` (an ONNX file) the raster also shows that model's boxes on the sample, dashed.
    """
    if not 1 <= scale <= MAX_SCALE:
        raise ValueError(f"scale must be between 1 and {MAX_SCALE}, got {scale}")
    chosen = load_sample(Path(dataset_dir), sample=sample, index=index)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    raster_png = out_dir / f"{chosen.name}_raster.png"
    map_png = out_dir / f"{chosen.name}_map.png"
    # Draw both before writing either, so a failure never leaves half a pair behind.
    found = () if model is None else model_boxes(model, chosen.tensor, chosen.padding)
    raster_picture, map_picture = draw_raster_picture(chosen, scale, found), draw_map_picture(chosen)
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


def model_boxes(model: Path, tensor: object, padding: str) -> tuple[DetectedBox, ...]:
    """The boxes the run-time detector (its default thresholds) finds in one tensor of ``padding``."""
    import numpy as np

    from common.inference import OnnxDetector

    detector = OnnxDetector(model)
    if detector.padding != padding:
        raise ValueError(f"{model} reads {detector.padding!r} padding, the sample has {padding!r}")
    boxes, scores, classes, _ = detector.detect_boxes(np.asarray(tensor))
    return tuple(
        DetectedBox(int(c), *(float(v) for v in box), float(score))
        for box, score, c in zip(boxes, scores, classes, strict=True)
    )
