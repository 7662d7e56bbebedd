"""``triscan eval``: mAP, P, R per class of ONNX models through the run-time detector code.

``--preset NAME`` names a protocol of the recipe file (``[eval.NAME]``: ``unseen`` is the model cards'
unseen worlds under every LiDAR condition); a flag given with it overrides the preset's value.
``--bag`` scores the models on a recorded ROS bag instead (:mod:`training.real_eval`,
docs/real-recordings.md); ``--tracks`` scores the tracker over the detections of the --fresh
motions with CLEAR MOT (:mod:`training.track_eval`, docs/tracking.md).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from common.encoding import PADDINGS
from common.model_spec import BOX_GRIDS
from common.moving_people import add_motion_argument, motion_confirm_of
from services.cli.command import Command, add_recipe_argument
from services.simulator.sensors import PROFILES
from services.tracker import add_tracker_arguments, tracker_config

# The --fresh worlds' settings when no --preset gives them.
FRESH_DEFAULTS: dict[str, object] = {"seed": 1000, "positions": 90, "frame_stride": 15, "noise": ["clean"]}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--model", type=Path, required=True, action="append",
        help="ONNX model; repeat it to score several models on the very same --fresh tensors",
    )  # fmt: skip
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", type=Path, help="a data set written by `triscan dataset`")
    source.add_argument("--fresh", type=int, metavar="N", help="simulate N new scenarios instead")
    source.add_argument(
        "--preset", metavar="NAME",
        help="the fresh worlds and conditions of the recipe file's [eval.NAME] (unseen: the model cards' "
        "20 unseen worlds under five LiDAR conditions)",
    )  # fmt: skip
    source.add_argument(
        "--bag", type=Path,
        help="a recorded ROS bag: people, legs or false detections on real scans (docs/real-recordings.md)",
    )  # fmt: skip
    _add_bag_arguments(p.add_argument_group("recorded bags (--bag)"))
    add_recipe_argument(p, "recipe file holding --preset")
    p.add_argument("--split", default="test", choices=("train", "val", "test"), help="split of --data")
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help=f"seed of the --fresh scenarios (default {FRESH_DEFAULTS['seed']})",
    )
    p.add_argument(
        "--positions", type=int, default=None,
        help=f"positions per --fresh scenario (default {FRESH_DEFAULTS['positions']})",
    )  # fmt: skip
    p.add_argument(
        "--frame-stride", type=int, default=None,
        help=f"window stride of --fresh motions (default {FRESH_DEFAULTS['frame_stride']})",
    )  # fmt: skip
    p.add_argument(
        "--noise",
        nargs="+",
        default=None,
        metavar="CONDITION",
        help="LiDAR imperfections of the --fresh worlds: clean (default), sigma3, drop5, drop5+sigma3, "
        "drop10+sigma3+spur1, or sigma=S,dropout=D,spurious=P; several: each on the same worlds",
    )
    p.add_argument(
        "--clutter", type=int, default=0, metavar="N",
        help="up to N unlabelled poles and wall stubs per --fresh motion: does the model detect things "
        "that are none of its classes?",
    )  # fmt: skip
    p.add_argument(
        "--people", type=int, default=0, metavar="N",
        help="up to N walking or standing people (labelled 'person') per --fresh motion",
    )  # fmt: skip
    p.add_argument(
        "--open-space", type=float, default=0.0, metavar="SHARE",
        help="share of --fresh worlds whose walls stand 2.5-6 m from the centre (triscan dataset "
        "--open-space); default 0, the paper's 4 x 4 m room",
    )  # fmt: skip
    p.add_argument(
        "--sensor", nargs="+", default=None, choices=[*PROFILES, "all"], metavar="NAME",
        help="score --fresh worlds seen by these sensor profiles, one table row each ('all': every "
        f"profile: {', '.join(PROFILES)}); default: the LDS-01",
    )  # fmt: skip
    p.add_argument(
        "--padding", choices=PADDINGS, default=None, help="padding of the tensors (default: the model's own)"
    )
    p.add_argument(
        "--box-grid", choices=BOX_GRIDS, default=None,
        help="'pixel': round box edges to whole pixels after NMS (default: the model's own)",
    )  # fmt: skip
    p.add_argument(
        "--tracks", action="store_true",
        help="score the tracker (CLEAR MOT, furniture and people apart) over every scan of the --fresh "
        "motions instead of the detections; with --bag: its confirmed tracks and person passes",
    )  # fmt: skip
    add_tracker_arguments(p)
    add_motion_argument(p)
    p.add_argument("--threads", type=int, default=None, help="ONNX Runtime intra-op threads")
    p.add_argument("--out", type=Path, default=Path("eval"), help="directory for metrics.json and plots")


def _add_bag_arguments(g: argparse._ArgumentGroup) -> None:
    g.add_argument("--topic", default=None, help="LaserScan topic of --bag (default: its only one)")
    g.add_argument("--people-topic", default=None, help="person centres (PoseArray) in the laser frame")
    g.add_argument("--legs-topic", default=None, help="leg clusters (PoseArray) in the laser frame")
    g.add_argument(
        "--stream-bag", type=Path, default=None,
        help="the full recording --bag's scans were cut from: tensors stack its consecutive scans",
    )  # fmt: skip
    g.add_argument(
        "--bearing-window", type=float, nargs=2, default=None, metavar=("MIN", "MAX"),
        help="score only within these bearings, degrees counter-clockwise from forward (default: all)",
    )  # fmt: skip
    g.add_argument(
        "--legs-window", type=float, nargs=2, default=None, metavar=("MIN", "MAX"),
        help="bearings where --legs-topic's legs were extracted (default: the development set's own)",
    )  # fmt: skip
    g.add_argument("--people-free", action="store_true", help="the bag holds no people: false people/min")
    g.add_argument(
        "--field-of-view", type=float, default=None, metavar="DEG",
        help="score the recording as a sensor with this narrower field of view about the same heading "
        "would see it: only its beams within DEG/2 either side of forward (default: all its beams)",
    )  # fmt: skip
    g.add_argument("--conf", type=float, default=None, help="operating confidence (default: the detector's)")


def _run_bag(args: argparse.Namespace) -> int:
    from training.real_eval import (
        BagEvalConfig,
        Scope,
        detector_for,
        evaluate_bag,
        format_reports,
        write_reports,
    )

    config = BagEvalConfig(
        bag=args.bag,
        topic=args.topic,
        people_topic=args.people_topic,
        legs_topic=args.legs_topic,
        stream_bag=args.stream_bag,
        scope=Scope(*args.bearing_window) if args.bearing_window else Scope(),
        legs_window=Scope(*args.legs_window, max_range_m=float("inf")) if args.legs_window else None,
        people_free=args.people_free,
        field_of_view_deg=args.field_of_view,
        **({} if args.conf is None else {"conf": args.conf}),
    )
    if args.tracks:
        import json

        from training.track_eval import format_bag_tracks, track_bag

        rules = tracker_config(args)
        motion = motion_confirm_of(args)
        detectors = [detector_for(model, args.threads, motion) for model in args.model]
        tracked = [track_bag(detector, config, rules) for detector in detectors]
        print("\n".join(format_bag_tracks(report) for report in tracked))
        args.out.mkdir(parents=True, exist_ok=True)
        out = args.out / "bag_tracks.json"
        out.write_text(json.dumps([dataclasses.asdict(r) for r in tracked], indent=2) + "\n")
        print(f"written to {out}")
        return 0
    motion = motion_confirm_of(args)
    reports = [evaluate_bag(detector_for(model, args.threads, motion), config) for model in args.model]
    print(format_reports(reports))
    print(f"written to {write_reports(reports, args.out)}")
    return 0


def _apply_preset(args: argparse.Namespace) -> None:
    """Fill the --fresh settings left unset: from ``--preset``'s table, else :data:`FRESH_DEFAULTS`."""
    defaults = dict(FRESH_DEFAULTS)
    if args.preset is not None:
        from training.recipe import SHIPPED_RECIPE, load_recipe

        preset = load_recipe(args.recipe or SHIPPED_RECIPE).preset(args.preset)
        args.fresh = preset.fresh
        defaults = {
            "seed": preset.seed,
            "positions": preset.positions,
            "frame_stride": preset.frame_stride,
            "noise": list(preset.noise),
        }
    elif args.recipe is not None:
        raise ValueError("--recipe names the file of a --preset: give both")
    for name, value in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, value)


