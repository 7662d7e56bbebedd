"""``python -m services.detector``: robots' ``triscan/<robot>/tensor`` in, ``.../detections`` out.

The robot's perception process (base dependencies only: numpy, onnxruntime, zenoh, msgpack, pydantic).
``--from-scans`` runs the encoder in the same process and subscribes to ``triscan/*/scan`` instead,
saving one hop and one serialisation on a Raspberry Pi. Zenoh callbacks only decode and drop the
tensor into a newest-per-robot mailbox; inference threads drain it, so the detector never falls
behind (see :mod:`services.detector.core`). With ``--batch N`` and a ``-batch`` model, a thread runs
up to N waiting robots' tensors in one model call, which a CPU does for less per frame; without
``--batch`` the detector times its model at start and picks the cap itself
(:mod:`services.detector.batch_cap`). ``--detectors N`` (default: one per core) starts N-1 more
processes like this one; the live detector processes, here or on other hosts of the same Zenoh
network, share the robots among themselves (:mod:`services.shards`), and each subscribes only to the
tensors (``--from-scans``: the scans) of the announced robots it serves
(:mod:`services.shard_subscriptions`); with ``--from-scans`` one of them also serves the scans of
robots that announce nothing (a user's driver, a bridge).
"""

from __future__ import annotations

import logging
import math
import subprocess
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from common.inference import OnnxDetector
from common.keys import SCAN, TENSOR, detections_key, scan_key, tensor_key
from common.messages import Detections, encode_message
from common.model_spec import BOX_GRIDS, MODEL_ENV, SHIPPED_BATCH_MODEL, SHIPPED_MODEL
from common.moving_people import add_motion_argument, motion_confirm_of
from common.postprocess import DEFAULT_CONF, DEFAULT_IOU
from common.transport import ZenohSettings, payload_bytes, settings_from_args
from services.detector.batch_cap import (
    AUTO_BATCH,
    AUTO_BATCH_CALL_BUDGET_MS,
    detector_model_and_batch,
    timed_batch_cap,
)
from services.detector.core import (
    DEFAULT_GATHER_MS,
    DetectorCore,
    InferencePipeline,
    default_intra_op_threads,
    default_processes,
    default_workers,
)
from services.encoder.core import DEFAULT_FORGET_AFTER_S
from services.launcher import child_environment
from services.runtime import (
    ServiceRuntime,
    add_service_arguments,
    configure_logging,
    exit_code_of,
    exit_process,
    service_parser,
    stop_event_on_signals,
)
from services.shard_subscriptions import OwnedSubscriptions
from services.shards import ShardMembership, Siblings, add_processes_argument, sibling_commands

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

PROCESSES_FLAG = "--detectors"


def run(
    settings: ZenohSettings,
    stop: threading.Event,
    detectors: Sequence[OnnxDetector],
    *,
    from_scans: bool = False,
    forget_after_s: float = DEFAULT_FORGET_AFTER_S,
    duration_s: float = 0.0,
    batch: int = 1,
    gather_ms: float = DEFAULT_GATHER_MS,
    siblings: Siblings | None = None,
    processes: int = 1,
) -> DetectorCore:
    """Serve until ``stop`` is set (or ``duration_s`` passes); returns the core with its counters.

    The process serves its share of the robots among the live detector processes
    (:mod:`services.shards`); ``siblings`` are the other processes of this launch, restarted if one dies.
    It serves, and declares its health token, once ``processes`` detectors are live and settled, so
    that a launch's token means all of its processes serve their shares. Samples are subscribed per
    robot it serves, once the robot's source is announced; with ``from_scans`` the process that
    serves the robots with no source token also subscribes to every robot's scans.
    """
    with ServiceRuntime("detector", settings, stop, duration_s=duration_s) as runtime:
        publishers = runtime.robot_publishers(detections_key)
        shards = ShardMembership(runtime.session, "detector")

        def on_sample(sample: Any) -> None:
            sample_key = str(sample.key_expr)
            if not pipeline.not_ours(sample_key):  # another process's robot: no payload copy
                pipeline.handle_sample(sample_key, payload_bytes(sample))

        topic, key_of = (SCAN, scan_key) if from_scans else (TENSOR, tensor_key)
        unannounced = on_sample if from_scans else None  # scans also come from code that announces none
        subscriptions = OwnedSubscriptions(
            runtime.session, shards.me, topic, key_of, on_sample, unannounced=unannounced, view=shards.view
        )

        def publish(detections: Detections) -> None:
            publishers.put(detections.robot_id, encode_message(detections))

        pipeline = InferencePipeline(
            detectors,
            publish,
            batch=batch,
            from_scans=from_scans,
            forget_after_s=forget_after_s,
            owns=subscriptions.owns(shards.view) if from_scans else shards.owns,
            gather_ms=gather_ms,
        )

        def housekeeping() -> dict[str, object]:
            publishers.forget_silent(forget_after_s)  # no publisher leak as fleets change
            if siblings is not None:
                siblings.restart_dead()
            shard = shards.log_changes(forget_after_s)
            subscriptions.set_members(shards.view.members)  # a missed membership change heals here
            shard.update(subscriptions.counters(forget_after_s))
            return {**pipeline.housekeeping(), "robots": len(publishers), "shard": shard}

        pipeline.start()
        try:
            shards.join(subscriptions.set_members)
            shards.wait_settled(processes, stop)
            subscriptions.start()  # once settled: a robot it subscribes to is one it serves
            subscriptions.wait_serving(stop)
            detector = pipeline.core.detector
            log.info(
                "detector %s ready: %s (%s padding) on its announced robots' %ss%s → detections",
                shards.me[:8],
                detector.model_id,
                detector.padding,
                topic,
                " (and the unannounced robots' if it serves them)" if from_scans else "",
            )
            runtime.serve(housekeeping)
        finally:
            pipeline.stop()  # publishes nothing more, then gives its robots up
            subscriptions.close()
            shards.leave()
    return pipeline.core


