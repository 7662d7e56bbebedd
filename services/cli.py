"""The ``triscan`` command: one entry point, one subcommand per job.

Each subcommand imports its module only when chosen, so the robot's install (base dependencies only)
can run its commands without PyBullet, rerun or torch being present.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from common.encoding import PADDINGS


def _add_dataset(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("dataset", help="generate a seeded YOLO data set from the simulated room")
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
    p.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="processes (default: all cores)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing data set in --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (logs only)")
    p.set_defaults(run=_run_dataset)


def _run_dataset(args: argparse.Namespace) -> int:
    from training.dataset import DatasetConfig, generate_dataset

    config = DatasetConfig(
        out=args.out,
        scenarios=args.scenarios,
        positions=args.positions,
        seed=args.seed,
        padding=args.padding,
        frame_stride=args.frame_stride,
        workers=args.workers,
    )
    summary = generate_dataset(config, overwrite=args.overwrite, progress=not args.no_progress)
    samples = summary["samples"]
    print(f"samples: {samples}  ({summary['samples_per_s']:.0f} samples/s, {summary['elapsed_s']:.1f} s)")
    for split, per_class in summary["boxes_per_class"].items():  # type: ignore[union-attr]
        print(f"  {split:5s} boxes: " + ", ".join(f"{k} {v}" for k, v in per_class.items()))
    return 0


def _add_show(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("show", help="render one sample: RGB raster with label boxes, and a top-down map")
    p.add_argument("--dataset", type=Path, required=True, help="a directory written by `triscan dataset`")
    p.add_argument(
        "--sample",
        default=None,
        help="image path relative to the data set (e.g. images/train/s0000_p000_f002.png)",
    )
    p.add_argument("--index", type=int, default=0, help="line of samples.jsonl when --sample is not given")
    p.add_argument("--out", type=Path, default=Path("."), help="directory for the PNGs")
    p.add_argument("--scale", type=int, default=3, help="pixel magnification of the raster picture")
    p.set_defaults(run=_run_show)


def _run_show(args: argparse.Namespace) -> int:
    from training.pictures import render_sample

    raster_png, map_png = render_sample(
        args.dataset, args.out, sample=args.sample, index=args.index, scale=args.scale
    )
    print(f"raster: {raster_png}\nmap:    {map_png}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="triscan", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_dataset(sub)
    _add_show(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.run(args))
    except (FileExistsError, FileNotFoundError, ValueError) as exc:
        logging.getLogger("triscan").error("%s", exc)
        return 2


if __name__ == "__main__":
    sys.exit(main())
