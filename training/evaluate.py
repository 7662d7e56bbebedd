"""``triscan eval``: the paper's Table I for a shipped model, measured through the run-time code.

Predictions come from :class:`common.inference.OnnxDetector`, the decoder and NMS the detector
service runs, fed with the run-time tensor (a data set's PNGs are byte-for-byte ScanStacker output, a
test proves it; ``--fresh`` simulates new scenarios straight through ScanStacker instead). The metric
arithmetic is Ultralytics' own (``ap_per_class`` via ``DetMetrics``, its ``ConfusionMatrix``), and
predictions are matched to labels with the same greedy policy as its validator, so the figures can be
compared with ``yolo val`` — a test checks they agree within 0.01.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from common.encoding import IMAGE_WIDTH, RANGE_ROWS, Padding
from common.inference import OnnxDetector
from common.messages import CLASS_NAMES
from training.export import read_tensor_png

log = logging.getLogger(__name__)

IOU_THRESHOLDS = np.linspace(0.5, 0.95, 10)  # the COCO ladder behind mAP@0.5:0.95
VAL_CONF = 0.001  # Ultralytics' validation protocol: keep almost everything, let AP integrate
VAL_IOU = 0.7
VAL_MAX_DET = 300


@dataclass(frozen=True)
class EvalSample:
    """A tensor and its ground truth: boxes xyxy in raster pixels, class ids."""

    name: str
    tensor: np.ndarray
    boxes: np.ndarray  # float64[M, 4]
    classes: np.ndarray  # int64[M]


@dataclass
class EvalReport:
    """Everything ``triscan eval`` measured; ``to_json`` is what lands in metrics.json."""

    model_id: str
    source: str
    images: int = 0
    instances: int = 0
    overall: dict[str, float] = field(default_factory=dict)
    per_class: dict[str, dict[str, float]] = field(default_factory=dict)
    mean_timings_ms: dict[str, float] = field(default_factory=dict)
    files: dict[str, str] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {k: v for k, v in self.__dict__.items()}


def yolo_labels_to_boxes(text: str) -> tuple[np.ndarray, np.ndarray]:
    """YOLO lines (normalised centre/size) → raster-pixel xyxy boxes and class ids."""
    rows = np.array([[float(v) for v in line.split()] for line in text.splitlines() if line.strip()])
    if rows.size == 0:
        return np.zeros((0, 4)), np.zeros(0, dtype=np.int64)
    xc, yc = rows[:, 1] * IMAGE_WIDTH, rows[:, 2] * RANGE_ROWS
    w, h = rows[:, 3] * IMAGE_WIDTH, rows[:, 4] * RANGE_ROWS
    return np.stack([xc - w / 2, yc - h / 2, xc + w / 2, yc + h / 2], axis=1), rows[:, 0].astype(np.int64)


def dataset_samples(dataset_dir: Path, split: str = "test") -> Iterator[EvalSample]:
    """Samples of one split of a data set written by ``triscan dataset``."""
    image_dir = dataset_dir / "images" / split
    images = sorted(image_dir.glob("*.png"))
    if not images:
        raise FileNotFoundError(f"no images in {image_dir}: is {dataset_dir} a triscan data set?")
    for image in images:
        label = dataset_dir / "labels" / split / f"{image.stem}.txt"
        boxes, classes = yolo_labels_to_boxes(label.read_text() if label.exists() else "")
        yield EvalSample(image.stem, read_tensor_png(image), boxes, classes)


def fresh_samples(
    seed: int, scenarios: int, positions: int, padding: Padding, frame_stride: int
) -> Iterator[EvalSample]:
    """Newly simulated scenarios, straight through ScanStacker: data no model has seen."""
    from services.simulator.scenario import sample_scenario
    from services.simulator.world import World
    from training.dataset import plan_motions, simulate_samples

    with World() as world:
        for index in range(scenarios):
            scenario = sample_scenario(index, seed)
            motions = plan_motions(scenario, seed, positions)
            for sample in simulate_samples(world, scenario, motions, seed, padding, frame_stride):
                boxes = [box for label in sample.labels for box in label.boxes_px]
                classes = [label.class_id for label in sample.labels for _ in label.boxes_px]
                yield EvalSample(
                    sample.name,
                    sample.tensor,
                    np.array(boxes, dtype=np.float64).reshape(-1, 4),
                    np.array(classes, dtype=np.int64),
                )


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pairwise IoU, float64[len(a), len(b)], of xyxy boxes."""
    top_left = np.maximum(a[:, None, :2], b[None, :, :2])
    bottom_right = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.clip(bottom_right - top_left, 0, None).prod(axis=2)
    area_a = (a[:, 2:] - a[:, :2]).prod(axis=1)
    area_b = (b[:, 2:] - b[:, :2]).prod(axis=1)
    return inter / (area_a[:, None] + area_b[None, :] - inter + 1e-7)


