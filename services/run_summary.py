"""What a running loop finds, and how well: per robot, detections per class against the simulator's truth.

``triscan up`` feeds every ``GroundTruth`` and ``Detections`` message it sees into a :class:`RunSummary`
and logs :meth:`RunSummary.table` every ``SUMMARY_PERIOD_S`` and at the end. Everything since the
start is counted; nothing here knows about Zenoh or the clock, so tests feed it messages directly.

Pairing. A tensor stacks scans t-2, t-1 and t, and the model's boxes are those of the *middle* scan
t-1 (the labels were made for it). A ``Detections`` message carries ``seq`` and ``scan_stamp_ns`` of
scan t, and the encoder only stacks consecutive ``seq`` values, so its boxes are compared with the
truth of ``seq - 1``. The truth of ``seq`` must carry the same stamp as ``scan_stamp_ns``: after a
simulator restart the ``seq`` values repeat, and a frame is then left unpaired rather than compared
with another world.

Matching rule (:func:`match_frame`). A detection is correct when its box centre lies inside the label
box of a visible truth object of its class (both in raster pixels, the object's box of scan t-1; on
the circle, so a box across the 0°/360° seam counts), each object claimed by at most one detection,
highest score first. Recall is claimed objects / visible objects; precision is correct detections /
detections, both over the paired frames. Latency is ``stamp_ns - scan_stamp_ns`` of each message:
scan to published detections.
"""

from __future__ import annotations

import math
import threading
from collections import Counter, OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from common.encoding import ANGLE_COLUMNS
from common.messages import Detection, Detections, GroundTruth, TruthObject
from common.model_spec import CLASS_NAMES

TRUTH_KEPT = 64  # truths kept per robot for pairing: detections arrive a few scans late at most

# Latency histogram: bins 1 % wide from 10 µs to 100 s, so a percentile is within 1 % whatever the run
# length, in a fixed few kB per robot.
_LATENCY_EDGES_MS = np.geomspace(0.01, 100_000.0, round(math.log(1e7) / math.log(1.01)) + 1)


class LatencyHistogram:
    """Latencies in log-spaced bins; :meth:`percentile` is the upper edge of the bin holding it."""

    def __init__(self) -> None:
        self.counts = np.zeros(len(_LATENCY_EDGES_MS) + 1, dtype=np.int64)

    def add(self, latency_ms: float) -> None:
        self.counts[int(np.searchsorted(_LATENCY_EDGES_MS, latency_ms))] += 1

    @property
    def total(self) -> int:
        return int(self.counts.sum())

    def percentile(self, q: float) -> float | None:
        """The ``q``-th percentile (0-100) in ms, never below the true value; None when empty."""
        total = self.total
        if total == 0:
            return None
        index = int(np.searchsorted(np.cumsum(self.counts), math.ceil(q / 100.0 * total)))
        return float(_LATENCY_EDGES_MS[min(index, len(_LATENCY_EDGES_MS) - 1)])


def _centre_inside(x: float, y: float, box: tuple[float, float, float, float]) -> bool:
    x1, y1, x2, y2 = box
    return y1 <= y <= y2 and any(x1 <= x + shift <= x2 for shift in (0, -ANGLE_COLUMNS, ANGLE_COLUMNS))


def match_frame(
    detections: Sequence[Detection], objects: Sequence[TruthObject]
) -> tuple[list[bool], list[bool]]:
    """Which detections are correct and which visible objects were found, by the module's rule:
    (correct per detection, found per object); an object that is not visible is never found."""
    found = [False] * len(objects)
    correct = [False] * len(detections)
    for index in sorted(range(len(detections)), key=lambda i: -detections[i].score):
        detection = detections[index]
        x1, y1, x2, y2 = detection.box_px
        cx, cy = (x1 + x2) / 2.0, (y1 + y2) / 2.0
        for i, obj in enumerate(objects):
            if (
                not found[i]
                and obj.box_px is not None
                and obj.class_id == detection.class_id
                and _centre_inside(cx, cy, obj.box_px)
            ):
                found[i] = correct[index] = True
                break
    return correct, found


