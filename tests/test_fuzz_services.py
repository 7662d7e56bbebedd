"""The fuzz run at CI size: malformed payloads over real Zenoh into real encoder, detector and ROS 2
bridge processes; and, without processes, that each of its tensor payloads is one the decoder refuses."""

from __future__ import annotations

import random

import numpy as np
import pytest

from bench.fuzz_services import FUZZ_ROBOT, bad_payloads, fuzz_tensor, mutations, run
from common.messages import MessageError, Scan, StackedTensor, decode_message


def test_every_tensor_mutation_is_refused_each_for_its_own_reason() -> None:
    """A mutation the decoder accepted would fuzz nothing; two with one message would test one case."""
    scan = Scan(
        robot_id=FUZZ_ROBOT, seq=0, stamp_ns=1, angle_min=0.0, angle_increment=0.01, range_min=0.1,
        range_max=4.0, ranges=np.ones(360, np.float32),
    )  # fmt: skip
    kinds = len(mutations(scan, fuzz_tensor(), random.Random(1)))
    texts = {}
    for name, topic, _robot, payload in bad_payloads(kinds, scan, fuzz_tensor(), seed=1):
        if topic == "tensor":
            with pytest.raises(MessageError) as info:
                decode_message(payload, StackedTensor)
            texts[name] = str(info.value)
    assert {n for n in texts if n.startswith("tensor_lit")} == {
        "tensor_lit_under_version_2", "tensor_lit_extra_key", "tensor_lit_counts_huge",
        "tensor_lit_counts_short", "tensor_lit_bytes_short", "tensor_lit_index_outside",
        "tensor_lit_unsorted", "tensor_lit_repeated",
    }  # fmt: skip
    assert len(set(texts.values())) == len(texts), texts


@pytest.mark.slow
@pytest.mark.integration
def test_services_survive_fuzz_count_every_bad_payload_and_answer_every_good_scan() -> None:
    # 20 rounds of the 38 triscan mutation kinds (+ bad keys), and 300 ROS payloads (~11 rounds of 26)
    report = run(bad=760, good_every=30, seed=1, ros_bad=300)
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
