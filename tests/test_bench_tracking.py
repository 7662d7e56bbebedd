"""bench.tracking offline: a recorded run's detections through a fresh tracker with the rules given."""

from __future__ import annotations

import json
from pathlib import Path

import msgpack
import numpy as np
import pytest

from bench.tracking import detection_at, main
from common.keys import DETECTIONS, TRUTH
from common.messages import Detections, GroundTruth, StageTimings, TruthObject, encode_message
from common.model_spec import CLASS_NAMES
from services.tracker.core import TrackerConfig

PERSON = CLASS_NAMES.index("person")
MS = 1_000_000


def recording(path: Path, frames: int = 20) -> Path:
    """One robot, one person standing 2 m ahead for ``frames`` scans, detected in every one."""
    truths, found = [], []
    for seq in range(frames):
        person = TruthObject(
            class_id=PERSON, class_name="person", corners_xy=np.zeros((4, 2), np.float32),
            center_xy=(2.0, 0.0), yaw_rad=0.0, visible=True, box_px=(10.0, 10.0, 14.0, 20.0),
        )  # fmt: skip
        truth = GroundTruth(
            robot_id="robot0", seq=seq, stamp_ns=100 * seq * MS, scenario_id=0,
            robot_pose=(0.0, 0.0, 0.0), lidar_pose=(0.0, 0.0, 0.0), objects=[person],
        )  # fmt: skip
        seen = Detections(
            robot_id="robot0", seq=seq, stamp_ns=100 * seq * MS, scan_stamp_ns=100 * seq * MS,
            detections=[detection_at(2.0, 0.0, PERSON)], model_id="bench",
            timings=StageTimings(encode_ms=0.0, inference_ms=0.0, nms_ms=0.0),
        )  # fmt: skip
        truths.append(truth)
        found.append(seen)
    payloads = {TRUTH: [encode_message(t) for t in truths], DETECTIONS: [encode_message(d) for d in found]}
    path.write_bytes(msgpack.packb(payloads))
    return path


def test_offline_takes_the_trackers_travel_rule(tmp_path: Path) -> None:
    recorded = recording(tmp_path / "run.msgpack")
    assert main(["offline", str(recorded), "--out", str(tmp_path / "plain.json")]) == 0
    plain = json.loads((tmp_path / "plain.json").read_text())
    assert plain["config"]["person_confirm_travel_m"] == 0.0
    assert plain["people"]["total"]["matches"] >= 15  # confirmed on the third hit, then followed
    out = tmp_path / "travel.json"
    assert main(["offline", str(recorded), "--person-confirm-travel", "0.5", "--out", str(out)]) == 0
    travel = json.loads(out.read_text())
    assert travel["config"]["person_confirm_travel_m"] == 0.5
    assert travel["config"]["person_resume_s"] == TrackerConfig().person_resume_s  # the other rule unset
    assert main(["offline", str(recorded), "--person-resume", "0", "--out", str(out)]) == 0
    assert json.loads(out.read_text())["config"]["person_resume_s"] == 0.0
    assert travel["people"]["total"]["matches"] == 0  # a person who never moves is never confirmed
    assert travel["people"]["total"]["misses"] == plain["people"]["total"]["targets"]


@pytest.mark.parametrize(
    ("flag", "message"), [("--person-resume", "person resume"), ("--person-confirm-travel", "travel")]
)
def test_live_refuses_a_bad_tracker_rule_before_starting_anything(flag: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        main(["live", "--seconds", "1", flag, "-1", "--out", "/nonexistent/never-written.json"])
