"""The pipeline benchmarks run end to end at a tiny size and report every field (no timing thresholds)."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from bench import dataset_rate, fleet_capacity, pipeline_latency, robot_footprint
from common.model_spec import MODELS_DIR, SHIPPED_FP32_MODEL, SHIPPED_INT8_MODEL

pytestmark = [pytest.mark.slow, pytest.mark.integration]


def test_pipeline_latency_reports_every_field(tmp_path: Path) -> None:
    trace = tmp_path / "trace.csv"
    report = pipeline_latency.run(
        robots=1, rate_hz=10.0, duration_s=2.0, from_scans=False, threads=1, trace=trace, bare_frames=20
    )
    assert report.scans_published > 0 and report.scans_answered > 0
    assert set(report.latency_ms) == {"p50", "p95", "p99", "max", "mean"}
    assert all(v > 0 for v in report.latency_ms.values())
    stages = {"encode", "decode", "queue", "inference", "nms", "transport"}
    assert set(report.stage_ms_mean) == set(report.stage_ms_p50) == set(report.stage_ms_p99) == stages
    assert report.stage_ms_p50["decode"] > 0 and report.stage_ms_p50["queue"] > 0  # measured, not defaulted
    assert report.bare_ms["frames"] == 20 and report.bare_ms["p50"] > 0
    assert set(report.overhead_ms) == {"p50", "p99"}
    # What the pipeline added per frame is positive (three hops cost something) and below the latency.
    assert 0 < report.added_per_frame_ms["p50"] < report.latency_ms["p50"]
    rows = trace.read_text().splitlines()
    assert rows[0].startswith("total_ms,encode_ms") and len(rows) == report.scans_answered + 1
    assert set(report.peak_rss_mb) == {"encoder", "detector"} and all(
        v > 0 for v in report.peak_rss_mb.values()
    )


@pytest.mark.parametrize(
    ("extra", "processes"),
    [
        ((), {"encoder", "detector"}),
        (("--batch", "4", "--from-scans"), {"detector"}),
        (("--encode-on-robots", "--robot-processes", "2"), {"detector"}),
    ],
    ids=["encoder+detector", "from-scans-batched", "encode-on-robots-two-robot-processes"],
)
def test_fleet_capacity_runs_a_step_and_writes_json(
    tmp_path: Path, extra: tuple[str, ...], processes: set[str]
) -> None:
    out = tmp_path / "fleet.json"
    # Two robots for two seconds with generous criteria: the point is that every field is produced.
    argv = [
        "--ladder",
        "2",
        "--seconds",
        "2",
        "--workers",
        "1",
        "--p99-limit-ms",
        "1e9",
        "--min-answered",
        "0",
    ]
    assert fleet_capacity.main([*argv, *extra, "--rss-growth-mb", "1e9", "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    assert report["capacity_robots"] == 2
    (step,) = report["steps"]
    assert step["robots"] == 2 and step["scans_published"] > 0 and step["scans_answered"] > 0
    assert set(step["latency_ms"]) == {"p50", "p95", "p99", "max"}
    assert set(step["rss_mb_end"]) == processes
    assert step["detector_mean_batch"] >= 1.0  # read from the detector's own stats
    assert sum(step["detector_robots_per_process"]) == 2  # each robot answered by one process
    # The detector's CPU split by thread: its one inference thread by name, and Zenoh's threads.
    assert "inference-0" in step["detector_thread_cores"] and "rx-0" in step["detector_thread_cores"]
    assert report["encode_on_robots"] == ("--encode-on-robots" in extra)


def test_dataset_rate_reports_rate_and_paper_scale(tmp_path: Path) -> None:
    out = tmp_path / "rate.json"
    assert (
        dataset_rate.main(["--scenarios", "1", "--positions", "2", "--workers", "1", "--out", str(out)]) == 0
    )
    report = json.loads(out.read_text())
    assert report["samples"] > 0 and report["samples_per_s"] > 0 and report["bytes_per_sample"] > 0
    assert report["paper_scale"]["scenarios"] == 160 and report["paper_scale"]["minutes"] > 0
    assert report["paper_scale"]["measured"] is False


def test_robot_footprint_reports_both_deployments(tmp_path: Path) -> None:
    out = tmp_path / "footprint.json"
    assert robot_footprint.main(["--seconds", "1", "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    assert set(report["peak_rss_mb"]["encoder + detector (2 processes)"]) == {"encoder", "detector"}
    assert set(report["peak_rss_mb"]["detector --from-scans (1 process)"]) == {"detector"}
    shipped = {m.relative_to(MODELS_DIR).as_posix() for m in (SHIPPED_FP32_MODEL, SHIPPED_INT8_MODEL)}
    assert shipped <= set(report["model_files_mb"])


def test_replay_answered_reports_share_and_latency(tmp_path: Path) -> None:
    from bench import replay_answered

    out = tmp_path / "replay.json"
    replay_answered.main(["--scans", "20", "--out", str(out)])  # exit code: the 99 % goal, not judged here
    report = json.loads(out.read_text())
    assert report["scans_published"] == 20 and report["scans_answerable"] == 18
    assert 0 < report["scans_answered"] <= 18 and report["answered_share"] > 0
    assert set(report["latency_ms"]) == {"p50", "p95", "p99", "max"}
    assert report["detector_counters"]["processed"] > 0 and report["machine"]["logical_cpus"] > 0


def test_fleet_bound_measures_the_default_models_best_throughput() -> None:
    from bench.fleet_bound import compute_bound
    from common.model_spec import SHIPPED_BATCH_MODEL

    bound = compute_bound(SHIPPED_BATCH_MODEL, seconds=0.2)
    rows = bound["rows"]
    assert bound["model"] == SHIPPED_BATCH_MODEL.name and len(rows) >= 4  # type: ignore[arg-type]
    assert bound["best_frames_per_s"] == max(row["frames_per_s"] for row in rows)  # type: ignore[union-attr]
    assert all(row["frames_per_s"] > 0 for row in rows)  # type: ignore[union-attr]
    assert bound["best_batch"] in (1, 2, 4, 8)
    # every way to use the cores: one session with 1 or all threads, and one 1-thread session per core
    cores = os.cpu_count() or 1
    ways = {(row["workers"], row["threads"]) for row in rows}  # type: ignore[union-attr]
    assert ways == ({(1, 1), (1, cores), (cores, 1)} if cores > 1 else {(1, 1)})


def test_robot_footprint_runs_a_sensor_profile_at_another_rate(tmp_path: Path) -> None:
    """``NAME@HZ``: the same beams at another rate, to tell the rate's cost from a denser scan's."""
    import argparse

    assert robot_footprint.sensor_at_rate("ust-10lx") == ("ust-10lx", 40.0)
    assert robot_footprint.sensor_at_rate("ust-10lx@10") == ("ust-10lx", 10.0)
    for bad in ("lidar-9000", "ust-10lx@fast", "ust-10lx@0"):
        with pytest.raises(argparse.ArgumentTypeError):
            robot_footprint.sensor_at_rate(bad)
    out = tmp_path / "cpu.json"
    with pytest.raises(SystemExit):  # one row each: a second ust-10lx@40 would overwrite the first
        robot_footprint.main(["--seconds", "1", "--sensors", "ust-10lx", "ust-10lx@40", "--out", str(out)])
    assert not out.exists()
    argv = ["--seconds", "1", "--sensors", "lds-01@5", "--out", str(out)]
    assert robot_footprint.main(argv) == 0
    (row,) = json.loads(out.read_text())["sensors"].items()
    assert row[0] == "lds-01@5" and row[1]["rate_hz"] == 5.0 and row[1]["scans_published"] > 0
