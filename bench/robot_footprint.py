"""What the robot carries: peak memory of encoder + detector while serving, the model files, and the
CPU a faster sensor costs.

Runs the robot's processes under real load (one simulated robot at 10 Hz for ``--seconds``, via
:mod:`bench.pipeline_latency`) in both deployments: encoder and detector as two processes, and the
single ``--from-scans`` detector. Peak RSS is each process's ``VmHWM``; model sizes are every ONNX
file under ``models/``, named by its path there (the default's directory is
``common.model_spec.SHIPPED_DIR``). With ``--sensors``, the two processes serve each named sensor
profile at its own rate in turn, and the report gives each one's CPU (cores busy): a model that
declares its stacking period has the encoder stack a 40 Hz sensor's every 4th scan, so the detector
should cost what it costs at 10 Hz. ``NAME@HZ`` runs a profile at another rate: the same beams at 10 and
40 Hz tell the rate's cost from the denser scan's.

    python -m bench.robot_footprint --seconds 30
    python -m bench.robot_footprint --seconds 30 --sensors lds-01 ust-10lx ust-10lx@10 --model M --out F
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
from pathlib import Path

from bench.machine import machine_info
from bench.pipeline_latency import run as run_pipeline
from bench.report import write_report
from common.model_spec import MODELS_DIR
from services.simulator.sensors import PROFILES


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--out", type=Path, default=Path("bench/results/robot_footprint.json"))
    parser.add_argument(
        "--sensors", nargs="+", type=sensor_at_rate, metavar="NAME[@HZ]",
        help="instead: the CPU of encoder and detector serving each sensor profile at its own rate, or "
        f"at HZ scans a second (profiles: {', '.join(PROFILES)})",
    )  # fmt: skip
    parser.add_argument("--model", type=Path, default=None, help="ONNX model (default: the shipped one)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.sensors:
        labels = [sensor_label(name, hz) for name, hz in args.sensors]
        if len(set(labels)) < len(labels):
            parser.error(f"--sensors names a profile and rate twice: {' '.join(labels)}")
        write_report(sensor_cpu(args.sensors, args.seconds, args.model), args.out)
        return 0
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


def sensor_at_rate(text: str) -> tuple[str, float]:
    """``NAME`` (a profile at its own rate) or ``NAME@HZ``, for argparse: the profile and its rate."""
    name, _, rate = text.partition("@")
    if name not in PROFILES:
        raise argparse.ArgumentTypeError(f"no sensor profile {name!r}: one of {', '.join(PROFILES)}")
    try:
        hz = float(rate) if rate else PROFILES[name].rate_hz
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: the rate after @ must be a number of Hz") from None
    if not 0 < hz <= 100:
        raise argparse.ArgumentTypeError(f"{text!r}: the rate must lie in (0, 100] Hz")
    return name, hz


def sensor_label(name: str, rate_hz: float) -> str:
    """A report row's name: the profile, with ``@HZ`` when it runs at another rate than its own."""
    return name if rate_hz == PROFILES[name].rate_hz else f"{name}@{rate_hz:g}"


def sensor_cpu(sensors: list[tuple[str, float]], seconds: float, model: Path | None) -> dict[str, object]:
    """Cores busy in the encoder and the detector while one robot streams each sensor at its rate."""
    rows = {}
    for name, rate_hz in sensors:
        result = run_pipeline(1, rate_hz, seconds, from_scans=False, threads=None, model=model, sensor=name)
        rows[sensor_label(name, rate_hz)] = {
            "rate_hz": rate_hz,
            "beams": PROFILES[name].beams,
            "cpu_cores": result.cpu_cores,
            "scans_published": result.scans_published,
            "scans_answered": result.scans_answered,
        }
    return {
        "model": str(model) if model else "default",
        "seconds": seconds,
        "sensors": rows,
        "machine": dataclasses.asdict(machine_info()),
    }


if __name__ == "__main__":
    raise SystemExit(main())
