"""Data set generation rate: samples per second on all cores, and the time for the paper's full scale.

Runs ``training.dataset.generate_dataset`` (what ``triscan dataset`` runs) on ``--scenarios`` worlds at
the paper's 90 positions and every window kept (stride 1, as the paper), into a temporary directory,
and extrapolates the measured rate to the paper's 160 scenarios. ``--scenarios 160`` measures the full
scale instead of extrapolating.

    python -m bench.dataset_rate --scenarios 16
"""

from __future__ import annotations

import argparse
import logging
import os
import tempfile
import time
from pathlib import Path

from bench.report import write_report
from training.dataset import DatasetConfig, generate_dataset

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

PAPER_SCENARIOS = 160
PAPER_POSITIONS = 90


def measure(scenarios: int, positions: int, workers: int) -> dict[str, object]:
    with tempfile.TemporaryDirectory(prefix="triscan-bench-") as tmp:
        config = DatasetConfig(
            out=Path(tmp) / "data", scenarios=scenarios, positions=positions, seed=0, workers=workers
        )
        started = time.perf_counter()
        summary = generate_dataset(config, progress=False)
        elapsed = time.perf_counter() - started
        disk_bytes = sum(f.stat().st_size for f in (Path(tmp) / "data").rglob("*") if f.is_file())
    samples = sum(summary["samples"].values())  # type: ignore[union-attr]
    rate = samples / elapsed
    per_scenario = samples / scenarios
    paper_samples = per_scenario * PAPER_SCENARIOS
    return {
        "scenarios": scenarios,
        "positions": positions,
        "workers": workers,
        "samples": samples,
        "elapsed_s": round(elapsed, 2),
        "samples_per_s": round(rate, 1),
        "bytes_per_sample": round(disk_bytes / samples, 1),
        "paper_scale": {
            "scenarios": PAPER_SCENARIOS,
            "positions": PAPER_POSITIONS,
            "samples": round(paper_samples),
            "minutes": round(paper_samples / rate / 60, 1),
            "measured": scenarios == PAPER_SCENARIOS and positions == PAPER_POSITIONS,
        },
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", type=int, default=16)
    parser.add_argument("--positions", type=int, default=PAPER_POSITIONS)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--out", type=Path, default=Path("bench/results/dataset_rate.json"))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    report = measure(args.scenarios, args.positions, args.workers)
    write_report(report, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
