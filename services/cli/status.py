"""``triscan status``: which triscan services are up, and their counters (base install)."""

from __future__ import annotations

import argparse

from services.cli.command import Command
from services.runtime import default_of


def add_arguments(p: argparse.ArgumentParser) -> None:
    from common.transport import add_zenoh_arguments
    from services.status import collect_status

    p.add_argument(
        "--wait",
        type=float,
        default=default_of(collect_status, "wait_s"),
        help="seconds to listen for counters",
    )
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    add_zenoh_arguments(p)


def run(args: argparse.Namespace) -> int:
    import json
    from dataclasses import asdict

    from common.transport import settings_from_args
    from services.status import collect_status, format_status

    statuses = collect_status(settings_from_args(args), args.wait)
    print(json.dumps([asdict(s) for s in statuses], indent=2) if args.json else format_status(statuses))
    return 0 if statuses else 1


COMMAND = Command("status", "which triscan services are up, and their counters", add_arguments, run)
