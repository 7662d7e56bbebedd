"""``triscan eval``: the paper's Table I for a shipped model, measured through the run-time code.

Predictions come from :class:`common.inference.OnnxDetector`, the decoder and NMS the detector
service runs, fed with the run-time tensor (a data set's PNGs are byte-for-byte ScanStacker output, a
test proves it; ``--fresh`` simulates new scenarios straight through ScanStacker instead). The metric
arithmetic is Ultralytics' (``ap_per_class``, ported to numpy in :mod:`training.detection_metrics` so
that scoring needs no torch), and predictions are matched to labels with the same greedy policy as its
validator, so the figures can be compared with ``yolo val`` — a test checks they agree within 0.01.
The confusion matrix and the curves are drawn by Ultralytics, when the ``train`` extra is installed.

Two additions serve the ``zero`` vs ``wrap`` ablation (README, "The encoding"):

* With ``wrap`` padding one object can be labelled twice (whole across the seam and as the copy in
  columns 0–23 or 360–383), while the detector merges such copies into one detection. Labels are
  merged the same way and boxes are compared on the circle (IoU over ±360-column shifts), so both
  padding modes are scored per object.
* Every label carries whether its object crosses the 0°/360° seam (from the scene geometry, not the
  box), and a second set of figures is computed on those objects alone: in each image, a class is
  scored only when its object crosses the seam, with its predictions and label; other classes are
  left out of that set.
"""

from __future__ import annotations

import importlib.util
import json
import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from common.encoding import ANGLE_COLUMNS, IMAGE_WIDTH, RANGE_ROWS, InvalidRule, Padding
from common.inference import OnnxDetector
from common.model_spec import (
    CLASS_NAMES,
    DEFAULT_BOX_GRID,
    FURNITURE_CLASSES,
    MAX_DETECTIONS,
    PERSON,
    PERSON_ID,
)
from common.postprocess import DEFAULT_CONF, unwrap_seam_duplicates
from services.simulator.labels import MIN_BEAMS_ON_OBJECT
from training.detection_metrics import DetectionMetrics, box_iou
from training.png import read_tensor_png

if TYPE_CHECKING:
    from services.simulator.lidar import LidarSpec


log = logging.getLogger(__name__)

IOU_THRESHOLDS = np.linspace(0.5, 0.95, 10)  # the COCO ladder behind mAP@0.5:0.95
VAL_CONF = 0.001  # Ultralytics' validation protocol: keep almost everything, let AP integrate
VAL_IOU = 0.7
VAL_MAX_DET = MAX_DETECTIONS  # Ultralytics' max_det is 300 too


@dataclass(frozen=True)
class EvalSample:
    """A tensor and its ground truth: boxes xyxy in raster pixels, class ids, seam crossing."""

    name: str
    tensor: np.ndarray
    boxes: np.ndarray  # float64[M, 4]
    classes: np.ndarray  # int64[M]
    crosses_seam: np.ndarray | None = None  # bool[M]; None when the scene geometry is unknown
    beams: np.ndarray | None = None  # int64[M]: beams of scan t−1 on each label's object; None: unknown


@dataclass
class EvalReport:
    """Everything ``triscan eval`` measured; ``to_json`` is what lands in metrics.json."""

    model_id: str
    source: str
    images: int = 0
    instances: int = 0
    padding: str = "zero"
    box_grid: str = DEFAULT_BOX_GRID  # the post-processing the boxes went through (OnnxDetector.box_grid)
    overall: dict[str, float] = field(default_factory=dict)
    per_class: dict[str, dict[str, float]] = field(default_factory=dict)
    seam_crossing: dict[str, float] = field(default_factory=dict)  # the same figures, seam objects only
    # mAP at each IoU threshold of mAP@0.5:0.95 ("0.50" … "0.95"), overall and per class: where the
    # average loses, loose boxes (a steep fall towards 0.95) or missed objects (low from 0.50 on)
    map_by_iou: dict[str, float] = field(default_factory=dict)
    ap_by_iou_per_class: dict[str, dict[str, float]] = field(default_factory=dict)
    mean_timings_ms: dict[str, float] = field(default_factory=dict)
    # People by how many beams of scan t−1 hit them ("2", "3-4", …): instances and the share found, a
    # person box above the detector's default threshold with IoU ≥ 0.5. Where the class loses: a
    # person two beams light is a target (the label rule), and barely more than a pole.
    person_recall_by_beams: dict[str, dict[str, float]] = field(default_factory=dict)
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


