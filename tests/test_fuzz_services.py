"""The fuzz run at CI size: malformed payloads over real Zenoh into real encoder, detector and ROS 2
bridge processes."""

from __future__ import annotations

import pytest

from bench.fuzz_services import run

pytestmark = [pytest.mark.slow, pytest.mark.integration]


def test_services_survive_fuzz_count_every_bad_payload_and_answer_every_good_scan() -> None:
    # 20 rounds of the 30 triscan mutation kinds (+ bad keys), and 300 ROS payloads (~11 rounds of 26)
    report = run(bad=600, good_every=30, seed=1)
    assert all(report.alive_at_end.values()) and set(report.alive_at_end) == {
        "encoder",
        "detector",
        "ros2_bridge",
    }, report.alive_at_end
    assert report.good_scans >= 15 and report.ros_good_scans >= 15
    # every good scan answered, but for those the detector replaced with its robot's next one (stale)
    unanswered = report.good_scans - report.good_answered + report.ros_good_scans - report.ros_good_answered
    assert unanswered <= report.detector_dropped_stale, report
    assert (
        report.good_answered >= 0.9 * report.good_scans
        and report.ros_good_answered >= 0.9 * report.ros_good_scans
    )
    assert report.counted_rejected == report.expected_rejected, report.rejected_by_reason
    assert report.expected_rejected["encoder"] > 400 and report.expected_rejected["detector"] > 80
    assert report.ros_bad_sent == 300 and report.expected_rejected["ros2_bridge"] > 200
    assert report.bridge_scans_published["counted"] == report.bridge_scans_published["expected"] > 0
    assert report.passed
