"""The one place where YOLOv8 output becomes detections (README "The encoding", Algorithm 1 of the paper).

The detector (:class:`common.inference.OnnxDetector`), ``triscan eval`` and the benchmarks all call
this module, so the numbers they report come from the same decode, the same NMS and the same pixel →
bearing/range → x/y mapping. It runs on the robot's base install: numpy only, no torch, no Ultralytics.

Pipeline for the raw output of one frame, Ultralytics' detect head ``float32[1, 4 + nc, A]``: rows
``cx, cy, w, h`` in input pixels, then ``nc`` sigmoid class scores; ``A = 504`` anchors for a 64×384
input (8×48 + 4×24 + 2×12 over strides 8, 16, 32).

1. :func:`decode_yolov8`: best class per anchor, score threshold, xywh → xyxy.
2. :func:`nms`: class-aware greedy NMS, the same kept set as ``torchvision.ops.batched_nms``.
3. Boxes clipped to the image, as Ultralytics' ``predict`` and ``val`` do after their NMS, so
   ``triscan eval`` scores boxes the way Ultralytics' own validator would.
4. :func:`unwrap_seam_duplicates`: with ``wrap`` padding one object can be found twice across the
   0°/360° seam; keep one.
5. :func:`detections_from_boxes`: wire ``Detection`` objects with bearings, ranges and position.

Everything is vectorised numpy; the only Python loops run over *kept* detections (at most
``max_detections``), never over anchors. :meth:`PostprocessSettings.postprocess_many` and
:func:`detections_many` do the same for a batch's frames, decoding and placing every frame's boxes in
one pass (NMS and the seam merge stay per frame), so a detector serving many robots pays numpy's
per-call cost per batch.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np

from common.encoding import (
    ANGLE_COLUMNS,
    IMAGE_WIDTH,
    PADDINGS,
    RANGE_ROWS,
    Padding,
    pixel_x_to_bearing_deg,
    pixel_y_to_range_m,
    polar_to_xy,
    raster_to_laser_bearing_deg,
    wrap_bearing_deg,
)
from common.messages import Detection
from common.model_spec import CLASS_NAMES, DEFAULT_BOX_GRID, MAX_DETECTIONS, NUM_CLASSES, BoxGrid

log = logging.getLogger(__name__)

DEFAULT_CONF: Final[float] = 0.25
DEFAULT_IOU: Final[float] = 0.45
# A box is a seam duplicate when this share of the smaller box lies inside the other box's copy.
SEAM_CONTAINMENT: Final[float] = 0.7
_IMAGE_XYXY: Final[np.ndarray] = np.array([IMAGE_WIDTH, RANGE_ROWS, IMAGE_WIDTH, RANGE_ROWS], np.float32)


def _empty_result() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64)


# --------------------------------------------------------------------------------------------------
# Decode
# --------------------------------------------------------------------------------------------------


def decode_yolov8(
    output: np.ndarray, conf_threshold: float, *, num_classes: int | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate boxes of Ultralytics' raw detect output ``[1, 4 + nc, A]``.

    One label per anchor (the best class), like Ultralytics ``predict`` with ``multi_label=False``:
    several labels on one anchor would double-count objects in a scene that holds one of each class.
    An anchor is kept when its best score is strictly above ``conf_threshold`` (Ultralytics' rule).
    Anchors whose box is not finite are dropped: a broken model must not put NaN on the wire.

    Returns ``boxes_xyxy float32[K, 4]`` in input pixels, ``scores float32[K]``, ``class_ids int64[K]``,
    in anchor order. ``num_classes``, when given, is checked against the output's channel count.
    """
    return decode_yolov8_many(_single_frame(output), conf_threshold, num_classes=num_classes)[0]


def _single_frame(output: np.ndarray) -> np.ndarray:
    """``output`` as an array, refused unless it is one frame's raw output ``[1, 4 + nc, A]``."""
    out = np.asarray(output)
    if out.ndim != 3 or out.shape[0] != 1 or out.shape[1] < 5:
        raise ValueError(
            f"YOLOv8 output must have shape [1, 4 + nc, anchors] with nc >= 1, got {list(out.shape)}"
        )
    return out


