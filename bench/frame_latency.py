"""Per-frame latency, batch 1, of triscan and the runtimes it is compared with — side by side, one run.

What one *frame* is (the paper's Algorithm 1): a new scan arrives → it is encoded and pushed into the
three-scan FIFO (``ScanStacker.push_scan``) → the model input is built → the model runs → its raw
output is decoded and NMS'd into boxes. Every pipeline is timed over exactly that, wall clock, one
frame at a time, on the same pre-generated real simulated scans (``SimulatedFleet``, PyBullet);
generating the scans is never timed.

Pipelines:

* ``triscan_fp32`` / ``triscan_int8``: the shipped ONNX models in ONNX Runtime through
  :class:`common.inference.OnnxDetector` — exactly what the detector service runs.
* ``ultralytics_pt``: the paper's deployed runtime, Ultralytics ``YOLO(pt).predict`` on the ``.pt``
  checkpoint of the same model, fed the same stacked tensor (timing includes its own pre- and
  post-processing, as deployed). Ultralytics reads a numpy image as BGR and flips it to RGB, so it is
  given ``tensor[..., ::-1]``: the network then sees scan t−2 in channel 0, as the ONNX model does.
  Its letterbox is a no-op here: the tensor is already 64×384 = ``imgsz``. torch threads are set
  with ``torch.set_num_threads``.
* ``occupancy_grid``: the baseline (:mod:`bench.occupancy_grid`): the same scans drawn into a
  robot-centred 640×640 image, an untrained YOLOv8n (weights for timing only) in ONNX Runtime with
  the same session options, and this project's decode + NMS. Its encode step is its own rasteriser
  (the grid replaces the three-scan raster); the three other pipelines share ``ScanStacker``.

Protocol, for every pipeline at 1 thread and at all cores (``os.cpu_count()``): prime the FIFO with
two scans (untimed), run **one warm-up frame**, then time **100 consecutive frames** and report their
mean — the paper's protocol — and then, continuing on the following scans, time ``--frames`` more
(default 1,000) for p50 and p99: a mean of 100 hides the tail a robot's control loop has to live with.
Per-stage means (encode, preprocess, inference, postprocess, other = frame − stages) come from the
long run. Ratios are baseline ÷ triscan fp32 (and INT8 ÷ fp32) at each thread count. By default the
pipelines run one after the other; ``--rounds N`` splits every long run into N shares that the
pipelines time in turns (every pipeline in memory at once), for VMs whose speed drifts by more
than the difference being measured within a minute.

Nothing here asserts a time: the numbers depend on the machine, and a quiet machine is the caller's
job (load averages at start and end are recorded in the JSON to show whether it was).

    python -m bench.frame_latency                     # full run → bench/results/frame_latency.json
    python -m bench.frame_latency --frames 200 --skip-grid --skip-ultralytics
    python -m bench.frame_latency --threads 1 --skip-grid --rounds 10   # pipelines in turns
    python -m bench.frame_latency --threads 1 --rounds 10 --odometry    # scans with the robot's poses
"""

from __future__ import annotations

import argparse
import gc
import itertools
import json
import logging
import os
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Final, NamedTuple, Protocol

import numpy as np

from bench.machine import MachineInfo, machine_info
from bench.occupancy_grid import (
    GRID_PX,
    GRID_RADIUS_M,
    GridDetector,
    grid_model_onnx,
    rasterise_occupancy_grid,
)
from bench.report import write_report
from common.encoding import IMAGE_WIDTH, RANGE_ROWS, STACK_DEPTH, ScanStacker
from common.inference import OnnxDetector
from common.messages import Odometry
from common.model_spec import PAPER_CHECKPOINT, SHIPPED_FP32_MODEL, SHIPPED_INT8_MODEL
from common.moving_people import DEFAULT_MOTION_CONFIRM, add_motion_argument, motion_confirm_of
from common.postprocess import DEFAULT_CONF, DEFAULT_IOU

