"""Decode, NMS, seam merging and the ONNX detector against hand-computed values and the reference code.

The references are the libraries the model was trained and validated with: ``torchvision.ops.batched_nms``
for NMS and Ultralytics' own ``non_max_suppression`` for the whole post-processing, on the raw output of
a real YOLOv8n exported by Ultralytics. Those tests skip on the robot's base install (no torch); the
hand-computed ones, and the detector wiring through tiny constant ONNX graphs, run everywhere.
"""

from __future__ import annotations

import hashlib
import importlib.util
import math
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from common.encoding import R_MAX_M, polar_to_xy, to_model_input
from common.inference import OnnxDetector, model_facts
from common.messages import Detection, StageTimings
from common.model_meta import ModelFacts, metadata_entries
from common.model_spec import CLASS_NAMES, FURNITURE_CLASSES, MAX_DETECTIONS
from common.postprocess import (
    DEFAULT_CONF,
    DEFAULT_IOU,
    PostprocessSettings,
    decode_yolov8,
    detections_from_boxes,
    detections_many,
    nms,
    postprocess,
    snap_boxes_to_pixels,
    unwrap_seam_duplicates,
)
from tests.support.detection_builders import one_detection

ROW_M = R_MAX_M / 63.0  # metres per raster row
TENSOR_SHAPE = (64, 384, 3)


def raw_output(anchors: list[tuple[float, float, float, float, list[float]]], total: int = 0) -> np.ndarray:
    """A ``[1, 4 + nc, A]`` output holding the given anchors (cx, cy, w, h, class scores) first."""
    nc = len(anchors[0][4])
    out = np.zeros((1, 4 + nc, max(total, len(anchors))), np.float32)
    for a, (cx, cy, w, h, scores) in enumerate(anchors):
        out[0, :4, a] = (cx, cy, w, h)
        out[0, 4:, a] = scores
    return out


