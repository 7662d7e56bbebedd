"""The frame-latency benchmark keeps running: every pipeline, a handful of frames, every field reported.

No timing thresholds here: a test asserting milliseconds would fail on a busy CI runner and say nothing
about the code. The figures come from ``python -m bench.frame_latency`` on a quiet machine.
"""

from __future__ import annotations

import json
from dataclasses import fields

import numpy as np
import pytest

pytest.importorskip("ultralytics")
pytest.importorskip("pybullet")

from bench.frame_latency import (
    GRID,
    PRECISION_PIPELINES,
    PRIME_SCANS,
    STAGES,
    TRISCAN_FP32,
    TRISCAN_INT8,
    ULTRALYTICS,
    ULTRALYTICS_SAME,
    BenchConfig,
    LatencyRow,
    MachineInfo,
    RatioRow,
    TriscanPipeline,
    goals,
    main,
    measure_in_turns,
    ratios,
    round_bounds,
    simulated_scans,
)
from bench.occupancy_grid import rasterise_occupancy_grid

# The default (pico) is not the paper's network, so Ultralytics also runs the pico's own .pt: the
# runtime alone, beside the paper's runtime the goals are judged against.
PIPELINES = (TRISCAN_FP32, TRISCAN_INT8, ULTRALYTICS, ULTRALYTICS_SAME, GRID)
THREADS = (1, 2)
FRAMES, PAPER_FRAMES = 5, 3


pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """One tiny run of the real benchmark (grid at 320 px: the same export and code path, cheaper)."""
    tmp = tmp_path_factory.mktemp("frame_latency")
    out = tmp / "frame_latency.json"
    argv = ["--frames", str(FRAMES), "--paper-frames", str(PAPER_FRAMES), "--threads", "1,2"]
    argv += ["--grid-px", "320", "--cache-dir", str(tmp / "cache"), "--out", str(out)]
    assert main(argv) == 0
    return json.loads(out.read_text())


def test_every_pipeline_runs_at_every_thread_count(report: dict) -> None:
    got = [(row["pipeline"], row["threads"]) for row in report["rows"]]
    assert sorted(got) == sorted((p, t) for p in PIPELINES for t in THREADS)


def test_every_row_has_every_field_and_positive_times(report: dict) -> None:
    for row in report["rows"]:
        assert set(row) == {f.name for f in fields(LatencyRow)}
        assert row["frames"] == FRAMES
        assert row["paper_frames"] == PAPER_FRAMES
        assert row["paper_warmup_frames"] == 1
        for key in ("paper_mean_ms", "p50_ms", "p99_ms", "mean_ms", "max_ms"):
            assert row[key] > 0, (row["pipeline"], key)
        assert row["p50_ms"] <= row["p99_ms"] <= row["max_ms"]
        assert set(row["stage_mean_ms"]) == set(STAGES)
        for stage in STAGES[:-1]:
            assert row["stage_mean_ms"][stage] > 0, (row["pipeline"], stage)
        assert row["stage_mean_ms"]["other"] >= 0  # frame minus its stages: measured around them
        assert row["detections_per_frame"] >= 0
    assert "untrained weights: timing only" in next(
        r["label"] for r in report["rows"] if r["pipeline"] == GRID
    )


def test_ratios_goals_and_machine_are_reported(report: dict) -> None:
    # Every baseline over fp32; and over the detector's default file when that is INT8 (the card's call).
    default = PRECISION_PIPELINES[report["config"]["default"]]
    expected = {(p, TRISCAN_FP32) for p in (ULTRALYTICS, GRID, TRISCAN_INT8, ULTRALYTICS_SAME)}
    expected |= {(p, default) for p in (ULTRALYTICS, GRID)} if default != TRISCAN_FP32 else set()
    ratios = {(r["numerator"], r["denominator"], r["threads"]) for r in report["ratios"]}
    assert ratios == {(n, d, t) for n, d in expected for t in THREADS}
    for ratio in report["ratios"]:
        assert set(ratio) == {f.name for f in fields(RatioRow)}
        assert min(ratio["paper_mean"], ratio["p50"], ratio["p99"]) > 0
    assert len(report["goals"]) == 3
    assert all(isinstance(goal["met"], bool) and goal["value"] > 0 for goal in report["goals"].values())
    machine = report["machine"]
    assert set(machine) == {f.name for f in fields(MachineInfo)}
    assert machine["cpu_model"] and machine["logical_cpus"] >= 1 and len(machine["loadavg_end"]) == 3
    assert all(machine["versions"][m] != "not installed" for m in ("onnxruntime", "torch", "ultralytics"))
    assert report["scans"]["count"] == 2 + 1 + PAPER_FRAMES + FRAMES


