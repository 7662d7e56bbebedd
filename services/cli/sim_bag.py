"""``triscan sim-bag``: a ROS 2 bag of simulated LiDAR scans (the sim and ros2 extras)."""

from __future__ import annotations

import argparse
from pathlib import Path

from services.cli.command import Command
from services.runtime import default_of


def add_arguments(p: argparse.ArgumentParser) -> None:
    from services.sim_bag import write_sim_bag

    p.add_argument("--scans", type=int, default=150, help="scans to record (at --rate)")
    p.add_argument(
        "--seed",
        type=int,
        default=default_of(write_sim_bag, "seed"),
        help="simulator seed (the model trained on 0)",
    )
    p.add_argument(
        "--rate", type=float, default=default_of(write_sim_bag, "rate_hz"), help="scans per second"
    )
    p.add_argument("--topic", default=default_of(write_sim_bag, "topic"), help="LaserScan topic")
    p.add_argument("--out", type=Path, required=True, help="bag directory to create")


def run(args: argparse.Namespace) -> int:
    from services.sim_bag import write_sim_bag

    mcap = write_sim_bag(args.out, args.scans, seed=args.seed, rate_hz=args.rate, topic=args.topic)
    print(mcap)
    return 0


COMMAND = Command(
    "sim-bag",
    "write a ROS 2 bag (MCAP) of a simulated robot's LaserScans, to replay or benchmark",
    add_arguments,
    run,
    extras=("sim", "ros2"),
)
