"""The goal floors' arithmetic, on measurements written by hand (no processes, no model)."""

from __future__ import annotations

import pytest

from bench.fleet_bound import FLEET_GOAL_SHARE
from bench.goal_floors import FLEET_LAYOUTS, fleet_floors, hop_ms, latency_floors
from bench.pipeline_latency import FROM_SCANS_OVERHEAD_GOAL_P50_MS, OVERHEAD_GOAL_P50_MS
from bench.zenoh_rtt import SMALL_BYTES, TENSOR_BYTES, median_p50s

BOUND = {"best_frames_per_s": 1000.0, "best_workers": 2, "best_threads": 1, "best_batch": 8}


def _round_trip(kind: str, size: int, p50_ms: float) -> dict[str, object]:
    """One round of ``bench.zenoh_rtt.run_case``, as far as the floors read it."""
    return {"kind": kind, "variant": "default" if kind == "zenoh" else "-", "bytes": size,
            "rtt_ms": {"p50": p50_ms}, "wakeups_per_round_trip": {"ping": {}, "echo": {}}}  # fmt: skip


def _message_cpu(kind: str, size: int, sender_ms: float, receiver_ms: float) -> dict[str, object]:
    return {"kind": kind, "bytes": size, "cpu_ms_per_message": {"sender": sender_ms, "receiver": receiver_ms}}


def test_a_hop_is_half_the_median_round_trip_over_the_rounds() -> None:
    trips = [_round_trip("zenoh", 100, p50) for p50 in (0.70, 0.90, 0.72)] + [_round_trip("tcp", 100, 0.2)]
    summary = median_p50s(trips)
    assert hop_ms(summary, "zenoh", 100) == pytest.approx(0.36)
    with pytest.raises(ValueError, match="no zenoh round trip of 73728 bytes"):
        hop_ms(summary, "zenoh", TENSOR_BYTES)


def test_three_processes_cross_three_hops_and_from_scans_two() -> None:
    trips = [
        _round_trip("zenoh", SMALL_BYTES, 0.6),  # 0.3 ms a small hop
        _round_trip("zenoh", TENSOR_BYTES, 0.8),  # 0.4 ms the tensor's
        _round_trip("tcp", SMALL_BYTES, 0.2),
        _round_trip("tcp", TENSOR_BYTES, 0.3),
    ]
    three, from_scans = latency_floors(trips)
    assert three["pipeline"] == "3 processes" and three["goal_overhead_p50_ms"] == OVERHEAD_GOAL_P50_MS
    assert three["zenoh_hops_p50_ms"] == pytest.approx(1.0)  # scan + tensor + detections
    assert three["tcp_hops_p50_ms"] == pytest.approx(0.35)
    assert three["within_goal"]  # exactly on the budget is within it
    assert from_scans["goal_overhead_p50_ms"] == FROM_SCANS_OVERHEAD_GOAL_P50_MS
    assert from_scans["zenoh_hops_p50_ms"] == pytest.approx(0.6)  # scan + detections, no tensor hop
    assert not from_scans["within_goal"]


def test_each_fleet_layout_pays_the_network_and_the_message_ends_it_puts_on_the_host() -> None:
    message_cpu = [
        _message_cpu("zenoh", SMALL_BYTES, 0.10, 0.11),
        _message_cpu("zenoh", TENSOR_BYTES, 0.14, 0.12),
        _message_cpu("tcp", SMALL_BYTES, 0.05, 0.03),
        _message_cpu("tcp", TENSOR_BYTES, 0.06, 0.04),
    ]
    rows = {row["layout"]: row for row in fleet_floors(BOUND, message_cpu, cores=2)}
    assert list(rows) == list(FLEET_LAYOUTS)
    alone, encode_on_robots, benches = rows.values()
    # Two single-threaded sessions at 1,000 frames/s: 2 ms of CPU a frame.
    assert {row["network_cpu_ms_per_frame"] for row in rows.values()} == {2.0}
    # The detector alone receives the tensor and sends the detections.
    assert alone["message_cpu_ms_per_scan"] == pytest.approx(0.12 + 0.10)
    # The stand-in on the host adds the tensor's sending and the detections' receiving end.
    assert encode_on_robots["message_cpu_ms_per_scan"] == pytest.approx(0.14 + 0.12 + 0.10 + 0.11)
    # The encoder adds the scan's two ends.
    assert benches["message_cpu_ms_per_scan"] == pytest.approx(0.14 + 0.12 + 2 * (0.10 + 0.11))
    # 2 cores ÷ 2.22 ms a scan = 900.9 scans/s = 90.1 % of 1,000 frames/s.
    assert alone["cpu_ms_per_scan"] == pytest.approx(2.22)
    assert alone["most_scans_per_s"] == pytest.approx(900.9) and alone["share_of_bound"] == pytest.approx(
        0.901
    )
    assert FLEET_GOAL_SHARE == 0.8 and alone["within_goal"]
    # 2 ÷ 2.68 = 746 scans/s: under the goal.
    assert benches["share_of_bound"] == pytest.approx(0.746) and not benches["within_goal"]
    over_tcp = fleet_floors(BOUND, message_cpu, cores=2, kind="tcp")
    assert over_tcp[0]["message_cpu_ms_per_scan"] == pytest.approx(0.04 + 0.05)


def test_a_one_session_bound_leaves_the_other_cores_to_the_messages() -> None:
    one_session = {**BOUND, "best_workers": 1, "best_threads": 1, "best_frames_per_s": 500.0}
    message_cpu = [_message_cpu("zenoh", size, 0.0, 0.0) for size in (SMALL_BYTES, TENSOR_BYTES)]
    (alone, *_) = fleet_floors(one_session, message_cpu, cores=2)
    # One core at 500 frames/s: 2 ms a frame; two cores then serve 1,000 scans/s, twice the bound.
    assert alone["network_cpu_ms_per_frame"] == pytest.approx(2.0) and alone[
        "share_of_bound"
    ] == pytest.approx(2.0)