def run(args: argparse.Namespace) -> int:
    if args.bag is not None:
        return _run_bag(args)
    from common.inference import OnnxDetector
    from training.evaluate import (
        SENSOR_SEPARATOR,
        VAL_CONF,
        VAL_IOU,
        VAL_MAX_DET,
        FreshWorlds,
        condition_matrix,
        condition_spec,
        dataset_samples,
        evaluate,
        format_condition_table,
        format_table,
        fresh_samples,
    )

    _apply_preset(args)
    worlds = FreshWorlds(
        args.seed, args.fresh, args.positions, args.frame_stride, args.clutter, args.people, args.open_space
    )
    sensors = list(PROFILES) if args.sensor == ["all"] else args.sensor
    conditions = (
        args.noise
        if sensors is None
        else [f"{sensor}{SENSOR_SEPARATOR}{noise}" for sensor in sensors for noise in args.noise]
    )
    matrix = len(args.model) > 1 or len(conditions) > 1
    if args.tracks and (matrix or args.data is not None):
        raise ValueError("--tracks scores one --model on --fresh worlds under one condition")
    if matrix and args.data is not None:
        raise ValueError("several --model or --noise values need --fresh worlds, not --data")
    if (args.clutter or args.people or args.open_space or sensors) and args.data is not None:
        raise ValueError(
            "--clutter, --people, --open-space and --sensor shape --fresh worlds; a --data set has its own"
        )
    # mAP sweeps every confidence; the tracker sees what the detector service publishes (its defaults).
    thresholds = (
        {}
        if args.tracks
        else {"conf_threshold": VAL_CONF, "iou_threshold": VAL_IOU, "max_detections": VAL_MAX_DET}
    )
    detectors = [
        OnnxDetector(
            model,
            **thresholds,
            padding=args.padding,
            intra_op_threads=args.threads,
            box_grid=args.box_grid,
            motion_confirm=motion_confirm_of(args),
        )
        for model in args.model
    ]
    if matrix:
        reports = condition_matrix(detectors, conditions, worlds, args.out)
        print(format_condition_table(reports))
        print(f"per cell: {args.out}/<condition>/<model>/metrics.json; grid: {args.out}/summary.json")
        return 0
    detector = detectors[0]
    if args.tracks:
        from training.track_eval import evaluate_tracks, format_report, fresh_motions

        motions = fresh_motions(
            args.seed, args.fresh, args.positions, detector, spec=condition_spec(conditions[0]),
            clutter=args.clutter, people=args.people, open_space=args.open_space,
        )  # fmt: skip
        track_report = evaluate_tracks(
            detector, motions, args.out, source=worlds.source(conditions[0]), tracker=tracker_config(args)
        )
        print(format_report(track_report))
        print(f"written to {args.out}/tracks.json")
        return 0
    if args.data is not None:
        from training.onnx_export import dataset_invalid_rule, dataset_raster_yaw

        if (rule := dataset_invalid_rule(args.data)) != detector.invalid:
            raise ValueError(
                f"{args.data} puts invalid returns {rule!r}, {args.model[0]} reads them {detector.invalid!r}"
            )
        if (yaw := dataset_raster_yaw(args.data)) != detector.raster_yaw_deg:
            raise ValueError(
                f"{args.data} turns its scans by a raster yaw of {yaw:g} deg, {args.model[0]} by "
                f"{detector.raster_yaw_deg:g} deg"
            )
        samples, source = dataset_samples(args.data, args.split), f"{args.data}:{args.split}"
    else:
        noise = conditions[0]
        spec = condition_spec(noise)  # a bad condition is a ValueError: one line, exit 2
        samples = fresh_samples(
            args.seed, args.fresh, args.positions, detector.padding, args.frame_stride, spec=spec,
            invalid=detector.invalid, clutter=args.clutter, people=args.people,
            raster_yaw_deg=detector.raster_yaw_deg, open_space=args.open_space,
        )  # fmt: skip
        source = worlds.source(noise)
    report = evaluate(detector, samples, args.out, source=source)
    print(format_table(report))
    print(f"images {report.images}; mean ms: {report.mean_timings_ms}; written to {args.out}/metrics.json")
    return 0


COMMAND = Command(
    "eval",
    "mAP, P, R per class of an ONNX model, through the run-time detector code",
    add_arguments,
    run,
    extras=("sim",),
)
