"""``triscan show``: one sample of a data set as pictures (the sim extra)."""

from __future__ import annotations

import argparse
from pathlib import Path

from services.cli.command import Command


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dataset", type=Path, required=True, help="a directory written by `triscan dataset`")
    p.add_argument(
        "--sample",
        default=None,
        help="image path relative to the data set (e.g. images/train/s0000_p000_f002.png)",
    )
    p.add_argument("--index", type=int, default=0, help="line of samples.jsonl when --sample is not given")
    p.add_argument("--out", type=Path, default=Path("."), help="directory for the PNGs")
    p.add_argument("--scale", type=int, default=3, help="pixel magnification of the raster picture")
    p.add_argument(
        "--model", type=Path, default=None, help="ONNX model: draw its boxes (dashed) beside the labels"
    )


def run(args: argparse.Namespace) -> int:
    from training.pictures import render_sample

    raster_png, map_png = render_sample(
        args.dataset, args.out, sample=args.sample, index=args.index, scale=args.scale, model=args.model
    )
    print(f"raster: {raster_png}\nmap:    {map_png}")
    return 0


COMMAND = Command(
    "show",
    "render one sample: RGB raster with label boxes (and a model's), and a top-down map",
    add_arguments,
    run,
    extras=("sim",),
)