def _seam_flags_of_dataset(
    dataset_dir: Path, raster_yaw_deg: float = 0.0
) -> dict[str, dict[int, bool]] | None:
    """Image stem → class → whether that object crosses the seam, from scenarios.jsonl + samples.jsonl.

    The seam is the raster's: objects are seen turned by the set's ``raster_yaw_deg``, as its labels.
    ``None`` for a data set without them (e.g. recorded on a real robot in the YOLO layout).
    """
    from services.simulator.labels import (
        arc_crosses_seam,
        footprint_polar,
        person_footprint_polar,
        turned_arc,
    )
    from services.simulator.scenario import Scenario

    scenarios_file, samples_file = dataset_dir / "scenarios.jsonl", dataset_dir / "samples.jsonl"
    if not (scenarios_file.is_file() and samples_file.is_file()):
        return None
    scenarios: dict[int, Scenario] = {}
    for line in scenarios_file.read_text().splitlines():
        if line.strip():
            data = json.loads(line)
            scenarios[int(data["index"])] = Scenario.from_json(data)
    flags: dict[str, dict[int, bool]] = {}
    for line in samples_file.read_text().splitlines():
        if not line.strip():
            continue
        sample = json.loads(line)
        scenario = scenarios[int(sample["scenario"])]
        x, y, yaw = (float(v) for v in sample["lidar_pose"])
        pose = (x, y, yaw)
        flags[Path(sample["image"]).stem] = {
            class_id: arc_crosses_seam(
                *turned_arc(*footprint_polar(scenario.footprint_of(class_id), pose)[:3], raster_yaw_deg)
            )
            for class_id in range(len(FURNITURE_CLASSES))
        }
        # People are not part of the scenario: whether any of this sample's people crosses the seam.
        flags[Path(sample["image"]).stem][PERSON_ID] = any(
            arc_crosses_seam(*turned_arc(*person_footprint_polar(legs, pose)[:3], raster_yaw_deg))
            for legs in sample.get("people_legs", ())
        )
    return flags


def _crosses(class_id: int, box: np.ndarray, of_class: dict[int, bool]) -> bool:
    """Whether a label's object crosses the seam. A sample's people are not told apart in its labels,
    so a person's box counts when some person of the sample crosses and the box reaches the seam's
    column 0 or 360, where the seam rule clips it."""
    if class_id != PERSON_ID:
        return of_class[class_id]
    return of_class[PERSON_ID] and bool(box[0] <= 0.0 or box[2] >= ANGLE_COLUMNS)


def dataset_samples(dataset_dir: Path, split: str = "test") -> Iterator[EvalSample]:
    """Samples of one split of a data set written by ``triscan dataset``."""
    from training.onnx_export import dataset_raster_yaw

    image_dir = dataset_dir / "images" / split
    images = sorted(image_dir.glob("*.png"))
    if not images:
        raise FileNotFoundError(f"no images in {image_dir}: is {dataset_dir} a triscan data set?")
    seam_flags = _seam_flags_of_dataset(dataset_dir, dataset_raster_yaw(dataset_dir))
    for image in images:
        label = dataset_dir / "labels" / split / f"{image.stem}.txt"
        boxes, classes = yolo_labels_to_boxes(label.read_text() if label.exists() else "")
        crosses = None
        if seam_flags is not None:
            of_class = seam_flags[image.stem]
            crosses = np.array(
                [_crosses(int(c), b, of_class) for c, b in zip(classes, boxes, strict=True)], dtype=bool
            )
        yield EvalSample(image.stem, read_tensor_png(image), boxes, classes, crosses)