def clustered_boxes(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes jittered around a few object centres, so NMS has real suppression chains to resolve."""
    centres = rng.uniform([0, 0], [384, 64], size=(8, 2))
    sizes = rng.uniform([4, 2], [40, 12], size=(8, 2))
    which = rng.integers(0, len(centres), n)
    cxy = centres[which] + rng.normal(0, 1.5, (n, 2))
    wh = sizes[which] * rng.uniform(0.7, 1.3, (n, 2))
    boxes = np.concatenate([cxy - wh / 2, cxy + wh / 2], axis=1).astype(np.float32)
    return boxes, rng.random(n).astype(np.float32), rng.integers(0, 4, n).astype(np.int64)


# --------------------------------------------------------------------------------------------------
# decode
# --------------------------------------------------------------------------------------------------


def test_decode_hand_built_output() -> None:
    out = raw_output(
        [
            (100.0, 20.0, 20.0, 8.0, [0.1, 0.9, 0.2, 0.0]),  # box, 0.9
            (50.0, 30.0, 10.0, 10.0, [0.25, 0.1, 0.0, 0.2]),  # best score == threshold: dropped
            (10.5, 60.0, 3.0, 5.0, [0.3, 0.1, 0.1, 0.6]),  # doorframe, 0.6
            (200.0, 5.0, 4.0, 2.0, [0.0, 0.0, 0.26, 0.0]),  # desk, just above
            (300.0, 40.0, 6.0, 6.0, [0.01, 0.02, 0.03, 0.04]),  # background
        ],
        total=504,
    )
    boxes, scores, class_ids = decode_yolov8(out, 0.25)
    np.testing.assert_array_equal(
        boxes, [[90.0, 16.0, 110.0, 24.0], [9.0, 57.5, 12.0, 62.5], [198.0, 4.0, 202.0, 6.0]]
    )
    np.testing.assert_allclose(scores, [0.9, 0.6, 0.26], rtol=0, atol=1e-7)
    np.testing.assert_array_equal(class_ids, [1, 3, 2])
    assert (boxes.dtype, scores.dtype, class_ids.dtype) == (np.float32, np.float32, np.int64)

    boxes, scores, class_ids = decode_yolov8(out, 0.5)
    np.testing.assert_array_equal(class_ids, [1, 3])
    boxes, scores, class_ids = decode_yolov8(out, 0.95)
    assert boxes.shape == (0, 4) and scores.shape == (0,) and class_ids.shape == (0,)


def test_decode_drops_non_finite_boxes() -> None:
    out = raw_output([(np.nan, 20.0, 20.0, 8.0, [0.9, 0, 0, 0]), (100.0, 20.0, 20.0, 8.0, [0.8, 0, 0, 0])])
    boxes, scores, _ = decode_yolov8(out, 0.25)
    np.testing.assert_array_equal(boxes, [[90.0, 16.0, 110.0, 24.0]])
    np.testing.assert_allclose(scores, [0.8])


@pytest.mark.parametrize(
    ("shape", "dtype", "num_classes", "match"),
    [
        ((8, 504), np.float32, None, r"\[1, 4 \+ nc, anchors\]"),
        ((2, 8, 504), np.float32, None, r"\[1, 4 \+ nc, anchors\]"),
        ((1, 4, 504), np.float32, None, r"nc >= 1"),
        ((1, 84, 504), np.float32, 4, r"80 class rows .* expected 4"),
        ((1, 8, 504), np.int32, None, r"floating point"),
    ],
)
def test_decode_rejects_wrong_outputs(
    shape: tuple[int, ...], dtype: type, num_classes: int | None, match: str
) -> None:
    with pytest.raises(ValueError, match=match):
        decode_yolov8(np.zeros(shape, dtype), 0.25, num_classes=num_classes)


# --------------------------------------------------------------------------------------------------
# NMS
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("iou", [0.3, 0.45, 0.7])
@pytest.mark.parametrize("seed", range(4))
def test_nms_equals_torchvision_batched_nms(seed: int, iou: float) -> None:
    torch = pytest.importorskip("torch")
    torchvision = pytest.importorskip("torchvision")
    boxes, scores, class_ids = clustered_boxes(np.random.default_rng(seed), 200)
    expected = torchvision.ops.batched_nms(
        torch.from_numpy(boxes), torch.from_numpy(scores), torch.from_numpy(class_ids), iou
    ).numpy()
    keep = nms(boxes, scores, class_ids, iou, max_detections=1000)
    assert 10 < len(keep) < 190  # the case is not trivial: many kept, many suppressed
    assert set(keep.tolist()) == set(expected.tolist())
    np.testing.assert_array_equal(keep, expected)  # distinct scores: same order too
    assert keep.dtype == np.int64


def test_nms_is_class_aware() -> None:
    boxes = np.array([[10, 10, 30, 20], [11, 10, 31, 20], [10, 10, 30, 20]], np.float32)
    scores = np.array([0.9, 0.8, 0.7], np.float32)
    np.testing.assert_array_equal(nms(boxes, scores, np.array([0, 1, 2]), 0.45, 10), [0, 1, 2])
    np.testing.assert_array_equal(nms(boxes, scores, np.array([0, 0, 1]), 0.45, 10), [0, 2])
    np.testing.assert_array_equal(nms(boxes, scores, np.array([3, 3, 3]), 0.45, 10), [0])


@pytest.mark.parametrize("seed", range(3))
def test_nms_breaks_score_ties_like_torchvision(seed: int) -> None:
    """Scores on a 0.25 grid tie constantly: the earlier box wins, as with torchvision's stable sort."""
    torch = pytest.importorskip("torch")
    torchvision = pytest.importorskip("torchvision")
    boxes, scores, class_ids = clustered_boxes(np.random.default_rng(seed), 200)
    scores = (np.round(scores * 4) / 4).astype(np.float32)
    expected = torchvision.ops.batched_nms(
        torch.from_numpy(boxes), torch.from_numpy(scores), torch.from_numpy(class_ids), 0.45
    ).numpy()
    np.testing.assert_array_equal(nms(boxes, scores, class_ids, 0.45, 1000), expected)


@pytest.mark.parametrize(("threshold", "kept"), [(0.3, [0]), (0.45, [0, 1])])
def test_nms_threshold_compares_like_torchvision(threshold: float, kept: list[int]) -> None:
    """IoU exactly float32(t): float32(0.3) lies above 0.3 (suppressed), float32(0.45) below 0.45 (kept)."""
    boxes = np.array([[0, 0, 10, 10], [0, 0, 10, threshold * 10]], np.float32)
    np.testing.assert_array_equal(nms(boxes, np.array([0.9, 0.8]), np.zeros(2, np.int64), threshold), kept)


def test_nms_orders_by_score_and_caps() -> None:
    boxes, scores, class_ids = clustered_boxes(np.random.default_rng(7), 200)
    full = nms(boxes, scores, class_ids, 0.45, 1000)
    assert np.all(np.diff(scores[full]) <= 0)
    np.testing.assert_array_equal(nms(boxes, scores, class_ids, 0.45, 5), full[:5])
    assert len(nms(boxes, scores, class_ids, 0.45, MAX_DETECTIONS)) == min(len(full), MAX_DETECTIONS)


def test_nms_edge_cases() -> None:
    empty = nms(np.zeros((0, 4), np.float32), np.zeros(0, np.float32), np.zeros(0, np.int64), 0.45, 10)
    assert empty.shape == (0,) and empty.dtype == np.int64
    # Zero-area boxes have an undefined IoU: they neither suppress nor get suppressed.
    boxes = np.array([[5, 5, 5, 5], [5, 5, 5, 5], [0, 0, 10, 10]], np.float32)
    np.testing.assert_array_equal(
        nms(boxes, np.array([0.9, 0.8, 0.7]), np.zeros(3, np.int64), 0.45), [0, 1, 2]
    )
    with pytest.raises(ValueError, match=r"\[K, 4\]"):
        nms(np.zeros((3, 5)), np.zeros(3), np.zeros(3), 0.45)
    with pytest.raises(ValueError, match="must both have shape"):
        nms(np.zeros((3, 4)), np.zeros(2), np.zeros(3), 0.45)


# --------------------------------------------------------------------------------------------------
# seam duplicates
# --------------------------------------------------------------------------------------------------


def seam(
    boxes: list[list[float]], scores: list[float], classes: list[int], padding: str = "wrap"
) -> list[int]:
    keep = unwrap_seam_duplicates(
        np.array(boxes, np.float32),
        np.array(scores, np.float32),
        np.array(classes),
        padding,  # type: ignore[arg-type]
    )
    assert keep.dtype == np.int64
    return keep.tolist()


def test_seam_whole_and_partial_copy() -> None:
    whole, partial = [346, 10, 365, 14], [0, 10, 5, 14]
    assert seam([whole, partial], [0.8, 0.6], [1, 1]) == [0]
    assert seam([partial, whole], [0.6, 0.8], [1, 1]) == [1]
    assert seam([whole, partial], [0.5, 0.6], [1, 1]) == [1]  # the higher score wins, even if partial


def test_seam_two_whole_copies() -> None:
    assert seam([[5, 20, 15, 25], [368, 20, 383, 25]], [0.9, 0.8], [0, 0]) == [0]  # exactly 70 % inside
    assert seam([[5, 20, 15, 25], [365, 20, 375, 25]], [0.7, 0.9], [0, 0]) == [1]
    assert seam([[365, 20, 375, 25], [4, 20, 15, 25]], [0.9, 0.9], [0, 0]) == [1]  # tie: the wider
    assert seam([[5, 20, 15, 25], [365, 20, 375, 25]], [0.9, 0.9], [0, 0]) == [0]  # full tie: first


def test_seam_keeps_what_is_not_a_copy() -> None:
    assert seam([[5, 20, 15, 25], [365, 20, 375, 25]], [0.9, 0.8], [0, 2]) == [0, 1]  # other class
    assert seam([[5, 20, 15, 25], [365, 40, 375, 45]], [0.9, 0.8], [0, 0]) == [0, 1]  # other range
    assert seam([[5, 20, 15, 25], [371, 20, 383, 25]], [0.9, 0.8], [0, 0]) == [0, 1]  # 40 % < 70 %
    # Unshifted overlap is NMS's business, not the seam's (the last two boxes make the set span the
    # seam, so the pairwise check really runs).
    boxes = [[100, 20, 130, 30], [105, 21, 115, 29], [370, 0, 380, 5], [0, 50, 2, 52]]
    assert seam(boxes, [0.9, 0.8, 0.7, 0.6], [0, 0, 0, 0]) == [0, 1, 2, 3]
    boxes, scores, classes = [[346, 10, 365, 14], [0, 10, 5, 14]], [0.8, 0.6], [1, 1]
    assert seam(boxes, scores, classes, padding="zero") == [0, 1]
    with pytest.raises(ValueError, match="padding"):
        seam(boxes, scores, classes, padding="mirror")


def test_seam_chain_of_three_copies() -> None:
    # One chair found whole at 2–12 and at its copy 362–372, plus a fragment at 3–6: the best box
    # (the copy) absorbs both, the unrelated box at 200 stays.
    boxes = [[2, 30, 12, 36], [362, 30, 372, 36], [3, 30, 6, 36], [200, 30, 210, 36]]
    assert seam(boxes, [0.6, 0.8, 0.7, 0.5], [0, 0, 0, 0]) == [1, 3]


# --------------------------------------------------------------------------------------------------
# boxes -> detections
# --------------------------------------------------------------------------------------------------


def test_detection_from_box_hand_computed() -> None:
    det = one_detection(np.array([81.0, 20.0, 100.0, 27.0]), 0.75, 2)
    assert det.class_id == 2 and det.class_name == "desk" and det.score == 0.75
    assert det.box_px == (81.0, 20.0, 100.0, 27.0)
    assert det.bearing_min_deg == pytest.approx(80.5)
    assert det.bearing_max_deg == pytest.approx(99.5)
    assert det.bearing_deg == pytest.approx(90.0)
    assert det.range_min_m == pytest.approx(20 * 4 / 63)
    assert det.range_max_m == pytest.approx(27 * 4 / 63)
    assert det.x_m == pytest.approx(0.0, abs=1e-12)
    assert det.y_m == pytest.approx(23.5 * 4 / 63)  # straight left (REP-103: +y), at the middle range


def test_detection_in_padding_columns_wraps() -> None:
    det = one_detection((365.0, 10.0, 375.0, 12.0), 0.5, 0)
    assert (det.bearing_min_deg, det.bearing_deg, det.bearing_max_deg) == pytest.approx((4.5, 9.5, 14.5))
    x, y = polar_to_xy(9.5, 11 * ROW_M)
    assert (det.x_m, det.y_m) == pytest.approx((x, y))
    assert det.box_px == (365.0, 10.0, 375.0, 12.0)  # the box stays in pixels as detected


def test_detection_straddling_wrap_boundaries() -> None:
    across_zero = one_detection((346.0, 10.0, 365.0, 12.0), 0.5, 1)
    assert (
        across_zero.bearing_min_deg,
        across_zero.bearing_deg,
        across_zero.bearing_max_deg,
    ) == pytest.approx((-14.5, -5.0, 4.5))
    behind = one_detection((170.0, 0.0, 200.0, 2.0), 0.5, 1)  # straddles ±180°: min > max
    assert (behind.bearing_min_deg, behind.bearing_deg, behind.bearing_max_deg) == pytest.approx(
        (169.5, -175.5, -160.5)
    )
    assert behind.x_m < 0 and behind.y_m < 0  # centre at 184.5° = just right of straight back


def test_detection_ranges_are_clipped_at_zero() -> None:
    det = one_detection((10.0, -2.0, 20.0, 3.0), 0.5, 3)
    assert det.range_min_m == 0.0 and det.range_max_m == pytest.approx(3 * ROW_M)


def test_detections_from_boxes_matches_one_by_one() -> None:
    boxes = np.array([[81, 20, 100, 27], [365, 10, 375, 12], [0, 0, 384, 64]], np.float32)
    scores = np.array([0.9, 0.5, 0.3], np.float32)
    classes = np.array([0, 1, 3])
    batch = detections_from_boxes(boxes, scores, classes)
    assert batch == [
        one_detection(b, float(s), int(c)) for b, s, c in zip(boxes, scores, classes, strict=True)
    ]
    assert detections_from_boxes(np.zeros((0, 4)), np.zeros(0), np.zeros(0, np.int64)) == []
    with pytest.raises(ValueError, match="class ids"):
        detections_from_boxes(boxes, scores, np.array([0, 1, len(CLASS_NAMES)]))


def test_postprocess_clips_and_merges() -> None:
    out = raw_output(
        [
            (355.5, 12.0, 19.0, 4.0, [0.0, 0.8, 0.0, 0.0]),  # 346–365, whole chair... box across the seam
            (2.5, 12.0, 5.0, 4.0, [0.0, 0.6, 0.0, 0.0]),  # 0–5: its copy
            (100.0, 62.0, 10.0, 8.0, [0.0, 0.0, 0.0, 0.7]),  # reaches row 66: clipped to 64
        ],
        total=504,
    )
    boxes, scores, classes = postprocess(out, padding="zero")
    np.testing.assert_array_equal(boxes, [[346, 10, 365, 14], [95, 58, 105, 64], [0, 10, 5, 14]])
    np.testing.assert_array_equal(classes, [1, 3, 1])
    boxes, scores, classes = postprocess(out, padding="wrap")
    np.testing.assert_array_equal(boxes, [[346, 10, 365, 14], [95, 58, 105, 64]])
    np.testing.assert_allclose(scores, [0.8, 0.7])


def test_snapping_rounds_box_edges_to_whole_pixels_and_keeps_boxes_it_would_empty() -> None:
    boxes = np.array([[10.4, 3.6, 20.5, 9.49], [7.2, 5.1, 7.4, 5.3], [0.0, 0.0, 383.7, 63.8]], np.float32)
    snapped = snap_boxes_to_pixels(boxes)
    np.testing.assert_array_equal(snapped[0], [10, 4, 20, 9])  # half to even, as numpy rounds
    np.testing.assert_array_equal(snapped[1], boxes[1])  # 7–7 would be no box at all
    np.testing.assert_array_equal(snapped[2], [0, 0, 384, 64])
    assert snapped.dtype == np.float32 and boxes[0, 0] == np.float32(10.4)  # a new array


def test_postprocess_snaps_to_the_pixel_grid_only_when_asked() -> None:
    out = raw_output([(100.3, 30.2, 10.6, 8.8, [0.0, 0.0, 0.0, 0.7])], total=504)
    loose, _, _ = postprocess(out)
    snapped, _, classes = postprocess(out, box_grid="pixel")
    assert not np.array_equal(loose, np.round(loose))
    np.testing.assert_array_equal(snapped, np.round(loose))
    np.testing.assert_array_equal(classes, [3])


def test_detector_takes_the_box_grid_from_the_model_or_the_caller(tmp_path: Path) -> None:
    import onnx

    from training.onnx_model import set_metadata

    loose = raw_output([(100.3, 30.2, 10.6, 8.8, [0.0, 0.0, 0.0, 0.7])], total=504)
    plain = constant_model(tmp_path / "plain.onnx", loose)
    model = onnx.load(plain)
    set_metadata(model, {"triscan.box_grid": "pixel"})
    pixel = tmp_path / "pixel.onnx"
    onnx.save(model, pixel)
    assert OnnxDetector(plain).box_grid == "none"  # every model exported before the key
    assert OnnxDetector(pixel).box_grid == "pixel"
    assert OnnxDetector(pixel, box_grid="none").box_grid == "none"
    assert OnnxDetector(plain, box_grid="pixel").box_grid == "pixel"
    boxes, _, _, _ = OnnxDetector(pixel).detect_boxes(tensor())
    np.testing.assert_array_equal(boxes, [[95, 26, 106, 35]])
    detections, _ = OnnxDetector(pixel).detect(tensor())
    assert detections[0].box_px == (95.0, 26.0, 106.0, 35.0)  # the wire message carries the same edges
    boxes, _, _, _ = OnnxDetector(plain).detect_boxes(tensor())
    assert not np.array_equal(boxes, np.round(boxes))
    with pytest.raises(ValueError, match="box_grid must be one of"):
        OnnxDetector(plain, box_grid="subpixel")  # type: ignore[arg-type]
    set_metadata(model, {"triscan.box_grid": "hex"})
    onnx.save(model, tmp_path / "hex.onnx")
    with pytest.raises(ValueError, match=r"declares an unknown triscan\.box_grid 'hex'"):
        OnnxDetector(tmp_path / "hex.onnx")


# --------------------------------------------------------------------------------------------------
# OnnxDetector on tiny constant graphs (no torch needed)
# --------------------------------------------------------------------------------------------------


def constant_model(
    path: Path,
    output: np.ndarray,
    input_shape: tuple[int, ...] = (1, 3, 64, 384),
    metadata: dict[str, str] | None = None,
) -> Path:
    """An ONNX graph whose output is ``output`` whatever the input: the detector's wiring in isolation."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper, numpy_helper

    node = helper.make_node("Constant", [], ["output0"], value=numpy_helper.from_array(output, "value"))
    graph = helper.make_graph(
        [node],
        "constant",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, list(input_shape))],
        [helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(output.shape))],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=9)
    for key, value in (metadata or {}).items():
        model.metadata_props.add(key=key, value=value)
    onnx.save(model, str(path))
    return path


def known_output() -> np.ndarray:
    return raw_output(
        [
            (90.5, 23.5, 19.0, 7.0, [0.0, 0.0, 0.9, 0.0]),  # desk at 81..100 × 20..27
            (91.0, 23.5, 19.0, 7.0, [0.0, 0.0, 0.5, 0.0]),  # its weaker twin: suppressed
            (5.0, 40.0, 4.0, 2.0, [0.1, 0.0, 0.0, 0.0]),  # below threshold
        ],
        total=504,
    )


def tensor(seed: int = 0) -> np.ndarray:
    return (np.random.default_rng(seed).random(TENSOR_SHAPE) < 0.05).astype(np.uint8) * 255


def test_detector_wiring_on_constant_graph(tmp_path: Path) -> None:
    path = constant_model(tmp_path / "const.onnx", known_output())
    detector = OnnxDetector(path, providers=["CPUExecutionProvider"], intra_op_threads=1)
    assert (detector.num_classes, detector.num_anchors) == (4, 504)
    settings = detector.postprocessing
    assert (settings.conf_threshold, settings.iou_threshold, settings.max_detections) == (
        DEFAULT_CONF,
        DEFAULT_IOU,
        MAX_DETECTIONS,
    )
    detector.warmup()
    np.testing.assert_array_equal(detector.infer(tensor()), known_output())
    detections, timings = detector.detect(tensor())
    assert detections == [one_detection((81.0, 20.0, 100.0, 27.0), float(np.float32(0.9)), 2)]
    assert isinstance(timings, StageTimings)
    assert min(timings.encode_ms, timings.inference_ms, timings.nms_ms) >= 0.0
    boxes, scores, classes, frame = detector.detect_boxes(tensor())
    np.testing.assert_array_equal(boxes, [[81, 20, 100, 27]])
    np.testing.assert_array_equal(scores, [np.float32(0.9)])
    np.testing.assert_array_equal(classes, [2])
    assert frame.to_message().nms_ms == frame.nms_ms


def batch_constant_model(path: Path, output: np.ndarray, output_batch: str | int = "batch") -> Path:
    """Like :func:`constant_model` with a free batch axis: ``output`` repeated once per input frame."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper, numpy_helper

    nodes = [
        helper.make_node("Constant", [], ["one"], value=numpy_helper.from_array(output, "one_value")),
        helper.make_node("Shape", ["images"], ["in_shape"], start=0, end=1),
        helper.make_node(
            "Constant",
            [],
            ["rest"],
            value=numpy_helper.from_array(np.array(output.shape[1:])),
        ),
        helper.make_node("Concat", ["in_shape", "rest"], ["out_shape"], axis=0),
        helper.make_node("Expand", ["one", "out_shape"], ["output0"]),
    ]
    graph = helper.make_graph(
        nodes,
        "batch_constant",
        [helper.make_tensor_value_info("images", TensorProto.FLOAT, ["batch", 3, 64, 384])],
        [helper.make_tensor_value_info("output0", TensorProto.FLOAT, [output_batch, *output.shape[1:]])],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=9)
    onnx.save(model, str(path))
    return path


def test_detect_many_equals_detect_frame_by_frame_with_and_without_a_batch_axis(tmp_path: Path) -> None:
    cpu = ["CPUExecutionProvider"]
    fixed = OnnxDetector(constant_model(tmp_path / "fixed.onnx", known_output()), providers=cpu)
    batch = OnnxDetector(batch_constant_model(tmp_path / "batch.onnx", known_output()), providers=cpu)
    assert not fixed.batched and batch.batched
    frames = [tensor(seed) for seed in range(3)]
    expected = [fixed.detect(frame)[0] for frame in frames]
    assert expected[0], "the constant output holds a desk"
    for detector in (fixed, batch):
        results = detector.detect_many(frames)
        assert [detections for detections, _ in results] == expected
        assert all(min(t.encode_ms, t.inference_ms, t.nms_ms) >= 0.0 for _, t in results)
    assert batch.detect_many([]) == []
    batch.warmup(4)  # every batch size up to 4 once; a fixed model ignores the size
    fixed.warmup(4)
    with pytest.raises(ValueError, match="max_batch"):
        batch.warmup(0)
    with pytest.raises(ValueError, match="tensor 1 of 3"):  # refused before anything runs
        batch.detect_many([frames[0], np.zeros((64, 360, 3), np.uint8), frames[2]])


def test_a_free_batch_axis_must_reach_the_output(tmp_path: Path) -> None:
    model = batch_constant_model(tmp_path / "half.onnx", known_output(), output_batch=1)
    with pytest.raises(ValueError, match=r"expected \[batch, 4 \+ nc, anchors\]"):
        OnnxDetector(model, providers=["CPUExecutionProvider"])


def test_model_id_names_the_file(tmp_path: Path) -> None:
    path = constant_model(tmp_path / "tri-v1.onnx", known_output())
    detector = OnnxDetector(path, providers=["CPUExecutionProvider"])
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    assert detector.model_id == f"tri-v1@{digest[:12]}"


def test_the_metadata_export_writes_is_what_the_detector_and_the_launcher_read(tmp_path: Path) -> None:
    entries = metadata_entries(padding="wrap", invalid="empty", box_grid="pixel", classes=FURNITURE_CLASSES)
    path = constant_model(tmp_path / "declared.onnx", known_output(), metadata=entries)
    detector = OnnxDetector(path, providers=["CPUExecutionProvider"])
    assert (detector.padding, detector.invalid, detector.box_grid) == ("wrap", "empty", "pixel")
    assert model_facts(path) == ModelFacts(padding="wrap", invalid="empty", takes_batches=False)
    plain = constant_model(tmp_path / "plain.onnx", known_output())  # a model that declares nothing
    assert model_facts(plain) == ModelFacts(padding="zero", invalid="sentinel", takes_batches=False)
    foreign = metadata_entries(padding="zero", invalid="sentinel", box_grid="none", classes=("cat", "dog"))
    with pytest.raises(ValueError, match=r"trained for the classes \['cat', 'dog'\]"):
        OnnxDetector(constant_model(tmp_path / "foreign.onnx", known_output(), metadata=foreign))


@pytest.mark.parametrize(
    ("bad", "match"),
    [
        (np.zeros(TENSOR_SHAPE, np.float32), "uint8"),
        (np.zeros((64, 360, 3), np.uint8), "uint8"),
        (np.zeros((3, 64, 384), np.uint8), "uint8"),
        (np.zeros((1, 64, 384, 3), np.uint8), "uint8"),
        ([[0]], "numpy uint8 array"),
    ],
)
def test_detector_rejects_bad_tensors(tmp_path: Path, bad: Any, match: str) -> None:
    detector = OnnxDetector(
        constant_model(tmp_path / "m.onnx", known_output()), providers=["CPUExecutionProvider"]
    )
    with pytest.raises(ValueError, match=match):
        detector.detect(bad)
    with pytest.raises(ValueError, match=match):
        detector.infer(bad)


def test_detector_rejects_bad_models_and_settings(tmp_path: Path) -> None:
    cpu = ["CPUExecutionProvider"]
    with pytest.raises(FileNotFoundError, match=r"missing\.onnx"):
        OnnxDetector(tmp_path / "missing.onnx")
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    with pytest.raises(ValueError, match="not a loadable ONNX model"):
        OnnxDetector(tmp_path / "junk.onnx", providers=cpu)
    square = constant_model(tmp_path / "square.onnx", known_output(), input_shape=(1, 3, 384, 384))
    with pytest.raises(ValueError, match=r"expected tensor\(float\)\[1, 3, 64, 384\]"):
        OnnxDetector(square, providers=cpu)
    coco = constant_model(tmp_path / "coco.onnx", np.zeros((1, 84, 504), np.float32))
    with pytest.raises(ValueError, match="predicts 80 classes"):
        OnnxDetector(coco, providers=cpu)
    e2e = constant_model(
        tmp_path / "e2e.onnx", np.zeros((1, 300, 6), np.float32), metadata={"end2end": "True"}
    )
    with pytest.raises(ValueError, match="end-to-end"):
        OnnxDetector(e2e, providers=cpu)
    good = constant_model(tmp_path / "good.onnx", known_output())
    for kwargs in (
        {"conf_threshold": 1.5},
        {"iou_threshold": -0.1},
        {"max_detections": 0},
        {"padding": "mirror"},
        {"intra_op_threads": 0},
    ):
        with pytest.raises(ValueError):
            OnnxDetector(good, providers=cpu, **kwargs)


# --------------------------------------------------------------------------------------------------
# A real YOLOv8n exported by Ultralytics
# --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def offline_ultralytics(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """Ultralytics importable with no network and its settings in a temporary directory."""
    pytest.importorskip("torch")
    pytest.importorskip("torchvision")
    if importlib.util.find_spec("ultralytics") is None:  # importing it here would bypass the offline setup
        pytest.skip("ultralytics is not installed (train extra)")
    with pytest.MonkeyPatch.context() as mp:
        for key in ("YOLO_CONFIG_DIR", "YOLO_OFFLINE", "YOLO_AUTOINSTALL"):
            mp.delenv(key, raising=False)  # restored when the module's tests are done
        from training.offline import configure_offline

        configure_offline(tmp_path_factory.mktemp("yolo-config"))
        yield


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory, offline_ultralytics: None) -> tuple[Path, Any]:
    """An untrained 4-class YOLOv8n from ``yolov8n.yaml``, saved as .pt and exported to ONNX once."""
    pytest.importorskip("onnx")
    import torch
    from ultralytics import YOLO
    from ultralytics.nn.tasks import DetectionModel

    root = tmp_path_factory.mktemp("yolo")
    torch.manual_seed(0)
    yolo = YOLO("yolov8n.yaml")
    yolo.model = DetectionModel("yolov8n.yaml", nc=4, verbose=False)  # the project's 4 classes
    weights = root / "tri.pt"
    yolo.save(weights)  # exporting from the .pt keeps every file inside the temporary directory
    onnx_path = Path(
        YOLO(weights).export(format="onnx", imgsz=(64, 384), batch=1, dynamic=False, simplify=True)
    )
    return onnx_path, YOLO(weights).model.float().eval()


