"""Evaluation arithmetic against Ultralytics' own implementation."""

from __future__ import annotations

import itertools
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from services.simulator.labels import ObjectLabel, yolo_lines
from training.evaluate import (
    IOU_THRESHOLDS,
    EvalSample,
    box_iou,
    circular_box_iou,
    format_table,
    match_predictions,
    merge_label_copies,
    seam_subset,
    yolo_labels_to_boxes,
)


@pytest.fixture(scope="module")
def ultralytics_offline(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Ultralytics, to compare with: only with the train extra."""
    pytest.importorskip("torch")
    pytest.importorskip("ultralytics")
    from training.offline import configure_offline

    configure_offline(tmp_path_factory.mktemp("yolo"))


def random_boxes(rng: np.random.Generator, n: int) -> np.ndarray:
    xy = rng.uniform(0, 340, size=(n, 2)) * [1, 60 / 340]
    wh = rng.uniform(2, 40, size=(n, 2)) * [1, 0.25]
    return np.concatenate([xy, xy + wh], axis=1)


@pytest.mark.parametrize("seed", range(5))
def test_matching_equals_ultralytics_validator(seed: int, ultralytics_offline: None) -> None:
    import torch
    from ultralytics.models.yolo.detect import DetectionValidator
    from ultralytics.utils.metrics import box_iou as ultralytics_iou

    rng = np.random.default_rng(seed)
    labels = random_boxes(rng, 12)
    # Predictions near the labels (jittered) plus clutter, in descending confidence like NMS output.
    preds = np.concatenate([labels + rng.normal(0, 2.0, labels.shape), random_boxes(rng, 10)])
    pred_cls = rng.integers(0, 4, len(preds))
    true_cls = rng.integers(0, 4, len(labels))
    pred_cls[: len(labels)] = np.where(rng.random(len(labels)) < 0.8, true_cls, pred_cls[: len(labels)])
    order = rng.permutation(len(preds))
    preds, pred_cls = preds[order], pred_cls[order]

    iou_ours = box_iou(labels, preds)
    iou_theirs = ultralytics_iou(torch.tensor(labels), torch.tensor(preds)).numpy()
    assert np.allclose(iou_ours, iou_theirs, atol=1e-6)

    validator = SimpleNamespace(iouv=torch.tensor(IOU_THRESHOLDS))
    theirs = DetectionValidator.match_predictions(
        validator, torch.tensor(pred_cls), torch.tensor(true_cls), torch.tensor(iou_theirs)
    ).numpy()
    ours = match_predictions(pred_cls, true_cls, iou_ours)
    assert ours.any() and np.array_equal(ours, theirs)


def test_matching_with_no_labels_or_no_predictions_is_all_false() -> None:
    assert match_predictions(np.array([0, 1]), np.array([], dtype=np.int64), np.zeros((0, 2))).shape == (
        2,
        10,
    )
    assert not match_predictions(np.array([0, 1]), np.array([], dtype=np.int64), np.zeros((0, 2))).any()
    assert match_predictions(np.array([], dtype=np.int64), np.array([1]), np.zeros((1, 0))).shape == (0, 10)


def test_label_lines_convert_back_to_the_pixel_boxes() -> None:
    label = ObjectLabel(
        2, 5, True, 90.0, 81.0, 99.0, 1.3, 1.7, ((81.0, 20.0, 100.0, 27.0), (363.0, 3.0, 382.0, 9.0))
    )
    boxes, classes = yolo_labels_to_boxes("\n".join(yolo_lines([label])))
    assert classes.tolist() == [2, 2]
    assert np.allclose(boxes, [[81, 20, 100, 27], [363, 3, 382, 9]], atol=1e-3)
    empty_boxes, empty_classes = yolo_labels_to_boxes("")
    assert empty_boxes.shape == (0, 4) and empty_classes.shape == (0,)


def test_table_has_a_row_per_class_and_all(tmp_path: Path) -> None:
    from training.evaluate import EvalReport

    report = EvalReport(model_id="m@0", source="x", images=3, instances=7)
    report.overall = {"precision": 0.9, "recall": 0.8, "mAP50": 0.95, "mAP50-95": 0.7}
    report.per_class = {
        "chair": {"instances": 7, "precision": 0.9, "recall": 0.8, "mAP50": 0.95, "mAP50-95": 0.7}
    }
    table = format_table(report).splitlines()
    assert table[1].split() == ["chair", "7", "0.900", "0.800", "0.950", "0.700"]
    assert table[-1].split()[0] == "all"


def test_circular_iou_sees_the_copy_across_the_seam() -> None:
    whole = np.array([[346.0, 20.0, 365.0, 27.0]])
    low_copy = np.array([[-14.0, 20.0, 5.0, 27.0]])  # the same bearings, one turn earlier
    partial = np.array([[0.0, 20.0, 5.0, 27.0]])  # the part of it in columns 0–4
    assert circular_box_iou(whole, low_copy)[0, 0] == pytest.approx(1.0)
    assert circular_box_iou(whole, partial)[0, 0] == pytest.approx(5.0 / 19.0)
    assert box_iou(whole, low_copy)[0, 0] == 0.0
    far = np.array([[100.0, 20.0, 120.0, 27.0]])
    assert circular_box_iou(whole, far)[0, 0] == 0.0


def test_wrap_label_copies_merge_to_the_whole_object() -> None:
    # The labels of a box across the seam under wrap: the partial copy at 0–5 and the whole box.
    boxes = np.array([[0.0, 20.0, 5.0, 27.0], [346.0, 20.0, 365.0, 27.0], [100.0, 5.0, 130.0, 15.0]])
    sample = EvalSample(
        "s", np.zeros((64, 384, 3), np.uint8), boxes, np.array([1, 1, 2]), np.array([1, 1, 0], bool)
    )
    merged = merge_label_copies(sample)
    assert merged.boxes.tolist() == [[346.0, 20.0, 365.0, 27.0], [100.0, 5.0, 130.0, 15.0]]
    assert merged.crosses_seam is not None and merged.crosses_seam.tolist() == [True, False]


def test_seam_subset_keeps_seam_objects_and_their_class_predictions() -> None:
    boxes = np.array([[346.0, 20.0, 365.0, 27.0], [100.0, 5.0, 130.0, 15.0]])
    sample = EvalSample(
        "s", np.zeros((64, 384, 3), np.uint8), boxes, np.array([1, 2]), np.array([True, False])
    )
    preds = np.array(
        [
            [347.0, 20.0, 364.0, 27.0],  # the seam box, found
            [101.0, 5.0, 129.0, 15.0],  # the desk, off the seam: out of the set
            [200.0, 5.0, 210.0, 15.0],  # a stray box of the seam object's class: counts against it
            [50.0, 5.0, 60.0, 15.0],  # a stray chair: its class has no seam object here, out
        ]
    )
    pred_classes = np.array([1, 2, 1, 0])
    label_in, pred_in = seam_subset(sample, box_iou(boxes, preds), pred_classes)
    assert label_in.tolist() == [True, False]
    assert pred_in.tolist() == [True, False, True, False]
    unknown = EvalSample("s", sample.tensor, boxes, sample.classes, None)
    assert not seam_subset(unknown, box_iou(boxes, preds), pred_classes)[0].any()


def test_evaluate_scores_a_missed_seam_object_when_the_model_finds_nothing(tmp_path: Path) -> None:
    """An empty scan with a seam-crossing label: no predictions at all is a miss, not a crash."""
    from common.inference import OnnxDetector
    from common.model_spec import default_model_path
    from training.evaluate import evaluate

    detector = OnnxDetector(default_model_path(), providers=["CPUExecutionProvider"], intra_op_threads=1)
    empty = np.zeros((64, 384, 3), np.uint8)
    seam_box = np.array([[346.0, 20.0, 365.0, 27.0]])
    samples = [EvalSample("empty", empty, seam_box, np.array([1]), np.array([True]))]
    report = evaluate(detector, iter(samples), tmp_path, source="empty scan", plots=False)
    assert (report.images, report.instances) == (1, 1)
    assert report.overall["recall"] == 0.0
    assert report.seam_crossing is not None and report.seam_crossing["instances"] == 1


def test_map_by_iou_threshold_splits_the_average(tmp_path: Path) -> None:
    """mAP@0.5:0.95 is the mean of the ten thresholds' mAP; each is at most the one below it."""
    from common.inference import OnnxDetector
    from common.model_spec import CLASS_NAMES, default_model_path
    from training.evaluate import VAL_CONF, VAL_IOU, VAL_MAX_DET, evaluate, fresh_samples

    detector = OnnxDetector(
        default_model_path(), conf_threshold=VAL_CONF, iou_threshold=VAL_IOU, max_detections=VAL_MAX_DET
    )
    report = evaluate(detector, fresh_samples(2024, 1, 3, "zero", 6), tmp_path, source="fresh", plots=False)
    by_iou = report.map_by_iou
    assert list(by_iou) == ["0.50", "0.55", "0.60", "0.65", "0.70", "0.75", "0.80", "0.85", "0.90", "0.95"]
    assert by_iou["0.50"] == pytest.approx(report.overall["mAP50"])
    assert np.mean(list(by_iou.values())) == pytest.approx(report.overall["mAP50-95"])
    values = list(by_iou.values())
    assert all(high <= low + 1e-12 for low, high in itertools.pairwise(values))
    assert set(report.ap_by_iou_per_class) <= set(CLASS_NAMES) and report.ap_by_iou_per_class
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["map_by_iou"] == by_iou


def test_people_are_counted_by_the_beams_on_them_and_found_only_above_the_threshold() -> None:
    from training.evaluate import BEAM_BANDS, PERSON_ID, _count_people_by_beams

    labels = np.array([[10, 10, 20, 20], [30, 10, 40, 20], [50, 10, 60, 20], [70, 10, 80, 20]], float)
    sample = EvalSample(
        "s",
        np.zeros((64, 384, 3), np.uint8),
        labels,
        np.array([PERSON_ID, PERSON_ID, 0, PERSON_ID]),
        None,
        np.array([2, 9, 2, 40]),
    )
    # On the 9-beam person a confident person box, on the 2-beam one a person box below the threshold
    # and a confident chair box, on the chair a chair box, and beside the 40-beam person a box with
    # IoU 1/3.
    shifts = np.array([[0, 0, 0, 0], [0, 0, 0, 0], [0, 0, 0, 0], [5, 0, 5, 0], [0, 0, 0, 0]])
    predictions = np.concatenate([labels, labels[:1]]) + shifts
    scores = np.array([0.1, 0.9, 0.9, 0.9, 0.9])
    classes = np.array([PERSON_ID, PERSON_ID, 0, PERSON_ID, 0])
    counts = {name: [0, 0] for name, _, _ in BEAM_BANDS}
    _count_people_by_beams(counts, sample, box_iou(labels, predictions), scores, classes, PERSON_ID)
    assert counts == {"2": [1, 0], "3-4": [0, 0], "5-7": [0, 0], "8-14": [1, 1], "15+": [1, 0]}


def test_fresh_worlds_with_people_report_them_by_beams(tmp_path: Path) -> None:
    from common.inference import OnnxDetector
    from common.model_spec import MODELS_DIR
    from training.evaluate import BEAM_BANDS, PERSON_ID, VAL_CONF, VAL_IOU, evaluate, fresh_samples

    people_model = MODELS_DIR / "yolov8p-relu-dfl12" / "triscan-yolov8p-relu-dfl12-zero-int8.onnx"
    detector = OnnxDetector(people_model, conf_threshold=VAL_CONF, iou_threshold=VAL_IOU, motion_confirm=None)
    samples = list(
        fresh_samples(9000, 1, 4, "zero", 15, people=4, raster_yaw_deg=180.0, invalid=detector.invalid)
    )
    assert all(s.beams is not None and len(s.beams) == len(s.classes) for s in samples)
    report = evaluate(detector, iter(samples), tmp_path, source="fresh", plots=False)
    by_beams = report.person_recall_by_beams
    people = sum(int((s.classes == PERSON_ID).sum()) for s in samples)
    assert people and sum(int(row["instances"]) for row in by_beams.values()) == people
    assert all(0.0 <= row["recall"] <= 1.0 for row in by_beams.values())
    assert set(by_beams) <= {name for name, _, _ in BEAM_BANDS}
    assert "people found at 0.25 by beams on them" in format_table(report)
