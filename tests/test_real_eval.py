"""``triscan eval --bag``: DR-SPAAM's person metric on hand-computed runs, leg hits, label pairing, a
synthetic bag end to end, one-line refusals, and (slow) a real recording of the development set."""

from __future__ import annotations

import json
import math
import os
from collections import Counter
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from common.inference import OnnxDetector
from common.model_spec import CLASS_NAMES, META_CLASSES, SHIPPED_MODEL
from services.cli import main as cli_main
from training.real_eval import (
    LEG_TRACKER_WINDOWS,
    PERSON_ID,
    BagEvalConfig,
    FrameDetections,
    Positions,
    RealEvalError,
    Scope,
    detector_for,
    evaluate_bag,
    leg_hits,
    narrowed,
    pair_labels,
    positions_of,
    precision_recall_curve,
    within_radius,
)

# The development set beside the checkout (CI has ../shared next to its clone); TRISCAN_REAL_DATA
# points elsewhere, e.g. from a git worktree.
ROOT = Path(__file__).resolve().parents[1]
REAL = Path(os.environ.get("TRISCAN_REAL_DATA", ROOT.parent / "shared" / "real" / "leg_tracker"))
T0_NS = 1_700_000_000_000_000_000
PERIOD_NS = 100_000_000


def frame(dets: list[tuple[float, float, float]], people: list[tuple[float, float]]) -> FrameDetections:
    """A frame from (score, x, y) detections and (x, y) people."""
    d = np.array(dets, dtype=np.float64).reshape(-1, 3)
    return FrameDetections(d[:, 0], d[:, 1:], np.array(people, dtype=np.float64).reshape(-1, 2))


# --------------------------------------------------------------------------------------------------
# DR-SPAAM's curve, AP and peak F1
# --------------------------------------------------------------------------------------------------


def test_curve_ap_and_peak_f1_of_a_hand_computed_run() -> None:
    # Two frames, one person each. 0.9 finds frame 0's person, 0.8 is a false alarm, 0.7 finds frame 1's.
    frames = [frame([(0.9, 1.0, 0.1)], [(1.0, 0.0)]), frame([(0.8, 3.0, 0.0), (0.7, 2.1, 2.0)], [(2.0, 2.0)])]
    curve = precision_recall_curve(frames, 0.3)
    np.testing.assert_allclose(curve.thresholds, [0.9, 0.8, 0.7])
    np.testing.assert_allclose(curve.recalls, [0.5, 0.5, 1.0])
    np.testing.assert_allclose(curve.precisions, [1.0, 0.5, 2 / 3])
    # Trapezoids between the curve's points: 0 from (0.5, 1) to (0.5, 0.5), then (0.5 + 2/3) / 2 · 0.5.
    assert curve.ap == pytest.approx((0.5 + 2 / 3) / 2 * 0.5)
    assert curve.peak_f1 == pytest.approx(0.8)  # at recall 1, precision 2/3
    # At 0.05 m nothing matches: recall and precision stay 0.
    tight = precision_recall_curve(frames, 0.05)
    assert (tight.ap, tight.peak_f1) == (0.0, 0.0)


def test_matching_is_optimal_not_greedy() -> None:
    # The best detection lies within 0.3 m of both people, the second only of the first person: a
    # greedy nearest match gives the first person to the best one and leaves one miss; the Hungarian
    # assignment finds both. The curve starts at the first detection's recall (as sklearn's auc).
    frames = [frame([(0.9, 0.25, 0.0), (0.8, -0.2, 0.0)], [(0.0, 0.0), (0.5, 0.0)])]
    curve = precision_recall_curve(frames, 0.3)
    np.testing.assert_allclose(curve.recalls, [0.5, 1.0])
    np.testing.assert_allclose(curve.precisions, [1.0, 1.0])
    assert (curve.ap, curve.peak_f1) == (pytest.approx(0.5), pytest.approx(1.0))