@dataclass
class _RobotTally:
    truths: OrderedDict[int, GroundTruth] = field(default_factory=OrderedDict)
    frames: int = 0
    paired: int = 0
    found: Counter[str] = field(default_factory=Counter)  # detections per class, every frame
    paired_detections: Counter[str] = field(default_factory=Counter)
    correct: Counter[str] = field(default_factory=Counter)
    visible: Counter[str] = field(default_factory=Counter)
    recalled: Counter[str] = field(default_factory=Counter)
    latency: LatencyHistogram = field(default_factory=LatencyHistogram)


class RunSummary:
    """Per robot: detections per class, recall and precision against the truth, latency p50/p99.

    ``classes`` are the model's (a prefix of the project's list): truth objects of other classes are
    counted but not held against the model. :meth:`update` may be called from several threads.
    """

    def __init__(self, classes: Sequence[str] = CLASS_NAMES, truth_kept: int = TRUTH_KEPT) -> None:
        self.classes = tuple(classes)
        self.truth_kept = truth_kept
        self._robots: dict[str, _RobotTally] = {}
        self._lock = threading.Lock()

    def update(self, message: GroundTruth | Detections) -> None:
        with self._lock:
            tally = self._robots.setdefault(message.robot_id, _RobotTally())
            if isinstance(message, GroundTruth):
                tally.truths[message.seq] = message
                tally.truths.move_to_end(message.seq)
                while len(tally.truths) > self.truth_kept:
                    tally.truths.popitem(last=False)
            else:
                self._add_detections(tally, message)

    def _add_detections(self, tally: _RobotTally, message: Detections) -> None:
        tally.frames += 1
        tally.found.update(d.class_name for d in message.detections)
        tally.latency.add((message.stamp_ns - message.scan_stamp_ns) / 1e6)
        newest, middle = tally.truths.get(message.seq), tally.truths.get(message.seq - 1)
        if newest is None or middle is None or newest.stamp_ns != message.scan_stamp_ns:
            return
        if middle.stamp_ns > newest.stamp_ns:
            return  # not one stream: the scan before was stamped later
        tally.paired += 1
        correct, found = match_frame(message.detections, middle.objects)
        for detection, ok in zip(message.detections, correct, strict=True):
            tally.paired_detections[detection.class_name] += 1
            tally.correct[detection.class_name] += ok
        for obj, ok in zip(middle.objects, found, strict=True):
            if obj.visible:
                tally.visible[obj.class_name] += 1
                tally.recalled[obj.class_name] += ok

    def table(self, elapsed_s: float | None = None) -> str:
        """A short table per robot (robots in name order); one line when nothing arrived yet."""
        with self._lock:
            robots = sorted(self._robots.items())
            since = "" if elapsed_s is None else f" after {elapsed_s:.0f} s"
            if not any(tally.frames for _, tally in robots):
                return f"no detections yet{since}"
            lines = [
                f"detections{since}, against the simulator's truth (a box is right when its centre lies in "
                "the label box of a visible object of its class):"
            ]
            for robot_id, tally in robots:
                lines += self._robot_lines(robot_id, tally)
            return "\n".join(lines)

    def _robot_lines(self, robot_id: str, tally: _RobotTally) -> list[str]:
        p50, p99 = tally.latency.percentile(50), tally.latency.percentile(99)
        latency = "-" if p50 is None or p99 is None else f"p50 {p50:.1f} ms, p99 {p99:.1f} ms"
        lines = [
            f"  {robot_id}: {tally.frames} frames ({tally.paired} with truth), scan-to-detections {latency}",
            f"    {'class':10s} {'found':>6s} {'objects':>7s} {'recall':>6s} {'precision':>9s}",
        ]
        extra = sorted(set(tally.visible) - set(self.classes), key=_class_order)
        for name in (*self.classes, *extra):
            if name not in self.classes:
                lines.append(
                    f"    {name:10s} {'-':>6s} {tally.visible[name]:7d}  (not a class of this model)"
                )
                continue
            recall = _ratio(tally.recalled[name], tally.visible[name])
            precision = _ratio(tally.correct[name], tally.paired_detections[name])
            lines.append(
                f"    {name:10s} {tally.found[name]:6d} {tally.visible[name]:7d} {recall:>6s} {precision:>9s}"
            )
        return lines


def _ratio(numerator: int, denominator: int) -> str:
    return "-" if denominator == 0 else f"{numerator / denominator:.2f}"


def _class_order(name: str) -> int:
    return CLASS_NAMES.index(name) if name in CLASS_NAMES else len(CLASS_NAMES)