def fresh_samples(
    seed: int,
    scenarios: int,
    positions: int,
    padding: Padding,
    frame_stride: int,
    spec: LidarSpec | None = None,
    invalid: InvalidRule = "sentinel",
    clutter: int = 0,
    people: int = 0,
    raster_yaw_deg: float = 0.0,
    open_space: float = 0.0,
) -> Iterator[EvalSample]:
    """Newly simulated scenarios, straight through ScanStacker: data no model has seen.

    ``spec`` is the sensor (default: the clean LDS-01); the same seed gives the same worlds, motions and
    Gaussian noise draws under every imperfection setting, with labels of the true geometry. ``padding``
    ``invalid`` and ``raster_yaw_deg`` must be the model's own (:attr:`OnnxDetector.padding`,
    ``.invalid``, ``.raster_yaw_deg``): tensors and labels are made in its raster's frame. ``clutter``
    puts up to that many unlabelled poles and wall stubs into each motion, drawn
    from their own stream: the same worlds and motions with things in them that must not be detected
    (a pole is not a chair leg), and which occlude what must. ``people`` puts up to that many labelled
    people into each motion; ``open_space`` moves the walls of that share of the worlds out
    (:func:`services.simulator.scenario.room_half_of`, as ``triscan dataset --open-space`` does).
    """
    from services.simulator.labels import arc_crosses_seam
    from services.simulator.lidar import DEFAULT_SPEC
    from services.simulator.scenario import room_half_of, sample_scenario
    from services.simulator.world import World
    from training.dataset import plan_motions, simulate_samples

    with World() as world:
        for index in range(scenarios):
            scenario = sample_scenario(index, seed, room_half_of(seed, index, open_space))
            motions = plan_motions(scenario, seed, positions)
            samples = simulate_samples(
                world,
                scenario,
                motions,
                seed,
                padding,
                frame_stride,
                spec=spec or DEFAULT_SPEC,
                clutter=clutter,
                invalid=invalid,
                people=people,
                raster_yaw_deg=raster_yaw_deg,
            )
            for sample in samples:
                boxes = [box for label in sample.labels for box in label.boxes_px]
                classes = [label.class_id for label in sample.labels for _ in label.boxes_px]
                crosses = [
                    arc_crosses_seam(label.bearing_center_deg, label.bearing_min_deg, label.bearing_max_deg)
                    for label in sample.labels
                    for _ in label.boxes_px
                ]
                beams = [label.beams_on_object for label in sample.labels for _ in label.boxes_px]
                yield EvalSample(
                    sample.name,
                    sample.tensor,
                    np.array(boxes, dtype=np.float64).reshape(-1, 4),
                    np.array(classes, dtype=np.int64),
                    np.array(crosses, dtype=bool),
                    np.array(beams, dtype=np.int64),
                )


def circular_box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU on the circle: the best of ``b`` as it is and moved by ±360 columns (the same bearings)."""
    shift = np.array([ANGLE_COLUMNS, 0.0, ANGLE_COLUMNS, 0.0])
    return np.maximum.reduce([box_iou(a, b), box_iou(a, b + shift), box_iou(a, b - shift)])


def merge_label_copies(sample: EvalSample) -> EvalSample:
    """One label per object under ``wrap`` padding: the copies the detector would merge, merged."""
    if len(sample.classes) < 2:
        return sample
    keep = unwrap_seam_duplicates(sample.boxes, np.ones(len(sample.classes)), sample.classes, "wrap")
    return _kept(sample, keep)


def _kept(sample: EvalSample, keep: np.ndarray) -> EvalSample:
    """``sample`` with only the labels ``keep`` selects."""
    crosses = None if sample.crosses_seam is None else sample.crosses_seam[keep]
    beams = None if sample.beams is None else sample.beams[keep]
    return EvalSample(sample.name, sample.tensor, sample.boxes[keep], sample.classes[keep], crosses, beams)


def seam_subset(
    sample: EvalSample, iou: np.ndarray, pred_classes: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Masks (labels, predictions) of the seam-crossing set.

    A label is in when its object crosses the seam. A prediction is in when its class has such a
    label in this image and its best-overlapping label of that class crosses the seam, so a stray
    box of that class still counts against it while boxes of objects off the seam stay out.
    """
    crosses = (
        np.zeros(len(sample.classes), dtype=bool) if sample.crosses_seam is None else sample.crosses_seam
    )
    label_in = crosses.copy()
    pred_in = np.zeros(len(pred_classes), dtype=bool)
    if not label_in.any() or len(pred_classes) == 0:
        return label_in, pred_in
    same_class = sample.classes[:, None] == pred_classes[None, :]
    overlap = np.where(same_class, iou, -1.0)
    has_seam_label = (same_class & crosses[:, None]).any(axis=0)
    best_label = overlap.argmax(axis=0)
    pred_in = has_seam_label & crosses[best_label]
    return label_in, pred_in


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


