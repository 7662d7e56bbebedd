"""``triscan replay``: the LaserScans of ROS 1/2 bags published as triscan scans (the ros2 extra)."""

from __future__ import annotations

import argparse

from services.cli.command import Command


def add_arguments(p: argparse.ArgumentParser) -> None:
    from services.bag_replay import add_replay_arguments

    add_replay_arguments(p)


def run(args: argparse.Namespace) -> int:
    from common.transport import settings_from_args
    from services.bag_replay import config_from_args, run_replay
    from services.runtime import stop_event_on_signals

    summary = run_replay(
        settings_from_args(args), config_from_args(args), wait_s=args.wait, stop=stop_event_on_signals()
    )
    robots = ", ".join(f"{topic} → {robot}" for topic, robot in summary.robots.items())
    print(f"published {summary.published} scans in {summary.passes} pass(es): {robots}")
    if summary.rejected:
        print(f"skipped: {dict(summary.rejected)}")
    return 0


COMMAND = Command(
    "replay",
    "publish the LaserScans of ROS 1/2 bags (.bag, .db3, .mcap) as triscan scans",
    add_arguments,
    run,
    extras=("ros2",),
)