ROOT: Final[Path] = Path(__file__).resolve().parents[1]
DEFAULT_OUT: Final[Path] = ROOT / "bench" / "results" / "frame_latency.json"
DEFAULT_CACHE: Final[Path] = ROOT / "runs" / "bench_cache"

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

TRISCAN_FP32: Final[str] = "triscan_fp32"
TRISCAN_INT8: Final[str] = "triscan_int8"
ULTRALYTICS: Final[str] = "ultralytics_pt"
ULTRALYTICS_SAME: Final[str] = "ultralytics_same_network_pt"
GRID: Final[str] = "occupancy_grid"
LABELS: Final[dict[str, str]] = {
    TRISCAN_FP32: "triscan 64×384, ONNX Runtime fp32",
    TRISCAN_INT8: "triscan 64×384, ONNX Runtime INT8",
    ULTRALYTICS: "triscan 64×384, Ultralytics predict on the paper's YOLOv8n .pt",
    ULTRALYTICS_SAME: "triscan 64×384, Ultralytics predict on the fp32 model's own .pt",
}
PRECISION_PIPELINES: Final[dict[str, str]] = {"fp32": TRISCAN_FP32, "int8": TRISCAN_INT8}


def label(name: str, grid_px: int = GRID_PX) -> str:
    """The row label of a pipeline (the grid's carries its image size)."""
    if name == GRID:
        return f"occupancy grid {grid_px}×{grid_px} (YOLOv8n, untrained weights: timing only)"
    return LABELS[name]


STAGES: Final[tuple[str, ...]] = ("encode", "preprocess", "inference", "postprocess", "other")
GOAL_P50_MS: Final[float] = 1.5
GOAL_ULTRALYTICS_RATIO: Final[float] = 6.0
GOAL_GRID_RATIO: Final[float] = 30.0
PRIME_SCANS: Final[int] = 2  # the FIFO needs two scans before the first frame yields a tensor
_NS_PER_MS: Final[float] = 1e6


# --------------------------------------------------------------------------------------------------
# Records
# --------------------------------------------------------------------------------------------------


class ScanArgs(NamedTuple):
    """One scan's ``push_scan`` arguments, unpacked ahead of time so no pydantic access is timed, and
    the robot's pose when it was taken (``--odometry``; None: the scan carries none)."""

    ranges: np.ndarray
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    odom: Odometry | None = None

    @property
    def beams(self) -> tuple[np.ndarray, float, float, float, float]:
        return self.ranges, self.angle_min, self.angle_increment, self.range_min, self.range_max


@dataclass
class BenchConfig:
    frames: int = 1000
    paper_frames: int = 100
    paper_warmup: int = 1
    threads: tuple[int, ...] = (1, os.cpu_count() or 1)
    seed: int = 1
    fp32_model: Path = SHIPPED_FP32_MODEL
    int8_model: Path = SHIPPED_INT8_MODEL
    pt_model: Path = PAPER_CHECKPOINT  # the paper's runtime: its network (YOLOv8n), Ultralytics
    # Ultralytics on the same network as fp32_model (its .pt beside it), when that is not pt_model's
    same_network_pt: Path | None = None
    default: str = "fp32"  # which triscan file the detector runs by default (the card's recommendation)
    grid_px: int = GRID_PX
    cache_dir: Path = DEFAULT_CACHE
    skip_int8: bool = False
    skip_ultralytics: bool = False
    skip_grid: bool = False
    # 1: each pipeline's long run in one go, one pipeline after the other; N: in N rounds taking turns
    rounds: int = 1
    # The detector's motion confirmation of people (a model with a person class; common.moving_people),
    # part of its post-processing. Without odometry on the scans every frame asks the tensor whether
    # the robot stood still: the cost of a robot without odometry. With it (the simulator's, as the live
    # loop and a ROS robot send it) a driving robot's frames skip it and a standing one's skip the test.
    motion_confirm: bool = True
    odometry: bool = False

    @property
    def scans_needed(self) -> int:
        return PRIME_SCANS + self.paper_warmup + self.paper_frames + self.frames


