"""The ``triscan`` command: one entry point, one subcommand per job.

Each subcommand imports its module only when chosen, so the robot's install (base dependencies only)
can run its commands without PyBullet, rerun or torch being present.
"""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path

from common.encoding import INVALID_RULES, PADDINGS
from common.model_spec import BOX_GRIDS, DEFAULT_BOX_GRID
from services.runtime import LOG_FORMAT
from training.architectures import (
    ACTIVATIONS,
    ARCHS,
    DEFAULT_ACTIVATION,
    DEFAULT_ARCH,
    DEFAULT_DFL_BINS,
    DFL_BINS,
)
from training.quantization import (
    ACTIVATION_TYPES,
    CALIB_METHODS,
    DEFAULT_CALIB_COUNT,
    DEFAULT_CALIB_METHOD,
    DEFAULT_FLOAT_LEADING_MODULES,
)


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
    p.add_argument(
        "--invalid",
        choices=INVALID_RULES,
        default="sentinel",
        help="invalid returns: sentinel row 63 (paper) or empty (no pixel)",
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
        help="up to N unlabelled poles, wall stubs and walking leg pairs per robot motion",
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
        invalid=args.invalid,
        dropout_rate=tuple(args.dropout),
        spurious_rate=tuple(args.spurious),
        clutter=args.clutter,
        **({"noise_sigma_m": tuple(args.noise_sigma)} if args.noise_sigma else {}),
    )
    summary = generate_dataset(config, overwrite=args.overwrite, progress=not args.no_progress)
    samples = summary["samples"]
    print(f"samples: {samples}  ({summary['samples_per_s']:.0f} samples/s, {summary['elapsed_s']:.1f} s)")
    boxes_per_class: dict[str, dict[str, int]] = summary["boxes_per_class"]
    for split, per_class in boxes_per_class.items():
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