def match_predictions(
    pred_classes: np.ndarray,
    true_classes: np.ndarray,
    iou: np.ndarray,
    thresholds: np.ndarray = IOU_THRESHOLDS,
) -> np.ndarray:
    """Correct-at-each-IoU matrix bool[N, T], greedy one-to-one as Ultralytics' validator matches.

    ``iou`` is [labels, predictions]; predictions must come in descending confidence. Each
    prediction, in turn, claims the best still-unclaimed label of its class at every threshold.
    """
    correct = np.zeros((len(pred_classes), len(thresholds)), dtype=bool)
    if len(pred_classes) == 0 or len(true_classes) == 0:
        return correct
    iou = iou * (true_classes[:, None] == pred_classes[None, :])
    matched = np.zeros((len(true_classes), len(thresholds)), dtype=bool)
    columns = np.arange(len(thresholds))
    for j in np.flatnonzero((iou >= thresholds.min()).any(axis=0)):
        available = np.where(matched, 0.0, iou[:, j, None])
        best = available.argmax(axis=0)
        correct[j] = available[best, columns] >= thresholds
        matched[best, columns] |= correct[j]
    return correct


def evaluate(
    detector: OnnxDetector,
    samples: Iterator[EvalSample],
    out_dir: Path,
    *,
    source: str,
    plots: bool = True,
) -> EvalReport:
    """Run every sample through the detector and write metrics.json (+ plots) into ``out_dir``."""
    from training.offline import configure_offline

    configure_offline()
    import torch
    from ultralytics.utils.metrics import ConfusionMatrix, DetMetrics

    names = dict(enumerate(CLASS_NAMES))
    metrics = DetMetrics(names=names)
    confusion = ConfusionMatrix(names=names)
    report = EvalReport(model_id=detector.model_id, source=source)
    timing_sums = {"encode_ms": 0.0, "inference_ms": 0.0, "nms_ms": 0.0}
    for sample in samples:
        boxes, scores, classes, timings = detector.detect_boxes(sample.tensor)
        for key in timing_sums:
            timing_sums[key] += float(getattr(timings, key))
        iou = box_iou(sample.boxes, boxes) if len(boxes) and len(sample.boxes) else np.zeros((0, 0))
        metrics.update_stats(
            {
                "tp": match_predictions(classes, sample.classes, iou),
                "conf": scores.astype(np.float64),
                "pred_cls": classes.astype(np.float64),
                "target_cls": sample.classes.astype(np.float64),
                "target_img": np.unique(sample.classes).astype(np.float64),
                "im_name": sample.name,
            }
        )
        confusion.process_batch(
            {
                "bboxes": torch.from_numpy(np.asarray(boxes, dtype=np.float32)),
                "conf": torch.from_numpy(np.asarray(scores, dtype=np.float32)),
                "cls": torch.from_numpy(np.asarray(classes, dtype=np.float32)),
            },
            {
                "bboxes": torch.from_numpy(sample.boxes.astype(np.float32)),
                "cls": torch.from_numpy(sample.classes.astype(np.float32)),
            },
        )
        report.images += 1
        report.instances += len(sample.classes)
    if report.images == 0:
        raise ValueError(f"{source}: no samples to evaluate")
    out_dir.mkdir(parents=True, exist_ok=True)
    metrics.process(save_dir=out_dir, plot=plots)
    precision, recall, map50, map50_95 = (float(v) for v in metrics.mean_results())
    report.overall = {"precision": precision, "recall": recall, "mAP50": map50, "mAP50-95": map50_95}
    for class_index in metrics.ap_class_index:
        p, r, ap50, ap = (
            float(v) for v in metrics.class_result(list(metrics.ap_class_index).index(class_index))
        )
        report.per_class[names[int(class_index)]] = {
            "instances": int(metrics.nt_per_class[int(class_index)]),
            "precision": p,
            "recall": r,
            "mAP50": ap50,
            "mAP50-95": ap,
        }
    report.mean_timings_ms = {k: v / report.images for k, v in timing_sums.items()}
    if plots:
        confusion.plot(normalize=True, save_dir=out_dir)
        report.files = {
            "confusion_matrix": str(out_dir / "confusion_matrix_normalized.png"),
            "recall_confidence": str(out_dir / "BoxR_curve.png"),
            "precision_recall": str(out_dir / "BoxPR_curve.png"),
        }
    (out_dir / "metrics.json").write_text(json.dumps(report.to_json(), indent=2) + "\n")
    log.info("%s on %s: %s", report.model_id, source, report.overall)
    return report


def format_table(report: EvalReport) -> str:
    """The paper's Table I layout: one row per class plus 'all'."""
    lines = [f"{'class':10s} {'inst':>7s} {'P':>6s} {'R':>6s} {'mAP50':>6s} {'mAP50-95':>8s}"]
    for name, row in report.per_class.items():
        lines.append(
            f"{name:10s} {row['instances']:7d} {row['precision']:6.3f} {row['recall']:6.3f} "
            f"{row['mAP50']:6.3f} {row['mAP50-95']:8.3f}"
        )
    o = report.overall
    lines.append(
        f"{'all':10s} {report.instances:7d} {o['precision']:6.3f} {o['recall']:6.3f} "
        f"{o['mAP50']:6.3f} {o['mAP50-95']:8.3f}"
    )
    return "\n".join(lines)