@dataclass
class LatencyRow:
    """One pipeline at one thread count. Times in ms; ``stage_mean_ms`` over the ``frames`` run."""

    pipeline: str
    label: str
    threads: int
    paper_warmup_frames: int
    paper_frames: int
    paper_mean_ms: float
    frames: int
    p50_ms: float
    p99_ms: float
    mean_ms: float
    max_ms: float
    stage_mean_ms: dict[str, float]
    detections_per_frame: float


@dataclass
class RatioRow:
    """``numerator ÷ denominator`` of two pipelines' latencies at one thread count."""

    threads: int
    numerator: str
    denominator: str
    paper_mean: float
    p50: float
    p99: float


@dataclass
class BenchReport:
    config: dict[str, Any]
    machine: MachineInfo
    scans: dict[str, Any]
    rows: list[LatencyRow]
    ratios: list[RatioRow]
    goals: dict[str, dict[str, Any]]
    notes: list[str]
    wall_s: float = 0.0


# --------------------------------------------------------------------------------------------------
# Pipelines
# --------------------------------------------------------------------------------------------------

Stages = tuple[float, float, float, float]  # encode, preprocess, inference, postprocess (ms)


class Pipeline(Protocol):
    def prime(self, scan: ScanArgs) -> None: ...

    def frame(self, scan: ScanArgs) -> tuple[Stages, int]: ...


def _stacked(stacker: ScanStacker, scan: ScanArgs) -> np.ndarray:
    """The stacked tensor of a FIFO primed with two scans (``prime``), after pushing ``scan``."""
    tensor = stacker.push_scan(*scan.beams)
    if tensor is None:
        raise RuntimeError("the scan FIFO holds fewer than three scans: prime the pipeline first")
    return tensor


class TriscanPipeline:
    """ScanStacker + OnnxDetector: the detector service's per-frame path."""

    def __init__(self, model_path: Path, threads: int, motion_confirm: bool = True) -> None:
        self.stacker = ScanStacker()
        self.detector = OnnxDetector(
            model_path,
            intra_op_threads=threads,
            providers=["CPUExecutionProvider"],
            motion_confirm=DEFAULT_MOTION_CONFIRM if motion_confirm else None,
        )
        self.poses: deque[Odometry | None] = deque(maxlen=STACK_DEPTH)  # the FIFO's scans', oldest first

    def prime(self, scan: ScanArgs) -> None:
        self.stacker.push_scan(*scan.beams)
        self.poses.append(scan.odom)

    def frame(self, scan: ScanArgs) -> tuple[Stages, int]:
        t0 = time.perf_counter_ns()
        tensor = _stacked(self.stacker, scan)
        self.poses.append(scan.odom)
        t1 = time.perf_counter_ns()
        # What odometry says of the tensor's three scans, as the detector service asks it (None
        # without odometry: motion confirmation then asks the tensor).
        still = self.detector.still_by_odometry(list(self.poses))
        boxes, _scores, _classes, timings = self.detector.detect_boxes(tensor, still)
        encode_ms = (t1 - t0) / _NS_PER_MS
        return (encode_ms, timings.encode_ms, timings.inference_ms, timings.nms_ms), len(boxes)


class UltralyticsPipeline:
    """ScanStacker + Ultralytics ``predict`` on the ``.pt`` checkpoint (torch, CPU)."""

    def __init__(self, pt_path: Path, threads: int) -> None:
        from training.offline import configure_offline

        configure_offline()
        import torch
        from ultralytics import YOLO

        torch.set_num_threads(threads)
        if torch.get_num_threads() != threads:
            raise RuntimeError(f"torch refused {threads} threads (has {torch.get_num_threads()})")
        self.stacker = ScanStacker()
        self.model = YOLO(str(pt_path), task="detect")

    def prime(self, scan: ScanArgs) -> None:
        self.stacker.push_scan(*scan.beams)

    def frame(self, scan: ScanArgs) -> tuple[Stages, int]:
        t0 = time.perf_counter_ns()
        tensor = _stacked(self.stacker, scan)
        bgr = np.ascontiguousarray(tensor[..., ::-1])  # Ultralytics flips "BGR" back: net sees t−2 first
        t1 = time.perf_counter_ns()
        results: Any = self.model.predict(  # Ultralytics types its results loosely
            source=bgr,
            imgsz=(RANGE_ROWS, IMAGE_WIDTH),
            device="cpu",
            verbose=False,
            conf=DEFAULT_CONF,
            iou=DEFAULT_IOU,
        )
        result = results[0]
        boxes = result.boxes.xyxy.numpy()  # what a consumer would read; part of the deployed cost
        speed = result.speed  # ms, measured by Ultralytics inside predict
        encode_ms = (t1 - t0) / _NS_PER_MS
        return (encode_ms, speed["preprocess"], speed["inference"], speed["postprocess"]), len(boxes)