def test_a_detection_exactly_at_the_radius_matches_and_one_beyond_does_not() -> None:
    assert within_radius(np.array([[0.5, 0.0]]), np.array([[0.0, 0.0]]), 0.5).all()
    assert not within_radius(np.array([[0.5001, 0.0]]), np.array([[0.0, 0.0]]), 0.5).any()
    # On the curve: a lone detection 0.5 m from a lone person is found at r = 0.5 (precision = recall
    # = 1) and missed at r = 0.4999 (both 0).
    at_radius = [frame([(0.9, 0.5, 0.0)], [(0.0, 0.0)])]
    assert precision_recall_curve(at_radius, 0.5).peak_f1 == pytest.approx(1.0)
    assert precision_recall_curve(at_radius, 0.4999).peak_f1 == 0.0


def test_detections_in_frames_without_people_are_false_alarms_and_ties_go_later_first() -> None:
    # Equal scores: DR-SPAAM walks its stable ascending sort backwards, so the later detection first.
    frames = [frame([(0.5, 1.0, 0.0)], [(1.0, 0.0)]), frame([(0.5, 9.0, 9.0)], [])]
    curve = precision_recall_curve(frames, 0.3)
    np.testing.assert_allclose(curve.recalls, [0.0, 1.0])
    np.testing.assert_allclose(curve.precisions, [0.0, 0.5])
    assert curve.ap == pytest.approx(0.25)


def test_runs_without_detections_or_without_people() -> None:
    no_detections = precision_recall_curve([frame([], [(1.0, 0.0)])], 0.5)
    assert (no_detections.ap, no_detections.peak_f1) == (0.0, 0.0)
    no_people = precision_recall_curve([frame([(0.9, 1.0, 0.0)], [])], 0.5)
    assert (no_people.ap, no_people.peak_f1) == (None, None)
    assert precision_recall_curve([], 0.5).ap is None


def test_a_later_detection_reassigns_the_earlier_ones_along_a_chain() -> None:
    # Frame 0: people A (0, 0), B (0.5, 0), C (1, 0). Frame 1: person D (3, 3). Four people in all.
    #   0.9 at (0.25, 0):  0.25 m from A and B, 0.75 m from C
    #   0.8 at (0.75, 0):  0.25 m from B and C, 0.75 m from A
    #   0.7 at (3, 3.4):   0.40 m from D (frame 1)
    #   0.6 at (-0.1, 0):  0.10 m from A, 0.60 m from B
    #   0.3 at (1, 0.1):   0.10 m from C, 0.51 m from B
    # r = 0.3, accepted in score order (TP, precision, recall):
    #   0.9: A or B                                   1, 1/1, 1/4
    #   0.8: the other of A, B / C                    2, 2/2, 2/4
    #   0.7: D lies 0.4 m off: a false alarm          2, 2/3, 2/4
    #   0.6: only A; the optimum moves 0.9 to B and
    #        0.8 to C, so all three of frame 0 match  3, 3/4, 3/4
    #   0.3: only C, already taken: a false alarm     3, 3/5, 3/4
    # AP = 0.25 · 1 + 0 + 0.25 · (2/3 + 3/4) / 2 + 0 = 1/4 + 17/96 = 41/96.
    # F1 along the curve: 0.4, 2/3, 4/7, 3/4, 2/3 -> peak 3/4.
    # r = 0.5: D is found too, the 0.3 detection still only reaches C (0.51 m from B):
    #   TP 1, 2, 3, 4, 4; precision 1, 1, 1, 1, 4/5; recall 1/4, 2/4, 3/4, 1, 1.
    # AP = 3 · 0.25 · 1 = 0.75 (the curve starts at recall 1/4); peak F1 = 1.
    frames = [
        frame(
            [(0.9, 0.25, 0.0), (0.8, 0.75, 0.0), (0.6, -0.1, 0.0), (0.3, 1.0, 0.1)],
            [(0.0, 0.0), (0.5, 0.0), (1.0, 0.0)],
        ),
        frame([(0.7, 3.0, 3.4)], [(3.0, 3.0)]),
    ]
    tight = precision_recall_curve(frames, 0.3)
    np.testing.assert_allclose(tight.thresholds, [0.9, 0.8, 0.7, 0.6, 0.3])
    np.testing.assert_allclose(tight.precisions, [1.0, 1.0, 2 / 3, 3 / 4, 3 / 5])
    np.testing.assert_allclose(tight.recalls, [0.25, 0.5, 0.5, 0.75, 0.75])
    assert (tight.ap, tight.peak_f1) == (pytest.approx(41 / 96), pytest.approx(0.75))
    wide = precision_recall_curve(frames, 0.5)
    np.testing.assert_allclose(wide.precisions, [1.0, 1.0, 1.0, 1.0, 0.8])
    np.testing.assert_allclose(wide.recalls, [0.25, 0.5, 0.75, 1.0, 1.0])
    assert (wide.ap, wide.peak_f1) == (pytest.approx(0.75), pytest.approx(1.0))


