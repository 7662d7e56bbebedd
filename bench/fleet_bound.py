"""The fleet the services hold at 10 Hz against the compute bound of the model, in one run.

The bound is what the network alone could do on this machine: the default detector model's best
throughput (frames/s) over batch sizes and the ways to use every core (one session with one or all
ONNX Runtime threads, or one single-threaded session per core at once), no Zenoh, no encoder.
Divided by the scan rate it is the most robots any pipeline could serve here. Then
``bench.fleet_capacity`` climbs a ladder of robot counts at fractions of that bound with the detector
left to its own defaults (``--detector-defaults``: no ``--workers``, ``--batch`` or ``--threads``),
and the share of the bound it holds (p99 < 100 ms, ≥ 95 % answered, flat memory) is the fleet goal's
figure (goal ≥ ``FLEET_GOAL_SHARE``). Each step's CPU per
answered scan, process by process, says how far the whole pipeline's cost per scan is from the
network's own (:func:`cpu_per_scan`).

    python -m bench.fleet_bound --seconds 15 --out bench/results/fleet_bound.json

``--encode-on-robots`` runs the fleet as a fleet server sees it: the robots encode on board and send
tensors, and this host runs the detector alone (``bench.fleet_capacity --encode-on-robots``).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import tempfile
import threading
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from bench import fleet_capacity
from bench.machine import machine_info
from common.encoding import to_model_input
from common.inference import model_facts, session_options
from services.detector.batch_cap import detector_model_and_batch
from services.encoder.core import EncoderCore
from services.sim_bag import recorded_scans

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

FRACTIONS = (0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0)  # from low: a VM minute can fail 50 %
FLEET_GOAL_SHARE = 0.8  # the fleet goal: the robots held ÷ the compute bound
BOUND_FRAMES = 64  # distinct real frames the bound's batches are cut from in turn
BOUND_BATCHES = (1, 2, 4, 8)  # the batch sizes the detector may pick


def real_model_inputs(count: int) -> np.ndarray:
    """``float32[count, 3, 64, 384]``: simulated scans through the encoder and the detector's conversion,
    so the network sees the sparsity it sees in service."""
    encoder = EncoderCore("zero")
    inputs = []
    for scan in recorded_scans(count + 2, seed=11):
        tensor = encoder.push(scan)
        if tensor is not None:
            inputs.append(to_model_input(tensor.tensor))
    return np.concatenate(inputs[:count])


def frames_per_s(
    model: Path, sessions: int, threads: int, batch: int, seconds: float, frames: np.ndarray
) -> float:
    """Frames/s of ``sessions`` ONNX Runtime sessions of ``threads`` threads each running ``model`` at
    once, one Python thread each (ONNX Runtime releases the GIL), ``batch`` frames a call: the
    detector's ``--workers sessions --threads threads`` on the network alone."""
    import onnxruntime as ort

    runners = [
        ort.InferenceSession(str(model), session_options(threads), providers=["CPUExecutionProvider"])
        for _ in range(sessions)
    ]
    name = runners[0].get_inputs()[0].name
    feeds = [
        {name: np.take(frames, range(i, i + batch), axis=0, mode="wrap")}
        for i in range(0, len(frames), batch)
    ]
    for runner in runners:
        for feed in feeds[:3]:
            runner.run(None, feed)
    counts = [0] * sessions
    go, stop = threading.Barrier(sessions + 1), threading.Event()

    def serve(index: int) -> None:
        go.wait()
        while not stop.is_set():
            runners[index].run(None, feeds[counts[index] % len(feeds)])
            counts[index] += 1

    workers = [threading.Thread(target=serve, args=(i,)) for i in range(sessions)]
    for worker in workers:
        worker.start()
    go.wait()  # every session starts at once
    started = time.perf_counter()
    time.sleep(seconds)
    stop.set()
    for worker in workers:
        worker.join()
    return sum(counts) * batch / (time.perf_counter() - started)


def compute_bound(model: Path, seconds: float) -> dict[str, object]:
    """Best frames/s of ``model`` (the network alone) over batch sizes and the ways to use the cores:
    one session with 1 or all threads, or one single-threaded session per core running at once."""
    frames = real_model_inputs(BOUND_FRAMES)
    cores = os.cpu_count() or 1
    ways = sorted({(1, 1), (1, cores), (cores, 1)})
    rows = []
    for sessions, threads in ways:
        for batch in BOUND_BATCHES:
            rate = frames_per_s(model, sessions, threads, batch, seconds, frames)
            rows.append(
                {"workers": sessions, "threads": threads, "batch": batch, "frames_per_s": round(rate, 1)}
            )
            log.info(
                "%s: %d x %d threads, batch %d: %.1f frames/s", model.name, sessions, threads, batch, rate
            )
    best = max(rows, key=lambda row: row["frames_per_s"])
    return {
        "model": model.name,
        "best_frames_per_s": best["frames_per_s"],
        "best_workers": best["workers"],
        "best_batch": best["batch"],
        "best_threads": best["threads"],
        "rows": rows,
    }


