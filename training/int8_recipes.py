"""Which INT8 recipe keeps a model's accuracy: each one quantised, then scored like the fp32 model.

Raw-output distance (``triscan export``'s INT8-vs-fp32 check) says how far the numbers moved, not
whether detections survived: percentile ranges moved boxes less than MinMax on an untrained network,
yet on the trained pico network they cut test recall from 0.96 to 0.63. This command decides by the
metric that ships: every recipe (activation-range method × stem quantised or float) is built from
the same fp32 file and calibration images, then evaluated through
:class:`common.inference.OnnxDetector` on the same samples of one split, beside the fp32 model.

    python -m training.int8_recipes --fp32 models/yolov8p-dfl12/triscan-yolov8p-dfl12-zero.onnx \\
        --data data/train_dr
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from training.quantization import (
    CALIB_METHODS,
    DEFAULT_CALIB_COUNT,
    DEFAULT_FLOAT_LEADING_MODULES,
    CalibMethod,
    calibration_images,
    float_modules_label,
    quantize_int8,
)

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m


# The recipes compared unless told otherwise: no module, the stem alone and the default kept float,
# each with the box logits quantised and float.
RECIPE_FLOAT_MODULES: tuple[int, ...] = (0, 1, DEFAULT_FLOAT_LEADING_MODULES)
RECIPE_BOX_LOGITS_FLOAT: tuple[bool, ...] = (False, True)
RECIPE_CLASS_LOGITS_FLOAT: tuple[bool, ...] = (True,)  # the export's default (--class-logits int8 float)


@dataclass(frozen=True)
class RecipeScore:
    """One model's figures on the shared samples; ``recipe`` is ``fp32`` for the reference."""

    recipe: str
    map50: float
    map50_95: float
    worst_class: str
    worst_class_map50: float
    delta_map50: float  # against the fp32 model, in mAP (0.005 = half a point)


def recipe_name(
    method: str,
    float_leading_modules: int,
    box_logits_float: bool,
    head_convs_float: bool = False,
    class_logits_float: bool = True,
) -> str:
    label = float_modules_label(float_leading_modules)
    leading = f"{label} float" if label else "all modules int8"
    if head_convs_float:  # both logit convs are among the head's convs
        return f"{method}, {leading}, Detect head convs float"
    name = f"{method}, {leading}, box logits {'float' if box_logits_float else 'int8'}"
    return name if class_logits_float else f"{name}, class logits int8"


def score(
    detector_path: Path, recipe: str, samples: list[Any], scratch: Path, reference: float | None
) -> RecipeScore:
    """Evaluate one ONNX file with the validation protocol (``triscan eval``'s thresholds)."""
    from common.inference import OnnxDetector
    from training.evaluate import VAL_CONF, VAL_IOU, evaluate

    detector = OnnxDetector(detector_path, conf_threshold=VAL_CONF, iou_threshold=VAL_IOU, intra_op_threads=1)
    report = evaluate(detector, iter(samples), scratch / recipe.replace(", ", "-").replace(" ", "_"),
                      source=recipe, plots=False)  # fmt: skip
    worst = min(report.per_class, key=lambda name: report.per_class[name]["mAP50"])
    map50 = report.overall["mAP50"]
    return RecipeScore(
        recipe=recipe,
        map50=round(map50, 4),
        map50_95=round(report.overall["mAP50-95"], 4),
        worst_class=worst,
        worst_class_map50=round(report.per_class[worst]["mAP50"], 4),
        delta_map50=round(map50 - (map50 if reference is None else reference), 4),
    )


