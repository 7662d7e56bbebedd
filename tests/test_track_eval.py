"""``triscan eval --tracks``: CLEAR MOT of the tracker over fresh motions, furniture and people apart."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path
from typing import Any, cast

import numpy as np

from bench.tracking import detection_at
from common.messages import Detection, StageTimings
from common.model_spec import CLASS_NAMES, SHIPPED_MODEL
from services.tracker.core import TrackerConfig
from services.tracker.mot import MotScore
from training.track_eval import (
    BagTracks,
    MotionFrame,
    evaluate_tracks,
    format_bag_tracks,
    format_report,
    fresh_motions,
    person_passes,
)

PERSON_ID = CLASS_NAMES.index("person")


class TruthDetector:
    """Detects exactly the frame's targets (the tensor carries the frame's index), a chair for furniture."""

    model_id = "truth"
    padding = "zero"
    invalid = "sentinel"

    def __init__(self, frames: list[MotionFrame], class_names: tuple[str, ...]) -> None:
        self.frames = frames
        self.class_names = class_names

    def detect(self, tensor: np.ndarray) -> tuple[list[Detection], StageTimings]:
        frame = self.frames[int(tensor[0, 0, 0])]
        found = [detection_at(x, y, 0) for x, y in frame.targets["furniture"].values()]
        if "person" in self.class_names:
            found += [detection_at(x, y, PERSON_ID) for x, y in frame.targets["people"].values()]
        return found, StageTimings(encode_ms=0.0, inference_ms=0.0, nms_ms=0.0)

    def detect_many(
        self, tensors: list[np.ndarray], still: list[bool | None] | None = None
    ) -> list[tuple[list[Detection], StageTimings]]:
        return [self.detect(tensor) for tensor in tensors]

    def still_by_odometry(self, poses: object) -> None:
        return None  # confirms nothing by motion


def _motion(frames: int) -> list[MotionFrame]:
    """A robot driving +x past a still chair while a person walks across, poses and truth consistent."""
    out = []
    for k in range(frames):
        pose = (0.05 * k, 0.0, 0.02 * k)
        c, s = math.cos(pose[2]), math.sin(pose[2])

        def laser(x: float, y: float, pose: tuple[float, float, float] = pose, c: float = c, s: float = s):
            dx, dy = x - pose[0], y - pose[1]
            return (c * dx + s * dy, -s * dx + c * dy)

        tensor = np.full((64, 384, 3), k, dtype=np.uint8)
        targets = {"furniture": {"chair": laser(2.0, 1.0)}, "people": {"p0": laser(1.0, -1.5 + 0.1 * k)}}
        out.append(MotionFrame(tensor, (k + 1) * 100_000_000, pose, targets, {"furniture": {}, "people": {}}))
    return out


def test_perfect_detections_score_near_one_for_furniture_and_people_apart(tmp_path: Path) -> None:
    frames = _motion(30)
    detector = cast(Any, TruthDetector(frames, CLASS_NAMES))
    report = evaluate_tracks(detector, iter([("m0", frames)]), tmp_path, source="synthetic")
    # A track is tentative until it is confirmed: a miss for each frame before (three hits confirm
    # furniture, two a person).
    for group, misses in (("furniture", 2), ("people", 1)):
        score = report.scores[group]
        counts = (score.targets, score.misses, score.false_positives, score.id_switches)
        assert counts == (30, misses, 0, 0), group
        assert score.motp_m < 0.05
    written = json.loads((tmp_path / "tracks.json").read_text())
    assert (
        written["people"]["mota"] == report.scores["people"].mota and written["furniture"]["goal_mota"] == 0.9
    )
    # With leg_tracker's travel rule the walker (0.1 m a frame) waits for 0.5 m; the chair does not.
    travel = evaluate_tracks(
        detector, iter([("m0", frames)]), tmp_path, source="synthetic",
        tracker=TrackerConfig(person_confirm_travel_m=0.5),
    )  # fmt: skip
    assert travel.scores["furniture"].misses == 2 and 5 <= travel.scores["people"].misses <= 8


def test_a_model_without_people_is_scored_on_furniture_only_and_says_so(tmp_path: Path) -> None:
    frames = _motion(10)
    detector = cast(Any, TruthDetector(frames, CLASS_NAMES[:4]))
    report = evaluate_tracks(detector, iter([("m0", frames)]), tmp_path, source="synthetic")
    assert report.scored == ("furniture",)
    assert json.loads((tmp_path / "tracks.json").read_text())["people"] is None
    assert "people     not scored: the model predicts no person" in format_report(report)


def test_scores_of_motions_add_up() -> None:
    a, b = MotScore(10, 8, 2, 1, 1, 0.8), MotScore(5, 5, 0, 2, 0, 0.5)
    merged = a.merged(b)
    assert (merged.targets, merged.matches, merged.misses, merged.false_positives, merged.id_switches) == (
        15, 13, 2, 3, 1,
    )  # fmt: skip
    assert merged.motp_m == 1.3 / 13


def test_fresh_motions_give_consecutive_frames_with_truth_in_the_laser_frame() -> None:
    from common.inference import OnnxDetector

    detector = OnnxDetector(SHIPPED_MODEL, intra_op_threads=1)
    motions = list(fresh_motions(1000, 1, 1, detector, people=2))
    assert len(motions) == 1
    name, frames = motions[0]
    assert name == "s0000_p000" and len(frames) > 10
    steps = {b.stamp_ns - a.stamp_ns for a, b in itertools.pairwise(frames)}
    assert len(steps) == 1  # one scan after the other, none skipped
    furniture = [p for f in frames for p in f.targets["furniture"].values()]
    assert furniture and all(math.hypot(*p) < 8.0 for p in furniture)


def test_person_tracks_chain_into_passes_and_extra_tracks_in_a_pass_are_switches() -> None:
    tracks = [
        {"track_id": 1, "first_s": 0.0, "last_s": 4.0, "hits": 40},
        {"track_id": 2, "first_s": 4.5, "last_s": 7.0, "hits": 25},  # lost and picked up again: same pass
        {"track_id": 3, "first_s": 20.0, "last_s": 24.0, "hits": 40},  # the person walks back later
    ]
    passes = person_passes(tracks)
    assert [p["track_ids"] for p in passes] == [[1, 2], [3]]
    assert (passes[0]["start_s"], passes[0]["end_s"]) == (0.0, 7.0)
    report = BagTracks(
        bag="b", model="m", classes=list(CLASS_NAMES), conf=0.25, tensors=300,
        confirmed_tracks={"person": 3}, person_tracks=tracks, passes=passes, id_switches=1,
    )  # fmt: skip
    assert "3 confirmed tracks in 2 passes, 1 ID switches" in format_bag_tracks(report)
    four = BagTracks(
        bag="b", model="m", classes=list(CLASS_NAMES[:4]), conf=0.25, tensors=300,
        confirmed_tracks={"doorframe": 2}, person_tracks=[], passes=[], id_switches=0,
    )  # fmt: skip
    assert "this model has no person class" in format_bag_tracks(four)
