"""The launcher's periodic table: pairing by scan, the matching rule, and the latency percentiles."""

from __future__ import annotations

import numpy as np

from common.messages import Detection, Detections, GroundTruth, StageTimings, TruthObject
from common.model_spec import CLASS_NAMES
from services.run_summary import LatencyHistogram, RunSummary, match_frame

MS = 1_000_000
FURNITURE = CLASS_NAMES[:4]


def truth_object(class_id: int, box: tuple[float, float, float, float] | None) -> TruthObject:
    return TruthObject(
        class_id=class_id,
        class_name=CLASS_NAMES[class_id],
        corners_xy=np.zeros((4, 2), np.float32),
        center_xy=(0.0, 0.0),
        yaw_rad=0.0,
        visible=box is not None,
        box_px=box,
    )


def truth(
    seq: int, objects: list[TruthObject], robot: str = "robot0", stamp_ms: int | None = None
) -> GroundTruth:
    return GroundTruth(
        robot_id=robot,
        seq=seq,
        stamp_ns=(100 * seq if stamp_ms is None else stamp_ms) * MS,
        scenario_id=0,
        robot_pose=(0.0, 0.0, 0.0),
        lidar_pose=(0.0, 0.0, 0.0),
        objects=objects,
    )


def detection(class_id: int, box: tuple[float, float, float, float], score: float = 0.9) -> Detection:
    return Detection(
        class_id=class_id,
        class_name=CLASS_NAMES[class_id],
        score=score,
        box_px=box,
        bearing_deg=0.0,
        bearing_min_deg=0.0,
        bearing_max_deg=0.0,
        range_min_m=1.0,
        range_max_m=1.0,
        x_m=1.0,
        y_m=0.0,
    )


def detections(
    seq: int, found: list[Detection], latency_ms: float = 5.0, robot: str = "robot0"
) -> Detections:
    scan_stamp_ns = 100 * seq * MS
    return Detections(
        robot_id=robot,
        seq=seq,
        stamp_ns=scan_stamp_ns + round(latency_ms * MS),
        detections=found,
        timings=StageTimings(encode_ms=0.0, inference_ms=0.0, nms_ms=0.0),
        model_id="m@0",
        scan_stamp_ns=scan_stamp_ns,
    )


CHAIR_BOX = (100.0, 10.0, 110.0, 20.0)


def rows(table: str) -> dict[str, list[str]]:
    """The class rows of a one-robot table, by class name."""
    return {line.split()[0]: line.split()[1:] for line in table.splitlines()[3:]}


def test_detections_are_scored_against_the_middle_scans_truth() -> None:
    """The boxes of the tensor ending at scan 5 are those of scan 4: scan 5's truth is not used."""
    summary = RunSummary(FURNITURE)
    summary.update(truth(4, [truth_object(0, CHAIR_BOX)]))
    summary.update(truth(5, [truth_object(0, (200.0, 10.0, 210.0, 20.0))]))  # the chair seen elsewhere
    summary.update(detections(5, [detection(0, (101.0, 11.0, 109.0, 19.0))]))
    table = summary.table(elapsed_s=10)
    assert "robot0: 1 frames (1 with truth)" in table
    assert rows(table)["chair"] == ["1", "1", "1.00", "1.00"]


def test_a_frame_whose_truth_stamp_differs_is_not_paired() -> None:
    """A restarted simulator repeats seq values: the stamp of scan t tells the worlds apart."""
    summary = RunSummary(FURNITURE)
    summary.update(truth(4, [truth_object(0, CHAIR_BOX)]))
    summary.update(truth(5, [], stamp_ms=999_999))
    summary.update(detections(5, [detection(0, (101.0, 11.0, 109.0, 19.0))]))
    table = summary.table()
    assert "1 frames (0 with truth)" in table
    assert rows(table)["chair"] == ["1", "0", "-", "-"]


