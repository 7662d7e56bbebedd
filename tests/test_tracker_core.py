"""The tracker's core: ids that hold, velocities, still furniture in the odometry frame, and bad input."""

from __future__ import annotations

import argparse
import math

import numpy as np
import pytest

from common.keys import detections_key
from common.messages import (
    Detection,
    Detections,
    Odometry,
    StageTimings,
    Tracks,
    decode_message,
    encode_message,
)
from common.model_spec import CLASS_NAMES
from services.tracker import RULE_FLAGS, add_tracker_arguments, rule_flags, rules_of
from services.tracker.core import TrackerConfig, TrackerCore

PERIOD_NS = 100_000_000  # 10 Hz
T0_NS = 1_700_000_000_000_000_000


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def det(x: float, y: float, class_name: str = "chair", score: float = 0.9) -> Detection:
    r, b = math.hypot(x, y), math.degrees(math.atan2(y, x))
    return Detection(
        class_id=CLASS_NAMES.index(class_name),
        class_name=class_name,
        score=score,
        box_px=(0.0, 0.0, 1.0, 1.0),
        bearing_deg=b,
        bearing_min_deg=b,
        bearing_max_deg=b,
        range_min_m=r,
        range_max_m=r,
        x_m=x,
        y_m=y,
    )


def message(
    seq: int,
    detections: list[Detection],
    odom: Odometry | None = None,
    robot: str = "r1",
    stamp: int | None = None,
) -> Detections:
    return Detections(
        robot_id=robot,
        seq=seq,
        stamp_ns=T0_NS + seq * PERIOD_NS,
        detections=detections,
        timings=StageTimings(encode_ms=0.0, inference_ms=0.0, nms_ms=0.0),
        model_id="test",
        scan_stamp_ns=T0_NS + seq * PERIOD_NS if stamp is None else stamp,
        odom=odom,
    )


def pose(x: float, y: float, yaw: float, frame: str = "odom") -> Odometry:
    return Odometry(x_m=x, y_m=y, yaw_rad=yaw, frame_id=frame, stamp_ns=0)


def in_laser(world: tuple[float, float], robot: Odometry) -> tuple[float, float]:
    dx, dy = world[0] - robot.x_m, world[1] - robot.y_m
    c, s = math.cos(robot.yaw_rad), math.sin(robot.yaw_rad)
    return c * dx + s * dy, -s * dx + c * dy


def robot_pose(k: int) -> Odometry:
    """A robot driving at 0.3 m/s and turning at 0.2 rad/s: its detections of still objects move."""
    return pose(0.03 * k, 0.01 * k, 0.02 * k)


def drive(core: TrackerCore, frames: int, first: int = 0) -> list[Tracks]:
    """A still chair at (2, 1) and a person walking at (0.5, -0.8) m/s, seen from the moving robot."""
    out = []
    for k in range(first, first + frames):
        robot = robot_pose(k)
        person = (1.0 + 0.05 * k, 1.0 - 0.08 * k)
        dets = [det(*in_laser((2.0, 1.0), robot), "chair"), det(*in_laser(person, robot), "person")]
        tracks = core.update(message(k, dets, robot))
        assert tracks is not None
        out.append(tracks)
    return out


def by_class(tracks: Tracks, name: str) -> list:
    return [t for t in tracks.tracks if t.class_name == name]


def test_ids_hold_furniture_stays_still_and_people_get_their_velocity_in_the_odom_frame() -> None:
    core = TrackerCore(TrackerConfig(confirm_hits=3, person_confirm_hits=2))
    frames = drive(core, 40)
    assert [t.state for t in frames[0].tracks] == ["tentative", "tentative"]
    assert {t.class_name: t.state for t in frames[1].tracks} == {"chair": "tentative", "person": "confirmed"}
    assert {t.state for t in frames[2].tracks} == {"confirmed"}
    last = frames[-1]
    assert last.frame == "odom" and last.seq == 39
    (chair,) = by_class(last, "chair")
    (person,) = by_class(last, "person")
    assert {chair.track_id, person.track_id} == {t.track_id for t in frames[0].tracks}  # never switched
    assert (chair.odom_x_m, chair.odom_y_m) == pytest.approx((2.0, 1.0), abs=1e-3)
    assert math.hypot(chair.vx_mps, chair.vy_mps) < 0.01
    assert (person.vx_mps, person.vy_mps) == pytest.approx((0.5, -0.8), abs=0.05)
    # x_m, y_m: the laser frame of this scan.
    assert (chair.x_m, chair.y_m) == pytest.approx(in_laser((2.0, 1.0), robot_pose(39)), abs=1e-3)
    assert (chair.hits, chair.misses, chair.age_s) == (40, 0, pytest.approx(3.9))
    assert decode_message(encode_message(last), Tracks) == last


