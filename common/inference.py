"""The one place where YOLOv8 output becomes detections (README "The encoding", Algorithm 1 of the paper).

The detector service, ``triscan eval`` and the benchmarks all call this module, so the numbers they
report come from the same decode, the same NMS and the same pixel → bearing/range → x/y mapping. It
runs on the robot's base install: numpy and onnxruntime only, no torch, no Ultralytics.

Pipeline for one stacked tensor ``uint8[64, 384, 3]``:

1. ``to_model_input`` (the exact conversion training used) → ``float32[1, 3, 64, 384]``.
2. ONNX Runtime → Ultralytics' raw detect output ``float32[1, 4 + nc, A]``: rows ``cx, cy, w, h`` in
   input pixels, then ``nc`` sigmoid class scores; ``A = 504`` anchors for a 64×384 input
   (8×48 + 4×24 + 2×12 over strides 8, 16, 32).
3. :func:`decode_yolov8`: best class per anchor, score threshold, xywh → xyxy.
4. :func:`nms`: class-aware greedy NMS, the same kept set as ``torchvision.ops.batched_nms``.
5. Boxes clipped to the image, as Ultralytics' ``predict`` and ``val`` do after their NMS, so
   ``triscan eval`` scores boxes the way Ultralytics' own validator would.
6. :func:`unwrap_seam_duplicates`: with ``wrap`` padding one object can be found twice across the
   0°/360° seam; keep one.
7. :func:`detections_from_boxes`: wire ``Detection`` objects with bearings, ranges and position.

Everything after ``session.run`` is vectorised numpy; the only Python loops run over *kept*
detections (at most ``max_detections``), never over anchors.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, NamedTuple

import numpy as np
import onnxruntime as ort

from common.encoding import (
    ANGLE_COLUMNS,
    IMAGE_WIDTH,
    INVALID_RULES,
    PADDINGS,
    RANGE_ROWS,
    STACK_DEPTH,
    InvalidRule,
    Padding,
    pixel_x_to_bearing_deg,
    pixel_y_to_range_m,
    polar_to_xy,
    to_model_input,
    wrap_bearing_deg,
)
from common.messages import Detection, StageTimings
from common.model_spec import (
    BOX_GRIDS,
    CLASS_NAMES,
    DEFAULT_BOX_GRID,
    INPUT_SHAPE,
    MAX_DETECTIONS,
    META_BOX_GRID,
    META_CLASSES,
    META_INVALID,
    META_PADDING,
    MODELS_DIR,
    NUM_ANCHORS,
    NUM_CLASSES,
    SHIPPED_BATCH_MODEL,
    BoxGrid,
    default_model_path,
    file_model_id,
)

log = logging.getLogger(__name__)

DEFAULT_CONF: Final[float] = 0.25
DEFAULT_IOU: Final[float] = 0.45
# A box is a seam duplicate when this share of the smaller box lies inside the other box's copy.
SEAM_CONTAINMENT: Final[float] = 0.7
_NS_PER_MS: Final[float] = 1e6
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
    out = np.asarray(output)
    if out.ndim != 3 or out.shape[0] != 1 or out.shape[1] < 5:
        raise ValueError(
            f"YOLOv8 output must have shape [1, 4 + nc, anchors] with nc >= 1, got {list(out.shape)}"
        )
    if num_classes is not None and out.shape[1] != 4 + num_classes:
        raise ValueError(
            f"YOLOv8 output has {out.shape[1] - 4} class rows (shape {list(out.shape)}), "
            f"expected {num_classes}"
        )
    if not np.issubdtype(out.dtype, np.floating):
        raise ValueError(f"YOLOv8 output must be floating point, got {out.dtype}")
    pred = out[0]
    class_scores = pred[4:]
    best = class_scores.max(axis=0)
    # Compared in float32, as torch compares a float32 tensor with a Python float in Ultralytics.
    candidates = np.flatnonzero(best > np.float32(conf_threshold))
    if candidates.size == 0:
        return _empty_result()
    scores = best[candidates].astype(np.float32, copy=False)
    class_ids = class_scores[:, candidates].argmax(axis=0).astype(np.int64)
    boxes = xywh_rows_to_xyxy(pred[:4, candidates].astype(np.float32, copy=False))
    finite = np.isfinite(boxes).all(axis=1)
    if not finite.all():
        log.warning("dropped %d candidate boxes with non-finite coordinates", int((~finite).sum()))
        boxes, scores, class_ids = boxes[finite], scores[finite], class_ids[finite]
    return boxes, scores, class_ids


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


def detections_from_boxes(boxes: np.ndarray, scores: np.ndarray, class_ids: np.ndarray) -> list[Detection]:
    """Wire ``Detection`` objects for xyxy pixel boxes, all geometry computed in one vectorised pass.

    * ``box_px`` is the box as given.
    * Bearings come from the x extent (pixel ``u`` is bearing ``u − 0.5``°): ``bearing_min_deg`` from
      x1, ``bearing_max_deg`` from x2, ``bearing_deg`` their midpoint, each wrapped to (−180, 180].
      A box can straddle ±180° (or, from the padding columns, 0°), so after wrapping ``bearing_min_deg``
      may be greater than ``bearing_max_deg``: consumers must read ``[min, max]`` as the
      counter-clockwise arc from min to max, never as a numeric interval.
    * ``range_min_m``/``range_max_m`` from y1/y2 (pixel ``v`` is ``v · 4/63`` m), clipped at 0.
    * ``x_m``/``y_m``: the point at the centre bearing and the middle range, sensor frame (REP-103:
      x forward, y left) — where a robot would steer to or around.
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
    bearing_lo = pixel_x_to_bearing_deg(b[:, 0])
    bearing_hi = pixel_x_to_bearing_deg(b[:, 2])
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
    boxes, scores, class_ids = decode_yolov8(output, conf_threshold, num_classes=num_classes)
    keep = nms(boxes, scores, class_ids, iou_threshold, max_detections)
    return finish_kept_boxes(boxes[keep], scores[keep], class_ids[keep], padding=padding, box_grid=box_grid)