def _stats(
    correct: np.ndarray, scores: np.ndarray, classes: np.ndarray, true_classes: np.ndarray, name: str
) -> dict[str, Any]:
    """One image's entry for ``DetectionMetrics.update_stats`` (Ultralytics' ``DetMetrics``')."""
    return {
        "tp": correct,
        "conf": scores.astype(np.float64),
        "pred_cls": classes.astype(np.float64),
        "target_cls": true_classes.astype(np.float64),
        "target_img": np.unique(true_classes).astype(np.float64),
        "im_name": name,
    }


def evaluate(
    detector: OnnxDetector,
    samples: Iterator[EvalSample],
    out_dir: Path,
    *,
    source: str,
    plots: bool = True,
) -> EvalReport:
    """Run every sample through the detector and write metrics.json (+ plots, with the ``train``
    extra) into ``out_dir``."""
    # A model is scored on the classes it predicts: a four-class model on a set with people is judged
    # on the furniture, its people labels set aside.
    model_classes: tuple[str, ...] = getattr(detector, "class_names", CLASS_NAMES)
    names = dict(enumerate(model_classes))
    metrics = DetectionMetrics(names)
    seam_metrics = DetectionMetrics(names)
    plots = plots and _can_plot()
    confusion = _ultralytics_confusion_matrix(names) if plots else None
    wrap = detector.padding == "wrap"
    report = EvalReport(
        model_id=detector.model_id, source=source, padding=detector.padding, box_grid=detector.box_grid
    )
    timing_sums = {"encode_ms": 0.0, "inference_ms": 0.0, "nms_ms": 0.0}
    seam_instances = 0
    person_id = model_classes.index(PERSON) if PERSON in model_classes else None
    people_by_beams = {name: [0, 0] for name, _, _ in BEAM_BANDS}  # [instances, found]
    for raw_sample in samples:
        sample = merge_label_copies(raw_sample) if wrap else raw_sample
        if np.any(sample.classes >= len(names)):
            sample = _of_classes(sample, len(names))
        boxes, scores, classes, timings = detector.detect_boxes(sample.tensor)
        for key in timing_sums:
            timing_sums[key] += float(getattr(timings, key))
        iou_of = circular_box_iou if wrap else box_iou
        # [labels, predictions] even when one side is empty: the seam subset indexes it by both
        iou = (
            iou_of(sample.boxes, boxes)
            if len(boxes) and len(sample.boxes)
            else np.zeros((len(sample.boxes), len(boxes)))
        )
        correct = match_predictions(classes, sample.classes, iou)
        metrics.update_stats(_stats(correct, scores, classes, sample.classes, sample.name))
        if person_id is not None and sample.beams is not None:
            _count_people_by_beams(people_by_beams, sample, iou, scores, classes, person_id)
        seam_instances += _update_seam_stats(seam_metrics, sample, iou, scores, classes)
        if confusion is not None:
            confusion.process_batch(*_confusion_batch(sample, boxes, scores, classes))
        report.images += 1
        report.instances += len(sample.classes)
    if report.images == 0:
        raise ValueError(f"{source}: no samples to evaluate")
    out_dir.mkdir(parents=True, exist_ok=True)
    metrics.process()
    report.overall = _figures(metrics.mean_results())
    for class_index in metrics.ap_class_index:
        report.per_class[names[int(class_index)]] = {
            "instances": int(metrics.nt_per_class[int(class_index)]),
            **_figures(metrics.class_result(list(metrics.ap_class_index).index(class_index))),
        }
    report.map_by_iou, report.ap_by_iou_per_class = _ap_by_iou(metrics)
    if seam_instances:
        seam_metrics.process()
        report.seam_crossing = {"instances": seam_instances, **_figures(seam_metrics.mean_results())}
    report.mean_timings_ms = {k: v / report.images for k, v in timing_sums.items()}
    report.person_recall_by_beams = {
        name: {"instances": count, "recall": found / count}
        for name, (count, found) in people_by_beams.items()
        if count
    }
    if confusion is not None:
        confusion.plot(normalize=True, save_dir=out_dir)
        _plot_curves(metrics, out_dir)
        report.files = {
            "confusion_matrix": str(out_dir / "confusion_matrix_normalized.png"),
            "recall_confidence": str(out_dir / "BoxR_curve.png"),
            "precision_recall": str(out_dir / "BoxPR_curve.png"),
        }
    (out_dir / "metrics.json").write_text(json.dumps(report.to_json(), indent=2) + "\n")
    log.info("%s on %s: %s", report.model_id, source, report.overall)
    return report