def network_cpu_ms_per_frame(bound: dict[str, Any], cores: int) -> float:
    """CPU one frame costs at the bound: the cores its best setting kept busy ÷ its frames/s."""
    used = min(cores, int(bound["best_workers"]) * int(bound["best_threads"]))
    return 1e3 * used / float(bound["best_frames_per_s"])


def cpu_per_scan(
    fleet: dict[str, Any], bound: dict[str, Any], rate_hz: float, cores: int | None = None
) -> list[dict[str, Any]]:
    """Where each step's CPU went, in ms of CPU per answered scan, against the network at the bound.

    At the bound one frame costs ``cores used ÷ best frames/s`` of CPU. A step's processes together
    spend more per scan (Zenoh's hops, the encoder, hand-offs, this bench's publishing); at that cost
    even a machine kept 100 % busy serves at most ``cores ÷ (CPU per scan × rate)`` robots, the
    ceiling that no scheduling can lift.
    """
    cores = cores or os.cpu_count() or 1
    network_ms = network_cpu_ms_per_frame(bound, cores)
    rows = []
    for step in fleet["steps"]:
        if not step.get("cpu_cores") or not step["scans_answered"]:
            continue
        seconds = float(step.get("window_s") or fleet["seconds_per_step"])  # the window as measured
        answered_per_s = step["scans_answered"] / seconds
        per_process = {name: round(1e3 * c / answered_per_s, 2) for name, c in step["cpu_cores"].items()}
        total = sum(per_process.values())
        rows.append(
            {
                "robots": step["robots"],
                "cpu_ms_per_scan": per_process,
                "cpu_ms_per_scan_total": round(total, 2),
                "network_ms_per_frame_at_bound": round(network_ms, 2),
                "ceiling_robots_at_full_cpu": round(1e3 * cores / total / rate_hz, 1),
            }
        )
    return rows


PROFILE_BATCH = 8  # a full batch: what each frame costs past a fleet's knee


