"""Detector settings compared on the same fleets, taking turns: which one holds more robots?

This VM's throughput drifts between minutes, so settings measured one after the other compare the
machine's moods as much as the settings. Here every robot count of ``--robots`` is run ``--rounds``
times for each ``--setting`` in turn (each a full ``bench.fleet_capacity`` step: fresh services,
warm-up, measured window, p99 < 100 ms and ≥ 95 % answered to pass), and the medians per setting and
count are printed and written as JSON. ``bench.fleet_batch_ab`` is the batch-size special case, run
through :func:`run_rounds` here.

    python -m bench.fleet_ab --robots 14,17 --rounds 2 \\
        --setting "defaults=--detector-defaults" --setting "one-session=--workers 1 --batch 4"
"""

from __future__ import annotations

import argparse
import logging
import shlex
import statistics
from dataclasses import asdict
from pathlib import Path

from bench import fleet_capacity
from bench.harness import recorded_scans
from bench.machine import machine_info
from bench.report import write_report

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m


def parse_setting(text: str) -> tuple[str, list[str]]:
    """``NAME=FLAGS``: a label and the ``bench.fleet_capacity`` flags that configure the detector."""
    name, sep, flags = text.partition("=")
    if not sep or not name.strip():
        raise argparse.ArgumentTypeError(f"{text!r}: use NAME=FLAGS, e.g. 'defaults=--detector-defaults'")
    return name.strip(), shlex.split(flags)


def summary(steps: list[fleet_capacity.FleetStep]) -> dict[str, float]:
    """Medians over the rounds of one setting at one fleet size."""
    return {
        "answered_share": statistics.median(s.answered_share for s in steps),
        "p50_ms": statistics.median(s.latency_ms.get("p50", float("nan")) for s in steps),
        "p99_ms": statistics.median(s.latency_ms.get("p99", float("nan")) for s in steps),
        "mean_batch": statistics.median(s.detector_mean_batch for s in steps),
        "rounds_passed": sum(s.passed for s in steps),
    }


def run_rounds(
    sizes: list[int], settings: dict[str, argparse.Namespace], rounds: int
) -> dict[str, dict[int, list[fleet_capacity.FleetStep]]]:
    """Every size under every setting, ``rounds`` times, the settings taking turns within a round."""
    scans = recorded_scans(fleet_capacity.RECORDED_SCANS, seed=7)
    frames = {name: fleet_capacity.frames_to_send(scans, step_args) for name, step_args in settings.items()}
    steps: dict[str, dict[int, list[fleet_capacity.FleetStep]]] = {
        n: {r: [] for r in sizes} for n in settings
    }
    for round_index in range(rounds):
        for robots in sizes:
            for name, step_args in settings.items():
                step = fleet_capacity.run_step(robots, frames[name], step_args)
                steps[name][robots].append(step)
                log.info(
                    "round %d, %d robots, %s: %s, p99 %s ms, answered %.1f %%, mean batch %.2f",
                    round_index + 1, robots, name, "pass" if step.passed else "FAIL",
                    step.latency_ms.get("p99"), 100 * step.answered_share, step.detector_mean_batch,
                )  # fmt: skip
    return steps


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", default="14,17", help="fleet sizes, comma-separated")
    parser.add_argument("--rounds", type=int, default=2, help="rounds per setting and size, alternating")
    parser.add_argument("--setting", type=parse_setting, action="append", required=True, help="NAME=FLAGS")
    parser.add_argument("--seconds", type=float, default=15.0, help="measured seconds per step")
    parser.add_argument("--out", type=Path, default=Path("bench/results/fleet_ab.json"))
    args = parser.parse_args(argv)
    sizes = [int(n) for n in args.robots.split(",")]
    if len(args.setting) < 2 or args.rounds < 1 or min(sizes) < 1:
        parser.error("give at least two --setting, --rounds >= 1 and robot counts >= 1")
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    settings = {
        name: fleet_capacity.parse_step_args(["--seconds", str(args.seconds), *flags])
        for name, flags in args.setting
    }
    steps = run_rounds(sizes, settings, args.rounds)
    report = {
        "settings": {name: flags for name, flags in args.setting},
        "seconds_per_step": args.seconds,
        "summary": {
            name: {str(robots): summary(runs) for robots, runs in by_size.items()}
            for name, by_size in steps.items()
        },
        "steps": {
            name: {str(robots): [asdict(s) for s in runs] for robots, runs in by_size.items()}
            for name, by_size in steps.items()
        },
        "machine": asdict(machine_info()),
    }
    for name, by_size in report["summary"].items():
        for robots, figures in by_size.items():
            log.info("%s, %s robots (median of %d): %s", name, robots, args.rounds, figures)
    write_report(report, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