def test_without_odometry_tracks_live_in_the_laser_frame() -> None:
    core = TrackerCore()
    for k in range(10):
        out = core.update(message(k, [det(1.0 + 0.05 * k, 0.5, "box")]))
    assert out is not None and out.frame == "laser"
    (track,) = out.tracks
    assert track.odom_x_m is None and track.state == "confirmed"
    assert track.vx_mps == pytest.approx(0.5, abs=0.1)  # the free model: the robot's motion moves things


def test_coasting_through_an_occlusion_then_deletion_after_the_timeout() -> None:
    core = TrackerCore(TrackerConfig(delete_after_s=0.5, still_delete_after_s=0.5))
    for k in range(5):
        core.update(message(k, [det(2.0, 0.0)], pose(0, 0, 0)))
    coasting = core.update(message(5, [], pose(0, 0, 0)))
    assert coasting is not None and [(t.state, t.misses) for t in coasting.tracks] == [("coasting", 1)]
    back = core.update(message(6, [det(2.02, 0.0)], pose(0, 0, 0)))
    assert back is not None and [t.state for t in back.tracks] == ["confirmed"]
    assert back.tracks[0].track_id == coasting.tracks[0].track_id
    for k in range(7, 13):
        gone = core.update(message(k, [], pose(0, 0, 0)))
    assert gone is not None and gone.tracks == [] and core.counters.tracks_deleted == 1


@pytest.mark.parametrize(("seen_scans", "shown_scans"), [(31, 8), (12, 3)])
def test_a_coasting_person_leaves_the_message_before_their_track_ends_and_keeps_their_id(
    seen_scans: int, shown_scans: int
) -> None:
    """Shown coasting for person_show_coast_s (0.8 s) after a 3 s track, for 0.3 of its age after a
    1.1 s one (0.33 s: person_show_coast_share): a short track lost is the likelier false person."""
    config = TrackerConfig()
    assert (config.person_show_coast_s, config.person_show_coast_share) == (0.8, 0.3)
    core = TrackerCore(config)
    for k in range(seen_scans):
        seen = core.update(message(k, [det(2.0, 0.0, "chair"), det(0.0, 2.0, "person")]))
    assert seen is not None
    ids = {t.class_name: t.track_id for t in seen.tracks}
    last = seen_scans - 1
    for k in range(seen_scans, seen_scans + 12):  # 1.2 s unseen: past the show time, within delete_after_s
        out = core.update(message(k, []))
        assert out is not None
        shown = {t.class_name for t in out.tracks}
        assert "chair" in shown  # furniture coasts in the message until delete_after_s
        assert ("person" in shown) is (k - last <= shown_scans), k
    back = core.update(message(seen_scans + 12, [det(2.0, 0.0, "chair"), det(0.0, 2.05, "person")]))
    assert back is not None and {t.class_name: t.track_id for t in back.tracks} == ids


def test_a_person_show_time_that_is_no_number_of_seconds_or_share_is_refused() -> None:
    for bad in (-0.1, math.nan):
        with pytest.raises(ValueError, match="person show coast must be >= 0 seconds"):
            TrackerConfig(person_show_coast_s=bad)
        with pytest.raises(ValueError, match="person show coast share must be >= 0"):
            TrackerConfig(person_show_coast_share=bad)


def test_still_furniture_out_of_sight_is_hidden_then_takes_its_id_back_and_a_person_is_deleted() -> None:
    core = TrackerCore(TrackerConfig(delete_after_s=0.5, still_delete_after_s=5.0))
    for k in range(5):
        seen = core.update(message(k, [det(2.0, 0.0, "chair"), det(0.0, 2.0, "person")], pose(0, 0, 0)))
    assert seen is not None
    ids = {t.class_name: t.track_id for t in seen.tracks}
    for k in range(5, 35):  # 3 s unseen: past delete_after_s, within still_delete_after_s
        hidden = core.update(message(k, [], pose(0.01 * k, 0, 0)))
        assert hidden is not None and (k < 11 or hidden.tracks == [])  # not shown once over 0.5 s
    assert core.counters.tracks_deleted == 1  # the person; the chair is kept, dormant
    back = core.update(
        message(35, [det(2.0 - 0.35, 0.0, "chair"), det(0.0, 2.0, "person")], pose(0.35, 0, 0))
    )
    assert back is not None
    got = {t.class_name: t.track_id for t in back.tracks}
    assert got["chair"] == ids["chair"] and got["person"] != ids["person"]
    for k in range(36, 100):  # past still_delete_after_s: gone
        core.update(message(k, [], pose(0.35, 0, 0)))
    assert core.counters.tracks_deleted == 3