def test_an_assigned_pair_beyond_the_radius_is_no_true_positive() -> None:
    # One person at (0, 0). The assignment pairs the 0.9 detection, 1 m off, with them (cost 1 is the
    # best there is), but it is a false alarm; the 0.5 detection 0.1 m off then takes the person.
    #   0.9: TP 0, precision 0, recall 0;   0.5: TP 1, precision 1/2, recall 1.
    # AP = the trapezoid from (0, 0) to (1, 1/2) = 1/4; peak F1 = 2 · 1/2 · 1 / (3/2) = 2/3.
    curve = precision_recall_curve([frame([(0.9, 1.0, 0.0), (0.5, 0.1, 0.0)], [(0.0, 0.0)])], 0.3)
    np.testing.assert_allclose(curve.precisions, [0.0, 0.5])
    np.testing.assert_allclose(curve.recalls, [0.0, 1.0])
    assert (curve.ap, curve.peak_f1) == (pytest.approx(0.25), pytest.approx(2 / 3))


# --------------------------------------------------------------------------------------------------
# Legs, scope, labels
# --------------------------------------------------------------------------------------------------


def test_leg_hits_count_legs_found_and_detections_on_legs() -> None:
    legs = np.array([[1.0, 0.1], [1.0, -0.1], [3.0, 0.0]])  # one person's two legs, a third leg far off
    dets = np.array([[1.15, 0.0], [2.0, 2.0]])  # one on the pair, one on nothing
    assert leg_hits(dets, legs) == (2, 1)
    assert leg_hits(np.zeros((0, 2)), legs) == (0, 0)
    assert leg_hits(dets, np.zeros((0, 2))) == (0, 0)


def test_scope_keeps_bearings_and_ranges_inside_and_intersects() -> None:
    scope = Scope(-15.0, 10.0, 4.0)
    points = np.array([[2.0, 0.0], [2.0, 2.0 * math.tan(math.radians(12))], [4.5, 0.0], [-1.0, 0.0]])
    assert scope.contains(points).tolist() == [True, False, False, False]
    assert Scope().within(LEG_TRACKER_WINDOWS["positive_4_extracted.bag"]) == Scope(-15.0, 10.0, 4.0)
    with pytest.raises(RealEvalError, match="bearing window"):
        Scope(10.0, -10.0)