def test_ultralytics_sees_the_same_objects_as_onnx_runtime(report: dict) -> None:
    """A sanity check that it is fed the right tensor (the exact comparison lives in test_export)."""
    per_frame = {(r["pipeline"], r["threads"]): r["detections_per_frame"] for r in report["rows"]}
    assert per_frame[(ULTRALYTICS, 1)] == pytest.approx(per_frame[(TRISCAN_FP32, 1)], abs=0.5)
    assert per_frame[(ULTRALYTICS_SAME, 1)] == pytest.approx(per_frame[(TRISCAN_FP32, 1)], abs=0.5)


def test_the_detectors_default_file_is_judged_as_its_card_says(report: dict) -> None:
    """Without ``--default`` the bench reads the recommendation of the card beside the fp32 file."""
    from common.model_spec import SHIPPED_DIR

    card = json.loads((SHIPPED_DIR / "MODEL_CARD.json").read_text())
    assert report["config"]["default"] == card["recommended"]


def test_occupancy_grid_is_robot_centred_forward_up_left_left() -> None:
    ranges = np.full(360, np.inf, dtype=np.float32)
    ranges[0] = 2.0  # straight ahead, 2 m
    ranges[90] = 1.0  # to the left, 1 m
    image = rasterise_occupancy_grid(ranges, 0.0, np.deg2rad(1.0), 0.12, 3.5, size=640, radius_m=4.0)
    assert image.shape == (640, 640, 3) and image.dtype == np.uint8
    rows, cols = np.nonzero(image[..., 0])
    assert sorted(zip(rows.tolist(), cols.tolist(), strict=True)) == [(160, 320), (320, 240)]
    assert (image[rows, cols] == 255).all() and int((image > 0).sum()) == 2 * 3


def latency_row(pipeline: str, p50: float, threads: int = 1) -> LatencyRow:
    return LatencyRow(
        pipeline=pipeline, label=pipeline, threads=threads, paper_warmup_frames=1, paper_frames=3,
        paper_mean_ms=p50, frames=5, p50_ms=p50, p99_ms=2 * p50, mean_ms=p50, max_ms=3 * p50,
        stage_mean_ms=dict.fromkeys(STAGES, 0.0), detections_per_frame=1.0,
    )  # fmt: skip


def test_ratios_name_the_same_network_and_the_shipped_default() -> None:
    """A pico default in INT8: the runtime alone (Ultralytics on the pico .pt ÷ pico fp32) and what a user
    gains (the paper's YOLOv8n in Ultralytics ÷ the default file), the goals judged on the latter."""
    rows = [
        latency_row(TRISCAN_FP32, 4.0), latency_row(TRISCAN_INT8, 3.0), latency_row(ULTRALYTICS, 18.0),
        latency_row(ULTRALYTICS_SAME, 12.0), latency_row(GRID, 120.0),
    ]  # fmt: skip
    got = {(r.numerator, r.denominator): r.p50 for r in ratios(rows, TRISCAN_INT8)}
    assert got == {
        (ULTRALYTICS, TRISCAN_FP32): 4.5, (GRID, TRISCAN_FP32): 30.0, (TRISCAN_INT8, TRISCAN_FP32): 0.75,
        (ULTRALYTICS_SAME, TRISCAN_FP32): 3.0, (ULTRALYTICS, TRISCAN_INT8): 6.0, (GRID, TRISCAN_INT8): 40.0,
    }  # fmt: skip
    judged = goals(rows, ratios(rows, TRISCAN_INT8), TRISCAN_INT8)
    assert judged["ultralytics_pt_over_triscan_int8_p50_at_1_thread"] == {
        "value": 6.0,
        "target": ">= 6.0",
        "met": True,
    }
    assert judged["occupancy_grid_over_triscan_int8_p50_at_1_thread"]["met"]
    assert not judged["triscan_fp32_p50_ms_at_1_thread"]["met"]