def test_boxes_are_placed_with_the_pose_of_the_middle_scan_they_are_of() -> None:
    core = TrackerCore()
    turning = [pose(0.05 * k, 0.0, 0.3 * k) for k in range(8)]  # a fast turn: 0.3 rad a scan
    for k in range(8):
        middle = turning[max(k - 1, 0)]  # the boxes are scan t-1's; the odometry is scan t's
        detections = message(k, [det(*in_laser((2.0, 1.0), middle))], turning[k])
        pose_stamp = None if k == 0 else T0_NS + (k - 1) * PERIOD_NS
        out = core.update(detections.model_copy(update={"pose_stamp_ns": pose_stamp}))
        assert out is not None
        (track,) = out.tracks
        assert (track.odom_x_m, track.odom_y_m) == pytest.approx((2.0, 1.0), abs=1e-9)
        assert (track.x_m, track.y_m) == pytest.approx(in_laser((2.0, 1.0), turning[k]), abs=1e-9)


def turning_message(k: int, turning: list[Odometry]) -> Detections:
    """Scan k's detections of a still chair at (2, 1): the boxes of scan k-1, the odometry of scan k."""
    detections = message(k, [det(*in_laser((2.0, 1.0), turning[k - 1]))], turning[k])
    return detections.model_copy(update={"pose_stamp_ns": T0_NS + (k - 1) * PERIOD_NS})


def test_a_middle_scan_whose_tensor_was_skipped_is_placed_with_an_interpolated_pose() -> None:
    """The detector drops a stale tensor now and then, and with it the pose of the scan that the
    next message's boxes belong to: it lies between the poses of the scans around it."""
    core = TrackerCore()
    turning = [pose(0.05 * k, 0.02 * k, 0.2 * k) for k in range(10)]  # steady: exact between scans
    core.update(message(0, [], turning[0]))
    for k in (1, 2, 3, 5, 6, 8, 9):  # tensors 4 and 7 were skipped
        out = core.update(turning_message(k, turning))
        assert out is not None
        (track,) = out.tracks
        assert (track.odom_x_m, track.odom_y_m) == pytest.approx((2.0, 1.0), abs=1e-9), k
    assert not core.counters.dropped


def test_boxes_with_no_pose_known_from_before_their_scan_open_no_track() -> None:
    """After a reset (or at start) the middle scan's pose is unknown, and the newest scan's would put
    the boxes where the robot's turn moved them: a track there would stand off its object."""
    core = TrackerCore()
    turning = [pose(0.05 * k, 0.0, 0.3 * k) for k in range(6)]
    first = core.update(turning_message(1, turning))
    assert first is not None and first.tracks == [] and first.frame == "odom"
    assert core.counters.dropped == {"unplaced": 1}
    for k in range(2, 6):
        out = core.update(turning_message(k, turning))
        assert out is not None
    (track,) = out.tracks
    assert (track.odom_x_m, track.odom_y_m) == pytest.approx((2.0, 1.0), abs=1e-9)
    assert track.hits == 4
    assert core.counters.published == core.counters.received == 5  # the unplaced one went out too


def test_one_desk_followed_by_two_tracks_keeps_the_older_and_close_people_stay_apart() -> None:
    """A big desk seen in part gives two boxes with their own centres; the second opens a track while
    the first is still tentative. Once both are established the younger is retired. Two chairs, and
    two people walking side by side, further apart than the duplicate radius stay two."""
    core = TrackerCore()
    still = pose(0.0, 0.0, 0.0)
    first = core.update(message(0, [det(2.0, 1.0, "desk")], still))
    assert first is not None
    (desk_id,) = [t.track_id for t in first.tracks]
    for k in range(1, 6):
        dets = [det(2.0, 1.0, "desk"), det(2.0, 0.5, "desk"), det(0.0, 2.0, "chair"), det(0.7, 2.0, "chair")]
        people = [det(1.0, -1.0 + 0.1 * k, "person"), det(1.7, -1.0 + 0.1 * k, "person")]
        out = core.update(message(k, dets + people, still))
        assert out is not None
    confirmed = [t for t in out.tracks if t.state == "confirmed"]
    assert [t.track_id for t in confirmed if t.class_name == "desk"] == [desk_id]
    assert len([t for t in confirmed if t.class_name == "chair"]) == 2
    assert len([t for t in confirmed if t.class_name == "person"]) == 2
    assert core.counters.tracks_merged == 1


def test_a_second_detection_of_a_tracked_object_opens_no_track() -> None:
    core = TrackerCore(TrackerConfig(duplicate_m=0.4))
    for k in range(4):
        out = core.update(message(k, [det(2.0, 0.0, "doorframe")], pose(0, 0, 0)))
    doubled = core.update(message(4, [det(2.0, 0.0, "doorframe"), det(2.1, 0.2, "doorframe")], pose(0, 0, 0)))
    assert out is not None and doubled is not None and len(doubled.tracks) == 1
    assert core.counters.duplicates == 1 and core.counters.tracks_created == 1
    # a person beside a chair is no duplicate of it: another group
    person = core.update(message(5, [det(2.0, 0.0, "doorframe"), det(2.1, 0.2, "person")], pose(0, 0, 0)))
    assert person is not None and core.counters.tracks_created == 2


