"""Does ``--batch`` raise what one detector serves? The same fleet, batch 1 and batched, taking turns.

This VM's throughput drifts by up to 2× between minutes (the same ``bench.fleet_capacity`` ladder has
put the knee anywhere from 10 to 20 robots), so two ladders run one after the other compare the
machine's moods as much as the two settings. Here one fleet size is run ``--rounds`` times with the
batch-1 model at ``--batch 1`` and the ``-batch`` model at ``--batch N``, alternating, each round a
full ``bench.fleet_capacity`` step (fresh services, warm-up, measured window); the medians per
setting are printed and written as JSON. The rounds are ``bench.fleet_ab``'s, with the two settings
built from ``--precision`` and ``--batch``.

    python -m bench.fleet_batch_ab --robots 24 --rounds 3 --precision int8
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import asdict
from pathlib import Path

from bench import fleet_capacity
from bench.fleet_ab import run_rounds, summary
from bench.machine import machine_info
from bench.report import write_report
from common.model_spec import SHIPPED_FP32_MODEL, SHIPPED_INT8_MODEL, batch_variant_path

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

MODELS = {
    "fp32": (SHIPPED_FP32_MODEL, batch_variant_path(SHIPPED_FP32_MODEL)),
    "int8": (SHIPPED_INT8_MODEL, batch_variant_path(SHIPPED_INT8_MODEL)),
}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", type=int, default=24, help="fleet size, the same in every round")
    parser.add_argument("--rounds", type=int, default=3, help="rounds per setting, alternating")
    parser.add_argument("--batch", type=int, default=8, help="the batched setting's --batch")
    parser.add_argument(
        "--precision", choices=sorted(MODELS), default="int8", help="which shipped model pair"
    )
    parser.add_argument("--seconds", type=float, default=20.0, help="measured seconds per round")
    parser.add_argument("--from-scans", action="store_true", help="one detector --from-scans process")
    parser.add_argument("--out", type=Path, default=Path("bench/results/fleet_batch_ab.json"))
    args = parser.parse_args(argv)
    if args.robots < 1 or args.rounds < 1 or args.batch < 2:
        parser.error("--robots and --rounds must be >= 1 and --batch >= 2")
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    fixed_model, batch_model = MODELS[args.precision]
    common = ["--seconds", str(args.seconds), *(["--from-scans"] if args.from_scans else [])]
    settings = {
        "batch_1": fleet_capacity.parse_step_args([*common, "--model", str(fixed_model)]),
        f"batch_{args.batch}": fleet_capacity.parse_step_args(
            [*common, "--model", str(batch_model), "--batch", str(args.batch)]
        ),
    }
    rounds = {
        name: by_size[args.robots]
        for name, by_size in run_rounds([args.robots], settings, args.rounds).items()
    }
    report = {
        "robots": args.robots,
        "precision": args.precision,
        "from_scans": args.from_scans,
        "seconds_per_round": args.seconds,
        "summary": {name: summary(steps) for name, steps in rounds.items()},
        "rounds": {name: [asdict(s) for s in steps] for name, steps in rounds.items()},
        "machine": asdict(machine_info()),
    }
    for name, figures in report["summary"].items():
        log.info("%s (median of %d): %s", name, args.rounds, figures)
    write_report(report, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
