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
  ``person`` against the people, both in the laser frame of that scan;
* ignored: the objects there but no target in that scan (occluded, or too few beams on them): a track
  on one is no false positive (:class:`services.tracker.mot.ClearMot`).

A model that predicts no people (a prefix of the class list without ``person``) is scored on the
furniture only; the people are still in its worlds, occluding and being walked past.

``triscan eval --bag BAG --tracks`` (:func:`track_bag`) runs the detector and the tracker over a
recorded bag instead (in the laser frame: the development recordings carry no odometry) and reports
its confirmed tracks per class and, for people, per *pass*: the confirmed person tracks chained while
each starts within ``PASS_GAP_S`` of the last one's end. One person walking by should give one track
a pass; each further track in a pass is counted as an ID switch. With ``--people-topic`` labels the
people are also scored with CLEAR MOT.
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
from common.messages import Detections, Odometry
from common.model_spec import CLASS_NAMES, PERSON
from services.simulator.lidar import LidarSpec
from services.tracker.core import REPORTED_STATES, TrackerConfig, TrackerCore
from services.tracker.mot import DEFAULT_GATE_M, GROUPS, ClearMot, MotScore, hypotheses_of

log = logging.getLogger(__name__)

PASS_GAP_S = 1.0  # a person track starting this soon after another ended continues the same pass
GOALS: dict[str, float] = {"furniture": 0.90, "people": 0.85}  # MOTA, issue goals on fresh worlds

Points = dict[Any, tuple[float, float]]


@dataclass(frozen=True)
class MotionFrame:
    """One scan of a motion: its tensor, when it was taken, the true pose and the visible objects."""

    tensor: np.ndarray
    stamp_ns: int
    lidar_pose: tuple[float, float, float]  # of scan t-1, whose objects the boxes are
    targets: dict[str, Points]  # group → target id → (x, y) in the laser frame of scan t-1
    ignored: dict[str, Points]  # the same for the objects there but no target (mot.ClearMot)


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
    open_space: float = 0.0,
) -> Iterator[tuple[str, list[MotionFrame]]]:
    """Every motion of the fresh worlds, each as its consecutive scans (``training.evaluate``'s worlds)."""
    from services.simulator.lidar import DEFAULT_SPEC
    from services.simulator.scenario import room_half_of, sample_scenario
    from services.simulator.world import World
    from training.dataset import plan_motions, simulate_samples, stacked_period_s

    spec = spec or DEFAULT_SPEC
    period_ns = round(stacked_period_s(spec) * 1e9)
    with World() as world:
        for index in range(scenarios):
            scenario = sample_scenario(index, seed, room_half_of(seed, index, open_space))
            centres = [o.footprint.center for o in scenario.objects] + [scenario.door.frame.center]
            motions = plan_motions(scenario, seed, positions)
            frames: dict[int, list[MotionFrame]] = {}
            for sample in simulate_samples(
                world, scenario, motions, seed, detector.padding, 1, spec=spec, clutter=clutter,
                invalid=detector.invalid, people=people, raster_yaw_deg=detector.raster_yaw_deg,
            ):  # fmt: skip
                pose = sample.lidar_pose
                targets: dict[str, Points] = {group: {} for group in GROUPS}
                ignored: dict[str, Points] = {group: {} for group in GROUPS}
                for i, label in enumerate(sample.labels):
                    where = targets if label.visible else ignored
                    if i < len(centres):
                        where["furniture"][i] = _laser(centres[i], pose)
                    else:
                        legs = np.array(sample.people_legs[i - len(centres)])
                        where["people"][i] = _laser(
                            (float(legs[:, 0].mean()), float(legs[:, 1].mean())), pose
                        )
                stamp = (sample.frame - 1) * period_ns  # the boxes' scan
                frames.setdefault(sample.position, []).append(
                    MotionFrame(sample.tensor, stamp, pose, targets, ignored)
                )
            for position, motion in sorted(frames.items()):
                yield f"s{index:04d}_p{position:03d}", motion


def score_motion(
    core: TrackerCore, name: str, frames: list[MotionFrame], detector: OnnxDetector
) -> dict[str, MotScore]:
    """Track one motion's detections and score every frame; the core's robot ``name`` is this motion."""
    accumulators = {group: ClearMot(DEFAULT_GATE_M) for group in GROUPS}
    # Each tensor's scans t-2, t-1, t are the middle scans of this frame and its neighbours: their
    # poses are the odometry a robot's detector has for motion confirmation (common.moving_people).
    poses: list[Odometry | None] = [None]  # before the first frame's oldest scan: unknown
    for f in frames:
        x, y, yaw = f.lidar_pose
        poses.append(Odometry(x_m=x, y_m=y, yaw_rad=yaw, stamp_ns=f.stamp_ns))
    poses.append(None)  # after the last one's newest
    for seq, frame in enumerate(frames):
        still = detector.still_by_odometry(poses[seq : seq + 3])
        ((detections, timings),) = detector.detect_many([frame.tensor], [still])
        message = Detections(
            robot_id=name, seq=seq, stamp_ns=frame.stamp_ns, detections=detections, timings=timings,
            model_id=detector.model_id, scan_stamp_ns=frame.stamp_ns, odom=poses[seq + 1],
        )  # fmt: skip
        tracks = core.update(message)
        if tracks is None:
            raise RuntimeError(f"{name}: the tracker dropped frame {seq}")
        found = hypotheses_of(tracks)
        for group in GROUPS:
            accumulators[group].update(frame.targets[group], found[group], frame.ignored[group])
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
    detector: OnnxDetector,
    motions: Iterator[tuple[str, list[MotionFrame]]],
    out_dir: Path,
    *,
    source: str,
    tracker: TrackerConfig | None = None,
) -> TrackReport:
    """Score every motion with the ``tracker`` rules (default: the service's) and write
    ``tracks.json`` into ``out_dir``."""
    classes = tuple(getattr(detector, "class_names", CLASS_NAMES))
    scored = GROUPS if PERSON in classes else ("furniture",)
    report = TrackReport(detector.model_id, source, classes=classes, scored=scored)
    core = TrackerCore(tracker)
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