def test_a_second_detection_within_the_duplicate_radius_is_one_object_for_every_class() -> None:
    core = TrackerCore()  # the default radius, 0.6 m
    for k in range(4):
        core.update(message(k, [det(2.0, 0.0, "desk"), det(0.0, 2.0, "person")], pose(0, 0, 0)))
    assert core.counters.tracks_created == 2
    both = [det(2.0, 0.0, "desk"), det(2.0, 0.5, "desk"), det(0.0, 2.0, "person"), det(0.5, 2.0, "person")]
    core.update(message(4, both, pose(0, 0, 0)))
    assert core.counters.duplicates == 2  # the second desk, and a person's second detection (a long stride)
    assert core.counters.tracks_created == 2
    apart = [det(2.0, 0.0, "desk"), det(0.0, 2.0, "person"), det(0.8, 2.0, "person")]
    core.update(message(5, apart, pose(0, 0, 0)))
    assert core.counters.tracks_created == 3  # 0.8 m off is someone else


def test_a_person_seen_twice_in_one_scan_opens_one_track_and_the_better_detection_leads_it() -> None:
    """A newcomer detected twice in one scan, a second box beside the first, is one person: the weaker
    detection opens no second track to take turns with the first, and the track follows the better
    box wherever it is listed. Of two equal boxes the earlier counts. Someone further off than the
    duplicate radius is someone else."""
    core = TrackerCore()  # the default radius, 0.6 m
    for k in range(5):
        lesser, better = det(1.0, 2.0, "person", 0.3), det(1.4, 2.0, "person", 0.8)
        out = core.update(message(k, [lesser, better, det(1.0, -1.0, "person")], pose(0, 0, 0)))
        assert out is not None
    people = [t for t in out.tracks if t.class_name == "person"]
    assert len(people) == 2 and all(t.state == "confirmed" for t in people)
    assert core.counters.tracks_created == 2
    assert core.counters.duplicates == 5
    (seen_twice,) = [t for t in people if t.y_m > 0]
    assert seen_twice.x_m == pytest.approx(1.4, abs=1e-6) and seen_twice.score == pytest.approx(0.8)
    tie = TrackerCore()
    for k in range(3):
        out = tie.update(message(k, [det(2.0, 1.0, "person"), det(2.3, 1.0, "person")], pose(0, 0, 0)))
    assert out is not None and [t.x_m for t in out.tracks] == [pytest.approx(2.0, abs=1e-6)]


def test_two_people_together_share_one_track_and_the_other_takes_their_id_back_when_they_part() -> None:
    """Closer than the duplicate radius, the person whose detections score lower is not followed: their
    track coasts, leaves the message and ends. When they part, their new track takes that id back."""
    core = TrackerCore()
    ys = [1.6] * 10 + [1.6 - 0.115 * i for i in range(1, 11)] + [0.45] * 30
    ys += [0.45 + 0.115 * i for i in range(1, 11)] + [1.6] * 5
    shown: list[list[int]] = []
    for k, y in enumerate(ys):
        dets = [det(2.0, 0.0, "person", 0.9), det(2.0, y, "person", 0.6)]
        out = core.update(message(k, dets, pose(0, 0, 0)))
        assert out is not None
        shown.append(sorted(t.track_id for t in out.tracks if t.state != "tentative"))
    first = shown[9]
    assert len(first) == 2
    assert shown[45] == [first[0]]  # together: only the better-seen person's track is reported
    assert shown[-1] == first and core.counters.tracks_resumed == 1


@pytest.mark.parametrize("penalty", [0.05, 0.0])
def test_a_detection_both_could_take_goes_to_the_track_that_followed_its_person(penalty: float) -> None:
    """A walker reaches the spot where a lost person's track coasts, standing: the detection lies
    nearer that track's prediction than the walker's own, yet the walker's track, which followed them
    a scan ago, takes it (``person_coast_penalty_m``); without the penalty the lost track takes the
    walker for a scan, and hands them back: two ID switches to any consumer."""
    core = TrackerCore(TrackerConfig(person_coast_penalty_m=penalty))
    owners = []
    for k in range(14):
        dets = [det(2.0, 0.1 * k, "person")] + ([det(2.0, 1.0, "person")] if k < 5 else [])
        out = core.update(message(k, dets, pose(0, 0, 0)))
        assert out is not None
        owners.append({t.track_id for t in out.tracks if t.misses == 0 and abs(t.y_m - 0.1 * k) < 0.05})
    walker = owners[4]
    assert len(walker) == 1
    assert (owners[10] == walker) is (penalty > 0)
    assert owners[13] == walker