def ultralytics_nms() -> Any:
    try:
        from ultralytics.utils.nms import non_max_suppression
    except ImportError:  # Ultralytics before 8.3.x kept it in ops
        from ultralytics.utils.ops import non_max_suppression
    return non_max_suppression


def ultralytics_boxes(raw: np.ndarray, conf: float, iou: float, max_det: int) -> np.ndarray:
    """Ultralytics' own post-processing: its NMS, then the clip its predictor/validator applies."""
    import torch
    import torchvision  # noqa: F401  (Ultralytics uses torchvision's NMS kernel once it is imported)
    from ultralytics.utils.ops import clip_boxes

    result = ultralytics_nms()(torch.from_numpy(raw.copy()), conf, iou, max_det=max_det)[0]
    clip_boxes(result[:, :4], (64, 384))
    return result.numpy()


def test_exported_model_shapes_and_id(exported: tuple[Path, Any]) -> None:
    onnx_path, _ = exported
    detector = OnnxDetector(onnx_path, providers=["CPUExecutionProvider"])
    assert (detector.num_classes, detector.num_anchors) == (4, 504)
    assert re.fullmatch(r"tri@[0-9a-f]{12}", detector.model_id)
    out = detector.infer(tensor())
    assert out.shape == (1, 8, 504) and out.dtype == np.float32