def test_labels_pair_in_bag_order_without_stamps_and_by_nearest_stamp_with_them() -> None:
    scans = [T0_NS + k * PERIOD_NS for k in range(4)]
    xy = [np.full((1, 2), float(k)) for k in range(4)]
    by_order = pair_labels(scans, [Positions(0, "laser", p) for p in xy], "/legs")
    assert [float(by_order[s][0, 0]) for s in scans] == [0.0, 1.0, 2.0, 3.0]
    with pytest.raises(RealEvalError, match="cannot pair them in bag order"):
        pair_labels(scans, [Positions(0, "laser", p) for p in xy[:3]], "/legs")
    stamped = [Positions(scans[1] + PERIOD_NS // 3, "laser", xy[1]), Positions(scans[3] - 1, "laser", xy[3])]
    assert sorted(pair_labels(scans, stamped, "/people")) == [scans[1], scans[3]]
    with pytest.raises(RealEvalError, match="within half a scan interval"):
        pair_labels(scans, [Positions(scans[3] + 10 * PERIOD_NS, "laser", xy[0])], "/people")


def test_positions_of_pose_arrays_and_people_lists() -> None:
    def point(x: float, y: float) -> SimpleNamespace:
        return SimpleNamespace(x=x, y=y, z=0.0)

    poses = SimpleNamespace(poses=[SimpleNamespace(position=point(1.0, 2.0))])
    people = SimpleNamespace(people=[SimpleNamespace(pos=point(3.0, 4.0))])
    np.testing.assert_array_equal(positions_of(poses, "/t"), [[1.0, 2.0]])
    np.testing.assert_array_equal(positions_of(people, "/t"), [[3.0, 4.0]])
    with pytest.raises(RealEvalError, match="no positions"):
        positions_of(SimpleNamespace(data="hi", __msgtype__="std_msgs/msg/String"), "/t")


# --------------------------------------------------------------------------------------------------
# A synthetic bag end to end
# --------------------------------------------------------------------------------------------------


def person_model(path: Path, raster_yaw_deg: float = 0.0) -> Path:
    """A 5-class constant model: one person box at bearing 0.5°, 1.9–2.1 m, score 0.9, every frame; with
    a raster yaw, the box sits where that yaw puts bearing 0.5° (column 180 for 180°)."""
    from common.model_spec import META_RASTER_YAW
    from tests.test_inference import constant_model, raw_output

    rows = (2.0 * 63 / 4) - 1.5, (2.0 * 63 / 4) + 1.5  # a box 3 rows tall centred on 2 m
    anchor = (1.0 + raster_yaw_deg, sum(rows) / 2, 2.0, rows[1] - rows[0], [0.0, 0.0, 0.0, 0.0, 0.9])
    metadata = {META_CLASSES: json.dumps(list(CLASS_NAMES))}
    if raster_yaw_deg:
        metadata[META_RASTER_YAW] = repr(raster_yaw_deg)
    return constant_model(path, raw_output([anchor], total=504), metadata=metadata)


def write_bag(
    path: Path,
    people: list[list[tuple[float, float]]],
    *,
    beams: int = 360,
    fov: float = 2 * math.pi,
    odom_x: list[float] | None = None,
) -> Path:
    """A ROS 1 bag: len(people) scans on /scan, PERIOD_NS apart, and a stamped /people PoseArray each;
    with ``odom_x``, an /odom pose at that x just before each scan."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    t = store.types

    def header(k: int) -> Any:
        sec, nanosec = divmod(T0_NS + k * PERIOD_NS, 10**9)
        stamp = t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
        return t["std_msgs/msg/Header"](seq=k, stamp=stamp, frame_id="laser")

    def pose(x: float, y: float) -> Any:
        return t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        )

    with Writer(path) as writer:
        scan_conn = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=store)
        people_conn = writer.add_connection("/people", "geometry_msgs/msg/PoseArray", typestore=store)
        odom_conn = (
            writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=store) if odom_x else None
        )
        for k, persons in enumerate(people):
            if odom_conn is not None and odom_x is not None:
                odometry = t["nav_msgs/msg/Odometry"](
                    header=header(k),
                    child_frame_id="base_link",
                    pose=t["geometry_msgs/msg/PoseWithCovariance"](
                        pose=pose(odom_x[k], 0.0), covariance=np.zeros(36)
                    ),
                    twist=t["geometry_msgs/msg/TwistWithCovariance"](
                        twist=t["geometry_msgs/msg/Twist"](
                            linear=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                            angular=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                        ),
                        covariance=np.zeros(36),
                    ),
                )
                writer.write(
                    odom_conn,
                    T0_NS + k * PERIOD_NS - 1,
                    store.serialize_ros1(odometry, "nav_msgs/msg/Odometry"),
                )
            increment = fov / beams
            scan = t["sensor_msgs/msg/LaserScan"](
                header=header(k),
                angle_min=-fov / 2,
                angle_max=-fov / 2 + increment * (beams - 1),
                angle_increment=increment,
                time_increment=0.0,
                scan_time=0.1,
                range_min=0.1,
                range_max=8.0,
                ranges=np.full(beams, 3.0, np.float32),
                intensities=np.zeros(0, np.float32),
            )
            writer.write(
                scan_conn, T0_NS + k * PERIOD_NS, store.serialize_ros1(scan, "sensor_msgs/msg/LaserScan")
            )
            poses = t["geometry_msgs/msg/PoseArray"](header=header(k), poses=[pose(*p) for p in persons])
            writer.write(
                people_conn,
                T0_NS + k * PERIOD_NS + 1,
                store.serialize_ros1(poses, "geometry_msgs/msg/PoseArray"),
            )
    return path


def test_a_bag_is_scored_on_each_tensors_middle_scan(tmp_path: Path) -> None:
    pytest.importorskip("rosbags")
    detector = detector_for(person_model(tmp_path / "person.onnx"))
    # Five scans make three tensors, for middle scans 1, 2 and 3. The person stands at the detection
    # in scan 1 only: a tensor scored against its newest scan would never meet them.
    people = [[(2.0, 0.0)], [(2.0, 0.0)], [], [(5.0, 5.0)], [(2.0, 0.0)]]
    report = evaluate_bag(
        detector, BagEvalConfig(write_bag(tmp_path / "walk.bag", people), people_topic="/people")
    )
    assert (report.scans, report.tensors, report.has_person_class) == (5, 3, True)
    assert report.people is not None
    assert (report.people["frames"], report.people["people"]) == (3, 1)  # (5, 5) lies beyond 4 m
    # Equal scores, later frames first: two false alarms (recall 0), then the hit (recall 1, precision 1/3).
    assert report.people["r0.3"] == {"ap": pytest.approx(1 / 6), "peak_f1": pytest.approx(0.5)}
    assert report.detections["person"] == 3
    assert report.person_by_range_m is not None and sum(report.person_by_range_m.values()) == 3
    assert report.person_by_range_m["0-1"] == report.person_by_range_m["3-4"] == 0  # the one at 2 m
    assert report.per_minute["person"] == pytest.approx(3 / (3 * PERIOD_NS / 60e9))
    assert report.skipped == {"people_scans_without_tensor": 2}
    behind = evaluate_bag(
        detector,
        BagEvalConfig(
            tmp_path / "walk.bag", people_topic="/people", scope=Scope(90.0, 180.0), people_free=True
        ),
    )
    assert behind.detections["person"] == 0 and behind.false_people_per_minute == 0.0


def test_a_bags_odometry_tells_the_detector_whether_the_robot_stood(tmp_path: Path) -> None:
    pytest.importorskip("rosbags")
    asked: list[bool | None] = []

    class Recording(OnnxDetector):
        def detect_boxes(self, tensor: np.ndarray, still: bool | None = None) -> Any:
            asked.append(still)
            return super().detect_boxes(tensor, still)

    detector = Recording(person_model(tmp_path / "person.onnx"), conf_threshold=0.001)
    # Scans 0-2 and 1-3 stand; the robot moves 10 cm before scan 4; a bag without odometry says nothing.
    bag = write_bag(tmp_path / "odom.bag", [[]] * 5, odom_x=[1.0, 1.0, 1.0, 1.0, 1.1])
    evaluate_bag(detector, BagEvalConfig(bag, people_topic="/people"))
    assert asked == [True, True, False]
    asked.clear()
    evaluate_bag(detector, BagEvalConfig(write_bag(tmp_path / "plain.bag", [[]] * 4), people_topic="/people"))
    assert asked == [None, None]


def test_a_model_with_a_raster_yaw_scores_the_same_people_in_the_laser_frame(tmp_path: Path) -> None:
    pytest.importorskip("rosbags")
    people = [[(2.0, 0.0)], [(2.0, 0.0)], [], [(5.0, 5.0)], [(2.0, 0.0)]]
    config = BagEvalConfig(write_bag(tmp_path / "walk.bag", people), people_topic="/people")
    plain = evaluate_bag(detector_for(person_model(tmp_path / "plain.onnx")), config)
    turned_detector = detector_for(person_model(tmp_path / "turned.onnx", raster_yaw_deg=180.0))
    assert turned_detector.raster_yaw_deg == 180.0
    turned = evaluate_bag(turned_detector, config)
    assert turned.people == plain.people and turned.detections == plain.detections
    assert turned.people is not None and turned.people["r0.3"]["ap"] == pytest.approx(1 / 6)
    # Its box is at column 180 of its raster, its detection ahead of the robot, as the plain model's.
    from training.real_eval import _load, middle_scan_detections

    scans = _load(config).stream
    _, found = next(middle_scan_detections(turned_detector, scans, 0.25, Counter()))
    _, expected = next(middle_scan_detections(detector_for(tmp_path / "plain.onnx"), scans, 0.25, Counter()))
    assert found[0].box_px[0] == pytest.approx(180.0) and expected[0].box_px[0] == pytest.approx(0.0)
    for field in ("bearing_deg", "bearing_min_deg", "bearing_max_deg", "x_m", "y_m"):
        assert getattr(found[0], field) == pytest.approx(getattr(expected[0], field), abs=1e-9)
    assert found[0].x_m == pytest.approx(2.0, abs=0.01) and abs(found[0].y_m) < 0.05


def test_another_beam_geometry_works(tmp_path: Path) -> None:
    pytest.importorskip("rosbags")
    bag = write_bag(tmp_path / "narrow.bag", [[(2.0, 0.0)]] * 4, beams=97, fov=math.radians(100))
    report = evaluate_bag(
        detector_for(person_model(tmp_path / "p.onnx")), BagEvalConfig(bag, people_topic="/people")
    )
    assert report.tensors == 2 and report.people is not None
    assert report.people["r0.5"]["peak_f1"] == pytest.approx(1.0)


def test_a_narrower_field_of_view_keeps_the_forward_beams_at_their_bearings() -> None:
    from common.messages import Scan

    step = math.radians(270.0) / 768
    ranges = np.arange(768, dtype=np.float32) / 100.0 + 0.5
    scan = Scan(
        robot_id="r", seq=0, stamp_ns=1, angle_min=-math.radians(135.0), angle_increment=step,
        range_min=0.02, range_max=11.0, ranges=ranges,
    )  # fmt: skip
    narrow = narrowed(scan, 180.0)
    bearings = narrow.angle_min + step * np.arange(len(narrow.ranges))
    assert len(narrow.ranges) == 512 and narrow.angle_increment == step
    assert math.degrees(bearings[0]) >= -90.0 and math.degrees(bearings[-1]) < 90.0
    first = round((narrow.angle_min - scan.angle_min) / step)  # the same beams, at the same bearings
    np.testing.assert_array_equal(narrow.ranges, ranges[first : first + 512])
    for wrong in (0.0, 300.0):
        with pytest.raises(RealEvalError, match="field of view"):
            narrowed(scan, wrong)
    # A full circle from 0 rad, either way round: the kept beams run across the scan's end.
    for direction in (1.0, -1.0):
        circle = scan.model_copy(
            update={
                "angle_min": 0.0,
                "angle_increment": direction * math.radians(1.0),
                "ranges": ranges[:360],
            }
        )
        narrow = narrowed(circle, 180.0)
        bearings = narrow.angle_min + narrow.angle_increment * np.arange(len(narrow.ranges))
        assert len(narrow.ranges) == 180 and np.all(np.abs(np.degrees(bearings)) <= 90.0 + 1e-6)
        np.testing.assert_allclose(np.diff(bearings), narrow.angle_increment)
        beam_of = np.round(np.mod(np.degrees(bearings), 360.0) / np.degrees(abs(narrow.angle_increment)))
        if direction < 0:
            beam_of = np.mod(360 - beam_of, 360)
        np.testing.assert_array_equal(narrow.ranges, ranges[:360][beam_of.astype(int) % 360])


def test_cli_refuses_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    pytest.importorskip("rosbags")
    model = str(person_model(tmp_path / "p.onnx"))
    bag = str(write_bag(tmp_path / "walk.bag", [[(2.0, 0.0)]] * 4))
    garbage = tmp_path / "garbage.bag"
    garbage.write_bytes(bytes(range(256)) * 8)
    for argv, message in (
        (["--bag", bag, "--topic", "/front_scan"], "no LaserScan topic ['/front_scan']"),
        (["--bag", bag, "--people-topic", "/persons"], "no topic /persons in"),
        (["--bag", bag, "--legs-topic", "/scan"], "holds sensor_msgs/msg/LaserScan: no positions"),
        (["--bag", str(garbage)], "is not a readable ROS bag"),
        (["--bag", str(tmp_path / "missing.bag")], "not found"),
        (["--bag", bag, "--bearing-window", "30", "-30"], "bearing window"),
        (["--bag", bag, "--field-of-view", "400"], "at most the scan's own"),
    ):
        assert cli_main(["eval", "--model", model, *argv, "--out", str(tmp_path / "out")]) == 2
        errors = [r for r in caplog.records if r.levelname == "ERROR"]
        assert len(errors) == 1 and message in errors[0].getMessage() and errors[0].exc_info is None
        caplog.clear()
    assert (
        cli_main(
            [
                "eval",
                "--model",
                model,
                "--bag",
                bag,
                "--people-topic",
                "/people",
                "--out",
                str(tmp_path / "out"),
            ]
        )
        == 0
    )
    table = capsys.readouterr().out
    assert "AP@0.3 m / peak F1" in table and "person detections (/min)" in table
    (written,) = json.loads((tmp_path / "out" / "walk.json").read_text())
    assert written["people"]["r0.5"]["peak_f1"] == pytest.approx(1.0)


# --------------------------------------------------------------------------------------------------
# The real development set
# --------------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_a_real_extracted_recording_scores_its_leg_clusters() -> None:
    if not (REAL / "training_scans_res=0.33").is_dir():
        pytest.skip(f"the leg_tracker development set is not at {REAL} (../shared beside the checkout)")
    pytest.importorskip("rosbags")
    from rosbags.highlevel import AnyReader

    scans = REAL / "training_scans_res=0.33"
    bag = scans / "positive_2_extracted.bag"
    full = scans / "positive_not_extracted" / "positive_2.bag"
    config = BagEvalConfig(
        bag,
        legs_topic="/leg_cluster_positions",
        stream_bag=full,
    )
    detector = detector_for(SHIPPED_MODEL)
    report = evaluate_bag(detector, config)

    # The leg clusters within 4 m and ±15° of forward of every extracted scan that is some tensor's
    # middle scan in the full recording, counted here independently of the code under test.
    def stamps_and_legs(path: Path, topic: str) -> list[tuple[int, list[tuple[float, float]]]]:
        with AnyReader([path]) as reader:
            (conn,) = [c for c in reader.connections if c.topic == topic]
            messages: list[Any] = [
                reader.deserialize(raw, conn.msgtype) for _, _, raw in reader.messages(connections=[conn])
            ]
        return [
            (
                m.header.stamp.sec * 10**9 + m.header.stamp.nanosec,
                [(p.position.x, p.position.y) for p in getattr(m, "poses", [])],
            )
            for m in messages
        ]

    extracted = [stamp for stamp, _ in stamps_and_legs(bag, "/training_scan")]
    legs = [xy for _, xy in stamps_and_legs(bag, "/leg_cluster_positions")]
    middles = {stamp for stamp, _ in stamps_and_legs(full, "right_scan")[1:-1]}
    assert len(extracted) == len(legs) == 83
    scored = [k for k, stamp in enumerate(extracted) if stamp in middles]
    in_window = sum(
        math.hypot(x, y) <= 4.0 and abs(math.degrees(math.atan2(y, x))) <= 15.0
        for k in scored
        for x, y in legs[k]
    )
    assert report.legs is not None
    assert report.legs["scope"] == {"min_deg": -15.0, "max_deg": 15.0, "max_range_m": 4.0}
    assert (report.legs["frames"], report.legs["legs"]) == (len(scored), in_window)
    assert report.skipped.get("legs_scans_without_tensor", 0) == 83 - len(scored)
    assert report.tensors == report.scans - 2
    if detector.num_classes <= PERSON_ID:
        assert not report.has_person_class and report.legs["recall"] == 0.0
        assert report.legs["precision"] is None
    else:
        assert 0.0 <= report.legs["recall"] <= 1.0


@pytest.mark.slow
def test_motion_confirmation_finds_more_of_a_real_walkers_legs() -> None:
    """On a real recording of a still sensor, the people preview finds far more of the walker's legs
    with motion confirmation than without, and nearly all of its in-window people stay on legs."""
    if not (REAL / "training_scans_res=0.33").is_dir():
        pytest.skip(f"the leg_tracker development set is not at {REAL} (../shared beside the checkout)")
    pytest.importorskip("rosbags")
    model = SHIPPED_MODEL.parents[1] / "yolov8p-relu-dfl12" / "triscan-yolov8p-relu-dfl12-zero-int8.onnx"
    scans = REAL / "training_scans_res=0.33"
    config = BagEvalConfig(
        scans / "positive_2_extracted.bag",
        legs_topic="/leg_cluster_positions",
        stream_bag=scans / "positive_not_extracted" / "positive_2.bag",
    )
    on = evaluate_bag(detector_for(model), config).legs
    off = evaluate_bag(detector_for(model, motion_confirm=None), config).legs
    assert on is not None and off is not None
    assert on["recall"] >= off["recall"] + 0.3, (on, off)
    assert on["precision"] >= 0.9
