"""``triscan batch-model``: a copy of an exported model with a free batch axis (the train extra)."""

from __future__ import annotations

import argparse
from pathlib import Path

from services.cli.command import Command


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("model", type=Path, help="a fixed-shape triscan ONNX model (fp32 or INT8)")
    p.add_argument("--out", type=Path, default=None, help="default: <model stem>-batch.onnx beside it")


def run(args: argparse.Namespace) -> int:
    from common.model_spec import batch_variant_path
    from training.batch_variant import add_batch_axis

    out = add_batch_axis(args.model, args.out or batch_variant_path(args.model))
    print(f"wrote {out}: the same network, frames in one call equal frames one by one")
    return 0


COMMAND = Command(
    "batch-model",
    "a copy of an exported model with a free batch axis, for `services.detector --batch N`",
    add_arguments,
    run,
    extras=("train",),
)
