"""``triscan export``: ONNX fp32 and INT8 models from a checkpoint (the train extra).

The INT8 settings and the box grid default to the recipe file's ``[export]`` table (``--recipe``); a
flag given here overrides its value.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from common.encoding import PADDINGS
from common.model_spec import BOX_GRIDS
from services.cli.command import Command, add_recipe_argument, add_recipe_option, given_or_default

RECIPE_FLAGS = ("box_grid", "calib_count", "calib_method", "float_modules", "activations")  # [export] keys


def add_arguments(p: argparse.ArgumentParser) -> None:
    from training.quantization import ACTIVATION_TYPES, CALIB_METHODS

    p.add_argument("--weights", type=Path, required=True, help="Ultralytics checkpoint (best.pt)")
    p.add_argument(
        "--data", type=Path, required=True, help="the data set (or its data.yaml) it was trained on"
    )
    p.add_argument("--out", type=Path, default=Path("models"), help="directory for the .onnx files")
    p.add_argument(
        "--name",
        default=None,
        help="file stem (default: triscan-<network>-<padding>[-invalid-<rule>]: triscan-yolov8p-zero)",
    )
    p.add_argument("--padding", choices=PADDINGS, default=None, help="default: read from the data set")
    add_recipe_argument(p, "recipe file whose [export] table gives every unset INT8 flag and --box-grid")
    add_recipe_option(
        p, "--box-grid", choices=BOX_GRIDS,
        help="recorded for the detector: 'pixel' rounds box edges to whole pixels, as labels are (recipe)",
    )  # fmt: skip
    add_recipe_option(p, "--calib-count", type=int, help="val images used to calibrate INT8 (recipe)")
    add_recipe_option(p, "--calib-method", choices=CALIB_METHODS)
    add_recipe_option(
        p, "--float-modules", type=int,
        help="leading network modules INT8 keeps float (1: the stem alone, 0: none; default: the recipe's; "
        "`python -m training.int8_recipes` scores the choices)",
    )  # fmt: skip
    p.add_argument(
        "--quantize-box-logits", action="store_true",
        help="quantise the box branches' last convs too (default: float, for box tightness)",
    )  # fmt: skip
    p.add_argument(
        "--quantize-class-logits", action="store_true",
        help="quantise the class branches' last convs too (default: float, so scores keep their "
        "resolution and range)",
    )  # fmt: skip
    p.add_argument(
        "--float-head-convs", action="store_true",
        help="keep every conv of the Detect head float (box and class branches): tighter INT8 boxes, "
        "about a quarter more time per frame",
    )  # fmt: skip
    add_recipe_option(
        p, "--activations", choices=ACTIVATION_TYPES,
        help="INT8 activation type: uint8 for x86 (VNNI), int8 for ARM (default: the recipe's)",
    )  # fmt: skip
    p.add_argument("--compare-count", type=int, default=20, help="val images for the INT8-vs-fp32 check")
    p.add_argument("--timing-runs", type=int, default=200, help="latency runs per model (0 skips)")
    p.add_argument("--report", type=Path, default=None, help="also write the JSON report to this file")


def run(args: argparse.Namespace) -> int:
    from training.export import export_models
    from training.recipe import SHIPPED_RECIPE, load_recipe

    recipe = given_or_default(args, load_recipe(args.recipe or SHIPPED_RECIPE).export, RECIPE_FLAGS)
    result = export_models(
        args.weights,
        args.data,
        args.out,
        name=args.name,
        padding=args.padding,
        calib_count=recipe["calib_count"],
        method=recipe["calib_method"],
        activation_type=recipe["activations"],
        float_leading_modules=recipe["float_modules"],
        keep_box_logits_float=not args.quantize_box_logits,
        keep_class_logits_float=not args.quantize_class_logits,
        keep_head_convs_float=args.float_head_convs,
        compare_count=args.compare_count,
        timing_runs=args.timing_runs,
        box_grid=recipe["box_grid"],
    )
    text = json.dumps(result, indent=2, default=str)
    if args.report is not None:
        args.report.parent.mkdir(parents=True, exist_ok=True)
        args.report.write_text(text + "\n")
    print(text)
    return 0


COMMAND = Command(
    "export",
    "ONNX fp32 + INT8 (static QDQ, per-channel) models from a checkpoint",
    add_arguments,
    run,
    extras=("train",),
)
