"""The numpy AP arithmetic equals Ultralytics' own, and ``triscan eval`` runs without torch."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from training.detection_metrics import DetectionMetrics, ap_per_class, box_iou, compute_ap

REPO = Path(__file__).resolve().parents[1]
TOLERANCE = 1e-9


@pytest.fixture(scope="module")
def ultralytics_metrics(tmp_path_factory: pytest.TempPathFactory) -> Any:
    pytest.importorskip("torch")
    pytest.importorskip("ultralytics")
    from training.offline import configure_offline

    configure_offline(tmp_path_factory.mktemp("yolo"))
    from ultralytics.utils import metrics

    return metrics


def random_stats(rng: np.random.Generator, images: int, classes: int) -> list[dict[str, Any]]:
    """Per-image stats as a validator makes them: correct-at-10-thresholds falling with the IoU."""
    stats = []
    for index in range(images):
        n, m = int(rng.integers(0, 12)), int(rng.integers(0, 8))
        quality = rng.random(n)
        tp = quality[:, None] > np.linspace(0.2, 0.95, 10)[None, :]
        target = rng.integers(0, classes, m).astype(np.float64)
        stats.append(
            {
                "tp": tp,
                "conf": rng.random(n),
                "pred_cls": rng.integers(0, classes, n).astype(np.float64),
                "target_cls": target,
                "target_img": np.unique(target),
                "im_name": f"im{index}",
            }
        )
    return stats


@pytest.mark.parametrize("seed", range(6))
def test_ap_per_class_equals_ultralytics(seed: int, ultralytics_metrics: Any) -> None:
    rng = np.random.default_rng(seed)
    stats = random_stats(rng, 40, 5)
    tp, conf, pred, target = (
        np.concatenate([s[k] for s in stats]) for k in ("tp", "conf", "pred_cls", "target_cls")
    )
    theirs = ultralytics_metrics.ap_per_class(tp, conf, pred, target)
    ours = ap_per_class(tp, conf, pred, target)
    _, _, p, r, f1, all_ap, classes, p_curve, r_curve, f1_curve, x, prec_values = theirs
    for mine, reference in [
        (ours.p, p), (ours.r, r), (ours.f1, f1), (ours.all_ap, all_ap), (ours.p_curve, p_curve),
        (ours.r_curve, r_curve), (ours.f1_curve, f1_curve), (ours.x, x), (ours.prec_values, prec_values),
    ]:  # fmt: skip
        assert mine.shape == reference.shape
        assert np.allclose(mine, reference, rtol=0.0, atol=TOLERANCE)
    assert ours.classes.tolist() == classes.tolist()
    assert all_ap.max() > 0.0  # the draw is not degenerate


@pytest.mark.parametrize("seed", range(4))
def test_detection_metrics_equal_ultralytics_detmetrics(seed: int, ultralytics_metrics: Any) -> None:
    rng = np.random.default_rng(100 + seed)
    names = {0: "chair", 1: "box", 2: "desk", 3: "doorframe"}
    stats = random_stats(rng, 30, 4)
    ours, theirs = DetectionMetrics(names), ultralytics_metrics.DetMetrics(names=names)
    for stat in stats:
        ours.update_stats(stat)
        theirs.update_stats(stat)
    ours.process()
    theirs.process()
    assert np.allclose(ours.mean_results(), theirs.mean_results(), rtol=0.0, atol=TOLERANCE)
    assert list(ours.ap_class_index) == list(theirs.ap_class_index)
    for i in range(len(ours.ap_class_index)):
        assert np.allclose(ours.class_result(i), theirs.class_result(i), rtol=0.0, atol=TOLERANCE)
    assert ours.nt_per_class is not None and ours.nt_per_class.tolist() == theirs.nt_per_class.tolist()
    assert np.allclose(ours.all_ap, theirs.box.all_ap, rtol=0.0, atol=TOLERANCE)


def test_box_iou_and_compute_ap_equal_ultralytics(ultralytics_metrics: Any) -> None:
    rng = np.random.default_rng(7)
    a = np.concatenate([xy := rng.uniform(0, 300, (9, 2)), xy + rng.uniform(1, 40, (9, 2))], axis=1)
    b = np.concatenate([xy := rng.uniform(0, 300, (6, 2)), xy + rng.uniform(1, 40, (6, 2))], axis=1)
    b[:3] = a[:3] + rng.normal(0, 2, (3, 4))
    theirs = ultralytics_metrics.bbox_ioa(a, b, iou=True)
    assert np.allclose(box_iou(a, b), theirs, rtol=0.0, atol=TOLERANCE) and theirs.max() > 0.5
    recall = np.sort(rng.random(20))
    precision = rng.random(20)
    mine, reference = compute_ap(recall, precision), ultralytics_metrics.compute_ap(recall, precision)
    assert abs(mine[0] - reference[0]) <= TOLERANCE
    assert np.allclose(mine[1], reference[1]) and np.allclose(mine[2], reference[2])


def test_a_perfect_detector_scores_its_maximum_and_an_empty_one_zero() -> None:
    """Without Ultralytics: the arithmetic's end points. A perfect AP is 0.995, as in ``yolo val``: the
    101-point trapezoid falls to the sentinel precision 0 at recall 1."""
    names = {0: "chair", 1: "box"}
    metrics = DetectionMetrics(names)
    target = np.array([0.0, 1.0, 1.0])
    metrics.update_stats(
        {"tp": np.ones((3, 10), bool), "conf": np.array([0.9, 0.8, 0.7]), "pred_cls": target,
         "target_cls": target, "target_img": np.unique(target)}
    )  # fmt: skip
    metrics.process()
    assert np.allclose(metrics.mean_results(), (1.0, 1.0, 0.995, 0.995), atol=1e-9)
    empty = DetectionMetrics(names)
    empty.update_stats(
        {"tp": np.zeros((0, 10), bool), "conf": np.zeros(0), "pred_cls": np.zeros(0),
         "target_cls": target, "target_img": np.unique(target)}
    )  # fmt: skip
    empty.process()
    assert empty.mean_results() == (0.0, 0.0, 0.0, 0.0)


def test_triscan_eval_scores_fresh_worlds_without_torch_or_ultralytics(tmp_path: Path) -> None:
    """The sim install: torch and Ultralytics cannot be imported; eval still scores, without plots."""
    out = tmp_path / "eval"
    code = (
        "import sys\nsys.modules['torch'] = None\nsys.modules['ultralytics'] = None\n"
        "from services.cli import main\n"
        f"code = main(['eval', '--model', 'models/yolov8p-dfl12/triscan-yolov8p-dfl12-zero-int8.onnx', "
        f"'--fresh', '1', '--positions', '2', '--frame-stride', '30', '--out', {str(out)!r}])\n"
        "print(sorted({m.split('.')[0] for m in sys.modules if sys.modules[m] is not None} "
        "& {'torch', 'ultralytics'}))\nraise SystemExit(code)"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300, check=False
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.splitlines()[-1] == "[]"
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["images"] > 0 and 0.0 < metrics["overall"]["mAP50"] <= 1.0
    assert metrics["files"] == {} and not list(out.glob("*.png"))