def test_with_a_travel_rule_only_a_person_who_moves_is_confirmed() -> None:
    """leg_tracker's rule, opt-in: a still person-like cluster stays tentative however often it is seen,
    a walker is confirmed once it has moved far enough, and furniture is confirmed as before."""
    core = TrackerCore(TrackerConfig(person_confirm_travel_m=0.5))
    states: dict[str, list[str]] = {"still": [], "walker": [], "chair": []}
    for k in range(20):
        walker = (1.0 + 0.1 * k, -1.0)  # 1 m/s at 10 Hz
        dets = [det(2.0, 2.0, "person"), det(*walker, "person"), det(-2.0, 0.0, "chair")]
        tracks = core.update(message(k, dets, pose(0, 0, 0)))
        assert tracks is not None
        for t in tracks.tracks:
            name = (
                "chair" if t.class_name == "chair" else ("still" if t.x_m > 1.5 and t.y_m > 1.5 else "walker")
            )
            states[name].append(t.state)
    assert set(states["still"]) == {"tentative"} and len(states["still"]) == 20
    assert states["chair"][2] == "confirmed"  # the third hit, as without the rule
    first = states["walker"].index("confirmed")
    assert 5 <= first <= 8 and set(states["walker"][first:]) == {"confirmed"}  # after about 0.5 m
    default = TrackerCore()
    for k in range(3):
        tracks = default.update(message(k, [det(2.0, 2.0, "person")], pose(0, 0, 0)))
    assert tracks is not None and tracks.tracks[0].state == "confirmed"  # off by default
    for bad in (-1.0, math.nan):
        with pytest.raises(ValueError, match="person confirm travel must be >= 0 metres"):
            TrackerConfig(person_confirm_travel_m=bad)


def test_a_tentative_track_dies_quickly_and_ids_are_never_reused() -> None:
    core = TrackerCore(TrackerConfig(tentative_misses=1))
    first = core.update(message(0, [det(1.0, 1.0)]))
    assert first is not None and first.tracks[0].track_id == 1
    empty = core.update(message(1, []))
    assert empty is not None and empty.tracks == []
    again = core.update(message(2, [det(1.0, 1.0)]))
    assert again is not None and again.tracks[0].track_id == 2


def test_gated_assignment_keeps_two_close_objects_apart_and_refuses_far_jumps() -> None:
    core = TrackerCore(TrackerConfig(gate_m=0.8))
    for k in range(5):
        out = core.update(message(k, [det(1.0, 0.0, "chair"), det(1.0, 0.6, "box")], pose(0, 0, 0)))
    assert out is not None
    ids = {t.class_name: t.track_id for t in out.tracks}
    swapped = core.update(message(5, [det(1.0, 0.55, "box"), det(1.0, 0.05, "chair")], pose(0, 0, 0)))
    assert swapped is not None
    assert {t.class_name: t.track_id for t in swapped.tracks if t.misses == 0} == ids
    far = core.update(message(6, [det(3.0, 0.0, "chair"), det(1.0, 0.6, "box")], pose(0, 0, 0)))
    assert far is not None
    assert len(far.tracks) == 3 and core.counters.tracks_created == 3  # 2 m away: a new object, not a jump


def test_a_class_flicker_continues_the_track_and_the_class_is_smoothed() -> None:
    core = TrackerCore()
    for k in range(6):
        out = core.update(message(k, [det(2.0, 0.0, "box" if k == 4 else "chair")]))
    assert out is not None and len(out.tracks) == 1
    assert out.tracks[0].class_name == "chair" and out.tracks[0].hits == 6


def test_a_track_first_seen_as_a_walking_person_that_turns_out_a_box_stops_where_the_box_is() -> None:
    """Its velocity, learnt while it was a walking person, starts afresh when it becomes furniture:
    coasting, the box stays where it was seen rather than walking on."""
    core = TrackerCore()
    still = pose(0, 0, 0)
    for k in range(3):  # a person detection walking at 1 m/s, then the box it was
        core.update(message(k, [det(2.0 + 0.1 * k, 0.0, "person", 0.5)], still))
    for k in range(3, 12):
        out = core.update(message(k, [det(2.2, 0.0, "box")], still))
    assert out is not None and [t.class_name for t in out.tracks] == ["box"]
    for k in range(12, 24):  # out of sight for 1.2 s
        out = core.update(message(k, [], still))
    assert out is not None
    (box,) = out.tracks
    assert box.state == "coasting" and (box.odom_x_m, box.odom_y_m) == pytest.approx((2.2, 0.0), abs=0.05)
    assert math.hypot(box.vx_mps, box.vy_mps) < 0.02


