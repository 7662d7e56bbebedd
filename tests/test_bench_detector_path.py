"""The NMS-in-graph lever of ``bench.detector_path`` against the detector's own post-processing.

The lever is a measurement, not the detector's code, but a saving measured on wrong boxes would be
no saving: these tests put hand-made raw outputs through ONNX Runtime (an identity model with the
lever's nodes appended) and require exactly what ``common.postprocess.postprocess`` returns, also where
scores tie, where the IoU sits exactly on the threshold and where a broken model gives NaN.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.detector_path import boxes_from_selected, float32_at_most, with_nms_in_graph
from common.model_spec import NUM_CLASSES
from common.postprocess import PostprocessSettings

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

ANCHORS = 240
SETTINGS = PostprocessSettings(
    conf_threshold=0.25,
    iou_threshold=0.45,
    max_detections=300,
    padding="zero",
    num_classes=None,
    box_grid="pixel",
)


def identity_session(
    tmp_path: Path, settings: PostprocessSettings, anchors: int = ANCHORS, *, rank_ties: bool = True
) -> ort.InferenceSession:
    """A model whose raw output is its input, with the lever's nodes after it."""
    from onnx import TensorProto, helper

    shape = ["n", 4 + NUM_CLASSES, anchors]
    graph = helper.make_graph(
        [helper.make_node("Identity", ["raw_in"], ["output0"])],
        "identity",
        [helper.make_tensor_value_info("raw_in", TensorProto.FLOAT, shape)],
        [helper.make_tensor_value_info("output0", TensorProto.FLOAT, shape)],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
    plain = tmp_path / "identity.onnx"
    onnx.save(model, str(plain))
    with_nms = with_nms_in_graph(plain, tmp_path / "identity-nms.onnx", settings, rank_ties=rank_ties)
    return ort.InferenceSession(str(with_nms), providers=["CPUExecutionProvider"])


def clustered_raw(rng: np.random.Generator, frames: int, anchors: int = ANCHORS) -> np.ndarray:
    """Raw outputs whose boxes crowd around a few centres and whose scores lie on a 0.125 grid, so
    that NMS has suppression chains to resolve and equal scores everywhere, across classes too."""
    raw = np.empty((frames, 4 + NUM_CLASSES, anchors), np.float32)
    for frame in range(frames):
        centres = rng.uniform([0, 0], [384, 64], size=(6, 2))
        sizes = rng.uniform([4, 2], [40, 12], size=(6, 2))
        which = rng.integers(0, len(centres), anchors)
        raw[frame, :2] = (centres[which] + rng.normal(0, 1.5, (anchors, 2))).T
        raw[frame, 2:4] = (sizes[which] * rng.uniform(0.7, 1.3, (anchors, 2))).T
        raw[frame, 4:] = np.round(rng.random((NUM_CLASSES, anchors)) * 8) / 8
    return raw


def assert_same_as_postprocess(
    session: ort.InferenceSession, raw: np.ndarray, settings: PostprocessSettings = SETTINGS
) -> None:
    out, selected = session.run(None, {"raw_in": raw})
    for frame in range(len(raw)):
        expected = settings.postprocess(raw[frame : frame + 1])
        got = boxes_from_selected(out, selected, frame, settings)
        for name, want, have in zip(("boxes", "scores", "class ids"), expected, got, strict=True):
            np.testing.assert_array_equal(have, want, err_msg=f"frame {frame}: {name}")
            assert have.dtype == want.dtype, name


@pytest.mark.parametrize("rank_ties", [True, False])
@pytest.mark.parametrize("seed", range(4))
def test_nms_in_graph_equals_the_python_nms_where_scores_tie(
    tmp_path: Path, seed: int, rank_ties: bool
) -> None:
    """Ranked, by the ONNX spec; unranked, by ONNX Runtime's own order, which the spec leaves open: if
    an upgrade changes it, the unranked case fails here first."""
    raw = clustered_raw(np.random.default_rng(seed), frames=3)
    out = SETTINGS.postprocess(raw[:1])
    assert 10 < len(out[0]) < 200  # many kept, many suppressed
    assert len(np.unique(out[1])) < len(out[1])  # and kept scores that tie
    assert_same_as_postprocess(identity_session(tmp_path, SETTINGS, rank_ties=rank_ties), raw)


def test_ranking_is_what_orders_ties_in_the_ranked_graph(tmp_path: Path) -> None:
    """Equal scores along a chain of overlapping boxes: the kept set depends on which box of the
    chain goes first, so ranks in the wrong order (the last anchor first) must change it."""
    raw = np.zeros((1, 4 + NUM_CLASSES, 12), np.float32)
    raw[0, 0] = 100 + 3.0 * np.arange(12)  # each box overlaps its neighbours above 0.45, not the next ones
    raw[0, 1:4] = np.array([[30.0], [8.0], [6.0]])
    raw[0, 4] = 0.5
    kept = SETTINGS.postprocess(raw)[0]
    np.testing.assert_array_equal(kept[:, 0], 96 + 6.0 * np.arange(6))  # anchors 0, 2, 4, …
    session = identity_session(tmp_path, SETTINGS, anchors=12)
    assert_same_as_postprocess(session, raw)
    reversed_raw = raw[:, :, ::-1].copy()  # the same boxes, last first: the kept set is the other half
    assert not np.array_equal(SETTINGS.postprocess(reversed_raw)[0][:, 0], kept[:, 0][::-1])
    assert_same_as_postprocess(session, reversed_raw)


def test_nms_in_graph_caps_and_merges_like_the_detector(tmp_path: Path) -> None:
    settings = PostprocessSettings(0.1, 0.7, 7, "wrap", None, "none")
    raw = clustered_raw(np.random.default_rng(9), frames=2)
    raw[0, 0, :20] = np.linspace(362.0, 380.0, 20)  # boxes in the wrap columns, copies of 2°–20°
    raw[0, 0, 20:40] = np.linspace(2.0, 20.0, 20)
    assert_same_as_postprocess(identity_session(tmp_path, settings), raw, settings)


@pytest.mark.parametrize(("threshold", "kept"), [(0.3, 1), (0.45, 2)])
def test_nms_in_graph_compares_the_iou_threshold_like_torchvision(
    tmp_path: Path, threshold: float, kept: int
) -> None:
    """IoU exactly float32(t): float32(0.3) lies above 0.3 (suppressed), float32(0.45) below (kept)."""
    settings = PostprocessSettings(0.25, threshold, 300, "zero", None, "none")
    raw = np.zeros((1, 4 + NUM_CLASSES, 8), np.float32)
    raw[0, :4, 0] = (5.0, 5.0, 10.0, 10.0)  # xyxy 0, 0, 10, 10
    raw[0, :4, 1] = (5.0, threshold * 5, 10.0, threshold * 10)  # xyxy 0, 0, 10, 10·t
    raw[0, 4, :2] = (0.9, 0.8)
    session = identity_session(tmp_path, settings, anchors=8)
    assert len(settings.postprocess(raw)[0]) == kept
    assert_same_as_postprocess(session, raw, settings)


def test_a_broken_frame_goes_through_the_python_post_processing(tmp_path: Path) -> None:
    raw = clustered_raw(np.random.default_rng(3), frames=2)
    raw[1, 5, 17] = np.nan  # a NaN score: decode drops the anchor
    raw[1, 2, 30] = np.inf  # an infinite width: decode drops the box
    assert_same_as_postprocess(identity_session(tmp_path, SETTINGS), raw)


def test_float32_at_most_keeps_the_double_comparison() -> None:
    for value in (0.3, 0.45, 0.5, 0.7, 0.1, 1.0):
        bound = float32_at_most(value)
        assert float(bound) <= value
        above = np.nextafter(bound, np.float32(np.inf))
        assert float(above) > value  # the next float32 is above the double threshold