def decode_yolov8_many(
    outputs: np.ndarray, conf_threshold: float, *, num_classes: int | None = None
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """:func:`decode_yolov8` for each frame of a batch's output ``[B, 4 + nc, A]``, in one pass.

    The candidates of every frame are found, scored and turned into boxes together: per frame the
    same values, in the same order, as the frame decoded alone, for a handful of numpy calls per
    batch instead of per frame.
    """
    out = np.asarray(outputs)
    if out.ndim != 3 or out.shape[1] < 5:
        raise ValueError(
            f"YOLOv8 output must have shape [B, 4 + nc, anchors] with nc >= 1, got {list(out.shape)}"
        )
    if num_classes is not None and out.shape[1] != 4 + num_classes:
        raise ValueError(
            f"YOLOv8 output has {out.shape[1] - 4} class rows (shape {list(out.shape)}), "
            f"expected {num_classes}"
        )
    if not np.issubdtype(out.dtype, np.floating):
        raise ValueError(f"YOLOv8 output must be floating point, got {out.dtype}")
    best = out[:, 4:].max(axis=1)
    # Compared in float32, as torch compares a float32 tensor with a Python float in Ultralytics.
    frame, anchor = np.nonzero(best > np.float32(conf_threshold))  # frame-major, anchors in order
    scores = best[frame, anchor].astype(np.float32, copy=False)
    class_ids = out[frame, 4:, anchor].argmax(axis=1).astype(np.int64)
    boxes = xywh_rows_to_xyxy(out[frame, :4, anchor].T.astype(np.float32, copy=False))
    finite = np.isfinite(boxes).all(axis=1)
    if not finite.all():
        log.warning("dropped %d candidate boxes with non-finite coordinates", int((~finite).sum()))
        frame, boxes, scores, class_ids = frame[finite], boxes[finite], scores[finite], class_ids[finite]
    bounds = np.searchsorted(frame, np.arange(out.shape[0] + 1))
    return [
        (boxes[lo:hi], scores[lo:hi], class_ids[lo:hi])
        for lo, hi in zip(bounds[:-1].tolist(), bounds[1:].tolist(), strict=True)
    ]


def xywh_rows_to_xyxy(xywh: np.ndarray) -> np.ndarray:
    """``float32[K, 4]`` xyxy boxes of the raw output's ``[4, K]`` centre/size rows, in the same float32
    steps as Ultralytics' ``xywh2xyxy``, so the boxes equal the ones it scores."""
    half_wh = xywh[2:] / np.float32(2.0)
    boxes = np.empty((xywh.shape[1], 4), np.float32)
    boxes[:, :2] = (xywh[:2] - half_wh).T
    boxes[:, 2:] = (xywh[:2] + half_wh).T
    return boxes


# --------------------------------------------------------------------------------------------------
# NMS
# --------------------------------------------------------------------------------------------------


def _check_boxes(boxes: np.ndarray, scores: np.ndarray, class_ids: np.ndarray) -> None:
    if boxes.ndim != 2 or boxes.shape[1] != 4:
        raise ValueError(f"boxes must have shape [K, 4], got {list(boxes.shape)}")
    if scores.shape != (boxes.shape[0],) or class_ids.shape != (boxes.shape[0],):
        raise ValueError(
            f"scores {list(scores.shape)} and class_ids {list(class_ids.shape)} must both have shape "
            f"[{boxes.shape[0]}] to match boxes"
        )


def _iou_above(a: tuple[np.ndarray, ...], b: tuple[np.ndarray, ...], iou_threshold: np.float64) -> np.ndarray:
    """IoU of boxes ``a`` and ``b`` (x1, y1, x2, y2, area; broadcastable) above the threshold.

    One place for the arithmetic, in torchvision's CPU operation order, which the kept set depends
    on. Zero-area pairs give NaN and never suppress.
    """
    ax1, ay1, ax2, ay2, a_area = a
    bx1, by1, bx2, by2, b_area = b
    w = np.maximum(np.minimum(ax2, bx2) - np.maximum(ax1, bx1), 0)
    h = np.maximum(np.minimum(ay2, by2) - np.maximum(ay1, by1), 0)
    inter = w * h
    with np.errstate(invalid="ignore", divide="ignore"):
        return inter / (a_area + b_area - inter) > iou_threshold


def _nms_matrix(
    x1: np.ndarray,
    y1: np.ndarray,
    x2: np.ndarray,
    y2: np.ndarray,
    areas: np.ndarray,
    classes: np.ndarray,
    iou_threshold: np.float64,
    max_detections: int,
) -> list[int]:
    """Greedy NMS over score-sorted boxes with the whole IoU matrix computed in one vectorised step."""
    column = (x1[:, None], y1[:, None], x2[:, None], y2[:, None], areas[:, None])
    suppresses = _iou_above(column, (x1, y1, x2, y2, areas), iou_threshold)
    suppresses &= classes[:, None] == classes
    alive = np.ones(x1.size, dtype=bool)
    keep: list[int] = []
    i = 0
    while True:
        keep.append(i)
        if len(keep) >= max_detections:
            break
        alive &= ~suppresses[i]
        alive[i] = False
        step = int(alive[i:].argmax())
        if not alive[i + step]:
            break
        i += step
    return keep


def nms(
    boxes: np.ndarray,
    scores: np.ndarray,
    class_ids: np.ndarray,
    iou_threshold: float = DEFAULT_IOU,
    max_detections: int = MAX_DETECTIONS,
) -> np.ndarray:
    """Class-aware greedy NMS; indices of the kept boxes, highest score first (``int64[M]``).

    Boxes of different classes never suppress each other: a chair's legs under a desk are a real
    chair. A box is suppressed when its IoU with a kept, higher-scoring box of its class is strictly
    above ``iou_threshold``. Ties in score keep input order (a stable sort). IoU is computed in the
    boxes' float32 with the operation order of torchvision's CPU kernel, so the kept set equals
    ``torchvision.ops.batched_nms``; instead of torchvision's coordinate-offset trick, which perturbs
    coordinates by adding large offsets, pairs of different classes are simply masked out.
    """
    boxes = np.asarray(boxes, dtype=np.float32)
    scores = np.asarray(scores)
    class_ids = np.asarray(class_ids)
    _check_boxes(boxes, scores, class_ids)
    if boxes.shape[0] == 0 or max_detections <= 0:
        return np.zeros(0, np.int64)
    # torchvision compares its float32 IoU with a double threshold: an IoU of float32(0.3) is above
    # 0.3. A float64 scalar makes numpy compare the same way.
    threshold = np.float64(iou_threshold)
    order = np.argsort(-scores, kind="stable")
    ordered = boxes[order]
    x1, y1, x2, y2 = (np.ascontiguousarray(ordered[:, k]) for k in range(4))
    areas = (x2 - x1) * (y2 - y1)
    # One K×K matrix: K is at most the 504 anchors of a triscan model (more only for other heads).
    keep = _nms_matrix(x1, y1, x2, y2, areas, class_ids[order], threshold, max_detections)
    return order[np.asarray(keep, dtype=np.int64)].astype(np.int64, copy=False)


def snap_boxes_to_pixels(boxes: np.ndarray) -> np.ndarray:
    """Round xyxy box edges to whole pixels (a new array), the grid every label lies on.

    A range row is 5.5 cm and a column one beam, and chairs, boxes and doorframes are a few rows
    tall, so a box edge off by a fraction of a row costs a tenth of IoU; rounding puts an edge within
    half a pixel of its label exactly on it. A box that rounding would leave empty keeps its edges.
    """
    boxes = np.asarray(boxes, dtype=np.float32)
    snapped = np.round(boxes)
    empty = (snapped[:, 2] <= snapped[:, 0]) | (snapped[:, 3] <= snapped[:, 1])
    snapped[empty] = boxes[empty]
    return snapped


def clip_boxes_to_image(boxes: np.ndarray) -> np.ndarray:
    """Clip xyxy boxes to the 384×64 input (a new array), as Ultralytics does after its NMS.

    A box reaching beyond row 64 would claim ranges past ``R_MAX`` that the raster cannot show, and
    ``triscan eval`` must score the boxes Ultralytics' validator would score.
    """
    return np.clip(np.asarray(boxes, dtype=np.float32), np.float32(0.0), _IMAGE_XYXY)


# --------------------------------------------------------------------------------------------------
# Seam duplicates (wrap padding)
# --------------------------------------------------------------------------------------------------


def _x_overlap(x1: np.ndarray, x2: np.ndarray, shift: float) -> np.ndarray:
    """Pairwise x overlap of box i with box j moved by ``shift`` columns."""
    return np.maximum(np.minimum(x2[:, None], x2 + shift) - np.maximum(x1[:, None], x1 + shift), 0.0)


def unwrap_seam_duplicates(
    boxes: np.ndarray, scores: np.ndarray, class_ids: np.ndarray, padding: Padding
) -> np.ndarray:
    """Indices (input order, ``int64``) of the boxes left after merging copies across the seam.

    With ``wrap`` padding, columns 360–383 repeat 0–23, so one object near 0° can be detected twice:
    whole at x 346–365 and as a partial copy at 0–5, or whole twice at 5–15 and 365–375. Each box is
    compared with the other boxes moved by ±360 columns (the same bearings); a same-class pair where
    at least ``SEAM_CONTAINMENT`` of the smaller box's area lies inside the other's copy is one
    object, and the higher-scoring box survives (the wider one on equal scores, since the partial
    copy is the one cut by the image edge). Unshifted overlaps are left alone: they are NMS's
    decision, and ``zero`` and ``wrap`` runs must differ only where the padding differs. With
    ``zero`` padding there are no copies and every index is returned.
    """
    boxes = np.asarray(boxes, dtype=np.float64)
    scores = np.asarray(scores)
    class_ids = np.asarray(class_ids)
    _check_boxes(boxes, scores, class_ids)
    if padding not in PADDINGS:
        raise ValueError(f"padding must be one of {PADDINGS}, got {padding!r}")
    n = boxes.shape[0]
    everything = np.arange(n, dtype=np.int64)
    if padding == "zero" or n < 2:
        return everything
    x1, y1, x2, y2 = boxes.T
    span = float(ANGLE_COLUMNS)
    # Two boxes can only meet after a 360-column shift if together they span more than 360 columns;
    # that is the common case with no seam object, and it skips the pairwise work.
    if x2.max() - x1.min() <= span:
        return everything
    x_inter = np.maximum(_x_overlap(x1, x2, -span), _x_overlap(x1, x2, span))
    y_inter = np.maximum(np.minimum(y2[:, None], y2) - np.maximum(y1[:, None], y1), 0.0)
    inter = x_inter * y_inter
    areas = (x2 - x1) * (y2 - y1)
    smaller = np.minimum(areas[:, None], areas)
    duplicate = (inter > 0.0) & (inter >= SEAM_CONTAINMENT * smaller) & (class_ids[:, None] == class_ids)
    np.fill_diagonal(duplicate, False)
    involved = np.flatnonzero(duplicate.any(axis=1))
    if involved.size == 0:
        return everything
    widths = x2 - x1
    # Best first: higher score, then wider, then earlier (lexsort's last key is the primary one).
    ranked = involved[np.lexsort((involved, -widths[involved], -scores[involved]))]
    keep = np.ones(n, dtype=bool)
    for i in ranked:
        if keep[i]:
            keep &= ~duplicate[i]  # any better-ranked duplicate of i would already have removed i
    return np.flatnonzero(keep).astype(np.int64)


# --------------------------------------------------------------------------------------------------
# Boxes → wire detections
# --------------------------------------------------------------------------------------------------


def detections_from_boxes(
    boxes: np.ndarray, scores: np.ndarray, class_ids: np.ndarray, raster_yaw_deg: float = 0.0
) -> list[Detection]:
    """Wire ``Detection`` objects for xyxy pixel boxes, all geometry computed in one vectorised pass.

    * ``box_px`` is the box as given: raster pixels, in the frame of the model's raster yaw.
    * Bearings come from the x extent (pixel ``u`` is bearing ``u − 0.5``° in the raster, ``u − 0.5 −
      raster_yaw_deg``° in the laser frame: :mod:`common.encoding`): ``bearing_min_deg`` from x1,
      ``bearing_max_deg`` from x2, ``bearing_deg`` their midpoint, each in the laser frame and wrapped
      to (−180, 180].
      A box can straddle ±180° (or, from the padding columns, 0°), so after wrapping ``bearing_min_deg``
      may be greater than ``bearing_max_deg``: consumers must read ``[min, max]`` as the
      counter-clockwise arc from min to max, never as a numeric interval.
    * ``range_min_m``/``range_max_m`` from y1/y2 (pixel ``v`` is ``v · 4/63`` m), clipped at 0.
    * ``x_m``/``y_m``: the point at the centre bearing and the middle range, laser frame (REP-103:
      x forward, y left) — where a robot would steer to or around.

    So only ``box_px`` depends on the raster yaw: trackers, the ROS bridge and maps read the rest.
    """
    b = np.asarray(boxes, dtype=np.float64)
    scores = np.asarray(scores)
    class_ids = np.asarray(class_ids)
    _check_boxes(b, scores, class_ids)
    if b.shape[0] == 0:
        return []
    if class_ids.min() < 0 or class_ids.max() >= NUM_CLASSES:
        bad = sorted(set(class_ids.tolist()))
        raise ValueError(f"class ids must lie in [0, {NUM_CLASSES - 1}], got {bad}")
    bearing_lo = raster_to_laser_bearing_deg(pixel_x_to_bearing_deg(b[:, 0]), raster_yaw_deg)
    bearing_hi = raster_to_laser_bearing_deg(pixel_x_to_bearing_deg(b[:, 2]), raster_yaw_deg)
    bearing_mid = (bearing_lo + bearing_hi) / 2.0
    range_lo = np.maximum(pixel_y_to_range_m(b[:, 1]), 0.0)
    range_hi = np.maximum(pixel_y_to_range_m(b[:, 3]), 0.0)
    xy = polar_to_xy(bearing_mid, (range_lo + range_hi) / 2.0)
    columns = zip(
        class_ids.tolist(),
        np.asarray(scores, dtype=np.float64).tolist(),
        b.tolist(),
        wrap_bearing_deg(bearing_mid).tolist(),
        wrap_bearing_deg(bearing_lo).tolist(),
        wrap_bearing_deg(bearing_hi).tolist(),
        range_lo.tolist(),
        range_hi.tolist(),
        xy[:, 0].tolist(),
        xy[:, 1].tolist(),
        strict=True,
    )
    return [
        Detection(
            class_id=cid,
            class_name=CLASS_NAMES[cid],
            score=score,
            box_px=(box[0], box[1], box[2], box[3]),
            bearing_deg=mid,
            bearing_min_deg=lo,
            bearing_max_deg=hi,
            range_min_m=rlo,
            range_max_m=rhi,
            x_m=x,
            y_m=y,
        )
        for cid, score, box, mid, lo, hi, rlo, rhi, x, y in columns
    ]


def detections_many(
    frames: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]], raster_yaw_deg: float = 0.0
) -> list[list[Detection]]:
    """:func:`detections_from_boxes` for several frames' final boxes at once: their geometry in one
    vectorised pass, then the detections handed back frame by frame."""
    if not frames:
        return []
    everything = detections_from_boxes(
        np.concatenate([np.asarray(boxes, np.float64).reshape(-1, 4) for boxes, _, _ in frames]),
        np.concatenate([np.asarray(scores) for _, scores, _ in frames]),
        np.concatenate([np.asarray(class_ids) for _, _, class_ids in frames]),
        raster_yaw_deg,
    )
    ends = np.cumsum([len(scores) for _, scores, _ in frames]).tolist()
    return [everything[lo:hi] for lo, hi in zip([0, *ends[:-1]], ends, strict=True)]