def _add_train(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("train", help="train YOLOv8n (or the lighter pico) on a triscan data set (offline)")
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
    p.add_argument("--epochs", type=int, default=30)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--patience", type=int, default=8, help="early stopping: epochs without val improvement")
    p.add_argument("--workers", type=int, default=2, help="data loader processes")
    p.add_argument("--device", default="", help="'cpu', '0', ... (default: GPU if present, else CPU)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--fraction", type=float, default=1.0, help="share of the training images to use")
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
    p.set_defaults(run=_run_train)


def _run_train(args: argparse.Namespace) -> int:
    from training.train import TrainConfig, network_choices, train

    activation, dfl_bins = network_choices(args.arch, args.init, args.activation, args.dfl_bins)
    config = TrainConfig(
        data=args.data,
        out=args.out,
        epochs=args.epochs,
        batch=args.batch,
        patience=args.patience,
        workers=args.workers,
        device=args.device,
        seed=args.seed,
        fraction=args.fraction,
        arch=args.arch,
        activation=activation,
        init=args.init,
        dfl_bins=dfl_bins,
    )
    summary = train(config, resume=args.resume, resume_from=args.resume_from, stop_after=args.stop_after)
    print(f"best weights: {summary['best_weights']} (epochs run {summary['epochs_run']})")
    return 0


def _add_export(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="ONNX fp32 + INT8 (static QDQ, per-channel) models from a checkpoint")
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
    p.add_argument(
        "--box-grid", choices=BOX_GRIDS, default=DEFAULT_BOX_GRID,
        help="recorded for the detector: 'pixel' rounds box edges to whole pixels, as labels are",
    )  # fmt: skip
    p.add_argument(
        "--calib-count", type=int, default=DEFAULT_CALIB_COUNT, help="val images used to calibrate INT8"
    )
    p.add_argument("--calib-method", choices=CALIB_METHODS, default=DEFAULT_CALIB_METHOD)
    p.add_argument(
        "--float-modules", type=int, default=DEFAULT_FLOAT_LEADING_MODULES,
        help="leading network modules INT8 keeps float (1: the stem alone, 0: none; "
        "`python -m training.int8_recipes` scores the choices)",
    )  # fmt: skip
    p.add_argument(
        "--quantize-box-logits", action="store_true",
        help="quantise the box branches' last convs too (default: float, for box tightness)",
    )  # fmt: skip
    p.add_argument(
        "--float-head-convs", action="store_true",
        help="keep every conv of the Detect head float (box and class branches): tighter INT8 boxes, "
        "about a quarter more time per frame",
    )  # fmt: skip
    p.add_argument(
        "--activations",
        choices=ACTIVATION_TYPES,
        default="uint8",
        help="INT8 activation type: uint8 for x86 (VNNI), int8 for ARM",
    )
    p.add_argument("--compare-count", type=int, default=20, help="val images for the INT8-vs-fp32 check")
    p.add_argument("--timing-runs", type=int, default=200, help="latency runs per model (0 skips)")
    p.add_argument("--report", type=Path, default=None, help="also write the JSON report to this file")
    p.set_defaults(run=_run_export)


def _add_batch_model(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "batch-model",
        help="a copy of an exported model with a free batch axis, for `services.detector --batch N`",
    )
    p.add_argument("model", type=Path, help="a fixed-shape triscan ONNX model (fp32 or INT8)")
    p.add_argument("--out", type=Path, default=None, help="default: <model stem>-batch.onnx beside it")
    p.set_defaults(run=_run_batch_model)


def _run_batch_model(args: argparse.Namespace) -> int:
    from common.model_spec import batch_variant_path
    from training.batch_variant import add_batch_axis

    out = add_batch_axis(args.model, args.out or batch_variant_path(args.model))
    print(f"wrote {out}: the same network, frames in one call equal frames one by one")
    return 0


def _run_export(args: argparse.Namespace) -> int:
    import json

    from training.export import export_models

    result = export_models(
        args.weights,
        args.data,
        args.out,
        name=args.name,
        padding=args.padding,
        calib_count=args.calib_count,
        method=args.calib_method,
        activation_type=args.activations,
        float_leading_modules=args.float_modules,
        keep_box_logits_float=not args.quantize_box_logits,
        keep_head_convs_float=args.float_head_convs,
        compare_count=args.compare_count,
        timing_runs=args.timing_runs,
        box_grid=args.box_grid,
    )
    text = json.dumps(result, indent=2, default=str)
    if args.report is not None:
        args.report.parent.mkdir(parents=True, exist_ok=True)
        args.report.write_text(text + "\n")
    print(text)
    return 0


def _add_eval(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "eval", help="mAP, P, R per class of an ONNX model, through the run-time detector code"
    )
    p.add_argument(
        "--model", type=Path, required=True, action="append",
        help="ONNX model; repeat it to score several models on the very same --fresh tensors",
    )  # fmt: skip
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", type=Path, help="a data set written by `triscan dataset`")
    source.add_argument("--fresh", type=int, metavar="N", help="simulate N new scenarios instead")
    p.add_argument("--split", default="test", choices=("train", "val", "test"), help="split of --data")
    p.add_argument("--seed", type=int, default=1000, help="seed of the --fresh scenarios")
    p.add_argument("--positions", type=int, default=90, help="positions per --fresh scenario")
    p.add_argument("--frame-stride", type=int, default=15, help="window stride of --fresh motions")
    p.add_argument(
        "--noise",
        nargs="+",
        default=["clean"],
        metavar="CONDITION",
        help="LiDAR imperfections of the --fresh worlds: clean, sigma3, drop5, drop5+sigma3, "
        "drop10+sigma3+spur1, or sigma=S,dropout=D,spurious=P; several: each on the same worlds",
    )
    p.add_argument(
        "--clutter", type=int, default=0, metavar="N",
        help="up to N unlabelled poles, wall stubs and walking leg pairs per --fresh motion: does the "
        "model detect things that are not furniture?",
    )  # fmt: skip
    p.add_argument(
        "--padding", choices=PADDINGS, default=None, help="padding of the tensors (default: the model's own)"
    )
    p.add_argument(
        "--box-grid", choices=BOX_GRIDS, default=None,
        help="'pixel': round box edges to whole pixels after NMS (default: the model's own)",
    )  # fmt: skip
    p.add_argument("--threads", type=int, default=None, help="ONNX Runtime intra-op threads")
    p.add_argument("--out", type=Path, default=Path("eval"), help="directory for metrics.json and plots")
    p.set_defaults(run=_run_eval)


def _run_eval(args: argparse.Namespace) -> int:
    from common.inference import OnnxDetector
    from training.evaluate import (
        VAL_CONF,
        VAL_IOU,
        VAL_MAX_DET,
        FreshWorlds,
        condition_matrix,
        dataset_samples,
        evaluate,
        format_condition_table,
        format_table,
        fresh_samples,
    )

    worlds = FreshWorlds(args.seed, args.fresh, args.positions, args.frame_stride, args.clutter)
    matrix = len(args.model) > 1 or len(args.noise) > 1
    if matrix and args.data is not None:
        raise ValueError("several --model or --noise values need --fresh worlds, not --data")
    if args.clutter and args.data is not None:
        raise ValueError("--clutter places clutter in --fresh worlds; a --data set has its own")
    detectors = [
        OnnxDetector(
            model,
            conf_threshold=VAL_CONF,
            iou_threshold=VAL_IOU,
            max_detections=VAL_MAX_DET,
            padding=args.padding,
            intra_op_threads=args.threads,
            box_grid=args.box_grid,
        )
        for model in args.model
    ]
    if matrix:
        reports = condition_matrix(detectors, args.noise, worlds, args.out)
        print(format_condition_table(reports))
        print(f"per cell: {args.out}/<condition>/<model>/metrics.json; grid: {args.out}/summary.json")
        return 0
    detector = detectors[0]
    if args.data is not None:
        from training.onnx_export import dataset_invalid_rule

        if (rule := dataset_invalid_rule(args.data)) != detector.invalid:
            raise ValueError(
                f"{args.data} puts invalid returns {rule!r}, {args.model[0]} reads them {detector.invalid!r}"
            )
        samples, source = dataset_samples(args.data, args.split), f"{args.data}:{args.split}"
    else:
        from services.simulator.lidar import with_imperfections

        noise = args.noise[0]
        spec = with_imperfections(noise)  # a bad condition is a ValueError: one line, exit 2
        samples = fresh_samples(
            args.seed, args.fresh, args.positions, detector.padding, args.frame_stride, spec=spec,
            invalid=detector.invalid, clutter=args.clutter,
        )  # fmt: skip
        source = worlds.source(noise)
    report = evaluate(detector, samples, args.out, source=source)
    print(format_table(report))
    print(f"images {report.images}; mean ms: {report.mean_timings_ms}; written to {args.out}/metrics.json")
    return 0


def _add_card(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("card", help="write models/MODEL_CARD.md and .json from the measuring artefacts")
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
    p.add_argument("--gate-seed", type=int, default=1000)
    p.add_argument("--gate-scenarios", type=int, default=6)
    p.add_argument("--gate-positions", type=int, default=15)
    p.add_argument("--gate-frame-stride", type=int, default=15)
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
        "--compare-curve", type=_network_and_csv, default=None, metavar="NETWORK=RESULTS_CSV",
        help="another network's results.csv on the same data, e.g. yolov8n=runs/n_dr/results.csv: "
        "its val curve beside this run's, epoch for epoch",
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
    p.set_defaults(run=_run_card)


def _network_and_csv(text: str) -> tuple[str, Path]:
    """``yolov8n=path/results.csv`` → ("yolov8n", Path): a network's name and its training curve."""
    network, sep, path = text.partition("=")
    if not sep or not network or not path:
        raise argparse.ArgumentTypeError(
            f"expected NETWORK=RESULTS_CSV (yolov8n=runs/n/results.csv), got {text!r}"
        )
    return network, Path(path)


def _run_card(args: argparse.Namespace) -> int:
    from training.model_card import CurveComparison, GridSection, write_card

    def notes(path: Path | None) -> str:
        return path.read_text() if path else ""

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

    card = write_card(
        dataset_dir=args.data,
        run_dir=args.run_dir,
        export_json=args.export_report,
        eval_test_fp32=args.eval_fp32,
        eval_test_int8=args.eval_int8,
        eval_gate=args.eval_gate,
        out_dir=args.out,
        gate={
            "seed": args.gate_seed,
            "scenarios": args.gate_scenarios,
            "positions": args.gate_positions,
            "frame_stride": args.gate_frame_stride,
        },
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
    )
    print(f"wrote {args.out}/MODEL_CARD.md (recommended: {card['recommended']})")
    return 0


SIMULATOR_ONLY_FLAGS = {"robots": "--robots", "rate_hz": "--rate", "seed": "--seed"}
REPLAY_ONLY_FLAGS = {"topic": "--topic", "robot": "--robot", "speed": "--speed", "loop": "--loop"}


def _add_up(sub: argparse._SubParsersAction) -> None:
    from common.transport import add_zenoh_arguments

    p = sub.add_parser(
        "up", help="the full simulation loop: simulator, encoder, detector, visualizer as four processes"
    )
    # None: the default of UpConfig (simulator flags) or ReplayConfig (replay flags), so that a flag of
    # the other source can be refused rather than silently ignored.
    p.add_argument("--robots", type=int, default=None, help="simulated robots (default 1)")
    p.add_argument("--rate", dest="rate_hz", type=float, default=None, help="scans per second per robot")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: Ctrl-C)")
    p.add_argument("--headless", action="store_true", help="no viewer: record an .rrd instead")
    p.add_argument(
        "--rrd", type=Path, default=None, help="--headless recording (default: runs/triscan-<time>.rrd)"
    )
    p.add_argument(
        "--viewer", choices=("spawn", "web", "none"), default="spawn", help="viewer when not --headless"
    )
    p.add_argument("--model", type=Path, default=None, help="ONNX model (default: the shipped one)")
    p.add_argument(
        "--batch",
        type=int,
        default=None,
        help="detector: most robots per model call (default: it picks, 4 with the shipped -batch model)",
    )
    p.add_argument("--seed", type=int, default=None, help="simulator seed (default 1; training used 0)")
    p.add_argument(
        "--max-restarts", type=int, default=5, help="restarts of one service per minute before giving up"
    )
    replay = p.add_argument_group("replay (instead of the simulator; the run ends when the bag does)")
    replay.add_argument(
        "--replay",
        nargs="+",
        type=Path,
        default=None,
        metavar="BAG",
        help="ROS 1 .bag files or one ROS 2 bag",
    )
    replay.add_argument("--topic", action="append", default=None, help="LaserScan topic (default: all)")
    replay.add_argument("--robot", default=None, help="robot id of a single replayed topic (default: replay)")
    replay.add_argument("--speed", type=float, default=None, help="playback speed (default 1)")
    replay.add_argument("--loop", action="store_true", default=None, help="replay until stopped")
    add_zenoh_arguments(p)
    p.set_defaults(run=_run_up)


def _given(args: argparse.Namespace, flags: dict[str, str]) -> dict[str, object]:
    """The flags of ``flags`` (attribute → flag) given on the command line, by attribute."""
    return {name: getattr(args, name) for name in flags if getattr(args, name) is not None}


def _run_up(args: argparse.Namespace) -> int:
    from common.transport import ZenohSettings, settings_from_args
    from services.bag_replay import ReplayConfig
    from services.launcher import DEFAULT_LISTEN, UpConfig, up
    from services.runtime import stop_event_on_signals

    settings = settings_from_args(args)
    if not settings.listen and settings.config_file is None:
        settings = ZenohSettings(
            mode=settings.mode or "peer",
            connect=settings.connect,
            listen=(DEFAULT_LISTEN,),
            multicast_scouting=False if settings.multicast_scouting is None else settings.multicast_scouting,
        )
    simulator_flags, replay_flags = _given(args, SIMULATOR_ONLY_FLAGS), _given(args, REPLAY_ONLY_FLAGS)
    replay = None
    if args.replay is not None:
        if simulator_flags:
            raise ValueError(f"{', '.join(SIMULATOR_ONLY_FLAGS[k] for k in simulator_flags)}: simulator only")
        topics: list[str] = replay_flags.pop("topic", [])  # type: ignore[assignment]
        replay_flags["topics"] = tuple(topics)
        replay = ReplayConfig(bags=tuple(args.replay), progress=False, **replay_flags)  # type: ignore[arg-type]
    elif replay_flags:
        raise ValueError(f"{', '.join(REPLAY_ONLY_FLAGS[k] for k in replay_flags)}: needs --replay")
    config = UpConfig(
        duration_s=args.duration,
        headless=args.headless,
        rrd_path=args.rrd,
        viewer=args.viewer,
        model=args.model,
        batch=args.batch,
        max_restarts=args.max_restarts,
        settings=settings,
        verbose=args.verbose,
        replay=replay,
        **simulator_flags,  # type: ignore[arg-type]
    )
    return up(config, stop_event_on_signals())


def _add_status(sub: argparse._SubParsersAction) -> None:
    from common.transport import add_zenoh_arguments

    p = sub.add_parser("status", help="which triscan services are up, and their counters")
    p.add_argument("--wait", type=float, default=2.5, help="seconds to listen for counters")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    add_zenoh_arguments(p)
    p.set_defaults(run=_run_status)


def _run_status(args: argparse.Namespace) -> int:
    import json
    from dataclasses import asdict

    from common.transport import settings_from_args
    from services.status import collect_status, format_status

    statuses = collect_status(settings_from_args(args), args.wait)
    print(json.dumps([asdict(s) for s in statuses], indent=2) if args.json else format_status(statuses))
    return 0 if statuses else 1


def _add_replay(sub: argparse._SubParsersAction) -> None:
    from services.bag_replay import add_replay_arguments

    p = sub.add_parser(
        "replay", help="publish the LaserScans of ROS 1/2 bags (.bag, .db3, .mcap) as triscan scans"
    )
    add_replay_arguments(p)
    p.set_defaults(run=_run_replay)


def _run_replay(args: argparse.Namespace) -> int:
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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="triscan", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_dataset(sub)
    _add_show(sub)
    _add_train(sub)
    _add_export(sub)
    _add_batch_model(sub)
    _add_eval(sub)
    _add_card(sub)
    _add_up(sub)
    _add_status(sub)
    _add_replay(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format=LOG_FORMAT,
    )
    try:
        return int(args.run(args))
    except (FileExistsError, FileNotFoundError, ValueError) as exc:
        logging.getLogger(__name__).error("%s", exc)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