class GridPipeline:
    """Occupancy-grid rasteriser + untrained YOLOv8n at 640 in ONNX Runtime + our decode and NMS."""

    def __init__(self, model_path: Path, threads: int) -> None:
        self.detector = GridDetector(model_path, intra_op_threads=threads)

    def prime(self, scan: ScanArgs) -> None:
        pass  # the grid is drawn from one scan; nothing to fill

    def frame(self, scan: ScanArgs) -> tuple[Stages, int]:
        t0 = time.perf_counter_ns()
        image = rasterise_occupancy_grid(*scan.beams, size=self.detector.size)
        t1 = time.perf_counter_ns()
        boxes, _scores, _classes, (pre_ms, inference_ms, post_ms) = self.detector.detect_boxes(image)
        return ((t1 - t0) / _NS_PER_MS, pre_ms, inference_ms, post_ms), len(boxes)


# --------------------------------------------------------------------------------------------------
# Measurement
# --------------------------------------------------------------------------------------------------


def simulated_scans(count: int, seed: int, odometry: bool = False) -> list[ScanArgs]:
    """``count`` consecutive scans of one simulated robot (10 Hz, a new world every 30 s of sim time),
    with the simulator's odometry when ``odometry``."""
    from services.sim_bag import recorded_scans

    return [
        ScanArgs(
            np.ascontiguousarray(scan.ranges, dtype=np.float32),
            scan.angle_min,
            scan.angle_increment,
            scan.range_min,
            scan.range_max,
            scan.odom if odometry else None,
        )
        for scan in recorded_scans(count, seed=seed)
    ]


