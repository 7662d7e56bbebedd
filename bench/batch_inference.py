"""Would batching frames across robots raise fleet capacity? Per-image cost of YOLOv8n vs batch size.

Exports the shipped checkpoint once more with a dynamic batch axis (the shipped ONNX is fixed at
1×3×64×384, which the detector's input check relies on) into a cache directory, then times
``session.run`` on B stacked real-shaped tensors for each B and thread count. If the per-image cost
fell far below the batch-1 cost, a detector draining several robots per call would serve
proportionally more robots; this measures by how much.

    python -m bench.batch_inference --batches 1,2,4,8,16
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bench.machine import MachineInfo, machine_info
from bench.report import write_report

log = logging.getLogger("bench.batch_inference")

ROOT = Path(__file__).resolve().parents[1]
CHECKPOINT = ROOT / "models" / "triscan-yolov8n-zero.pt"


@dataclass
class BatchRow:
    threads: int
    batch: int
    ms_per_call: float
    ms_per_image: float
    speedup_per_image: float  # batch-1 cost per image ÷ this cost per image, same threads


@dataclass
class BatchReport:
    model: str
    rows: list[BatchRow] = field(default_factory=list)
    machine: MachineInfo = field(default_factory=machine_info)


def export_dynamic(cache_dir: Path) -> Path:
    """The shipped checkpoint as ONNX with a dynamic batch axis, exported once into ``cache_dir``."""
    from training.offline import configure_offline

    target = cache_dir / "triscan-yolov8n-zero-dynamic.onnx"
    if target.is_file() and target.stat().st_mtime >= CHECKPOINT.stat().st_mtime:
        return target
    configure_offline()
    import shutil

    from ultralytics import YOLO

    cache_dir.mkdir(parents=True, exist_ok=True)
    weights = cache_dir / CHECKPOINT.name
    shutil.copyfile(CHECKPOINT, weights)  # Ultralytics writes the export next to its weights
    exported = Path(YOLO(str(weights)).export(format="onnx", imgsz=(64, 384), dynamic=True, simplify=True))
    exported.replace(target)
    return target


def measure(model: Path, batches: list[int], threads_list: list[int], seconds: float) -> BatchReport:
    import onnxruntime as ort

    report = BatchReport(model=model.name)
    rng = np.random.default_rng(0)
    for threads in threads_list:
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        session = ort.InferenceSession(str(model), options, providers=["CPUExecutionProvider"])
        name = session.get_inputs()[0].name
        base_per_image = None
        for batch in batches:
            # Sparse binary frames like real rasters (about 1 % of pixels hit), scaled as the detector does.
            frames = (rng.random((batch, 3, 64, 384)) < 0.01).astype(np.float32)
            for _ in range(3):
                session.run(None, {name: frames})
            calls, started = 0, time.perf_counter()
            while (elapsed := time.perf_counter() - started) < seconds or calls < 3:
                session.run(None, {name: frames})
                calls += 1
            per_call = elapsed / calls * 1e3
            per_image = per_call / batch
            base_per_image = base_per_image or per_image
            row = BatchRow(
                threads, batch, round(per_call, 3), round(per_image, 3), round(base_per_image / per_image, 2)
            )
            report.rows.append(row)
            log.info(
                "threads %d batch %2d: %.2f ms/call, %.2f ms/image (%.2fx)",
                threads,
                batch,
                per_call,
                per_image,
                row.speedup_per_image,
            )
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batches", default="1,2,4,8,16", help="batch sizes, starting with 1")
    parser.add_argument("--threads", default=f"1,{os.cpu_count() or 1}", help="ONNX Runtime thread counts")
    parser.add_argument("--seconds", type=float, default=3.0, help="timed seconds per (threads, batch)")
    parser.add_argument("--cache-dir", type=Path, default=ROOT / "runs" / "bench_cache")
    parser.add_argument("--out", type=Path, default=Path("bench/results/batch_inference.json"))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    batches = [int(b) for b in args.batches.split(",")]
    if batches[0] != 1:
        parser.error("--batches must start with 1 (the reference)")
    threads = sorted({int(t) for t in args.threads.split(",")})
    report = measure(export_dynamic(args.cache_dir), batches, threads, args.seconds)
    write_report(report, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
