"""What the exact DFL rewrite buys: one checkpoint exported with and without it, timed in turns.

``triscan export`` rewrites the head's DFL softmax onto the innermost axis
(:mod:`training.onnx_rewrites`). This exports the same checkpoint both ways, checks the outputs are
equal on a simulated three-scan tensor, and times ``session.run`` of the two files run by run in
turns (1 ONNX Runtime thread, the detector's setting), so a noisy minute slows both alike.

    python -m bench.dfl_rewrite --weights models/yolov8p/triscan-yolov8p-zero.pt
    python -m bench.dfl_rewrite --weights models/triscan-yolov8n-zero.pt \
        --out bench/results/dfl_rewrite_n.json
"""

from __future__ import annotations

import argparse
import logging
import tempfile
from dataclasses import asdict
from pathlib import Path
from typing import Final

import numpy as np

from bench.harness import simulated_tensor
from bench.machine import machine_info
from bench.report import write_report
from common.encoding import to_model_input
from common.model_spec import SHIPPED_CHECKPOINT

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

DEFAULT_WEIGHTS: Final[Path] = SHIPPED_CHECKPOINT  # the default model's .pt
DEFAULT_OUT: Final[Path] = Path(__file__).resolve().parent / "results" / "dfl_rewrite.json"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", type=Path, default=DEFAULT_WEIGHTS, help="an Ultralytics checkpoint")
    parser.add_argument("--runs", type=int, default=2000, help="timed runs of each file")
    parser.add_argument("--out", type=Path, default=None, help=f"default {DEFAULT_OUT}")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    from training.export_checks import median_latency_ms
    from training.onnx_export import export_onnx
    from training.onnx_model import cpu_session
    from training.png import write_rgb_png

    with tempfile.TemporaryDirectory(prefix="triscan-dfl-") as scratch:
        before = export_onnx(args.weights, Path(scratch) / "before.onnx", rewrite_dfl=False)
        after = export_onnx(args.weights, Path(scratch) / "after.onnx")
        tensor = simulated_tensor()
        x = to_model_input(tensor)
        sessions = [cpu_session(path) for path in (before, after)]
        outputs = [session.run(None, {session.get_inputs()[0].name: x})[0] for session in sessions]
        max_abs = float(np.abs(outputs[0] - outputs[1]).max())
        image = Path(scratch) / "frame.png"
        write_rgb_png(image, tensor)
        before_ms, after_ms = median_latency_ms([before, after], image, runs=args.runs)
    log.info("outputs: max |before - after| = %g", max_abs)
    log.info(
        "session.run, 1 thread, median of %d in turns: before %.3f ms, after %.3f ms (%.3f ms less, %.1f %%)",
        *(args.runs, before_ms, after_ms, before_ms - after_ms, 100 * (1 - after_ms / before_ms)),
    )
    report = {
        "weights": str(args.weights),
        "runs": args.runs,
        "max_abs_output_difference": max_abs,
        "median_ms": {"before": round(before_ms, 4), "after": round(after_ms, 4)},
        "saved_ms": round(before_ms - after_ms, 4),
        "machine": asdict(machine_info()),
    }
    write_report(report, args.out or DEFAULT_OUT, echo=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
