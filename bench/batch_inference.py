"""Would batching frames across robots raise fleet capacity? Per-image cost of YOLOv8n vs batch size.

Times ``session.run`` of the shipped ``-batch`` models (the evaluated networks with a free batch
axis, :func:`training.batch_variant.add_batch_axis`) on B real stacked tensors at once, for each B and
thread count.
If the per-image cost falls below the batch-1 cost, a detector draining several robots per call
(``services.detector --batch``) serves proportionally more robots; this measures by how much. The
tensors come from simulated scans through the encoder, so sparsity matches what the detector sees.

    python -m bench.batch_inference --batches 1,2,4,8,16
"""

from __future__ import annotations

import argparse
import logging
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bench.harness import recorded_scans
from bench.machine import MachineInfo, machine_info
from bench.report import write_report
from common.encoding import to_model_input
from common.inference import session_options
from common.model_spec import SHIPPED_FP32_MODEL, SHIPPED_INT8_MODEL, batch_variant_path
from services.encoder.core import EncoderCore

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

MODELS = (batch_variant_path(SHIPPED_FP32_MODEL), batch_variant_path(SHIPPED_INT8_MODEL))
FRAMES = 64  # distinct real frames; batches are cut from them in turn


@dataclass
class BatchRow:
    model: str
    threads: int
    batch: int
    ms_per_call: float
    ms_per_image: float
    speedup_per_image: float  # batch-1 cost per image ÷ this cost per image, same model and threads


@dataclass
class BatchReport:
    models: list[str]
    frames: int
    rows: list[BatchRow] = field(default_factory=list)
    machine: MachineInfo = field(default_factory=machine_info)


def real_model_inputs(count: int) -> np.ndarray:
    """``float32[count, 3, 64, 384]``: simulated scans through the encoder and the detector's conversion."""
    encoder = EncoderCore("zero")
    inputs = []
    for scan in recorded_scans(count + 2, seed=11):
        tensor = encoder.push(scan)
        if tensor is not None:
            inputs.append(to_model_input(tensor.tensor))
    return np.concatenate(inputs[:count])


def measure(
    models: list[Path], batches: list[int], threads_list: list[int], seconds: float, frames: np.ndarray
) -> BatchReport:
    import onnxruntime as ort

    report = BatchReport(models=[m.name for m in models], frames=len(frames))
    for model in models:
        for threads in threads_list:
            session = ort.InferenceSession(
                str(model), session_options(threads), providers=["CPUExecutionProvider"]
            )
            name = session.get_inputs()[0].name
            base_per_image = None
            for batch in batches:
                feeds = batched_feeds(name, frames, batch)
                for feed in feeds[:3]:
                    session.run(None, feed)
                calls, started = 0, time.perf_counter()
                while (elapsed := time.perf_counter() - started) < seconds or calls < 3:
                    session.run(None, feeds[calls % len(feeds)])
                    calls += 1
                per_call = elapsed / calls * 1e3
                per_image = per_call / batch
                base_per_image = base_per_image or per_image
                row = BatchRow(
                    model.name,
                    threads,
                    batch,
                    round(per_call, 3),
                    round(per_image, 3),
                    round(base_per_image / per_image, 2),
                )
                report.rows.append(row)
                log.info(
                    "%s threads %d batch %2d: %.2f ms/call, %.2f ms/image (%.2fx)",
                    model.name,
                    threads,
                    batch,
                    per_call,
                    per_image,
                    row.speedup_per_image,
                )
    return report


def batched_feeds(input_name: str, frames: np.ndarray, batch: int) -> list[dict[str, np.ndarray]]:
    """The frames cut into model inputs of ``batch`` frames (the last one wraps around)."""
    return [
        {input_name: np.take(frames, range(i, i + batch), axis=0, mode="wrap")}
        for i in range(0, len(frames), batch)
    ]


def measure_parallel_sessions(
    model: Path, workers: int, batches: list[int], seconds: float, frames: np.ndarray
) -> list[dict[str, float]]:
    """Frames/s of ``workers`` single-threaded sessions running at once, one Python thread each (ONNX
    Runtime releases the GIL), per batch size: the detector's ``--workers N --threads 1`` on the
    network alone."""
    rows = []
    for batch in batches:
        frames_per_s = _parallel_frames_per_s(model, workers, batch, seconds, frames)
        rows.append(
            {"workers": workers, "threads": 1, "batch": batch, "frames_per_s": round(frames_per_s, 1)}
        )
        log.info(
            "%s %d sessions x 1 thread, batch %2d: %.1f frames/s", model.name, workers, batch, frames_per_s
        )
    return rows


def _parallel_frames_per_s(
    model: Path, workers: int, batch: int, seconds: float, frames: np.ndarray
) -> float:
    import onnxruntime as ort

    sessions = [
        ort.InferenceSession(str(model), session_options(1), providers=["CPUExecutionProvider"])
        for _ in range(workers)
    ]
    feeds = batched_feeds(sessions[0].get_inputs()[0].name, frames, batch)
    for session in sessions:
        session.run(None, feeds[0])
    counts = [0] * workers
    go, stop = threading.Barrier(workers + 1), threading.Event()

    def serve(index: int) -> None:
        go.wait()
        while not stop.is_set():
            sessions[index].run(None, feeds[counts[index] % len(feeds)])
            counts[index] += 1

    threads = [threading.Thread(target=serve, args=(i,)) for i in range(workers)]
    for thread in threads:
        thread.start()
    go.wait()  # every session starts at once
    started = time.perf_counter()
    time.sleep(seconds)
    stop.set()
    for thread in threads:
        thread.join()
    return sum(counts) * batch / (time.perf_counter() - started)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--models",
        type=Path,
        nargs="+",
        default=list(MODELS),
        help="models with a free batch axis (default: the shipped fp32 and INT8 -batch files)",
    )
    parser.add_argument("--batches", default="1,2,4,8,16", help="batch sizes, starting with 1")
    parser.add_argument("--threads", default=f"1,{os.cpu_count() or 1}", help="ONNX Runtime thread counts")
    parser.add_argument(
        "--seconds", type=float, default=3.0, help="timed seconds per model, threads and batch"
    )
    parser.add_argument("--frames", type=int, default=FRAMES, help="distinct real frames to cycle through")
    parser.add_argument("--out", type=Path, default=Path("bench/results/batch_inference.json"))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    batches = [int(b) for b in args.batches.split(",")]
    if batches[0] != 1 or any(b < 1 for b in batches):
        parser.error("--batches must start with 1 (the reference) and hold positive sizes")
    if args.frames < 1:
        parser.error("--frames must be >= 1")
    threads = sorted({int(t) for t in args.threads.split(",")})
    report = measure(args.models, batches, threads, args.seconds, real_model_inputs(args.frames))
    write_report(report, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