def time_frames(pipeline: Pipeline, scans: Sequence[ScanArgs]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Wall time of each frame (ms), its stage split ``[n, 4]`` (ms) and its detection count."""
    totals = np.empty(len(scans))
    stages = np.empty((len(scans), 4))
    detections = np.empty(len(scans), dtype=np.int64)
    for i, scan in enumerate(scans):
        t0 = time.perf_counter_ns()
        split, count = pipeline.frame(scan)
        totals[i] = (time.perf_counter_ns() - t0) / _NS_PER_MS
        stages[i] = split
        detections[i] = count
    return totals, stages, detections


def _paper_mean_phase(pipeline: Pipeline, scans: Sequence[ScanArgs], config: BenchConfig) -> np.ndarray:
    """Prime the FIFO, run the warm-up frames, then time the paper's consecutive frames."""
    for scan in scans[:PRIME_SCANS]:
        pipeline.prime(scan)
    start = PRIME_SCANS
    for scan in scans[start : start + config.paper_warmup]:
        pipeline.frame(scan)
    start += config.paper_warmup
    gc.collect()
    paper, _, _ = time_frames(pipeline, scans[start : start + config.paper_frames])
    return paper


def round_bounds(frames: int, rounds: int) -> list[tuple[int, int]]:
    """``[start, stop)`` of each round's share of the ``frames`` long-run frames: consecutive, as even
    as possible, together exactly ``range(frames)``."""
    if rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    edges = np.linspace(0, frames, min(rounds, frames) + 1).round().astype(int).tolist()
    return list(itertools.pairwise(edges))


def measure_in_turns(
    pipelines: Sequence[tuple[str, Pipeline]], threads: int, scans: Sequence[ScanArgs], config: BenchConfig
) -> list[LatencyRow]:
    """The protocol of the module docstring for several pipelines at one thread count, their long runs
    split into ``config.rounds`` rounds that take turns.

    Each pipeline first has its paper-style phase; then, round by round, each pipeline times its next
    share of the same consecutive scans (its FIFO continues where its last share ended), so a drift
    of the machine's speed during the run reaches every pipeline alike instead of whichever ran last.
    """
    papers = [_paper_mean_phase(pipeline, scans, config) for _, pipeline in pipelines]
    start = PRIME_SCANS + config.paper_warmup + config.paper_frames
    parts: list[list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = [[] for _ in pipelines]
    for lo, hi in round_bounds(config.frames, config.rounds):
        for timed, (_, pipeline) in zip(parts, pipelines, strict=True):
            gc.collect()
            timed.append(time_frames(pipeline, scans[start + lo : start + hi]))
    rows = []
    for (name, _), paper, timed in zip(pipelines, papers, parts, strict=True):
        totals = np.concatenate([t for t, _, _ in timed])
        stages = np.concatenate([s for _, s, _ in timed])
        detections = np.concatenate([d for _, _, d in timed])
        rows.append(_latency_row(name, threads, paper, totals, stages, detections, config))
    return rows


def _latency_row(
    name: str,
    threads: int,
    paper: np.ndarray,
    totals: np.ndarray,
    stages: np.ndarray,
    detections: np.ndarray,
    config: BenchConfig,
) -> LatencyRow:
    stage_means = stages.mean(axis=0)
    other = float(np.mean(totals - stages.sum(axis=1)))
    return LatencyRow(
        pipeline=name,
        label=label(name, config.grid_px),
        threads=threads,
        paper_warmup_frames=config.paper_warmup,
        paper_frames=len(paper),
        paper_mean_ms=round(float(paper.mean()), 4),
        frames=len(totals),
        p50_ms=round(float(np.percentile(totals, 50)), 4),
        p99_ms=round(float(np.percentile(totals, 99)), 4),
        mean_ms=round(float(totals.mean()), 4),
        max_ms=round(float(totals.max()), 4),
        stage_mean_ms={
            stage: round(value, 4)
            for stage, value in zip(STAGES, [*stage_means.tolist(), other], strict=True)
        },
        detections_per_frame=round(float(detections.mean()), 3),
    )


def ratios(rows: Sequence[LatencyRow], default: str = TRISCAN_FP32) -> list[RatioRow]:
    """Every baseline ÷ triscan fp32 (and INT8 ÷ fp32), for every thread count that has both rows;
    Ultralytics on the same network ÷ fp32 (the runtime alone); and, when the detector's default is
    another file (``default``: INT8), the baselines ÷ that default (what a user gains)."""
    by_key = {(row.pipeline, row.threads): row for row in rows}
    pairs = [(name, TRISCAN_FP32) for name in (ULTRALYTICS, GRID, TRISCAN_INT8, ULTRALYTICS_SAME)]
    if default != TRISCAN_FP32:
        pairs += [(ULTRALYTICS, default), (GRID, default)]
    out = []
    for threads in sorted({row.threads for row in rows}):
        for numerator, denominator in pairs:
            row, base = by_key.get((numerator, threads)), by_key.get((denominator, threads))
            if row is None or base is None:
                continue
            out.append(
                RatioRow(
                    threads=threads,
                    numerator=numerator,
                    denominator=denominator,
                    paper_mean=round(row.paper_mean_ms / base.paper_mean_ms, 3),
                    p50=round(row.p50_ms / base.p50_ms, 3),
                    p99=round(row.p99_ms / base.p99_ms, 3),
                )
            )
    return out


def goals(
    rows: Sequence[LatencyRow], ratio_rows: Sequence[RatioRow], default: str = TRISCAN_FP32
) -> dict[str, dict[str, Any]]:
    """The targets, evaluated (never asserted) on the 1-thread rows: medians. The speed ratios are
    the detector's default file against the paper's runtime and the grid pipeline."""
    out: dict[str, dict[str, Any]] = {}
    fp32 = next((r for r in rows if r.pipeline == TRISCAN_FP32 and r.threads == 1), None)
    if fp32 is not None:
        out["triscan_fp32_p50_ms_at_1_thread"] = {
            "value": fp32.p50_ms,
            "target": f"<= {GOAL_P50_MS}",
            "met": fp32.p50_ms <= GOAL_P50_MS,
        }
    for name, target in ((ULTRALYTICS, GOAL_ULTRALYTICS_RATIO), (GRID, GOAL_GRID_RATIO)):
        ratio = next(
            (r for r in ratio_rows if (r.numerator, r.denominator, r.threads) == (name, default, 1)), None
        )
        if ratio is not None:
            out[f"{name}_over_{default}_p50_at_1_thread"] = {
                "value": ratio.p50,
                "target": f">= {target}",
                "met": ratio.p50 >= target,
            }
    return out


# --------------------------------------------------------------------------------------------------
# Run, print, CLI
# --------------------------------------------------------------------------------------------------


def _shown(path: Path) -> str:
    """A path as the report shows it: relative to the repository when inside it (no home directories)."""
    resolved = Path(path).resolve()
    return str(resolved.relative_to(ROOT)) if resolved.is_relative_to(ROOT) else str(path)


def _factories(config: BenchConfig, grid_model: Path | None) -> list[tuple[str, Callable[[int], Pipeline]]]:
    motion = config.motion_confirm
    factories: list[tuple[str, Callable[[int], Pipeline]]] = [
        (TRISCAN_FP32, lambda t: TriscanPipeline(config.fp32_model, t, motion))
    ]
    if not config.skip_int8:
        factories.append((TRISCAN_INT8, lambda t: TriscanPipeline(config.int8_model, t, motion)))
    if not config.skip_ultralytics:
        factories.append((ULTRALYTICS, lambda t: UltralyticsPipeline(config.pt_model, t)))
        same = config.same_network_pt
        if same is not None and same.resolve() != config.pt_model.resolve():
            factories.append((ULTRALYTICS_SAME, lambda t: UltralyticsPipeline(same, t)))
    if grid_model is not None:
        factories.append((GRID, lambda t: GridPipeline(grid_model, t)))
    return factories


def _log_row(row: LatencyRow) -> None:
    log.info(
        "%-15s %d thread(s): p50 %.3f ms, p99 %.3f ms", row.pipeline, row.threads, row.p50_ms, row.p99_ms
    )


def run(config: BenchConfig) -> BenchReport:
    """Generate the scans, then measure every pipeline at every thread count: one after the other, or
    in ``config.rounds`` turns."""
    if config.frames < 1 or config.paper_frames < 1 or config.paper_warmup < 0 or config.rounds < 1:
        raise ValueError("need frames >= 1, paper_frames >= 1, paper_warmup >= 0 and rounds >= 1")
    started = time.perf_counter()
    machine = machine_info()
    if machine.loadavg_start[0] > 0.5 * machine.usable_cpus:
        log.warning(
            "load average %.2f on %d cpus: the machine is not quiet, figures will be noisy",
            machine.loadavg_start[0],
            machine.usable_cpus,
        )
    log.info("simulating %d scans (seed %d)…", config.scans_needed, config.seed)
    scans = simulated_scans(config.scans_needed, config.seed, config.odometry)
    # Exported (once, then cached) before anything is timed.
    grid_model = None if config.skip_grid else grid_model_onnx(config.cache_dir, config.grid_px)
    factories = _factories(config, grid_model)
    rows: list[LatencyRow] = []
    # One round: one pipeline after the other, each alone in memory. Rounds: all of them taking turns.
    groups = [[factory] for factory in factories] if config.rounds == 1 else [factories]
    for threads in dict.fromkeys(config.threads):  # ordered, without duplicates (1 core: one row)
        for group in groups:
            pipelines = [(name, factory(threads)) for name, factory in group]
            measured = measure_in_turns(pipelines, threads, scans, config)
            del pipelines
            gc.collect()
            for row in measured:
                _log_row(row)
            rows += measured
    machine.loadavg_end = [round(x, 2) for x in os.getloadavg()]
    default = PRECISION_PIPELINES[config.default]
    ratio_rows = ratios(rows, default)
    config_dict = {k: (_shown(v) if isinstance(v, Path) else v) for k, v in asdict(config).items()}
    return BenchReport(
        config=config_dict,
        machine=machine,
        scans={
            "source": "services.simulator.fleet.SimulatedFleet(robots=1, rate_hz=10), PyBullet",
            "seed": config.seed,
            "count": len(scans),
            "grid_model": _shown(grid_model) if grid_model else None,
            "beams": int(scans[0].ranges.size),
        },
        rows=rows,
        ratios=ratio_rows,
        goals=goals(rows, ratio_rows, default),
        notes=[
            "frame = encode (+ FIFO) + model-input conversion + inference + decode/NMS, batch 1, wall clock",
            "paper_mean_ms: mean of paper_frames consecutive frames after paper_warmup_frames warm-up",
            "p50/p99/mean/max and stage means: the following `frames` frames",
            "ultralytics_pt is given tensor[..., ::-1] (it reads numpy as BGR); its letterbox is a no-op "
            "at 64×384; its stage split is its own Results.speed",
            f"occupancy_grid: untrained YOLOv8n weights, timing only; encode = scan → "
            f"{config.grid_px}×{config.grid_px} occupancy image ({GRID_RADIUS_M:g} m centre to edge)",
            "ratios: numerator ÷ denominator (int8 ÷ fp32 < 1 means INT8 is faster); "
            f"the detector's default file: {default}",
        ],
        wall_s=round(time.perf_counter() - started, 1),
    )


def format_table(report: BenchReport) -> str:
    header = (
        f"{'pipeline':<64} {'thr':>3} {'paper':>9} {'p50':>9} {'p99':>9} {'mean':>9} │ "
        + " ".join(f"{s[:6]:>7}" for s in STAGES)
        + f" {'det/fr':>6}"
    )
    lines = [
        f"per-frame latency in ms, batch 1 — {report.machine.cpu_model}, {report.machine.logical_cpus} "
        f"cpus; paper = mean of {report.config['paper_frames']} after {report.config['paper_warmup']} "
        f"warm-up; p50/p99 over {report.config['frames']} frames",
        header,
        "─" * len(header),
    ]
    for row in report.rows:
        lines.append(
            f"{row.label:<64} {row.threads:>3} {row.paper_mean_ms:>9.3f} {row.p50_ms:>9.3f} "
            f"{row.p99_ms:>9.3f} {row.mean_ms:>9.3f} │ "
            + " ".join(f"{row.stage_mean_ms[s]:>7.3f}" for s in STAGES)
            + f" {row.detections_per_frame:>6.2f}"
        )
    lines.append("")
    lines.append(f"{'ratios':<52} {'paper':>8} {'p50':>7} {'p99':>7}")
    for ratio in report.ratios:
        pair = f"{ratio.numerator} ÷ {ratio.denominator}, {ratio.threads} thread(s)"
        lines.append(f"  {pair:<50} {ratio.paper_mean:>8.2f} {ratio.p50:>7.2f} {ratio.p99:>7.2f}")
    lines.append("")
    for name, goal in report.goals.items():
        lines.append(
            f"goal {name}: {goal['value']} (target {goal['target']}) → {'met' if goal['met'] else 'NOT met'}"
        )
    lines.append(f"load average start {report.machine.loadavg_start}, end {report.machine.loadavg_end}")
    return "\n".join(lines)


def _parse_threads(text: str) -> tuple[int, ...]:
    values = []
    for part in text.split(","):
        part = part.strip()
        values.append((os.cpu_count() or 1) if part == "all" else int(part))
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"threads must be positive integers or 'all', got {text!r}")
    return tuple(values)


def _existing(path: Path) -> Path | None:
    return path if path.is_file() else None


def _card_recommendation(fp32_model: Path) -> str:
    """What the card beside ``fp32_model`` recommends for the detector, when that card is the file's
    (``fp32`` otherwise: no card speaks for it)."""
    card_path = fp32_model.parent / "MODEL_CARD.json"
    if not card_path.is_file():
        return "fp32"
    card = json.loads(card_path.read_text())
    if card.get("files", {}).get("fp32") != fp32_model.name:
        return "fp32"
    return str(card.get("recommended", "fp32"))


def parse_args(argv: Sequence[str] | None) -> tuple[BenchConfig, Path]:
    assert __doc__ is not None
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, default=1000, help="frames for p50/p99 (default 1000)")
    parser.add_argument("--paper-frames", type=int, default=100, help="frames in the paper's mean (100)")
    parser.add_argument("--paper-warmup", type=int, default=1, help="warm-up frames before them (1)")
    parser.add_argument("--threads", type=_parse_threads, default="1,all", help="e.g. '1,all' or '1,2,4'")
    parser.add_argument("--seed", type=int, default=1, help="simulator seed of the scans")
    parser.add_argument("--fp32-model", type=Path, default=BenchConfig.fp32_model)
    parser.add_argument("--int8-model", type=Path, default=BenchConfig.int8_model)
    parser.add_argument("--pt-model", type=Path, default=BenchConfig.pt_model, help="the paper's runtime")
    parser.add_argument(
        "--same-network-pt", type=Path, default=None,
        help="Ultralytics checkpoint of the --fp32-model's network (default: its .pt beside it, if any)",
    )  # fmt: skip
    parser.add_argument(
        "--default", choices=sorted(PRECISION_PIPELINES), default=None,
        help="the detector's default file (default: the recommendation of the card beside --fp32-model)",
    )  # fmt: skip
    parser.add_argument("--grid-px", type=int, default=GRID_PX, help="grid image side (640)")
    parser.add_argument("--cache-dir", type=Path, default=DEFAULT_CACHE, help="exported grid model cache")
    parser.add_argument("--skip-int8", action="store_true")
    parser.add_argument("--skip-ultralytics", action="store_true")
    parser.add_argument("--skip-grid", action="store_true")
    parser.add_argument(
        "--rounds", type=int, default=1,
        help="split each pipeline's --frames into this many rounds, the pipelines taking turns (1: one "
        "after the other); ratios then hold when the machine's speed drifts during the run",
    )  # fmt: skip
    add_motion_argument(parser)
    parser.add_argument(
        "--odometry", action="store_true",
        help="the scans carry the simulator's odometry, as the live loop's and a ROS robot's do: motion "
        "confirmation asks it, not the tensor, whether the robot stood (default: no odometry)",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="JSON report path")
    args = parser.parse_args(argv)
    config = BenchConfig(
        frames=args.frames,
        paper_frames=args.paper_frames,
        paper_warmup=args.paper_warmup,
        threads=args.threads,
        seed=args.seed,
        fp32_model=args.fp32_model,
        int8_model=args.int8_model,
        pt_model=args.pt_model,
        same_network_pt=args.same_network_pt or _existing(args.fp32_model.with_suffix(".pt")),
        default=args.default or _card_recommendation(args.fp32_model),
        grid_px=args.grid_px,
        cache_dir=args.cache_dir,
        skip_int8=args.skip_int8,
        skip_ultralytics=args.skip_ultralytics,
        skip_grid=args.skip_grid,
        rounds=args.rounds,
        motion_confirm=motion_confirm_of(args) is not None,
        odometry=args.odometry,
    )
    return config, args.out


def main(argv: Sequence[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    config, out = parse_args(argv)
    report = run(config)
    print(format_table(report))
    write_report(report, out, echo=False)
    log.info("wrote %s (%.0f s)", out, report.wall_s)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
