"""The figures ``triscan export`` reports next to its files: INT8 vs fp32 outputs, and session.run times.

They are sanity checks on this machine, not verdicts: whether INT8 ships is decided by the evaluation
on the test split (``triscan eval``), and the robot's own latency by the bench. What they catch early
is a quantisation that moved the network far (:func:`compare_outputs`) or a model that got slower
(:func:`median_latency_ms`), before anyone spends an evaluation on it.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from common.encoding import to_model_input
from training.onnx_model import BOX_CHANNELS, cpu_session
from training.png import read_tensor_png

CONFIDENT_SCORE = 0.25  # Ultralytics' default predict threshold: anchors above it are candidate detections


def compare_outputs(
    fp32_onnx: Path, int8_onnx: Path, images: Iterable[Path], *, confident: float = CONFIDENT_SCORE
) -> dict[str, float]:
    """Absolute differences of raw outputs INT8 vs fp32 (boxes in px, scores in 0–1) over ``images``.

    Raw outputs, before thresholds and NMS, so the numbers say how far quantisation moved the network
    itself, independent of any decode setting. Over all anchors they are dominated by background
    cells, whose boxes nobody reads; the ``confident_*`` entries restrict them to anchors where fp32
    scores some class ≥ ``confident`` — the candidate detections — and add the share of those whose
    best class is unchanged. They are absent when no anchor is confident (an untrained model).
    """
    reference, quantised = cpu_session(fp32_onnx), cpu_session(int8_onnx)
    name = reference.get_inputs()[0].name
    box_diffs, score_diffs, kept_boxes, kept_scores, agree = [], [], [], [], []
    for path in images:
        x = to_model_input(read_tensor_png(path))
        a = reference.run(None, {name: x})[0][0]
        b = quantised.run(None, {name: x})[0][0]
        box, score = np.abs(a[:BOX_CHANNELS] - b[:BOX_CHANNELS]), np.abs(a[BOX_CHANNELS:] - b[BOX_CHANNELS:])
        box_diffs.append(box)
        score_diffs.append(score)
        mask = a[BOX_CHANNELS:].max(axis=0) >= confident
        kept_boxes.append(box[:, mask])
        kept_scores.append(score[:, mask])
        agree.append(np.argmax(a[BOX_CHANNELS:, mask], axis=0) == np.argmax(b[BOX_CHANNELS:, mask], axis=0))
    if not box_diffs:
        raise ValueError("compare_outputs needs at least one image")
    boxes, scores = np.stack(box_diffs), np.stack(score_diffs)
    result = {
        "images": float(len(box_diffs)),
        "box_max_abs_px": float(boxes.max()),
        "box_mean_abs_px": float(boxes.mean()),
        "score_max_abs": float(scores.max()),
        "score_mean_abs": float(scores.mean()),
        "confident_anchors": float(sum(m.size for m in agree)),
    }
    if result["confident_anchors"]:
        confident_boxes = np.concatenate(kept_boxes, axis=1)
        confident_scores = np.concatenate(kept_scores, axis=1)
        result |= {
            "confident_box_max_abs_px": float(confident_boxes.max()),
            "confident_box_mean_abs_px": float(confident_boxes.mean()),
            "confident_score_max_abs": float(confident_scores.max()),
            "confident_score_mean_abs": float(confident_scores.mean()),
            "confident_class_agreement": float(np.concatenate(agree).mean()),
        }
    return result


def median_latency_ms(
    onnx_paths: Sequence[Path], image: Path, *, runs: int = 200, warmup: int = 20, threads: int = 1
) -> list[float]:
    """Median single-image ``session.run`` time in ms of each model, after ``warmup`` untimed runs.

    The models take turns run by run, so a background load (training, another process) slows them
    alike instead of whichever happened to be measured second; the median ignores scheduler hiccups
    better than the mean. One intra-op thread by default, like the robot's detector, which shares its
    cores with the encoder and Zenoh.
    """
    if runs < 1 or warmup < 0:
        raise ValueError(f"runs must be >= 1 and warmup >= 0, got {runs}, {warmup}")
    sessions = [cpu_session(Path(p), threads) for p in onnx_paths]
    x = to_model_input(read_tensor_png(image))
    feeds = [{s.get_inputs()[0].name: x} for s in sessions]
    for session, feed in zip(sessions, feeds, strict=True):
        for _ in range(warmup):
            session.run(None, feed)
    times: list[list[float]] = [[] for _ in sessions]
    for _ in range(runs):
        for session, feed, samples in zip(sessions, feeds, times, strict=True):
            started = time.perf_counter()
            session.run(None, feed)
            samples.append((time.perf_counter() - started) * 1e3)
    return [statistics.median(samples) for samples in times]