def python_per_scan(model: Path, batches: int) -> dict[str, float]:
    """ms per scan of each part of the detector's own work, in this process on recorded tensors: the
    payload's decode and validation, the model call (uint8 → float32, ``session.run`` and
    post-processing, by the detector's own timings) and the detections message's encoding. Where the
    rest of a scan's CPU in ``cpu_per_scan`` goes is Zenoh's, the hand-offs' and the GIL's."""
    from common.inference import OnnxDetector
    from common.keys import tensor_key
    from common.messages import encode_message
    from services.detector.core import DetectorCore, InferencePipeline

    encoder = EncoderCore.for_model(model_facts(model))
    tensors = [t for scan in recorded_scans(PROFILE_BATCH * 4 + 2, seed=11) if (t := encoder.push(scan))]
    payloads = [encode_message(t) for t in tensors]
    core = DetectorCore(OnnxDetector(model, intra_op_threads=1))
    pipeline = InferencePipeline([core.detector], lambda _d: None)
    core.detector.warmup(PROFILE_BATCH)
    sections = dict.fromkeys(("receive", "decode", "convert", "inference", "postprocess", "encode"), 0.0)
    frames = 0
    for round_ in range(batches):
        batch = [i % len(tensors) for i in range(round_ * PROFILE_BATCH, (round_ + 1) * PROFILE_BATCH)]
        started = time.perf_counter()
        for i in batch:
            pipeline.not_ours(tensor_key(tensors[i].robot_id))  # the callback's first look at the key
        sections["receive"] += time.perf_counter() - started
        started = time.perf_counter()
        decoded = [core.decode(payloads[i], tensors[i].robot_id) for i in batch]
        sections["decode"] += time.perf_counter() - started
        accepted = [t for t in decoded if t is not None]
        messages = core.detect_many(accepted)
        for tensor, message in zip(accepted, messages, strict=True):
            sections["convert"] += (message.timings.encode_ms - tensor.encode_ms) / 1e3  # less the encoder's
            sections["postprocess"] += message.timings.nms_ms / 1e3
        sections["inference"] += messages[0].timings.inference_ms / 1e3
        started = time.perf_counter()
        for message in messages:
            encode_message(message)
        sections["encode"] += time.perf_counter() - started
        frames += len(messages)
    return {name: round(1e3 * seconds / frames, 3) for name, seconds in sections.items()}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=10.0, help="scans per second per robot")
    parser.add_argument("--bound-seconds", type=float, default=3.0, help="seconds per batch/thread setting")
    parser.add_argument("--seconds", type=float, default=15.0, help="measured seconds per fleet step")
    parser.add_argument(
        "--encode-on-robots",
        action="store_true",
        help="the robots send tensors (their own encoder on board): the detector alone on this host",
    )
    parser.add_argument(
        "--from-scans",
        action="store_true",
        help="the robots send scans and the detector processes encode their own robots' (no encoder)",
    )
    parser.add_argument(
        "--detectors",
        type=int,
        default=None,
        help="detector processes (default: the detector's own); 1/2/4 give the scaling table",
    )
    parser.add_argument(
        "--gather-ms", type=float, default=None, help="detector --gather-ms (default: the detector's own)"
    )
    parser.add_argument(
        "--fractions", default=",".join(map(str, FRACTIONS)), help="ladder steps as shares of the bound"
    )
    parser.add_argument("--out", type=Path, default=Path("bench/results/fleet_bound.json"))
    parser.add_argument(
        "--python-per-scan",
        type=int,
        default=0,
        metavar="BATCHES",
        help="only time the detector's own sections per scan over this many full batches, and exit",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    model, _ = detector_model_and_batch(None, None)  # the model the detector runs by default
    if args.python_per_scan:
        sections = python_per_scan(model, args.python_per_scan)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"ms_per_scan": sections, "batch": PROFILE_BATCH,
                                        "machine": asdict(machine_info())}, indent=2) + "\n")  # fmt: skip
        log.info("ms per scan at batch %d: %s; written to %s", PROFILE_BATCH, sections, args.out)
        return 0
    bound = compute_bound(model, args.bound_seconds)
    bound_robots = float(bound["best_frames_per_s"]) / args.rate  # type: ignore[arg-type]
    fractions = [float(f) for f in args.fractions.split(",")]
    ladder = sorted({max(1, math.floor(f * bound_robots)) for f in fractions})
    log.info("compute bound: %.1f frames/s = %.1f robots at %.0f Hz; ladder %s", bound["best_frames_per_s"],
             bound_robots, args.rate, ladder)  # fmt: skip
    with tempfile.TemporaryDirectory() as scratch:
        fleet_json = Path(scratch) / "fleet.json"
        fleet_capacity.main(
            [
                "--ladder", ",".join(map(str, ladder)), "--seconds", str(args.seconds),
                "--rate", str(args.rate), "--detector-defaults", "--out", str(fleet_json),
                *(("--encode-on-robots",) if args.encode_on_robots else ()),
                *(("--from-scans",) if args.from_scans else ()),
                *(("--detectors", str(args.detectors)) if args.detectors else ()),
                *(("--gather-ms", str(args.gather_ms)) if args.gather_ms is not None else ()),
            ]
        )  # fmt: skip
        fleet = json.loads(fleet_json.read_text())
    capacity = int(fleet["capacity_robots"])
    report = {
        "bound": bound,
        "bound_robots": round(bound_robots, 1),
        "capacity_robots": capacity,
        "share_of_bound": round(capacity / bound_robots, 3) if bound_robots else 0.0,
        "cpu_per_scan": cpu_per_scan(fleet, bound, args.rate),
        "fleet": fleet,
        "machine": asdict(machine_info()),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2, default=str) + "\n")
    for row in report["cpu_per_scan"]:  # type: ignore[attr-defined]
        log.info("%d robots: CPU per answered scan %.2f ms %s (the network at the bound: %.2f ms a frame); "
                 "at 100 %% CPU at most %.1f robots", row["robots"], row["cpu_ms_per_scan_total"],
                 row["cpu_ms_per_scan"], row["network_ms_per_frame_at_bound"],
                 row["ceiling_robots_at_full_cpu"])  # fmt: skip
    log.info(
        "held %d robots of a %.1f-robot bound: %.0f %% (goal >= %.0f %%); written to %s",
        capacity,
        bound_robots,
        100 * report["share_of_bound"],
        100 * FLEET_GOAL_SHARE,
        args.out,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
