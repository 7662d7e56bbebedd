"""``triscan card``: models/MODEL_CARD.md and .json from the measuring artefacts."""

from __future__ import annotations

import argparse
from pathlib import Path

from services.cli.command import Command, add_recipe_argument, add_recipe_option

GATE_FLAGS = ("seed", "scenarios", "positions", "frame_stride")  # --gate-*: the quality gate's worlds


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", type=Path, required=True, help="the training data set directory")
    p.add_argument(
        "--run-dir", type=Path, required=True, help="the Ultralytics run directory (results.csv, weights)"
    )
    p.add_argument(
        "--export-report", type=Path, required=True, help="JSON written by `triscan export --report`"
    )
    p.add_argument("--eval-fp32", type=Path, required=True, help="metrics.json of the fp32 test-split eval")
    p.add_argument("--eval-int8", type=Path, required=True, help="metrics.json of the INT8 test-split eval")
    p.add_argument("--eval-gate", type=Path, required=True, help="metrics.json of the quality-gate set eval")
    add_recipe_argument(
        p,
        "the recipe file the run and the export used, named in the card; its [eval.gate] gives every "
        "unset --gate-* flag",
    )
    for flag in GATE_FLAGS:
        add_recipe_option(p, f"--gate-{flag.replace('_', '-')}", type=int)
    for flag, what in (("people", "people"), ("clutter", "unlabelled clutter items")):
        p.add_argument(
            f"--gate-{flag}", type=int, default=0, metavar="N",
            help=f"the gate's worlds hold up to N {what} per motion, as `triscan eval --fresh --{flag} N` "
            "(default 0)",
        )  # fmt: skip
    p.add_argument("--train-command", required=True, help="the exact training command, quoted in the card")
    p.add_argument("--notes", type=Path, default=None, help="markdown file with known limits and status")
    p.add_argument(
        "--ablation-zero", type=Path, default=None, help="metrics.json of the zero-padding model's test eval"
    )
    p.add_argument(
        "--ablation-wrap", type=Path, default=None, help="metrics.json of the wrap-padding model's test eval"
    )
    p.add_argument("--ablation-command", default="", help="the wrap model's training command")
    p.add_argument("--ablation-notes", type=Path, default=None, help="markdown: what the ablation shows")
    p.add_argument(
        "--eval-conditions", type=Path, default=None,
        help="summary.json of `triscan eval --model FP32 --model INT8 --fresh N --noise …` (unseen worlds, "
        "LiDAR imperfections); INT8 is then recommended only within 0.5 points in every condition",
    )  # fmt: skip
    p.add_argument(
        "--compare", type=Path, default=None,
        help="summary.json of an eval grid with another network trained on the same data (e.g. YOLOv8n)",
    )  # fmt: skip
    p.add_argument("--compare-notes", type=Path, default=None, help="markdown: what the comparison shows")
    p.add_argument(
        "--compare-curve", type=network_and_csv, default=None, metavar="NETWORK=RESULTS_CSV",
        help="another network's results.csv on the same data, e.g. yolov8n=training/checkpoints/"
        "n_dr_results.csv: its val curve beside this run's, epoch for epoch",
    )  # fmt: skip
    p.add_argument(
        "--compare-curve-epochs-before", type=int, default=0, metavar="N",
        help="both runs of --compare-curve continued (--init) from N epochs each: count epochs from the "
        "start of training",
    )  # fmt: skip
    p.add_argument(
        "--invalid-ablation", type=Path, default=None,
        help="summary.json of an eval grid with models of each invalid-return rule (sentinel, empty)",
    )  # fmt: skip
    p.add_argument("--invalid-ablation-notes", type=Path, default=None, help="markdown: what it shows")
    p.add_argument("--out", type=Path, default=Path("models"))


def network_and_csv(text: str) -> tuple[str, Path]:
    """``yolov8n=path/results.csv`` → ("yolov8n", Path): a network's name and its training curve."""
    network, sep, path = text.partition("=")
    if not sep or not network or not path:
        raise argparse.ArgumentTypeError(
            f"expected NETWORK=RESULTS_CSV (yolov8n=runs/n/results.csv), got {text!r}"
        )
    return network, Path(path)


def run(args: argparse.Namespace) -> int:
    from training.model_card import CurveComparison, GridSection, write_card
    from training.recipe import SHIPPED_RECIPE, load_recipe, recipe_name

    def notes(path: Path | None) -> str:
        return path.read_text() if path else ""

    for flag in ("people", "clutter"):
        if getattr(args, f"gate_{flag}") < 0:
            raise ValueError(f"--gate-{flag} must be >= 0, got {getattr(args, f'gate_{flag}')}")
    if args.compare_curve_epochs_before and not args.compare_curve:
        raise ValueError(
            "--compare-curve-epochs-before counts the epochs of --compare-curve's runs: give both"
        )
    curves = None
    if args.compare_curve:
        network, results_csv = args.compare_curve
        curves = CurveComparison(network, results_csv, epochs_before=args.compare_curve_epochs_before)
    grids = [
        GridSection(title, summary, notes(intro))
        for title, summary, intro in (
            ("Networks compared on the same data", args.compare, args.compare_notes),
            (
                "Ablation: invalid returns in the sentinel row vs left empty",
                args.invalid_ablation,
                args.invalid_ablation_notes,
            ),
        )
        if summary is not None
    ]

    recipe_path = args.recipe or SHIPPED_RECIPE
    preset = load_recipe(recipe_path).preset("gate")
    worlds = {
        "seed": preset.seed,
        "scenarios": preset.fresh,
        "positions": preset.positions,
        "frame_stride": preset.frame_stride,
    }
    given = {flag: getattr(args, f"gate_{flag}") for flag in GATE_FLAGS}
    gate = {flag: worlds[flag] if value is None else value for flag, value in given.items()}
    gate.update(people=args.gate_people, clutter=args.gate_clutter)
    card = write_card(
        dataset_dir=args.data,
        run_dir=args.run_dir,
        export_json=args.export_report,
        eval_test_fp32=args.eval_fp32,
        eval_test_int8=args.eval_int8,
        eval_gate=args.eval_gate,
        out_dir=args.out,
        gate=gate,
        train_command=args.train_command,
        notes=notes(args.notes),
        ablation=(
            {"zero": args.ablation_zero, "wrap": args.ablation_wrap}
            if args.ablation_zero and args.ablation_wrap
            else None
        ),
        ablation_command=args.ablation_command,
        ablation_notes=notes(args.ablation_notes),
        conditions=args.eval_conditions,
        grids=grids,
        curves=curves,
        recipe=recipe_name(recipe_path),
    )
    print(f"wrote {args.out}/MODEL_CARD.md (recommended: {card['recommended']})")
    return 0


COMMAND = Command(
    "card", "write models/MODEL_CARD.md and .json from the measuring artefacts", add_arguments, run
)
