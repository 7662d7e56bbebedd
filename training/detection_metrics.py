"""Detection metrics in numpy alone: Ultralytics' AP arithmetic, ported so ``triscan eval`` needs no torch.

``triscan eval`` scores ONNX models on the ``sim`` install, which has neither torch nor Ultralytics.
The figures must still be the ones ``yolo val`` reports, so this is a line-for-line port of the parts
of ``ultralytics/utils/metrics.py`` that make them (Ultralytics 8.x, AGPL-3.0): ``bbox_ioa`` (IoU),
``compute_ap`` (101-point interpolated AP, COCO), ``ap_per_class`` (precision, recall and F1 at the
confidence of the best smoothed mean F1, AP at ten IoU thresholds) and the bookkeeping of
``DetMetrics``/``Metric``. A test holds every output equal to Ultralytics' own on random inputs to
1e-9 wherever Ultralytics is installed. Plots and the confusion matrix stay Ultralytics' (the
``train`` extra): :mod:`training.evaluate` draws them only when it is there.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

AP_RECALL_POINTS = np.linspace(0, 1, 101)  # COCO's 101-point interpolation
CURVE_POINTS = 1000  # confidence (and recall) samples of the P, R, F1 curves
_trapezoid = getattr(np, "trapezoid", None) or np.trapz  # numpy >= 2 renamed it


def box_iou(a: np.ndarray, b: np.ndarray, eps: float = 1e-7) -> np.ndarray:
    """Pairwise IoU float64[len(a), len(b)] of xyxy boxes (Ultralytics' ``bbox_ioa(a, b, iou=True)``)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    a_x1, a_y1, a_x2, a_y2 = a.T
    b_x1, b_y1, b_x2, b_y2 = b.T
    inter = (np.minimum(a_x2[:, None], b_x2) - np.maximum(a_x1[:, None], b_x1)).clip(0) * (
        np.minimum(a_y2[:, None], b_y2) - np.maximum(a_y1[:, None], b_y1)
    ).clip(0)
    union = (b_x2 - b_x1) * (b_y2 - b_y1) + ((a_x2 - a_x1) * (a_y2 - a_y1))[:, None] - inter
    return inter / (union + eps)


def compute_ap(recall: np.ndarray, precision: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """AP of one precision-recall curve, 101-point interpolated; also the precision envelope and the
    recall with its sentinels (Ultralytics' ``compute_ap``)."""
    mrec = np.concatenate(([0.0], recall, [recall[-1] if len(recall) else 1.0], [1.0]))
    mpre = np.concatenate(([1.0], precision, [0.0], [0.0]))
    mpre = np.flip(np.maximum.accumulate(np.flip(mpre)))
    ap = float(_trapezoid(np.interp(AP_RECALL_POINTS, mrec, mpre), AP_RECALL_POINTS))
    return ap, mpre, mrec


def smooth(y: np.ndarray, f: float = 0.05) -> np.ndarray:
    """Box filter over a fraction ``f`` of the length (Ultralytics' ``smooth``)."""
    nf = round(len(y) * f * 2) // 2 + 1  # odd
    p = np.ones(nf // 2)
    yp = np.concatenate((p * y[0], y, p * y[-1]), 0)
    return np.convolve(yp, np.ones(nf) / nf, mode="valid")


@dataclass(frozen=True)
class ClassCurves:
    """What :func:`ap_per_class` measures, per class with labels (``classes``, ascending)."""

    p: np.ndarray  # (nc,) precision at the best mean-F1 confidence
    r: np.ndarray  # (nc,) recall there
    f1: np.ndarray  # (nc,)
    all_ap: np.ndarray  # (nc, T) AP at each IoU threshold
    classes: np.ndarray  # (nc,) int class ids
    p_curve: np.ndarray  # (nc, 1000) precision against confidence
    r_curve: np.ndarray  # (nc, 1000)
    f1_curve: np.ndarray  # (nc, 1000)
    x: np.ndarray  # (1000,) the curves' confidence (and recall) axis
    prec_values: np.ndarray  # (nc, 1000) precision against recall at the first IoU threshold


def ap_per_class(
    tp: np.ndarray, conf: np.ndarray, pred_cls: np.ndarray, target_cls: np.ndarray, eps: float = 1e-16
) -> ClassCurves:
    """Ultralytics' ``ap_per_class`` without its plots: ``tp`` bool[N, T] (correct at each IoU
    threshold), ``conf``/``pred_cls`` [N] of the predictions, ``target_cls`` [M] of the labels."""
    order = np.argsort(-conf)
    tp, conf, pred_cls = tp[order], conf[order], pred_cls[order]
    unique_classes, nt = np.unique(target_cls, return_counts=True)
    nc = unique_classes.shape[0]
    x, prec_values = np.linspace(0, 1, CURVE_POINTS), []
    ap = np.zeros((nc, tp.shape[1]))
    p_curve, r_curve = np.zeros((nc, CURVE_POINTS)), np.zeros((nc, CURVE_POINTS))
    for ci, c in enumerate(unique_classes):
        i = pred_cls == c
        n_l, n_p = nt[ci], i.sum()
        if n_p == 0 or n_l == 0:
            prec_values.append(np.zeros_like(x))
            continue
        fpc = (1 - tp[i]).cumsum(0)
        tpc = tp[i].cumsum(0)
        recall = tpc / (n_l + eps)
        r_curve[ci] = np.interp(-x, -conf[i], recall[:, 0], left=0)  # negated: conf decreases
        precision = tpc / (tpc + fpc)
        p_curve[ci] = np.interp(-x, -conf[i], precision[:, 0], left=1)
        for j in range(tp.shape[1]):
            ap[ci, j], mpre, mrec = compute_ap(recall[:, j], precision[:, j])
            if j == 0:
                prec_values.append(np.interp(x, mrec, mpre))
    values = np.array(prec_values) if prec_values else np.zeros((1, CURVE_POINTS))
    f1_curve = 2 * p_curve * r_curve / (p_curve + r_curve + eps)
    best = smooth(f1_curve.mean(0), 0.1).argmax() if nc else 0
    return ClassCurves(
        p=p_curve[:, best],
        r=r_curve[:, best],
        f1=f1_curve[:, best],
        all_ap=ap,
        classes=unique_classes.astype(int),
        p_curve=p_curve,
        r_curve=r_curve,
        f1_curve=f1_curve,
        x=x,
        prec_values=values,
    )


@dataclass
class DetectionMetrics:
    """Ultralytics' ``DetMetrics`` for boxes: per-image stats in, P, R, mAP50, mAP50-95 out.

    :meth:`update_stats` takes the dict ``DetMetrics.update_stats`` takes (``tp``, ``conf``,
    ``pred_cls``, ``target_cls``, ``target_img``); :meth:`process` computes, after which
    :attr:`curves`, :attr:`nt_per_class`, :meth:`mean_results` and :meth:`class_result` hold the figures.
    """

    names: dict[int, str]
    stats: dict[str, list[np.ndarray]] = field(
        default_factory=lambda: {k: [] for k in ("tp", "conf", "pred_cls", "target_cls", "target_img")}
    )
    curves: ClassCurves | None = None
    nt_per_class: np.ndarray | None = None

    def update_stats(self, stat: dict[str, Any]) -> None:
        for key, values in self.stats.items():
            values.append(stat[key])

    def process(self) -> None:
        stats = {k: np.concatenate(v, 0) for k, v in self.stats.items()}
        self.curves = ap_per_class(stats["tp"], stats["conf"], stats["pred_cls"], stats["target_cls"])
        self.nt_per_class = np.bincount(stats["target_cls"].astype(int), minlength=len(self.names))

    def _done(self) -> ClassCurves:
        if self.curves is None:
            raise RuntimeError("call process() first")
        return self.curves

    @property
    def ap_class_index(self) -> np.ndarray:
        return self._done().classes

    @property
    def all_ap(self) -> np.ndarray:
        return self._done().all_ap

    def mean_results(self) -> tuple[float, float, float, float]:
        """Mean precision, recall, mAP@0.5 and mAP@0.5:0.95 over the classes with labels."""
        c = self._done()
        if not len(c.classes):
            return 0.0, 0.0, 0.0, 0.0
        return float(c.p.mean()), float(c.r.mean()), float(c.all_ap[:, 0].mean()), float(c.all_ap.mean())

    def class_result(self, i: int) -> tuple[float, float, float, float]:
        """Precision, recall, AP@0.5 and AP@0.5:0.95 of the ``i``-th class of :attr:`ap_class_index`."""
        c = self._done()
        return float(c.p[i]), float(c.r[i]), float(c.all_ap[i, 0]), float(c.all_ap[i].mean())
