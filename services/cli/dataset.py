"""``triscan dataset``: a seeded YOLO data set from the simulated room (the sim extra)."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from common.encoding import INVALID_RULES, PADDINGS
from services.cli.command import Command
from services.simulator.sensors import DEFAULT_PROFILE, RANDOM_PROFILE, SENSOR_CHOICES, check_sensor


def _sensor(text: str) -> str:
    try:
        return check_sensor(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenarios", type=int, default=160, help="number of random worlds (paper: 160)")
    p.add_argument("--positions", type=int, default=90, help="robot positions per world (paper: 90)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, required=True, help="output directory")
    p.add_argument(
        "--padding", choices=PADDINGS, default="zero", help="columns 360-383: zero (paper) or wrap"
    )
    p.add_argument(
        "--frame-stride",
        type=int,
        default=1,
        help="keep every k-th three-scan window of each motion (1 = every window)",
    )
    p.add_argument(
        "--invalid",
        choices=INVALID_RULES,
        default="sentinel",
        help="invalid returns: sentinel row 63 (paper) or empty (no pixel)",
    )
    p.add_argument(
        "--raster-yaw",
        type=float,
        default=0.0,
        metavar="DEG",
        help="turn every scan and label by DEG before binning (180: the 0°/360° seam behind the robot); "
        "default 0, the paper's raster",
    )
    dr = p.add_argument_group("domain randomisation (defaults: the paper's clean LDS-01)")
    for flag, default, what in (
        ("--noise-sigma", None, "range noise σ in metres (default 0.015 0.015)"),
        ("--dropout", (0.0, 0.0), "share of beams returned invalid (e.g. 0 0.1)"),
        ("--spurious", (0.0, 0.0), "share of beams returned short: dust, mixed pixels (e.g. 0 0.01)"),
    ):
        dr.add_argument(
            flag, type=float, nargs=2, metavar=("LOW", "HIGH"), default=default, help=what + ", per scenario"
        )
    dr.add_argument(
        "--clutter",
        type=int,
        default=0,
        metavar="N",
        help="up to N unlabelled poles and wall stubs per robot motion",
    )
    dr.add_argument(
        "--people",
        type=int,
        default=0,
        metavar="N",
        help="up to N walking or standing people per robot motion, labelled as class 'person' "
        "(0: the paper's four classes only)",
    )
    dr.add_argument(
        "--open-space",
        type=float,
        default=0.0,
        metavar="SHARE",
        help="share of scenarios whose walls stand 2.5-6 m from the room's centre instead of 2 m: scans "
        "reach beyond the 4 m full scale and people walk farther off, as in halls (default 0)",
    )
    dr.add_argument(
        "--door-watch",
        type=float,
        default=0.0,
        metavar="SHARE",
        help="share of motions where the robot stands 0.6-1.6 m in front of the doorway, facing it, while "
        "someone passes outside: people seen only through a near opening (needs --people; default 0)",
    )
    dr.add_argument(
        "--sensor",
        type=_sensor,
        default=DEFAULT_PROFILE,
        metavar="NAME",
        help=f"the LiDAR: one of {', '.join(SENSOR_CHOICES)} ('{RANDOM_PROFILE}': a profile drawn per "
        "scenario); geometry, rate and range from docs/sensors.md",
    )
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="processes (default: all cores)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing data set in --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (logs only)")


def run(args: argparse.Namespace) -> int:
    from training.dataset import DatasetConfig, generate_dataset

    config = DatasetConfig(
        out=args.out,
        scenarios=args.scenarios,
        positions=args.positions,
        seed=args.seed,
        padding=args.padding,
        frame_stride=args.frame_stride,
        workers=args.workers,
        invalid=args.invalid,
        dropout_rate=tuple(args.dropout),
        spurious_rate=tuple(args.spurious),
        clutter=args.clutter,
        people=args.people,
        sensor=args.sensor,
        raster_yaw_deg=args.raster_yaw,
        open_space=args.open_space,
        door_watch=args.door_watch,
        **({"noise_sigma_m": tuple(args.noise_sigma)} if args.noise_sigma else {}),
    )
    summary = generate_dataset(config, overwrite=args.overwrite, progress=not args.no_progress)
    samples = summary["samples"]
    print(f"samples: {samples}  ({summary['samples_per_s']:.0f} samples/s, {summary['elapsed_s']:.1f} s)")
    boxes_per_class: dict[str, dict[str, int]] = summary["boxes_per_class"]
    for split, per_class in boxes_per_class.items():
        print(f"  {split:5s} boxes: " + ", ".join(f"{k} {v}" for k, v in per_class.items()))
    return 0


COMMAND = Command(
    "dataset", "generate a seeded YOLO data set from the simulated room", add_arguments, run, extras=("sim",)
)
