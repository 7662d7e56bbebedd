"""What ``bench.fleet_capacity``'s robots send: every re-stamped payload must pass the receiver's own
validation, or a fleet step would measure rejections instead of detections (no services, no timing)."""

from __future__ import annotations

import numpy as np
import pytest

from bench import fleet_capacity
from bench.fleet_capacity import RecordedFrame
from common.inference import OnnxDetector
from common.messages import Scan, StackedTensor, decode_message
from common.model_spec import SHIPPED_INT8_MODEL, default_model_path
from services.detector.core import DetectorCore
from services.encoder.core import EncoderCore
from tests.support.scan_replay import replay_scans

PERIOD_NS = 100_000_000
STAMP_NS = 1_700_000_000_000_000_000


def recorded_tensor() -> StackedTensor:
    encoder = EncoderCore("zero")
    tensors = [t for r in replay_scans("r1", 3) if (t := encoder.push(r.scan)) is not None]
    return tensors[-1]


def test_a_restamped_tensor_passes_the_detectors_validation_as_the_robots_own() -> None:
    recorded = recorded_tensor()
    frame = RecordedFrame(recorded)
    core = DetectorCore(OnnxDetector(default_model_path(batched=True), intra_op_threads=1))
    for tick in (0, 1, 57):
        stamp = STAMP_NS + tick * PERIOD_NS
        tensor = core.decode(frame.payload("fleet007", tick, stamp, PERIOD_NS), key_robot_id="fleet007")
        assert tensor is not None, core.counters.to_dict()
        seq = frame.seq(tick)
        assert (tensor.robot_id, tensor.seq, tensor.stamp_ns) == ("fleet007", seq, stamp)
        assert seq == tick + 2  # the tensor's newest scan; its oldest is never negative
        assert tensor.scan_seqs == (seq - 2, seq - 1, seq)
        assert np.diff(tensor.scan_stamps_ns).tolist() == [PERIOD_NS, PERIOD_NS]
        assert tensor.scan_stamps_ns[2] == tensor.stamp_ns
        np.testing.assert_array_equal(tensor.tensor, recorded.tensor)  # the recorded content, untouched
    assert not core.counters.rejected


def test_a_restamped_scan_keeps_the_tick_as_its_seq() -> None:
    recorded = replay_scans("r1", 1)[0].scan
    payload = RecordedFrame(recorded).payload("fleet001", 12, STAMP_NS, PERIOD_NS)
    scan = decode_message(payload, Scan)
    assert (scan.robot_id, scan.seq, scan.stamp_ns) == ("fleet001", 12, STAMP_NS)
    np.testing.assert_array_equal(scan.ranges, recorded.ranges)


def test_the_two_one_process_fleets_are_refused_together(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        fleet_capacity.main(["--from-scans", "--encode-on-robots", "--ladder", "1"])
    assert exit_info.value.code == 2
    assert "--from-scans and --encode-on-robots" in capsys.readouterr().err


def test_a_batch_the_model_cannot_take_is_refused_before_any_process_starts(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        fleet_capacity.parse_step_args(["--model", str(SHIPPED_INT8_MODEL), "--batch", "4"])
    assert exit_info.value.code == 2
    assert "free batch axis" in capsys.readouterr().err


def test_the_counters_of_several_processes_add_up() -> None:
    from bench.report import summed_counters

    first = {"pid": 1, "processed": 3, "rejected": {"bad_key": 1}, "shard": {"member": "a", "members": 2}}
    second = {"pid": 2, "processed": 4, "rejected": {"bad_key": 2, "too_large": 1}, "shard": {"member": "b"}}
    assert summed_counters([first, second]) == {
        "pid": 1,
        "processed": 7,
        "rejected": {"bad_key": 3, "too_large": 1},
        "shard": {"member": "a", "members": 2},
    }


def test_the_robots_are_split_over_enough_processes_to_send_them_on_time() -> None:
    per = fleet_capacity.ROBOTS_PER_PROCESS
    assert fleet_capacity.robot_processes(1, None) == 1
    assert fleet_capacity.robot_processes(per, None) == 1
    assert fleet_capacity.robot_processes(per + 1, None) == 2
    assert fleet_capacity.robot_processes(5 * per, None) == 5
    assert fleet_capacity.robot_processes(10, 4) == 4  # as asked
    assert fleet_capacity.robot_processes(3, 8) == 3  # never a process without a robot


def test_memory_growth_is_judged_process_by_process() -> None:
    import argparse

    args = argparse.Namespace(p99_limit_ms=100.0, min_answered=0.95, rss_growth_mb=20.0)
    published = {("fleet000", seq): seq * 1_000_000 for seq in range(10)}
    received = {key: stamp + 5_000_000 for key, stamp in published.items()}

    def judged(start: dict[int, float], end: dict[int, float]) -> fleet_capacity.FleetStep:
        step = fleet_capacity.FleetStep(1, rss_mb_by_pid_start=start, rss_mb_by_pid_end=end)
        fleet_capacity._judge_step(step, published, received, args)
        return step

    sixteen_warming = judged({pid: 130.0 for pid in range(16)}, {pid: 132.0 for pid in range(16)})
    assert sixteen_warming.passed, sixteen_warming.why_not  # 32 MB in all, 2 MB each
    one_leaking = judged({1: 130.0, 2: 130.0}, {1: 155.0, 2: 130.0})
    assert not one_leaking.passed and "RSS grew 25.0 MB" in one_leaking.why_not
    restarted = judged({1: 130.0}, {2: 180.0})  # a process that came and went is not compared
    assert restarted.passed


def test_a_fleet_without_robot_processes_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        fleet_capacity.parse_step_args(["--robot-processes", "0"])
    assert exit_info.value.code == 2
    assert "--robot-processes must be >= 1" in capsys.readouterr().err