def test_onnx_output_equals_pytorch_forward(exported: tuple[Path, Any]) -> None:
    import torch

    onnx_path, torch_model = exported
    detector = OnnxDetector(onnx_path, providers=["CPUExecutionProvider"])
    for seed in range(3):
        frame = np.random.default_rng(seed).integers(0, 256, TENSOR_SHAPE, dtype=np.uint8)
        with torch.no_grad():
            expected = torch_model(torch.from_numpy(to_model_input(frame)))[0].numpy()
        got = detector.infer(frame)
        assert expected.shape == got.shape
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-4)


@pytest.mark.parametrize("iou", [0.45, 0.7])
def test_detector_equals_ultralytics_postprocess_on_real_output(
    exported: tuple[Path, Any], iou: float
) -> None:
    onnx_path, _ = exported
    conf = 0.001  # an untrained head scores ~1e-3: this keeps a few dozen real candidates
    detector = OnnxDetector(
        onnx_path, conf_threshold=conf, iou_threshold=iou, providers=["CPUExecutionProvider"]
    )
    compared = 0
    for seed in range(3):
        frame = tensor(seed)
        raw = detector.infer(frame)
        expected = ultralytics_boxes(raw, conf, iou, MAX_DETECTIONS)
        boxes, scores, classes, _ = detector.detect_boxes(frame)
        assert len(boxes) == len(expected)
        np.testing.assert_allclose(boxes, expected[:, :4], rtol=0, atol=1e-3)
        np.testing.assert_allclose(scores, expected[:, 4], rtol=0, atol=1e-6)
        np.testing.assert_array_equal(classes, expected[:, 5].astype(np.int64))
        compared += len(boxes)
    assert compared >= 3, "the untrained model produced no boxes: the comparison would be vacuous"