def main(argv: list[str] | None = None) -> int:
    parser = service_parser("services.detector", __doc__.splitlines()[0])
    parser.add_argument(
        "--model", type=Path, default=None, help=f"ONNX model (default: ${MODEL_ENV} or {SHIPPED_MODEL.name})"
    )
    parser.add_argument("--conf", type=float, default=DEFAULT_CONF, help="score threshold")
    parser.add_argument("--iou", type=float, default=DEFAULT_IOU, help="NMS IoU threshold")
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="ONNX Runtime threads per worker (default: cores / workers; one core less with --from-scans)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        help="parallel inference threads, each with its own session (default: one per core)",
    )
    parser.add_argument(
        "--batch",
        type=int,
        default=None,
        help="most robots' tensors per model call, each worker (default with a -batch model, "
        f"{SHIPPED_BATCH_MODEL.name} when no --model is given: the largest of 1, 2, 4 ... {AUTO_BATCH} "
        f"whose call takes at most {AUTO_BATCH_CALL_BUDGET_MS:g} ms on this machine; 1 with a fixed model)",
    )
    parser.add_argument(
        "--gather-ms",
        type=float,
        default=DEFAULT_GATHER_MS,
        help="longest a tensor waits for other robots' to fill a batch (0: take what is ready)",
    )
    parser.add_argument(
        "--from-scans", action="store_true", help="encode scans here too (encoder + detector)"
    )
    parser.add_argument(
        "--box-grid",
        choices=BOX_GRIDS,
        default=None,
        help="'pixel': round box edges to whole pixels after NMS (default: the model's triscan.box_grid)",
    )
    parser.add_argument(
        "--no-spin",
        dest="spin_wait",
        action="store_false",
        help="ONNX Runtime threads sleep instead of spinning between frames (frees the cores they spin on)",
    )
    add_motion_argument(parser)
    add_processes_argument(parser, PROCESSES_FLAG, "one per core")
    add_service_arguments(parser, forget_after_s=DEFAULT_FORGET_AFTER_S)
    argv = sys.argv[1:] if argv is None else argv
    args = parser.parse_args(argv)
    configure_logging(args.verbose)
    for flag, value in (("--workers", args.workers), (PROCESSES_FLAG, args.detectors)):
        if value is not None and value < 1:
            parser.error(f"{flag} must be >= 1, got {value}")
    processes = args.detectors or default_processes()
    workers = args.workers or default_workers(processes=processes)
    if not (args.gather_ms >= 0 and math.isfinite(args.gather_ms)):
        parser.error(f"--gather-ms must be a finite number >= 0, got {args.gather_ms}")
    if args.batch is not None and args.batch < 1:
        parser.error(f"--batch must be >= 1, got {args.batch}")  # before loading any model
    threads = args.threads or default_intra_op_threads(workers, args.from_scans, processes=processes)
    try:
        model, batch = detector_model_and_batch(args.model, args.batch)
        detectors = [
            OnnxDetector(
                model,
                conf_threshold=args.conf,
                iou_threshold=args.iou,
                intra_op_threads=threads,
                spin_wait=args.spin_wait,
                box_grid=args.box_grid,
                motion_confirm=motion_confirm_of(args),
            )
            for _ in range(workers)
        ]
    except (FileNotFoundError, ValueError) as exc:
        log.error("cannot load the model: %s", exc)
        return 2
    if args.batch is None and batch > 1:  # no --batch: the cap this machine runs within budget
        batch, call_ms = timed_batch_cap(detectors[0], batch)
        log.info(
            "batch cap %d: model calls of %s frames took %s ms here (budget %g ms a call)",
            batch,
            "/".join(str(size) for size in call_ms),
            "/".join(f"{ms:.1f}" for ms in call_ms.values()),
            AUTO_BATCH_CALL_BUDGET_MS,
        )
    siblings = None
    if processes > 1 and not args.sibling:  # the others run this cap too: timed once, on an idle machine
        extra = ("--batch", str(batch)) if args.batch is None else ()
        commands = sibling_commands("services.detector", argv, PROCESSES_FLAG, processes, extra)
        siblings = Siblings(commands, lambda command: subprocess.Popen(command, env=child_environment()))
        siblings.start()
        log.info("%d detector processes share the fleet: this one and pids %s", processes,
                 ", ".join(str(p.pid) for p in siblings.processes))  # fmt: skip
    try:
        run(
            settings_from_args(args),
            stop_event_on_signals(),
            detectors,
            from_scans=args.from_scans,
            forget_after_s=args.forget_after,
            duration_s=args.duration,
            batch=batch,
            gather_ms=args.gather_ms,
            siblings=siblings,
            processes=processes,
        )
    finally:
        if siblings is not None:
            siblings.stop()
    return 0


if __name__ == "__main__":
    exit_process(exit_code_of(main))