@dataclass
class BagTracks:
    """What ``triscan eval --bag --tracks`` prints and writes for one model."""

    bag: str
    model: str
    classes: list[str]
    conf: float
    tensors: int
    confirmed_tracks: dict[str, int]  # per class: tracks that were ever confirmed
    person_tracks: list[dict[str, float | int]]  # id, first_s, last_s, hits
    passes: list[dict[str, Any]]  # start_s, end_s, track_ids
    id_switches: int  # person tracks beyond the first of each pass
    people_mot: dict[str, float | int] | None = None  # with labelled people only
    skipped: dict[str, int] = dataclasses.field(default_factory=dict)

    @property
    def has_person_class(self) -> bool:
        return PERSON in self.classes


def person_passes(tracks: list[dict[str, float | int]], gap_s: float = PASS_GAP_S) -> list[dict[str, Any]]:
    """Confirmed person tracks chained into passes (see the module docstring), in time order."""
    passes: list[dict[str, Any]] = []
    for track in sorted(tracks, key=lambda t: t["first_s"]):
        if passes and float(track["first_s"]) <= passes[-1]["end_s"] + gap_s:
            passes[-1]["end_s"] = max(passes[-1]["end_s"], float(track["last_s"]))
            passes[-1]["track_ids"].append(track["track_id"])
        else:
            passes.append(
                {
                    "start_s": float(track["first_s"]),
                    "end_s": float(track["last_s"]),
                    "track_ids": [track["track_id"]],
                }
            )
    return passes


def track_bag(detector: OnnxDetector, config: Any, tracker: TrackerConfig | None = None) -> BagTracks:
    """Detector and tracker (the ``tracker`` rules, default the service's) over ``config.bag`` (a
    :class:`training.real_eval.BagEvalConfig`)."""
    from collections import Counter

    from common.messages import StageTimings
    from training.real_eval import _load, middle_scan_detections

    bag = _load(config)
    rejected: Counter[str] = Counter(bag.skipped)
    core = TrackerCore(tracker)
    confirmed: dict[int, dict[str, Any]] = {}
    mot = ClearMot(DEFAULT_GATE_M) if bag.people is not None else None
    t0 = bag.stream[0].stamp_ns
    tensors = 0
    zero = StageTimings(encode_ms=0.0, inference_ms=0.0, nms_ms=0.0)
    for stamp, found in middle_scan_detections(detector, bag.stream, config.conf, rejected):
        tensors += 1
        kept = [d for d in found if d.score > config.conf]
        message = Detections(
            robot_id="bag", seq=tensors, stamp_ns=stamp, detections=kept, timings=zero,
            model_id=detector.model_id, scan_stamp_ns=stamp,
        )  # fmt: skip
        tracks = core.update(message)
        if tracks is None:
            rejected["out_of_order"] += 1
            continue
        seconds = (stamp - t0) / 1e9
        for t in tracks.tracks:
            if t.state == "confirmed":
                entry = confirmed.setdefault(t.track_id, {"track_id": t.track_id, "first_s": seconds})
                entry.update(class_name=t.class_name, last_s=seconds, hits=t.hits)
        if mot is not None and bag.people is not None and stamp in bag.people:
            people = {i: (float(x), float(y)) for i, (x, y) in enumerate(bag.people[stamp])}
            mot.update(people, hypotheses_of(tracks)["people"])
    person_tracks = [
        {k: v for k, v in t.items() if k != "class_name"}
        for t in confirmed.values()
        if t["class_name"] == PERSON
    ]
    passes = person_passes(person_tracks)
    by_class = {
        name: sum(t["class_name"] == name for t in confirmed.values()) for name in detector.class_names
    }
    return BagTracks(
        bag=str(config.bag), model=detector.model_id, classes=list(detector.class_names), conf=config.conf,
        tensors=tensors, confirmed_tracks=by_class, person_tracks=person_tracks, passes=passes,
        id_switches=sum(len(p["track_ids"]) - 1 for p in passes),
        people_mot=None if mot is None else mot.score.to_dict(), skipped=dict(rejected),
    )  # fmt: skip


def format_bag_tracks(report: BagTracks) -> str:
    tracks = ", ".join(f"{name} {count}" for name, count in report.confirmed_tracks.items())
    lines = [f"{report.model} on {report.bag}: {report.tensors} tensors; confirmed tracks: {tracks}"]
    if not report.has_person_class:
        lines.append("people: this model has no person class, so no person track and no pass to report")
        return "\n".join(lines)
    lines.append(
        f"people: {len(report.person_tracks)} confirmed tracks in {len(report.passes)} passes, "
        f"{report.id_switches} ID switches (tracks beyond the first of a pass)"
    )
    for p in report.passes:
        lines.append(f"  pass {p['start_s']:.1f}-{p['end_s']:.1f} s: tracks {p['track_ids']}")
    if report.people_mot is not None:
        m = report.people_mot
        lines.append(
            f"labelled people: MOTA {m['mota']:.3f}, {m['id_switches']} ID switches, {m['misses']} misses, "
            f"{m['false_positives']} false positives of {m['targets']}"
        )
    return "\n".join(lines)