def test_round_bounds_split_the_frames_into_consecutive_shares() -> None:
    assert round_bounds(10, 1) == [(0, 10)]
    assert round_bounds(10, 3) == [(0, 3), (3, 7), (7, 10)]
    assert round_bounds(2, 5) == [(0, 1), (1, 2)]  # never an empty round
    with pytest.raises(ValueError, match="rounds"):
        round_bounds(10, 0)


class RecordingPipeline:
    """Counts what it is given, in the order it is given it, into a log shared with the others."""

    def __init__(self, name: str, log: list[tuple[str, str, int]]) -> None:
        self.name, self.log = name, log

    def prime(self, scan: int) -> None:
        self.log.append((self.name, "prime", scan))

    def frame(self, scan: int) -> tuple[tuple[float, float, float, float], int]:
        self.log.append((self.name, "frame", scan))
        return (0.0, 0.0, 0.0, 0.0), 1


def test_pipelines_take_turns_each_on_the_same_consecutive_scans() -> None:
    """In rounds, every pipeline still sees every scan once and in order (its FIFO stays continuous),
    and the long run alternates between pipelines instead of running one after the other."""
    config = BenchConfig(frames=6, paper_frames=2, paper_warmup=1, rounds=3)
    scans = list(range(config.scans_needed))
    log: list[tuple[str, str, int]] = []
    a, b = TRISCAN_FP32, TRISCAN_INT8
    pipelines = [(a, RecordingPipeline(a, log)), (b, RecordingPipeline(b, log))]
    rows = measure_in_turns(pipelines, 1, scans, config)  # type: ignore[arg-type]
    assert [(r.pipeline, r.frames, r.paper_frames) for r in rows] == [(a, 6, 2), (b, 6, 2)]
    for name in (a, b):
        assert [scan for who, _, scan in log if who == name] == scans
    long_run_start = PRIME_SCANS + config.paper_warmup + config.paper_frames
    long_run = [who for who, _, scan in log if scan >= long_run_start]
    assert long_run == [a, a, b, b] * 3


def test_a_real_run_in_rounds_reports_every_frame(tmp_path) -> None:
    out = tmp_path / "rounds.json"
    argv = ["--frames", "4", "--paper-frames", "2", "--threads", "1", "--rounds", "2"]
    argv += ["--skip-grid", "--skip-ultralytics", "--out", str(out)]
    assert main(argv) == 0
    report = json.loads(out.read_text())
    assert report["config"]["rounds"] == 2
    assert [(r["pipeline"], r["frames"]) for r in report["rows"]] == [(TRISCAN_FP32, 4), (TRISCAN_INT8, 4)]


def test_with_odometry_the_bench_tells_the_detector_what_the_poses_say_as_the_service_does() -> None:
    """``--odometry``: each frame passes what the poses of its three scans say (driving, standing) to
    the detector's motion confirmation; without it, nothing, and the tensor is asked."""
    from common.model_spec import MODELS_DIR

    people_int8 = MODELS_DIR / "yolov8p-relu-dfl12" / "triscan-yolov8p-relu-dfl12-zero-int8.onnx"
    driving = simulated_scans(PRIME_SCANS + 4, seed=1, odometry=True)
    assert all(scan.odom is not None for scan in driving)
    standing = [scan._replace(odom=driving[0].odom) for scan in driving]
    without = [scan._replace(odom=None) for scan in driving]
    # Standing for the first tensor's three scans, then driving: only that tensor stood.
    starts = [scan._replace(odom=driving[0].odom) for scan in driving[: PRIME_SCANS + 1]]
    starts += driving[PRIME_SCANS + 1 :]
    cases: list[tuple[list, list[bool | None]]] = [
        (driving, [False] * 4),
        (standing, [True] * 4),
        (without, [None] * 4),
        (starts, [True, False, False, False]),
    ]
    for scans, expected in cases:
        pipeline = TriscanPipeline(people_int8, 1)
        asked: list[bool | None] = []
        detect_boxes = pipeline.detector.detect_boxes

        def recording(tensor: np.ndarray, still: bool | None = None, real=detect_boxes, log=asked):
            log.append(still)
            return real(tensor, still)

        pipeline.detector.detect_boxes = recording
        for scan in scans[:PRIME_SCANS]:
            pipeline.prime(scan)
        for scan in scans[PRIME_SCANS:]:
            pipeline.frame(scan)
        assert asked == expected