@dataclass(frozen=True)
class PostprocessSettings:
    """Everything :func:`postprocess` takes besides the raw output: one detector's settings, kept
    together so that whatever post-processes that detector's outputs another way (``bench.detector_path``'s
    levers) does it with the detector's own values."""

    conf_threshold: float
    iou_threshold: float
    max_detections: int
    padding: Padding
    num_classes: int | None
    box_grid: BoxGrid

    def postprocess(self, output: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:func:`postprocess` with these settings."""
        return postprocess(
            output,
            conf_threshold=self.conf_threshold,
            iou_threshold=self.iou_threshold,
            max_detections=self.max_detections,
            padding=self.padding,
            num_classes=self.num_classes,
            box_grid=self.box_grid,
        )


def finish_kept_boxes(
    boxes: np.ndarray, scores: np.ndarray, class_ids: np.ndarray, *, padding: Padding, box_grid: BoxGrid
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The NMS's kept boxes (highest score first) → final boxes: clip to the image, snap to the pixel
    grid (``box_grid`` ``pixel``), merge seam duplicates (``padding`` ``wrap``)."""
    boxes = clip_boxes_to_image(boxes)
    if box_grid == "pixel" and len(boxes):
        boxes = snap_boxes_to_pixels(boxes)
    if padding != "zero":
        keep = unwrap_seam_duplicates(boxes, scores, class_ids, padding)
        boxes, scores, class_ids = boxes[keep], scores[keep], class_ids[keep]
    return boxes, scores, class_ids


# --------------------------------------------------------------------------------------------------
# ONNX Runtime detector
# --------------------------------------------------------------------------------------------------


class FrameTimings(NamedTuple):
    """Stage durations of one frame in milliseconds; a plain tuple so hot loops skip validation."""

    encode_ms: float
    inference_ms: float
    nms_ms: float

    def to_message(self) -> StageTimings:
        return StageTimings(encode_ms=self.encode_ms, inference_ms=self.inference_ms, nms_ms=self.nms_ms)


def _declared(
    session: ort.InferenceSession, path: Path | str, key: str, allowed: tuple[str, ...], absent: str | None
) -> Any:
    """One ``triscan.*`` metadata value of the model, checked against ``allowed``; ``absent`` when the
    model does not have the key (it was exported before the key existed)."""
    value = session.get_modelmeta().custom_metadata_map.get(key, absent)
    if value is not None and value not in allowed:
        raise ValueError(f"{path} declares an unknown {key} {value!r}")
    return value


def _declared_padding(session: ort.InferenceSession, path: Path | str) -> Padding | None:
    """The model's ``triscan.padding`` metadata, checked; None for a model without it."""
    return _declared(session, path, META_PADDING, PADDINGS, None)


def session_options(
    intra_op_threads: int | None = None, *, optimise: bool = True, spin_wait: bool = True
) -> ort.SessionOptions:
    """The ONNX Runtime options every triscan session uses (detector, export checks, benchmarks).

    Sequential execution and one inter-op thread: the graph is one small chain with nothing to run
    in parallel. ``intra_op_threads`` None lets ONNX Runtime use every core. ``optimise`` False skips
    graph optimisation, for sessions that only read a model's metadata and signature. ``spin_wait``
    False makes the intra-op threads sleep instead of spinning while they wait for work: slower to
    wake, but the cores they would spin on go to the other processes of the pipeline.
    """
    options = ort.SessionOptions()
    options.graph_optimization_level = (
        ort.GraphOptimizationLevel.ORT_ENABLE_ALL if optimise else ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    )
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.inter_op_num_threads = 1
    if intra_op_threads is not None:
        options.intra_op_num_threads = intra_op_threads
    if not spin_wait:
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return options


def _declared_box_grid(session: ort.InferenceSession, path: Path | str) -> BoxGrid:
    """The model's ``triscan.box_grid`` (``none`` when absent: models exported before the key)."""
    return _declared(session, path, META_BOX_GRID, BOX_GRIDS, DEFAULT_BOX_GRID)


def _declared_invalid_rule(session: ort.InferenceSession, path: Path | str) -> InvalidRule:
    """The model's ``triscan.invalid`` metadata (``sentinel``, the paper's rule, when it does not say)."""
    return _declared(session, path, META_INVALID, INVALID_RULES, "sentinel")


def _unoptimised_session(path: Path | str) -> ort.InferenceSession:
    """A session only to read a model's metadata and signature: no graph optimisation, so it is cheap."""
    return ort.InferenceSession(
        str(path), sess_options=session_options(optimise=False), providers=["CPUExecutionProvider"]
    )


def _is_free_dimension(dim: object) -> bool:
    """ONNX Runtime reports a symbolic dimension as its name (a str) and an unnamed one as None."""
    return dim is None or isinstance(dim, str)


class ModelFacts(NamedTuple):
    """What a triscan ONNX file says about itself, read without running it."""

    padding: Padding  # ``zero`` for a model that does not say
    invalid: InvalidRule  # ``sentinel`` for a model that does not say
    takes_batches: bool  # a free batch axis (a ``-batch`` file)


def model_facts(path: Path | str) -> ModelFacts:
    """Padding, invalid-return rule and batch axis of a model, from one cheap metadata session, so a
    launcher can start the encoder to match the detector's model and refuse a ``--batch`` the model
    cannot run before any process starts."""
    session = _unoptimised_session(path)
    shape = session.get_inputs()[0].shape
    return ModelFacts(
        padding=_declared_padding(session, path) or "zero",
        invalid=_declared_invalid_rule(session, path),
        takes_batches=bool(shape) and _is_free_dimension(shape[0]),
    )


def check_batch(batch: int, takes_batches: bool, model_path: Path | str) -> None:
    """Refuse a batch size the model cannot run, before any frame is lost to it (``--batch``)."""
    if batch < 1:
        raise ValueError(f"--batch must be >= 1, got {batch}")
    if batch > 1 and not takes_batches:
        raise ValueError(
            f"--batch {batch} needs a model with a free batch axis; {model_path} is fixed at batch 1 "
            f"(its -batch variant, e.g. {SHIPPED_BATCH_MODEL.relative_to(MODELS_DIR.parent)}, is the same "
            "network)"
        )


AUTO_BATCH: Final[int] = 8
"""The largest batch cap the detector picks by itself when none is given and its model takes batches
(:func:`timed_batch_cap` keeps the largest power of two up to this whose model call fits
:data:`AUTO_BATCH_CALL_BUDGET_MS` on the machine it runs on). A worker never waits to fill a batch, so a
lone robot is served at batch 1 (same outputs, same speed); several waiting robots share one model call,
which on a CPU costs less per frame, and past a fleet's knee a larger batch keeps more scans answered
(bench/README.md, "The batch cap picked by timing")."""

AUTO_BATCH_CALL_BUDGET_MS: Final[float] = 30.0
"""The longest model call :func:`timed_batch_cap` accepts. A frame that just misses a call waits for it
and rides the next: two calls, 60 ms, leave 40 of the fleet's 100 ms p99 for transport, encoding and
the mailbox. On the slower 2-vCPU EPYC VM the default INT8 model runs 8 frames in about 12 ms (cap 8);
YOLOv8n's fp32 file took about 27 ms for 4 and 50 for 8, which pushed p99 past 100 ms (cap 4)."""


def batch_cap_within(call_ms: Mapping[int, float], budget_ms: float) -> int:
    """The largest batch size whose call, and every smaller size's, took at most ``budget_ms``; 1 when
    none did (a lone frame is served whatever it costs)."""
    cap = 1
    for size in sorted(call_ms):
        if call_ms[size] > budget_ms:
            break
        cap = size
    return cap


def detector_model_and_batch(model: Path | None, batch: int | None) -> tuple[Path, int]:
    """The model and batch cap a detector runs when the user may have chosen neither.

    ``batch`` None picks by itself: the shipped ``-batch`` model (or ``model``) with :data:`AUTO_BATCH`
    when the model takes batches (the largest cap: the detector then keeps what its own timing allows,
    :func:`timed_batch_cap`), batch 1 when it does not. An explicit ``batch`` is checked against
    the model (:func:`check_batch`); with ``batch`` 1 and no model, the fixed batch-1 file is used.
    """
    if batch is None:
        path = model or default_model_path(batched=True)
        return path, AUTO_BATCH if model_facts(path).takes_batches else 1
    path = model or default_model_path(batched=batch > 1)
    check_batch(batch, batch == 1 or model_facts(path).takes_batches, path)
    return path, batch


def default_providers() -> list[str]:
    """CUDA when this onnxruntime build has it (CPU stays as fallback for unsupported nodes), else CPU."""
    if "CUDAExecutionProvider" in ort.get_available_providers():
        return ["CUDAExecutionProvider", "CPUExecutionProvider"]
    return ["CPUExecutionProvider"]


class OnnxDetector:
    """An exported YOLOv8 detect model in ONNX Runtime, plus this module's post-processing.

    One instance per model and process; ``detect`` is not meant to be called from several threads at
    once (ONNX Runtime sessions are thread-safe, but the timings would interleave).
    """

    def __init__(
        self,
        model_path: Path | str,
        *,
        conf_threshold: float = DEFAULT_CONF,
        iou_threshold: float = DEFAULT_IOU,
        max_detections: int = MAX_DETECTIONS,
        padding: Padding | None = None,
        intra_op_threads: int | None = None,
        providers: list[str] | None = None,
        spin_wait: bool = True,
        box_grid: BoxGrid | None = None,
    ) -> None:
        """``padding`` defaults to the model's own ``triscan.padding`` metadata (``zero`` if absent);
        asking for the other one than the model was trained with is refused. ``box_grid`` defaults to
        the model's ``triscan.box_grid`` (``none`` if absent); either value may be asked for, as it
        changes only the post-processing. ``spin_wait``: see :func:`session_options`."""
        path = Path(model_path)
        if not path.is_file():
            raise FileNotFoundError(f"ONNX model {path} not found")
        if not 0.0 <= conf_threshold <= 1.0:
            raise ValueError(f"conf_threshold must lie in [0, 1], got {conf_threshold}")
        if not 0.0 <= iou_threshold <= 1.0:
            raise ValueError(f"iou_threshold must lie in [0, 1], got {iou_threshold}")
        if max_detections < 1:
            raise ValueError(f"max_detections must be >= 1, got {max_detections}")
        if padding is not None and padding not in PADDINGS:
            raise ValueError(f"padding must be one of {PADDINGS}, got {padding!r}")
        if box_grid is not None and box_grid not in BOX_GRIDS:
            raise ValueError(f"box_grid must be one of {BOX_GRIDS}, got {box_grid!r}")
        if intra_op_threads is not None and intra_op_threads < 1:
            raise ValueError(f"intra_op_threads must be >= 1, got {intra_op_threads}")
        self.model_path = path
        self.model_id = file_model_id(path)

        try:
            self._session = ort.InferenceSession(
                str(path),
                sess_options=session_options(intra_op_threads, spin_wait=spin_wait),
                providers=providers or default_providers(),
            )
        except Exception as exc:  # onnxruntime raises its own exception zoo for unreadable models
            raise ValueError(f"{path} is not a loadable ONNX model: {exc}") from exc
        self.providers: list[str] = self._session.get_providers()
        self._input_name, self._output_names, num_classes, self.num_anchors, batched = self._check_model(path)
        # A free batch axis (the ``-batch`` model files): ``detect_many`` runs several frames per call.
        self.batched: bool = batched
        self.invalid: InvalidRule = _declared_invalid_rule(self._session, path)
        # The one home of this detector's thresholds, padding, class count and box grid.
        self.postprocessing = PostprocessSettings(
            conf_threshold,
            iou_threshold,
            max_detections,
            self._padding_of_model(path, padding),
            num_classes,
            box_grid or _declared_box_grid(self._session, path),
        )
        log.info(
            "loaded %s (%d classes, %d anchors, %s) on %s, padding=%s box grid=%s conf=%.3g iou=%.3g",
            self.model_id,
            self.num_classes,
            self.num_anchors,
            "free batch axis" if self.batched else "batch 1",
            ",".join(self.providers),
            self.padding,
            self.box_grid,
            conf_threshold,
            iou_threshold,
        )

    @property
    def padding(self) -> Padding:
        """The padding this detector's model was trained with: what its input tensors must use."""
        return self.postprocessing.padding

    @property
    def box_grid(self) -> BoxGrid:
        """Whether box edges are snapped to whole pixels after the NMS (the model's metadata by default)."""
        return self.postprocessing.box_grid

    @property
    def num_classes(self) -> int:
        """Classes the model predicts; loading checked it against the project's class list."""
        return self.postprocessing.num_classes or NUM_CLASSES  # None would mean "read it off the output"

    def _padding_of_model(self, path: Path, requested: Padding | None) -> Padding:
        trained = _declared_padding(self._session, path)
        if requested is not None and trained is not None and requested != trained:
            raise ValueError(
                f"{path} was trained with {trained!r} padding; running it on {requested!r} tensors would "
                "misplace every object near the seam"
            )
        return requested or trained or "zero"

    def _check_model(self, path: Path) -> tuple[str, list[str], int, int, bool]:
        """Refuse, with the reason, any model this pipeline would misread rather than fail later."""
        meta = self._session.get_modelmeta().custom_metadata_map
        if meta.get("end2end", "").lower() == "true":
            raise ValueError(
                f"{path} is an end-to-end (NMS-free) export; "
                "export the raw detect head (nms=False, end2end off)"
            )
        inputs = self._session.get_inputs()
        if len(inputs) != 1:
            raise ValueError(f"{path} must have exactly one input, got {[i.name for i in inputs]}")
        model_input = inputs[0]
        in_shape = list(model_input.shape)
        batch = in_shape[0] if in_shape else 1
        free_batch = _is_free_dimension(batch)
        if (
            len(in_shape) != 4
            or not (batch == 1 or free_batch)
            or in_shape[1:] != list(INPUT_SHAPE[1:])
            or model_input.type != "tensor(float)"
        ):
            raise ValueError(
                f"{path} input {model_input.name!r} is {model_input.type}{in_shape}, expected "
                f"tensor(float){list(INPUT_SHAPE)} or a free batch axis in front "
                "(export with `triscan export`, imgsz=(64, 384))"
            )
        output = self._session.get_outputs()[0]
        shape = list(output.shape)
        if (
            len(shape) != 3
            or not all(isinstance(d, int) for d in shape[1:])
            or (not _is_free_dimension(shape[0]) if free_batch else shape[0] != 1)
            or shape[1] < 5
        ):
            raise ValueError(
                f"{path} output {output.name!r} has shape {shape}, expected [batch, 4 + nc, anchors]"
            )
        num_classes = shape[1] - 4
        if num_classes != NUM_CLASSES:
            raise ValueError(
                f"{path} predicts {num_classes} classes, this project has {NUM_CLASSES} {CLASS_NAMES}"
            )
        if shape[2] != NUM_ANCHORS:
            raise ValueError(f"{path} has {shape[2]} anchors, a 64×384 YOLOv8 head has {NUM_ANCHORS}")
        declared = meta.get(META_CLASSES)
        if declared is not None and tuple(json.loads(declared)) != CLASS_NAMES:
            raise ValueError(
                f"{path} was trained for the classes {json.loads(declared)}, this build knows {CLASS_NAMES}"
                " (the class list lives in common/model_spec.py)"
            )
        return model_input.name, [output.name], num_classes, shape[2], free_batch

    def infer(self, tensor: np.ndarray) -> np.ndarray:
        """Raw model output ``float32[1, 4 + nc, A]`` for a stacked ``uint8[64, 384, 3]`` tensor (any
        model, batch or not)."""
        return self._run(self._model_input(tensor))[0]

    def _model_input(self, tensor: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        if not isinstance(tensor, np.ndarray):
            raise ValueError(f"detector input must be a numpy uint8 array, got {type(tensor).__name__}")
        return to_model_input(tensor, out)  # the exact conversion training used; raises a ValueError

    def _run(self, model_input: np.ndarray) -> tuple[np.ndarray, float]:
        """Raw output for a model input, and the ``session.run`` time in ms."""
        started = time.perf_counter_ns()
        output = self._session.run(self._output_names, {self._input_name: model_input})[0]
        return output, (time.perf_counter_ns() - started) / _NS_PER_MS

    def _boxes_many(
        self, tensors: Sequence[np.ndarray]
    ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, FrameTimings]]:
        """The one frame pipeline behind every ``detect*`` method: convert, run, post-process.

        Every tensor is converted (and so checked) before anything runs. A batch model runs several
        frames in one ``session.run``, whose whole time each of them reports as ``inference_ms``; their
        frames are converted straight into one batch array, not concatenated afterwards.
        """
        batch = np.empty((len(tensors), *INPUT_SHAPE[1:]), np.float32) if self.batched else None
        inputs, encode_ms = [], []
        for index, tensor in enumerate(tensors):
            started = time.perf_counter_ns()
            try:
                inputs.append(self._model_input(tensor, None if batch is None else batch[index : index + 1]))
            except ValueError as exc:
                if len(tensors) == 1:
                    raise
                raise ValueError(f"tensor {index} of {len(tensors)}: {exc}") from exc
            encode_ms.append((time.perf_counter_ns() - started) / _NS_PER_MS)
        if batch is not None and len(inputs) > 1:
            batch_output, inference_ms = self._run(batch)
            outputs = [(batch_output[i : i + 1], inference_ms) for i in range(len(inputs))]
        else:
            outputs = [self._run(model_input) for model_input in inputs]
        results = []
        for frame_encode_ms, (output, inference_ms) in zip(encode_ms, outputs, strict=True):
            started = time.perf_counter_ns()
            boxes, scores, class_ids = self.postprocessing.postprocess(output)
            nms_ms = (time.perf_counter_ns() - started) / _NS_PER_MS
            results.append((boxes, scores, class_ids, FrameTimings(frame_encode_ms, inference_ms, nms_ms)))
        return results

    def detect_boxes(self, tensor: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, FrameTimings]:
        """Final boxes (xyxy pixels), scores and class ids, highest score first, and stage timings.

        ``encode_ms`` is only the uint8 → float32 conversion done here (the service adds its raster
        time); ``nms_ms`` covers decode, NMS, clipping and seam merging.
        """
        return self._boxes_many([tensor])[0]

    def detect(self, tensor: np.ndarray) -> tuple[list[Detection], StageTimings]:
        """Wire detections and timings for one tensor; ``nms_ms`` includes building the detections."""
        return self.detect_many([tensor])[0]

    def detect_many(self, tensors: Sequence[np.ndarray]) -> list[tuple[list[Detection], StageTimings]]:
        """:meth:`detect` for several robots' tensors, in one ``session.run`` when the model allows.

        With a batch model (:attr:`batched`, the ``-batch`` files) the frames share one call, which
        costs less per frame than one call each on a CPU (``bench.batch_inference``); with a fixed
        batch-1 model they run one by one. Each frame's detections equal what :meth:`detect` gives it
        alone. Timings per frame: ``encode_ms`` its own conversion, ``inference_ms`` the whole shared
        call (every frame in the batch waited for all of it), ``nms_ms`` its own post-processing.

        Every tensor is checked before anything runs, so one bad tensor raises a ``ValueError`` that
        names its index instead of failing the batch half-way.
        """
        results = []
        for boxes, scores, class_ids, timings in self._boxes_many(tensors):
            started = time.perf_counter_ns()
            detections = detections_from_boxes(boxes, scores, class_ids)
            convert_ms = (time.perf_counter_ns() - started) / _NS_PER_MS
            results.append((detections, timings._replace(nms_ms=timings.nms_ms + convert_ms).to_message()))
        return results

    def call_ms_by_batch(self, sizes: Sequence[int], repeats: int = 2) -> dict[int, float]:
        """The fastest of ``repeats`` ``session.run`` calls on blank frames at each batch size, in ms,
        each size run once untimed first (ONNX Runtime plans the memory of a new shape on its first run).
        A network's cost does not depend on what the frames hold."""
        if not self.batched and any(size != 1 for size in sizes):
            raise ValueError(f"{self.model_id} is fixed at batch 1: cannot time batches {list(sizes)}")
        timings = {}
        for size in sizes:
            blank = np.zeros((size, *INPUT_SHAPE[1:]), np.float32)
            self._run(blank)
            timings[size] = min(self._run(blank)[1] for _ in range(repeats))
        return timings

    def warmup(self, max_batch: int = 1) -> None:
        """Run blank frames through the whole path, so the first real frame's timing is honest.

        ONNX Runtime allocates its arenas and plans memory on the first run of each input shape; the
        benchmarks measure after one warm-up. With a batch model every batch size up to ``max_batch`` is run
        once, so the first batch of each size in service does not pay for it.
        """
        if max_batch < 1:
            raise ValueError(f"max_batch must be >= 1, got {max_batch}")
        blank = np.zeros((RANGE_ROWS, IMAGE_WIDTH, STACK_DEPTH), dtype=np.uint8)
        for size in range(1, (max_batch if self.batched else 1) + 1):
            self.detect_many([blank] * size)


def timed_batch_cap(
    detector: OnnxDetector, largest: int = AUTO_BATCH, budget_ms: float = AUTO_BATCH_CALL_BUDGET_MS
) -> tuple[int, dict[int, float]]:
    """The batch cap a detector picks by itself on this machine: the largest power of two up to
    ``largest`` whose model call fits ``budget_ms`` (:func:`batch_cap_within`), and the call times it
    measured. A heavier network, or a slower computer, gets a smaller cap without a tuning table."""
    if largest < 1:
        raise ValueError(f"largest must be >= 1, got {largest}")
    sizes = [1 << k for k in range(largest.bit_length())]  # 1, 2, 4, … up to largest
    call_ms = detector.call_ms_by_batch(sizes)
    return batch_cap_within(call_ms, budget_ms), call_ms
