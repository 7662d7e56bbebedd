"""``triscan train``: YOLOv8n or the pico on a triscan data set (the train extra).

The run's settings default to the recipe file's ``[train]`` table (``--recipe``); a flag given here
overrides its value.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from services.cli.command import Command, add_recipe_argument, add_recipe_option, given_or_default

RECIPE_FLAGS = ("epochs", "batch", "patience", "workers", "seed", "fraction")  # [train] keys, flag names


def add_arguments(p: argparse.ArgumentParser) -> None:
    from training.architectures import (
        ACTIVATIONS,
        ARCHS,
        DEFAULT_ACTIVATION,
        DEFAULT_ARCH,
        DEFAULT_DFL_BINS,
        DFL_BINS,
    )

    p.add_argument(
        "--arch", choices=ARCHS, default=DEFAULT_ARCH, help="n: YOLOv8n (paper); p: pico, width 0.125"
    )
    p.add_argument(
        "--activation", choices=ACTIVATIONS, default=None,
        help=f"silu: YOLOv8's own; relu: folds into the conv, faster in INT8 (bench.activation_speed) "
        f"(default: the --init checkpoint's, else {DEFAULT_ACTIVATION})",
    )  # fmt: skip
    p.add_argument(
        "--dfl-bins", type=int, choices=DFL_BINS, default=None,
        help="DFL bins per box edge (Ultralytics' reg_max): 8 halve the head's box branch, 12 cut a quarter "
        f"(default: the --init checkpoint's, else {DEFAULT_DFL_BINS})",
    )  # fmt: skip
    p.add_argument("--data", type=Path, required=True, help="data.yaml written by `triscan dataset`")
    p.add_argument("--out", type=Path, default=Path("runs/triscan"), help="run directory")
    add_recipe_argument(p, "recipe file whose [train] table gives every unset flag")
    add_recipe_option(p, "--epochs", type=int)
    add_recipe_option(p, "--batch", type=int)
    add_recipe_option(
        p, "--patience", type=int, help="early stopping: epochs without val improvement (recipe)"
    )
    add_recipe_option(p, "--workers", type=int, help="data loader processes (default: the recipe's)")
    p.add_argument("--device", default="", help="'cpu', '0', ... (default: GPU if present, else CPU)")
    add_recipe_option(p, "--seed", type=int)
    add_recipe_option(p, "--fraction", type=float, help="share of the training images to use (recipe)")
    p.add_argument(
        "--lr0", type=float, default=None,
        help="peak learning rate (default: the recipe's lr0): a fine-tune that loses its start's accuracy "
        "in the first epochs may want a lower one",
    )  # fmt: skip
    p.add_argument(
        "--init", type=Path, default=None, metavar="WEIGHTS",
        help="start from these weights instead of random ones, e.g. a shipped .pt to fine-tune on your "
        "own rooms (--arch must name its network; another --activation, or fewer --dfl-bins with the box "
        "branch cut from the trained one, starts that network from them)",
    )  # fmt: skip
    p.add_argument("--resume", action="store_true", help="continue from OUT/weights/last.pt if it exists")
    p.add_argument(
        "--resume-from",
        type=Path,
        default=None,
        help="with --resume: checkpoint to continue from when OUT has none (e.g. training/checkpoints/;"
        " a .gz one is gunzipped)",
    )
    p.add_argument(
        "--stop-after",
        type=int,
        default=None,
        metavar="EPOCH",
        help="end this invocation after EPOCH (1-based) without changing the --epochs schedule",
    )


def run(args: argparse.Namespace) -> int:
    from training.recipe import SHIPPED_RECIPE, load_recipe
    from training.train import TrainConfig, network_choices, train

    recipe_path = args.recipe or SHIPPED_RECIPE
    settings = given_or_default(args, load_recipe(recipe_path).train, RECIPE_FLAGS)
    activation, dfl_bins = network_choices(args.arch, args.init, args.activation, args.dfl_bins)
    config = TrainConfig(
        data=args.data,
        out=args.out,
        device=args.device,
        arch=args.arch,
        activation=activation,
        init=args.init,
        dfl_bins=dfl_bins,
        recipe=recipe_path,
        lr0=args.lr0,
        **settings,
    )
    summary = train(config, resume=args.resume, resume_from=args.resume_from, stop_after=args.stop_after)
    print(f"best weights: {summary['best_weights']} (epochs run {summary['epochs_run']})")
    return 0


COMMAND = Command(
    "train",
    "train YOLOv8n (or the lighter pico) on a triscan data set (offline)",
    add_arguments,
    run,
    extras=("train",),
)
