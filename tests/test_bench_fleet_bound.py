"""The fleet bound's CPU accounting, on a fleet report written by hand (no services, no model)."""

from __future__ import annotations

import pytest

from bench.fleet_bound import cpu_per_scan

BOUND = {"best_frames_per_s": 300.0, "best_workers": 2, "best_threads": 1, "best_batch": 8}


def test_cpu_per_scan_prices_every_process_against_the_network_at_the_bound() -> None:
    fleet = {
        "seconds_per_step": 10.0,
        "steps": [
            # 1,000 scans answered in 10 s = 100 per second; 1.5 cores → 15 ms of CPU per scan.
            {
                "robots": 10,
                "scans_answered": 1000,
                "cpu_cores": {"detector": 1.2, "encoder": 0.2, "bench": 0.1},
            },
            {"robots": 20, "scans_answered": 0, "cpu_cores": {"detector": 2.0}},  # nothing answered: no row
            {"robots": 30, "scans_answered": 10, "cpu_cores": {}},  # no CPU recorded: no row
        ],
    }
    (row,) = cpu_per_scan(fleet, BOUND, rate_hz=10.0, cores=2)
    assert row["robots"] == 10
    assert row["cpu_ms_per_scan"] == {"detector": 12.0, "encoder": 2.0, "bench": 1.0}
    assert row["cpu_ms_per_scan_total"] == pytest.approx(15.0)
    # Two single-threaded sessions at 300 frames/s: 2 cores ÷ 300 = 6.67 ms of CPU a frame.
    assert row["network_ms_per_frame_at_bound"] == pytest.approx(6.67)
    # 2 cores ÷ 15 ms a scan = 133 scans/s = 13.3 robots at 10 Hz, however well scheduled.
    assert row["ceiling_robots_at_full_cpu"] == pytest.approx(13.3)


def test_a_step_is_priced_over_its_window_as_measured() -> None:
    # 1,000 scans in a window of 12.5 s (not the nominal 10): 80 a second, 1.2 cores → 15 ms a scan.
    step = {"robots": 10, "scans_answered": 1000, "cpu_cores": {"detector": 1.2}, "window_s": 12.5}
    (row,) = cpu_per_scan({"seconds_per_step": 10.0, "steps": [step]}, BOUND, rate_hz=10.0, cores=2)
    assert row["cpu_ms_per_scan"] == {"detector": 15.0}


def test_a_one_session_bound_counts_only_the_cores_it_used() -> None:
    fleet = {"seconds_per_step": 1.0, "steps": [{"robots": 1, "scans_answered": 10, "cpu_cores": {"d": 0.1}}]}
    one_thread = {**BOUND, "best_workers": 1, "best_threads": 1}
    (row,) = cpu_per_scan(fleet, one_thread, rate_hz=10.0, cores=4)
    assert row["network_ms_per_frame_at_bound"] == pytest.approx(3.33)


def test_python_per_scan_times_every_section_of_the_detectors_own_work() -> None:
    from bench.fleet_bound import python_per_scan
    from services.detector.batch_cap import detector_model_and_batch

    model, _ = detector_model_and_batch(None, None)
    sections = python_per_scan(model, batches=2)
    assert set(sections) == {"receive", "decode", "convert", "inference", "postprocess", "encode"}
    assert all(ms > 0 for ms in sections.values()), sections