def compare_recipes(
    fp32: Path,
    dataset_dir: Path,
    *,
    methods: list[CalibMethod],
    float_modules: Sequence[int] = RECIPE_FLOAT_MODULES,
    box_logits: Sequence[bool] = RECIPE_BOX_LOGITS_FLOAT,
    class_logits: Sequence[bool] = RECIPE_CLASS_LOGITS_FLOAT,
    head_convs: bool = False,
    split: str = "test",
    every: int = 5,
    calib_count: int = DEFAULT_CALIB_COUNT,
) -> list[RecipeScore]:
    """fp32 first, then each method × leading float modules × box logits × class logits (float or
    not), on every ``every``-th sample; with ``head_convs`` True, one more recipe per method × leading
    modules that keeps every conv of the Detect head float (both logit convs included)."""
    from training.evaluate import dataset_samples

    if every < 1:
        raise ValueError(f"every must be >= 1, got {every}")
    samples = list(dataset_samples(dataset_dir, split))[::every]
    calibration = calibration_images(dataset_dir, calib_count)
    with tempfile.TemporaryDirectory(prefix="triscan-int8-recipes-") as tmp:
        scratch = Path(tmp)
        reference = score(fp32, "fp32", samples, scratch, None)
        log.info("%s", reference)
        scores = [reference]
        # (box logits float, class logits float, head convs float): the logit choices, then the head
        # convs (logits included)
        variants = [(box, cls, False) for box in box_logits for cls in class_logits]
        variants += [(True, True, True)] if head_convs else []
        for method in methods:
            for leading in float_modules:
                for box_float, class_float, head_float in variants:
                    name = recipe_name(method, leading, box_float, head_float, class_float)
                    model = quantize_int8(
                        fp32, scratch / f"{method}-{leading}-{box_float}-{class_float}-{head_float}.onnx",
                        calibration, method=method, float_leading_modules=leading,
                        keep_box_logits_float=box_float, keep_class_logits_float=class_float,
                        keep_head_convs_float=head_float,
                    )  # fmt: skip
                    scores.append(score(model, name, samples, scratch, reference.map50))
                    log.info("%s", scores[-1])
    return scores


def format_recipe_table(scores: list[RecipeScore]) -> str:
    lines = [
        "| recipe | mAP@0.5 | Δ vs fp32 (points) | mAP@0.5:0.95 | weakest class |",
        "|---|---:|---:|---:|---|",
    ]
    lines += [
        f"| {s.recipe} | {s.map50:.3f} | {100 * s.delta_map50:+.2f} | {s.map50_95:.3f} | "
        f"{s.worst_class} {s.worst_class_map50:.3f} |"
        for s in scores
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m training.int8_recipes", description=__doc__.splitlines()[0], allow_abbrev=False
    )
    parser.add_argument("--fp32", type=Path, required=True, help="the fp32 ONNX model `triscan export` wrote")
    parser.add_argument(
        "--data", type=Path, required=True, help="its data set: calibration from val, scores on --split"
    )
    parser.add_argument("--split", default="test", choices=("val", "test"))
    parser.add_argument("--every", type=int, default=5, help="score every N-th sample of the split")
    parser.add_argument("--calib-count", type=int, default=DEFAULT_CALIB_COUNT)
    parser.add_argument("--methods", nargs="+", choices=CALIB_METHODS, default=["percentile", "minmax"])
    parser.add_argument(
        "--float-modules", nargs="+", type=int, default=list(RECIPE_FLOAT_MODULES),
        help="leading modules kept float, one recipe each (default: %(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--box-logits", nargs="+", choices=("int8", "float"),
        default=["float" if kept else "int8" for kept in RECIPE_BOX_LOGITS_FLOAT],
        help="the box branches' last convs quantised, float, or one recipe each (default: %(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--class-logits", nargs="+", choices=("int8", "float"),
        default=["float" if kept else "int8" for kept in RECIPE_CLASS_LOGITS_FLOAT],
        help="the class branches' last convs quantised, float, or one recipe each (default: %(default)s)",
    )  # fmt: skip
    parser.add_argument(
        "--head-convs", action="store_true",
        help="also score, per method and leading modules, the recipe keeping every Detect head conv float",
    )  # fmt: skip
    parser.add_argument("--out", type=Path, default=None, help="also write the scores as JSON")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("training.quantization").setLevel(logging.WARNING)
    scores = compare_recipes(
        args.fp32, args.data, methods=args.methods, float_modules=args.float_modules,
        box_logits=tuple(choice == "float" for choice in args.box_logits),
        class_logits=tuple(choice == "float" for choice in args.class_logits), head_convs=args.head_convs,
        split=args.split,
        every=args.every, calib_count=args.calib_count,
    )  # fmt: skip
    print(format_recipe_table(scores))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        report = {
            "fp32": str(args.fp32), "data": str(args.data), "split": args.split, "every": args.every,
            "calibration_images": args.calib_count, "scores": [asdict(s) for s in scores],
        }  # fmt: skip
        args.out.write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
