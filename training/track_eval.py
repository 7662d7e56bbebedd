"""``triscan eval --tracks``: CLEAR MOT of the tracker on fresh worlds, furniture and people apart.

Each fresh motion (a robot driving, or standing while people walk past) is simulated scan by scan,
every scan's tensor goes through the run-time detector, and the detections, in scan order and placed
with the robot's true pose, through the tracker's pure core (:class:`services.tracker.core.TrackerCore`,
one robot per motion). Its confirmed and coasting tracks are scored with CLEAR MOT
(:mod:`services.tracker.mot`, 0.75 m gate) against the truth of the scan the boxes are of (t-1):

* targets: the objects labelled visible in that scan, each one identity per motion; a piece of
  furniture at its footprint centre (the doorframe at its frame's), a person at the midpoint of their
  legs;
* hypotheses: the tracks whose class is a furniture class score against the furniture, those of class
  ``person`` against the people, both in the laser frame of that scan.

A model that predicts no people (a prefix of the class list without ``person``) is scored on the
furniture only; the people are still in its worlds, occluding and being walked past.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from common.inference import OnnxDetector
from common.messages import Detections, Odometry, Tracks
from common.model_spec import CLASS_NAMES
from services.simulator.lidar import LidarSpec
from services.tracker.core import REPORTED_STATES, TrackerCore
from services.tracker.mot import DEFAULT_GATE_M, ClearMot, MotScore

log = logging.getLogger(__name__)

PERSON = "person"
GROUPS: tuple[str, ...] = ("furniture", "people")
GOALS: dict[str, float] = {"furniture": 0.90, "people": 0.85}  # MOTA, issue goals on fresh worlds

Points = dict[Any, tuple[float, float]]


@dataclass(frozen=True)
class MotionFrame:
    """One scan of a motion: its tensor, when it was taken, the true pose and the visible objects."""

    tensor: np.ndarray
    stamp_ns: int
    lidar_pose: tuple[float, float, float]  # of scan t-1, whose objects the boxes are
    targets: dict[str, Points]  # group → target id → (x, y) in the laser frame of scan t-1


def _laser(point: tuple[float, float], pose: tuple[float, float, float]) -> tuple[float, float]:
    dx, dy = point[0] - pose[0], point[1] - pose[1]
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return c * dx + s * dy, -s * dx + c * dy


def fresh_motions(
    seed: int,
    scenarios: int,
    positions: int,
    detector: OnnxDetector,
    *,
    spec: LidarSpec | None = None,
    clutter: int = 0,
    people: int = 0,
) -> Iterator[tuple[str, list[MotionFrame]]]:
    """Every motion of the fresh worlds, each as its consecutive scans (``training.evaluate``'s worlds)."""
    from services.simulator.lidar import DEFAULT_SPEC
    from services.simulator.scenario import sample_scenario
    from services.simulator.world import World
    from training.dataset import plan_motions, simulate_samples, stacked_period_s

    spec = spec or DEFAULT_SPEC
    period_ns = round(stacked_period_s(spec) * 1e9)
    with World() as world:
        for index in range(scenarios):
            scenario = sample_scenario(index, seed)
            centres = [o.footprint.center for o in scenario.objects] + [scenario.door.frame.center]
            motions = plan_motions(scenario, seed, positions)
            frames: dict[int, list[MotionFrame]] = {}
            for sample in simulate_samples(
                world, scenario, motions, seed, detector.padding, 1, spec=spec, clutter=clutter,
                invalid=detector.invalid, people=people,
            ):  # fmt: skip
                pose = sample.lidar_pose
                targets: dict[str, Points] = {group: {} for group in GROUPS}
                for i, label in enumerate(sample.labels):
                    if not label.visible:
                        continue
                    if i < len(centres):
                        targets["furniture"][i] = _laser(centres[i], pose)
                    else:
                        legs = sample.people_legs[i - len(centres)]
                        middle = (
                            sum(leg[0] for leg in legs) / len(legs),
                            sum(leg[1] for leg in legs) / len(legs),
                        )
                        targets["people"][i] = _laser(middle, pose)
                stamp = (sample.frame - 1) * period_ns  # the boxes' scan
                frames.setdefault(sample.position, []).append(
                    MotionFrame(sample.tensor, stamp, pose, targets)
                )
            for position, motion in sorted(frames.items()):
                yield f"s{index:04d}_p{position:03d}", motion


def hypotheses(tracks: Tracks) -> dict[str, Points]:
    """The reported tracks by group, in the laser frame of their scan."""
    out: dict[str, Points] = {group: {} for group in GROUPS}
    for t in tracks.tracks:
        if t.state in REPORTED_STATES:
            group = "people" if t.class_name == PERSON else "furniture"
            out[group][t.track_id] = (t.x_m, t.y_m)
    return out


def score_motion(
    core: TrackerCore, name: str, frames: list[MotionFrame], detector: OnnxDetector
) -> dict[str, MotScore]:
    """Track one motion's detections and score every frame; the core's robot ``name`` is this motion."""
    accumulators = {group: ClearMot(DEFAULT_GATE_M) for group in GROUPS}
    for seq, frame in enumerate(frames):
        detections, timings = detector.detect(frame.tensor)
        x, y, yaw = frame.lidar_pose
        message = Detections(
            robot_id=name, seq=seq, stamp_ns=frame.stamp_ns, detections=detections, timings=timings,
            model_id=detector.model_id, scan_stamp_ns=frame.stamp_ns,
            odom=Odometry(x_m=x, y_m=y, yaw_rad=yaw, stamp_ns=frame.stamp_ns),
        )  # fmt: skip
        tracks = core.update(message)
        if tracks is None:
            raise RuntimeError(f"{name}: the tracker dropped frame {seq}")
        found = hypotheses(tracks)
        for group in GROUPS:
            accumulators[group].update(frame.targets[group], found[group])
    return {group: accumulators[group].score for group in GROUPS}


@dataclass
class TrackReport:
    model_id: str
    source: str
    motions: int = 0
    frames: int = 0
    scores: dict[str, MotScore] = dataclasses.field(default_factory=lambda: {g: MotScore() for g in GROUPS})
    classes: tuple[str, ...] = CLASS_NAMES  # the model's
    scored: tuple[str, ...] = GROUPS  # people only when the model predicts them

    def to_dict(self) -> dict[str, Any]:
        return {
            "model_id": self.model_id,
            "source": self.source,
            "classes": list(self.classes),
            "gate_m": DEFAULT_GATE_M,
            "scored_states": list(REPORTED_STATES),
            "motions": self.motions,
            "frames": self.frames,
            **{
                group: (
                    {**self.scores[group].to_dict(), "goal_mota": GOALS[group]}
                    if group in self.scored
                    else None
                )
                for group in GROUPS
            },
        }


def evaluate_tracks(
    detector: OnnxDetector, motions: Iterator[tuple[str, list[MotionFrame]]], out_dir: Path, *, source: str
) -> TrackReport:
    """Score every motion and write ``tracks.json`` into ``out_dir``."""
    classes = tuple(getattr(detector, "class_names", CLASS_NAMES))
    scored = GROUPS if PERSON in classes else ("furniture",)
    report = TrackReport(detector.model_id, source, classes=classes, scored=scored)
    core = TrackerCore()
    for name, frames in motions:
        for group, score in score_motion(core, name, frames, detector).items():
            report.scores[group] = report.scores[group].merged(score)
        report.motions += 1
        report.frames += len(frames)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "tracks.json").write_text(json.dumps(report.to_dict(), indent=2) + "\n")
    return report


def format_report(report: TrackReport) -> str:
    lines = [
        f"{report.model_id} on {report.source}: {report.motions} motions, {report.frames} frames "
        f"(CLEAR MOT, {DEFAULT_GATE_M} m gate, {'/'.join(REPORTED_STATES)} tracks)",
        f"{'objects':<10} {'MOTA':>6} {'goal':>5} {'MOTP m':>7} {'IDsw':>5} {'miss':>6} {'FP':>6} "
        f"{'targets':>8}",
    ]
    for group in GROUPS:
        if group not in report.scored:
            lines.append(
                f"{group:<10} not scored: the model predicts no {PERSON} ({', '.join(report.classes)})"
            )
            continue
        s = report.scores[group]
        lines.append(
            f"{group:<10} {s.mota:>6.3f} {GOALS[group]:>5.2f} {s.motp_m:>7.3f} {s.id_switches:>5d} "
            f"{s.misses:>6d} {s.false_positives:>6d} {s.targets:>8d}"
        )
    return "\n".join(lines)