@pytest.mark.parametrize(("conf", "iou", "max_det"), [(0.25, 0.45, 100), (0.25, 0.7, 100), (0.1, 0.45, 7)])
@pytest.mark.parametrize("seed", range(3))
def test_postprocess_equals_ultralytics_on_synthetic_output(
    seed: int, conf: float, iou: float, max_det: int, offline_ultralytics: None
) -> None:
    """Crowded scenes a trained model produces: hundreds of overlapping candidates over 4 classes."""
    rng = np.random.default_rng(seed)
    boxes, _, _ = clustered_boxes(rng, 504)
    raw = np.zeros((1, 8, 504), np.float32)
    raw[0, :2] = ((boxes[:, :2] + boxes[:, 2:]) / 2).T
    raw[0, 2:4] = (boxes[:, 2:] - boxes[:, :2]).T
    raw[0, 4:] = 1.0 / (1.0 + np.exp(-rng.normal(-2.0, 2.0, (4, 504))))
    expected = ultralytics_boxes(raw, conf, iou, max_det)
    got_boxes, got_scores, got_classes = postprocess(
        raw, conf_threshold=conf, iou_threshold=iou, max_detections=max_det
    )
    assert len(expected) >= min(max_det, 20)
    assert len(got_boxes) == len(expected)
    np.testing.assert_allclose(got_boxes, expected[:, :4], rtol=0, atol=1e-3)
    np.testing.assert_allclose(got_scores, expected[:, 4], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(got_classes, expected[:, 5].astype(np.int64))


@pytest.mark.parametrize("padding", ["zero", "wrap"])
def test_exported_model_detect_gives_valid_detections(exported: tuple[Path, Any], padding: str) -> None:
    onnx_path, _ = exported
    detector = OnnxDetector(
        onnx_path,
        conf_threshold=0.001,
        padding=padding,
        providers=["CPUExecutionProvider"],  # type: ignore[arg-type]
    )
    detector.warmup()
    detections, timings = detector.detect(tensor(1))
    assert detections and all(isinstance(d, Detection) for d in detections)
    assert len(detections) <= MAX_DETECTIONS
    scores = [d.score for d in detections]
    assert scores == sorted(scores, reverse=True)
    for det in detections:
        x1, y1, x2, y2 = det.box_px
        assert 0 <= x1 <= x2 <= 384 and 0 <= y1 <= y2 <= 64
        assert -180 < det.bearing_deg <= 180
        assert math.hypot(det.x_m, det.y_m) == pytest.approx((det.range_min_m + det.range_max_m) / 2)
    assert isinstance(timings, StageTimings)
    assert timings.encode_ms >= 0 and timings.inference_ms > 0 and timings.nms_ms >= 0


@pytest.mark.parametrize("padding", ["zero", "wrap"])
def test_a_batch_is_post_processed_as_each_of_its_frames_alone(padding: str) -> None:
    """Decoding, clipping and snapping run over the whole batch at once; nothing may leak between
    frames (no box of one frame suppresses or merges with another's), and an empty frame stays empty."""
    rng = np.random.default_rng(4)
    frames, nc, anchors = 6, 5, 504
    outputs = np.zeros((frames, 4 + nc, anchors), np.float32)
    outputs[:, 0] = rng.uniform(-5.0, 390.0, (frames, anchors))  # near and across both image edges
    outputs[:, 1] = rng.uniform(0.0, 70.0, (frames, anchors))
    outputs[:, 2:4] = rng.uniform(1.0, 30.0, (frames, 2, anchors))
    outputs[:, 4:] = rng.random((frames, nc, anchors)) ** 8  # a few dozen candidates a frame
    outputs[1] = outputs[0]  # the same boxes in two frames: each frame keeps its own
    outputs[2, 4:] = 0.0  # a frame with no candidate
    outputs[3, 0, 7], outputs[3, 4, 7] = np.nan, 0.99  # a broken box is dropped, in its frame only
    settings = {"padding": padding, "box_grid": "pixel", "num_classes": nc, "max_detections": 12}
    many = PostprocessSettings(DEFAULT_CONF, DEFAULT_IOU, **settings).postprocess_many(outputs)
    assert len(many) == frames and len(many[2][0]) == 0 and len(many[0][0]) > 3
    for frame, got in enumerate(many):
        alone = postprocess(outputs[frame : frame + 1], **settings)
        for a, b in zip(got, alone, strict=True):
            assert a.dtype == b.dtype and np.array_equal(a, b)
    detections = detections_many(many, raster_yaw_deg=180.0)
    assert [len(d) for d in detections] == [len(scores) for _, scores, _ in many]
    assert detections[1] == detections_from_boxes(*many[1], raster_yaw_deg=180.0)