# Bands of beams on a person in scan t−1 (name, least, most), from the least a target has.
BEAM_BANDS: tuple[tuple[str, int, int], ...] = (
    (str(MIN_BEAMS_ON_OBJECT), MIN_BEAMS_ON_OBJECT, 2),
    ("3-4", 3, 4),
    ("5-7", 5, 7),
    ("8-14", 8, 14),
    ("15+", 15, 1 << 30),
)


def _count_people_by_beams(
    counts: dict[str, list[int]],
    sample: EvalSample,
    iou: np.ndarray,
    scores: np.ndarray,
    classes: np.ndarray,
    person_id: int,
) -> None:
    """Add one image's people to ``counts`` by beam band: each, and whether a person box scoring above
    the detector's default threshold overlaps it with IoU ≥ 0.5 (the best box, not one-to-one)."""
    assert sample.beams is not None
    reported = (classes == person_id) & (scores > DEFAULT_CONF)
    for label in np.flatnonzero(sample.classes == person_id):
        beams = int(sample.beams[label])
        found = bool(reported.any() and iou[label, reported].max() >= IOU_THRESHOLDS[0])
        for name, least, most in BEAM_BANDS:
            if least <= beams <= most:
                counts[name][0] += 1
                counts[name][1] += found


def _of_classes(sample: EvalSample, count: int) -> EvalSample:
    """``sample`` with only the labels of the first ``count`` classes."""
    return _kept(sample, sample.classes < count)


def _can_plot() -> bool:
    """Whether the ``train`` extra (Ultralytics and torch) is here to draw the plots; said once if not."""
    if all(importlib.util.find_spec(name) is not None for name in ("ultralytics", "torch")):
        return True
    log.info("no plots or confusion matrix: they need the train extra (pip install 'triscan[train]')")
    return False


def _ultralytics_confusion_matrix(names: dict[int, str]) -> Any:
    from training.offline import configure_offline

    configure_offline()
    from ultralytics.utils.metrics import ConfusionMatrix

    return ConfusionMatrix(names=names)


def _plot_curves(metrics: DetectionMetrics, out_dir: Path) -> None:
    """Ultralytics' four curves (``Box{PR,F1,P,R}_curve.png``), as its ``ap_per_class(plot=True)`` draws."""
    from ultralytics.utils.metrics import plot_mc_curve, plot_pr_curve

    c = metrics.curves
    assert c is not None  # process() ran
    if not len(c.classes):
        return
    names = {i: metrics.names[k] for i, k in enumerate(c.classes) if k in metrics.names}
    plot_pr_curve(c.x, c.prec_values, c.all_ap, out_dir / "BoxPR_curve.png", names)
    for curve, ylabel, stem in (
        (c.f1_curve, "F1", "F1"),
        (c.p_curve, "Precision", "P"),
        (c.r_curve, "Recall", "R"),
    ):
        plot_mc_curve(c.x, curve, out_dir / f"Box{stem}_curve.png", names, ylabel=ylabel)