# -- bad input -------------------------------------------------------------------------------------


def test_an_odometry_jump_or_reset_resets_only_that_robots_tracks() -> None:
    core = TrackerCore()
    for k in range(5):
        core.update(message(k, [det(2.0, 0.0)], pose(0.0, 0.0, 0.0)))
        core.update(message(k, [det(1.0, 0.0)], pose(0.0, 0.0, 0.0), robot="r2"))
    jumped = core.update(message(5, [det(2.0, 0.0)], pose(1.5, 0.0, 0.0)))
    assert jumped is not None and [t.state for t in jumped.tracks] == ["tentative"]
    turned = core.update(message(6, [det(2.0, 0.0)], pose(1.5, 0.0, math.radians(40))))
    assert turned is not None and [t.hits for t in turned.tracks] == [1]
    renamed = core.update(message(7, [det(2.0, 0.0)], pose(1.5, 0.0, math.radians(40), frame="odom2")))
    assert renamed is not None and [t.hits for t in renamed.tracks] == [1]
    small = core.update(message(8, [det(2.0, 0.0)], pose(1.6, 0.0, math.radians(45), frame="odom2")))
    assert small is not None and [t.hits for t in small.tracks] == [2]
    other = core.update(message(5, [det(1.0, 0.0)], pose(0.0, 0.0, 0.0), robot="r2"))
    assert other is not None and [t.hits for t in other.tracks] == [6]
    assert core.counters.resets == {"odom_jump": 2, "odom_reset": 1}
    assert not core.counters.dropped and not core.counters.rejected


def test_nan_odometry_is_refused_and_the_last_pose_stands_in() -> None:
    core = TrackerCore()
    for k in range(4):
        core.update(message(k, [det(2.0, 0.0)], pose(0.5, 0.0, 0.0)))
    nan = Odometry(x_m=float("nan"), y_m=0.0, yaw_rad=0.0, stamp_ns=0)
    out = core.update(message(4, [det(2.0, 0.0)], nan))
    missing = core.update(message(5, [det(2.0, 0.0)]))
    assert out is not None and missing is not None and missing.frame == "odom"
    (track,) = missing.tracks
    assert track.hits == 6 and track.odom_x_m == pytest.approx(2.5)
    assert core.counters.odom_refused == {"not_finite": 1, "missing": 1} and not core.counters.resets


def test_out_of_order_detections_are_dropped_and_a_restart_resets() -> None:
    core = TrackerCore()
    for k in range(3):
        core.update(message(k, [det(2.0, 0.0)]))
    assert core.update(message(1, [det(2.0, 0.0)])) is None
    assert core.update(message(2, [det(2.0, 0.0)])) is None  # a duplicate
    restarted = core.update(message(0, [det(2.0, 0.0)], stamp=T0_NS + 10 * PERIOD_NS))
    assert restarted is not None and restarted.tracks[0].hits == 1
    assert core.counters.dropped == {"out_of_order": 2} and core.counters.resets == {"restart": 1}
    assert core.counters.published == 4 and core.counters.received == 6


def test_odometry_arriving_resets_laser_frame_tracks() -> None:
    core = TrackerCore()
    core.update(message(0, [det(2.0, 0.0)]))
    out = core.update(message(1, [det(2.0, 0.0)], pose(0.0, 0.0, 0.0)))
    assert out is not None and out.frame == "odom" and out.tracks[0].hits == 1
    assert core.counters.resets == {"frame_change": 1}


def test_a_forgotten_robots_tracks_are_dropped_and_its_ids_not_reused() -> None:
    clock = FakeClock()
    core = TrackerCore(forget_after_s=10.0, clock=clock)
    core.update(message(0, [det(2.0, 0.0), det(1.0, 1.0)], robot="r1"))
    clock.now = 5.0
    core.update(message(0, [det(2.0, 0.0)], robot="r2"))
    clock.now = 12.0
    assert core.forget_silent() == ["r1"] and core.robot_ids == ["r2"]
    assert core.counters.forgotten_robots == 1 and core.counters.tracks_forgotten == 2
    back = core.update(message(50, [det(2.0, 0.0)], robot="r1"))
    assert back is not None and back.tracks[0].track_id == 4


def test_bad_samples_are_counted_by_reason_and_good_ones_still_served() -> None:
    core = TrackerCore()
    good = encode_message(message(0, [det(2.0, 0.0)]))
    assert core.handle_sample("triscan/r1/nope", good) is None
    assert core.handle_sample(detections_key("r1"), b"\xc1") is None
    assert core.handle_sample(detections_key("r2"), good) is None
    served = core.handle_sample(detections_key("r1"), good)
    assert served is not None and len(served.tracks) == 1
    assert core.counters.rejected == {"bad_key": 1, "not_msgpack": 1, "robot_id_mismatch": 1}
    snapshot = core.snapshot()
    assert snapshot["received"] == 4 and snapshot["published"] == 1 and snapshot["tracks"] == 1