def test_recall_and_precision_per_class_by_the_centre_rule() -> None:
    summary = RunSummary(FURNITURE)
    objects = [truth_object(0, CHAIR_BOX), truth_object(2, (300.0, 5.0, 340.0, 30.0)), truth_object(1, None)]
    summary.update(truth(0, objects))
    summary.update(truth(1, objects))
    summary.update(
        detections(
            1,
            [
                detection(0, (104.0, 12.0, 118.0, 22.0), 0.9),  # centre (111, 17): outside the chair's box
                detection(2, (305.0, 6.0, 330.0, 28.0), 0.8),  # the desk
                detection(2, (306.0, 6.0, 331.0, 28.0), 0.7),  # the desk again: it is claimed already
                detection(1, (50.0, 5.0, 60.0, 10.0), 0.6),  # a box where none is visible
            ],
        )
    )
    table = rows(summary.table())
    assert table["chair"] == ["1", "1", "0.00", "0.00"]
    assert table["desk"] == ["2", "1", "1.00", "0.50"]
    assert table["box"] == ["1", "0", "-", "0.00"]  # the hidden box is not an object to find
    assert table["doorframe"] == ["0", "0", "-", "-"]


def test_a_box_across_the_seam_matches_its_objects_other_copy() -> None:
    seam_object = truth_object(1, (350.0, 20.0, 370.0, 27.0))  # the whole box, past column 360
    correct, found = match_frame([detection(1, (-8.0, 20.0, 8.0, 27.0))], [seam_object])
    assert correct == [True] and found == [True]


def test_higher_scores_claim_objects_first_whatever_the_order() -> None:
    objects = [truth_object(0, CHAIR_BOX)]
    low, high = detection(0, (101.0, 11.0, 109.0, 19.0), 0.3), detection(0, (102.0, 11.0, 108.0, 19.0), 0.8)
    assert match_frame([low, high], objects) == ([False, True], [True])


def test_classes_the_model_does_not_predict_are_shown_apart() -> None:
    summary = RunSummary(FURNITURE)
    people = [truth_object(4, (10.0, 10.0, 14.0, 14.0))]
    summary.update(truth(0, people))
    summary.update(truth(1, people))
    summary.update(detections(1, []))
    assert rows(summary.table())["person"][:2] == ["-", "1"]
    assert "not a class of this model" in summary.table()


def test_latency_percentiles_are_within_one_percent_and_never_low() -> None:
    histogram = LatencyHistogram()
    values = np.random.default_rng(0).lognormal(1.5, 0.6, 5000)
    for value in values:
        histogram.add(float(value))
    for q in (50, 99):
        true_value = float(np.percentile(values, q, method="inverted_cdf"))
        assert true_value <= histogram.percentile(q) <= true_value * 1.0101  # type: ignore[operator]
    assert LatencyHistogram().percentile(50) is None


def test_the_table_has_one_block_per_robot_and_the_latency() -> None:
    summary = RunSummary(FURNITURE)
    for seq, latency in enumerate([4.0, 4.0, 4.0, 20.0]):
        summary.update(detections(seq, [], latency_ms=latency, robot="b"))
    summary.update(detections(0, [], robot="a"))
    lines = summary.table(elapsed_s=10).splitlines()
    assert lines[0].startswith("detections after 10 s, against")
    robot_lines = [line.strip() for line in lines if line.startswith("  ") and not line.startswith("    ")]
    assert [line.split(":")[0] for line in robot_lines] == ["a", "b"]
    p50, p99 = (float(robot_lines[1].split(word)[1].split()[0]) for word in ("p50", "p99"))
    assert 4.0 <= p50 <= 4.04 and 20.0 <= p99 <= 20.2
    assert RunSummary().table(elapsed_s=3) == "no detections yet after 3 s"


def test_old_truth_is_forgotten() -> None:
    summary = RunSummary(FURNITURE, truth_kept=2)
    for seq in range(5):
        summary.update(truth(seq, [truth_object(0, CHAIR_BOX)]))
    summary.update(detections(2, [detection(0, (101.0, 11.0, 109.0, 19.0))]))  # truth of 1 and 2 is gone
    assert "(0 with truth)" in summary.table()


def test_the_launcher_reads_the_models_classes_as_the_detector_does() -> None:
    from common.inference import OnnxDetector, model_class_names
    from common.model_spec import default_model_path

    path = default_model_path()
    assert model_class_names(path) == OnnxDetector(path).class_names