def _ap_by_iou(metrics: DetectionMetrics) -> tuple[dict[str, float], dict[str, dict[str, float]]]:
    """The AP table (class × the ten IoU thresholds) as the mean per threshold, and per class."""
    table = np.asarray(metrics.all_ap, dtype=np.float64).reshape(len(metrics.ap_class_index), -1)
    labels = [f"{iou:.2f}" for iou in np.linspace(0.5, 0.95, table.shape[1])]
    overall = dict(zip(labels, (float(v) for v in table.mean(axis=0)), strict=True)) if len(table) else {}
    per_class = {
        CLASS_NAMES[int(class_index)]: dict(zip(labels, (float(v) for v in row), strict=True))
        for class_index, row in zip(metrics.ap_class_index, table, strict=True)
    }
    return overall, per_class


def _update_seam_stats(
    seam_metrics: DetectionMetrics,
    sample: EvalSample,
    iou: np.ndarray,
    scores: np.ndarray,
    classes: np.ndarray,
) -> int:
    """Score the sample's seam-crossing objects alone into ``seam_metrics``; return how many labels."""
    label_in, pred_in = seam_subset(sample, iou, classes)
    if not label_in.any():
        return 0
    seam_correct = match_predictions(classes[pred_in], sample.classes[label_in], iou[label_in][:, pred_in])
    seam_metrics.update_stats(
        _stats(seam_correct, scores[pred_in], classes[pred_in], sample.classes[label_in], sample.name)
    )
    return int(label_in.sum())