def test_triscan_status_shows_the_trackers_counters() -> None:
    from services.status import ServiceStatus, format_status

    core = TrackerCore()
    core.update(message(0, [det(2.0, 0.0)], pose(0.0, 0.0, 0.0)))
    core.update(message(1, [det(2.0, 0.0)], pose(2.0, 0.0, 0.0)))
    line = format_status([ServiceStatus("tracker", "123", True, core.snapshot())])
    assert line.startswith("tracker") and "resets.odom_jump=1" in line and "tracks=1" in line


@pytest.mark.parametrize(("decay_s", "same_id"), [(0.2, True), (0.0, False)])
def test_a_person_who_stops_out_of_sight_keeps_their_id_while_their_track_slows(
    decay_s: float, same_id: bool
) -> None:
    """1.4 m/s for 1.5 s, then unseen for 0.9 s while they stop, then seen where they stopped: a track
    that walked on at full speed would be about 1.3 m off, past the 0.8 m gate; with the default's
    0.2 s decay (from the second missed scan on) it is about 0.35 m off."""
    core = TrackerCore(TrackerConfig(person_coast_decay_s=decay_s))
    walk = [message(k, [det(1.0 + 0.14 * k, 0.0, "person")], pose(0, 0, 0)) for k in range(15)]
    for m in walk:
        out = core.update(m)
    assert out is not None
    ((first_id, vx),) = [(t.track_id, t.vx_mps) for t in out.tracks]
    assert vx == pytest.approx(1.4, abs=0.15)
    for k in range(15, 23):
        core.update(message(k, [], pose(0, 0, 0)))
    back = core.update(message(23, [det(1.0 + 0.14 * 14, 0.0, "person")], pose(0, 0, 0)))
    assert back is not None
    assert (first_id in {t.track_id for t in back.tracks if t.misses == 0}) is same_id
    for bad in (-0.1, math.nan):
        with pytest.raises(ValueError, match="person coast decay must be >= 0 seconds"):
            TrackerConfig(person_coast_decay_s=bad)


def lose_and_find(core: TrackerCore, unseen: range, back_at: tuple[float, float]) -> tuple[int, Tracks]:
    """A person seen for 1 s at (2, 0), unseen over ``unseen``'s scans, then seen at ``back_at`` until
    a new track is confirmed: their first id and the message that confirms the new track."""
    for k in range(10):
        out = core.update(message(k, [det(2.0, 0.0, "person")], pose(0, 0, 0)))
    assert out is not None
    (first_id,) = [t.track_id for t in out.tracks]
    for k in unseen:
        core.update(message(k, [], pose(0, 0, 0)))
    k = unseen.stop
    while True:
        back = core.update(message(k, [det(*back_at, "person")], pose(0, 0, 0)))
        assert back is not None
        if any(t.state == "confirmed" for t in back.tracks):
            return first_id, back
        k += 1


@pytest.mark.parametrize(
    ("unseen", "back_at", "resumed"),
    [
        (range(10, 40), (2.5, 0.5), True),  # 3 s later, 0.7 m off: ended, its id taken back
        (range(10, 16), (3.3, 0.0), True),  # 0.6 s later, 1.3 m off: still coasting, retired
        (range(10, 40), (8.0, 0.0), False),  # 6 m off in 3 s: someone else
        (range(10, 180), (2.0, 0.0), False),  # 17 s later: past person_resume_s
    ],
)
def test_a_person_found_again_near_where_their_track_was_lost_gets_its_id_back(
    unseen: range, back_at: tuple[float, float], resumed: bool
) -> None:
    core = TrackerCore()
    first_id, back = lose_and_find(core, unseen, back_at)
    ids = [t.track_id for t in back.tracks]
    assert len(ids) == len(set(ids))  # a retired track is gone the scan its id is taken back
    (confirmed,) = [t for t in back.tracks if t.state == "confirmed"]
    assert (confirmed.track_id == first_id) is resumed
    assert core.counters.tracks_resumed == int(resumed)
    if resumed:  # the same track to a consumer: its age runs from the first sighting
        assert confirmed.age_s > (unseen.stop - 1) * PERIOD_NS / 1e9


