"""What the robot carries: peak memory of encoder + detector while serving, and the model files.

Runs the robot's processes under real load (one simulated robot at 10 Hz for ``--seconds``, via
:mod:`bench.pipeline_latency`) in both deployments: encoder and detector as two processes, and the
single ``--from-scans`` detector. Peak RSS is each process's ``VmHWM``; model sizes are every ONNX
file under ``models/``, named by its path there (the default's directory is
``common.model_spec.SHIPPED_DIR``).

    python -m bench.robot_footprint --seconds 30
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from bench.pipeline_latency import run as run_pipeline
from bench.report import write_report
from common.model_spec import MODELS_DIR


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--out", type=Path, default=Path("bench/results/robot_footprint.json"))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    separate = run_pipeline(1, 10.0, args.seconds, from_scans=False, threads=None)
    combined = run_pipeline(1, 10.0, args.seconds, from_scans=True, threads=None)
    report = {
        "peak_rss_mb": {
            "encoder + detector (2 processes)": separate.peak_rss_mb,
            "detector --from-scans (1 process)": combined.peak_rss_mb,
        },
        "peak_rss_mb_total": {
            "encoder + detector (2 processes)": round(sum(separate.peak_rss_mb.values()), 1),
            "detector --from-scans (1 process)": round(sum(combined.peak_rss_mb.values()), 1),
        },
        "model_files_mb": {
            f.relative_to(MODELS_DIR).as_posix(): round(f.stat().st_size / 2**20, 2)
            for f in sorted(MODELS_DIR.rglob("*.onnx"))
        },
        "seconds": args.seconds,
    }
    write_report(report, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