def _confusion_batch(
    sample: EvalSample, boxes: np.ndarray, scores: np.ndarray, classes: np.ndarray
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Predictions and labels of one image as the torch dicts of Ultralytics' ``ConfusionMatrix``."""
    import torch

    return (
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


def _figures(results: Any) -> dict[str, float]:
    """(P, R, mAP@0.5, mAP@0.5:0.95) as the named floats of metrics.json."""
    precision, recall, map50, map50_95 = (float(v) for v in results)
    return {"precision": precision, "recall": recall, "mAP50": map50, "mAP50-95": map50_95}


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
    if report.seam_crossing:
        m = report.seam_crossing
        lines.append(
            f"{'seam':10s} {int(m['instances']):7d} {m['precision']:6.3f} {m['recall']:6.3f} "
            f"{m['mAP50']:6.3f} {m['mAP50-95']:8.3f}"
        )
    if report.person_recall_by_beams:
        bands = ", ".join(
            f"{name}: {row['recall']:.2f} of {int(row['instances'])}"
            for name, row in report.person_recall_by_beams.items()
        )
        lines.append(f"people found at {DEFAULT_CONF} by beams on them: {bands}")
    return "\n".join(lines)


# --- one run, several models under several conditions -------------------------------------------------


@dataclass(frozen=True)
class FreshWorlds:
    """Which unseen worlds ``--fresh`` simulates; every condition is applied to these same worlds."""

    seed: int
    scenarios: int
    positions: int
    frame_stride: int
    clutter: int = 0  # the most unlabelled clutter items per motion (fresh_samples)
    people: int = 0  # the most people per motion (fresh_samples)
    open_space: float = 0.0  # share of worlds with open-space rooms (fresh_samples)

    def __post_init__(self) -> None:
        if self.clutter < 0:
            raise ValueError(f"clutter must be >= 0 items per motion, got {self.clutter}")
        if self.people < 0:
            raise ValueError(f"people must be >= 0 per motion, got {self.people}")
        from services.simulator.scenario import check_open_space  # lazily, as every simulator import here

        check_open_space(self.open_space)

    def source(self, condition: str) -> str:
        """What metrics.json names as the source of these worlds under ``condition``."""
        clutter = f",clutter={self.clutter}" if self.clutter else ""
        people = f",people={self.people}" if self.people else ""
        open_space = f",open_space={self.open_space:g}" if self.open_space else ""
        return (
            f"fresh:seed={self.seed},scenarios={self.scenarios},positions={self.positions}{clutter}{people}"
            f"{open_space},noise={condition}"
        )


SENSOR_SEPARATOR = ":"  # a condition of a sensor other than the LDS-01 is "<sensor>:<imperfections>"


def condition_spec(condition: str) -> LidarSpec:
    """The sensor of a condition: ``drop5`` (the LDS-01 with 5 % dropouts) or ``ust-10lx:drop5``."""
    from services.simulator.lidar import with_imperfections
    from services.simulator.sensors import DEFAULT_PROFILE, profile

    sensor, _, noise = condition.rpartition(SENSOR_SEPARATOR)
    return with_imperfections(noise, profile(sensor or DEFAULT_PROFILE))


def condition_matrix(
    detectors: list[OnnxDetector],
    conditions: list[str],
    worlds: FreshWorlds,
    out_dir: Path,
    *,
    plots: bool = True,
) -> dict[str, dict[str, EvalReport]]:
    """Every detector on the same fresh worlds under every LiDAR condition: reports[condition][model].

    The worlds of a condition are simulated once per encoding (padding, invalid-return rule, raster yaw)
    and fed to each detector that reads that encoding: fp32 and INT8 of one network see identical tensors,
    which makes the pair's difference a measure of quantisation alone, and models of another rule see the
    same scans encoded their way. Each cell lands in ``out_dir/<condition>/<model stem>/metrics.json``;
    ``summary.json`` holds the grid.
    """
    specs = {condition: condition_spec(condition) for condition in conditions}  # bad names fail first
    stems = [d.model_path.stem for d in detectors]
    if len(set(stems)) != len(stems):
        raise ValueError(f"two models share a file stem: {stems}")
    encodings = list(dict.fromkeys((d.padding, d.invalid, d.raster_yaw_deg) for d in detectors))
    reports: dict[str, dict[str, EvalReport]] = {}
    for condition, spec in specs.items():
        reports[condition] = {}
        for padding, invalid, yaw in encodings:
            samples = list(
                fresh_samples(
                    worlds.seed, worlds.scenarios, worlds.positions, padding, worlds.frame_stride,
                    spec=spec, invalid=invalid, clutter=worlds.clutter, people=worlds.people,
                    open_space=worlds.open_space,
                    raster_yaw_deg=yaw,
                )
            )  # fmt: skip
            for stem, detector in zip(stems, detectors, strict=True):
                if (detector.padding, detector.invalid, detector.raster_yaw_deg) == (padding, invalid, yaw):
                    cell = out_dir / condition / stem
                    reports[condition][stem] = evaluate(
                        detector, iter(samples), cell, source=worlds.source(condition), plots=plots
                    )
        reports[condition] = {stem: reports[condition][stem] for stem in stems}  # the models' order
    summary = {
        "worlds": worlds.__dict__,
        "models": {stem: d.model_id for stem, d in zip(stems, detectors, strict=True)},
        "box_grid": {stem: d.box_grid for stem, d in zip(stems, detectors, strict=True)},
        "results": {
            condition: {stem: _summary_cell(report) for stem, report in row.items()}
            for condition, row in reports.items()
        },
    }
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return reports


def _summary_cell(report: EvalReport) -> dict[str, Any]:
    return {
        "images": report.images,
        "instances": report.instances,
        **report.overall,
        "per_class_mAP50": {name: row["mAP50"] for name, row in report.per_class.items()},
    }


def format_condition_table(reports: dict[str, dict[str, EvalReport]]) -> str:
    """One row per condition and model: mAP@0.5, mAP@0.5:0.95 and the weakest class's mAP@0.5."""
    lines = [f"{'condition':22s} {'model':32s} {'mAP50':>6s} {'50-95':>6s}  weakest class (mAP50)"]
    for condition, row in reports.items():
        for stem, report in row.items():
            weakest = min(report.per_class.items(), key=lambda item: item[1]["mAP50"])
            lines.append(
                f"{condition:22s} {stem:32s} {report.overall['mAP50']:6.3f} {report.overall['mAP50-95']:6.3f}"
                f"  {weakest[0]} {weakest[1]['mAP50']:.3f}"
            )
    return "\n".join(lines)