def test_a_person_seen_beside_the_lost_one_and_a_switched_off_rule_take_no_id_back() -> None:
    first_id, back = lose_and_find(TrackerCore(TrackerConfig(person_resume_s=0.0)), range(10, 40), (2.2, 0.0))
    assert [t.track_id for t in back.tracks if t.state == "confirmed"] != [first_id]
    core = TrackerCore()  # A at (2, 0); in scan 10 someone else at (2.7, 0) too, then only they are seen
    for k in range(10):
        core.update(message(k, [det(2.0, 0.0, "person")], pose(0, 0, 0)))
    core.update(message(10, [det(2.0, 0.0, "person"), det(2.7, 0.0, "person")], pose(0, 0, 0)))
    for k in range(11, 14):
        out = core.update(message(k, [det(2.7, 0.0, "person")], pose(0, 0, 0)))
    assert out is not None and core.counters.tracks_resumed == 0
    assert sorted(t.track_id for t in out.tracks) == [1, 2]  # A coasting beside the newcomer
    core = TrackerCore(TrackerConfig(delete_after_s=0.5, still_delete_after_s=0.5))
    for k in range(10):
        core.update(message(k, [det(2.0, 0.0, "chair")], pose(0, 0, 0)))
    for k in range(10, 20):
        core.update(message(k, [], pose(0, 0, 0)))
    for k in range(20, 25):
        out = core.update(message(k, [det(2.0, 0.0, "chair")], pose(0, 0, 0)))
    assert out is not None and [t.track_id for t in out.tracks] == [2] and core.counters.tracks_resumed == 0


def test_furniture_found_where_a_person_was_lost_takes_no_id() -> None:
    core = TrackerCore()
    for k in range(10):
        core.update(message(k, [det(2.0, 0.0, "person"), det(0.0, 2.0, "box")], pose(0, 0, 0)))
    for k in range(10, 40):  # both gone for 3 s: the person's track ends, the box's is kept, hidden
        core.update(message(k, [], pose(0, 0, 0)))
    for k in range(40, 45):  # a box where the person was
        out = core.update(message(k, [det(2.0, 0.0, "box")], pose(0, 0, 0)))
    assert out is not None and core.counters.tracks_resumed == 0
    assert [t.track_id for t in out.tracks] == [3]


def test_with_one_hit_to_confirm_two_newcomers_never_share_a_lost_persons_id() -> None:
    core = TrackerCore(TrackerConfig(confirm_hits=1, person_confirm_hits=1, delete_after_s=0.5))
    for k in range(10):
        core.update(message(k, [det(2.0, 0.0, "person")], pose(0, 0, 0)))
    for k in range(10, 15):
        core.update(message(k, [], pose(0, 0, 0)))
    out = core.update(message(15, [det(3.0, 0.0, "person"), det(2.0, 1.0, "person")], pose(0, 0, 0)))
    assert out is not None
    ids = [t.track_id for t in out.tracks]
    assert len(ids) == 2 and len(set(ids)) == 2 and core.counters.tracks_resumed == 1


@pytest.mark.parametrize("bad", [0, 2.0, True])
def test_a_person_confirm_hits_that_is_no_whole_number_of_at_least_one_is_refused(bad: float) -> None:
    with pytest.raises(ValueError, match="person confirm hits must be a whole number >= 1"):
        TrackerConfig(person_confirm_hits=bad)  # type: ignore[arg-type]


@pytest.mark.parametrize("bad", [-0.1, math.nan, math.inf])
def test_a_person_coast_penalty_that_is_no_finite_distance_is_refused(bad: float) -> None:
    with pytest.raises(ValueError, match="person coast penalty must be finite and >= 0 metres"):
        TrackerConfig(person_coast_penalty_m=bad)


@pytest.mark.parametrize(
    "bad", [{"person_resume_s": -1.0}, {"person_resume_speed_mps": math.nan}, {"person_resume_s": math.inf}]
)
def test_a_person_resume_rule_that_is_no_finite_number_is_refused(bad: dict[str, float]) -> None:
    with pytest.raises(ValueError, match="person resume must be finite and >= 0"):
        TrackerConfig(**bad)  # type: ignore[arg-type]


def test_every_rule_given_to_triscan_up_reaches_the_tracker_as_its_flags_parse_it() -> None:
    """``triscan up`` hands its tracker rules on as flags: each must parse back to the value given, a
    numpy float and an int for a float rule included."""
    given = {
        "person_confirm_travel_m": np.float64(0.5),
        "person_confirm_hits": 4,
        "person_coast_penalty_m": 0.1,
        "person_resume_s": 5,
        "person_show_coast_s": 1.25,
        "person_show_coast_share": 0.2,
    }
    assert set(given) == set(RULE_FLAGS)
    parser = argparse.ArgumentParser()
    add_tracker_arguments(parser)
    parsed = rules_of(parser.parse_args(rule_flags(given)))
    assert parsed == given and type(parsed["person_confirm_hits"]) is int
    assert TrackerConfig(**parsed).person_confirm_hits == 4  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"--person-confirm-hits takes a whole number, got 2\.5"):
        rule_flags({"person_confirm_hits": 2.5})