def postprocess(
    output: np.ndarray,
    *,
    conf_threshold: float = DEFAULT_CONF,
    iou_threshold: float = DEFAULT_IOU,
    max_detections: int = MAX_DETECTIONS,
    padding: Padding = "zero",
    num_classes: int | None = None,
    box_grid: BoxGrid = DEFAULT_BOX_GRID,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw output → final boxes: decode, NMS, clip to the image, snap to the pixel grid (``box_grid``
    ``pixel``), merge seam duplicates.

    Public so ``triscan eval`` can post-process outputs it obtained another way (a batch, a cache)
    exactly as the detector does. Boxes come back highest score first.
    """
    settings = PostprocessSettings(
        conf_threshold, iou_threshold, max_detections, padding, num_classes, box_grid
    )
    return settings.postprocess(output)


@dataclass(frozen=True)
class PostprocessSettings:
    """Everything :func:`postprocess` takes besides the raw output: one detector's settings, kept
    together so that whatever post-processes that detector's outputs another way does it with the
    detector's own values."""

    conf_threshold: float
    iou_threshold: float
    max_detections: int
    padding: Padding
    num_classes: int | None
    box_grid: BoxGrid

    def postprocess(self, output: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:func:`postprocess` with these settings."""
        return self.postprocess_many(_single_frame(output))[0]

    def postprocess_many(
        self, outputs: np.ndarray, low_class: tuple[int, float] | None = None
    ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """:func:`postprocess` for each frame of a batch's output ``[B, 4 + nc, A]``: per frame the very
        boxes, scores and classes it gives that frame alone.

        Decoding, clipping and snapping work on every frame's boxes at once, NMS and the seam merge
        frame by frame: a batch costs a few numpy calls more than one frame, not a few per frame.
        ``low_class`` ``(class id, floor)`` also keeps that class's candidates scoring above ``floor``
        though below the threshold, for a later step that may confirm them
        (:mod:`common.moving_people`); the NMS is per class, so the other classes' boxes stay the same.
        """
        threshold = self.conf_threshold if low_class is None else min(self.conf_threshold, low_class[1])
        kept = []
        for boxes, scores, class_ids in decode_yolov8_many(outputs, threshold, num_classes=self.num_classes):
            if threshold < self.conf_threshold and low_class is not None:
                wanted = (scores > np.float32(self.conf_threshold)) | (class_ids == low_class[0])
                boxes, scores, class_ids = boxes[wanted], scores[wanted], class_ids[wanted]
            keep = nms(boxes, scores, class_ids, self.iou_threshold, self.max_detections)
            kept.append((boxes[keep], scores[keep], class_ids[keep]))
        placed = _clip_and_snap(np.concatenate([boxes for boxes, _, _ in kept]), self.box_grid)
        ends = np.cumsum([len(scores) for _, scores, _ in kept]).tolist()
        results = []
        for (_, scores, class_ids), boxes in zip(kept, np.split(placed, ends[:-1]), strict=True):
            if self.padding != "zero":
                keep = unwrap_seam_duplicates(boxes, scores, class_ids, self.padding)
                boxes, scores, class_ids = boxes[keep], scores[keep], class_ids[keep]
            results.append((boxes, scores, class_ids))
        return results


def _clip_and_snap(boxes: np.ndarray, box_grid: BoxGrid) -> np.ndarray:
    """Box by box: clipped to the image, then on the pixel grid when ``box_grid`` is ``pixel``."""
    boxes = clip_boxes_to_image(boxes)
    if box_grid == "pixel" and len(boxes):
        boxes = snap_boxes_to_pixels(boxes)
    return boxes
