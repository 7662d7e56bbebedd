"""``python -m services.detector``: tensors in on ``triscan/*/tensor``, detections out on ``.../detections``.

The robot's perception process (base dependencies only: numpy, onnxruntime, zenoh, msgpack, pydantic).
``--from-scans`` runs the encoder in the same process and subscribes to ``triscan/*/scan`` instead,
saving one hop and one serialisation on a Raspberry Pi. Zenoh callbacks only decode and drop the
tensor into a newest-per-robot mailbox; inference threads drain it, so the detector never falls
behind (see :mod:`services.detector.core`). With ``--batch N`` and a ``-batch`` model, a thread runs
up to N waiting robots' tensors in one model call, which a CPU does for less per frame.
"""

from __future__ import annotations

import argparse
import logging
import os
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from common.inference import DEFAULT_CONF, DEFAULT_IOU, OnnxDetector
from common.keys import SCAN, TENSOR, detections_key, parse_key, wildcard_key
from common.messages import Detections, StackedTensor, encode_message
from common.transport import (
    ZenohSettings,
    open_session,
    payload_bytes,
    settings_from_args,
)
from services.detector.core import DetectorCore, LatestPerRobot
from services.encoder.core import DEFAULT_FORGET_AFTER_S, EncoderCore
from services.runtime import (
    StatsPublisher,
    add_service_arguments,
    configure_logging,
    declare_health,
    stop_event_on_signals,
)

log = logging.getLogger("triscan.detector")

MODEL_ENV = "TRISCAN_MODEL"
SHIPPED_MODEL = Path(__file__).resolve().parents[2] / "models" / "triscan-yolov8n-zero.onnx"
# The same model with a free batch axis (training.export.add_batch_axis), for --batch above 1.
SHIPPED_BATCH_MODEL = SHIPPED_MODEL.with_name("triscan-yolov8n-zero-batch.onnx")
TAKE_TIMEOUT_S = 0.5
SUMMARY_EVERY_S = 10.0


def default_model_path(batched: bool = False) -> Path:
    """``$TRISCAN_MODEL`` if set, else the model shipped in the repository's ``models/`` (its batch
    variant when ``batched``)."""
    if os.environ.get(MODEL_ENV):
        return Path(os.environ[MODEL_ENV])
    return SHIPPED_BATCH_MODEL if batched else SHIPPED_MODEL


def check_batch(detectors: Sequence[OnnxDetector], batch: int) -> None:
    """Refuse a batch size the model cannot run, before any frame is lost to it."""
    if batch < 1:
        raise ValueError(f"batch must be >= 1, got {batch}")
    if batch > 1 and not all(d.batched for d in detectors):
        raise ValueError(
            f"batch {batch} needs a model with a free batch axis; {detectors[0].model_path} is fixed at "
            f"batch 1 (its -batch variant, e.g. models/{SHIPPED_BATCH_MODEL.name}, is the same network)"
        )


def run(
    settings: ZenohSettings,
    stop: threading.Event,
    detectors: Sequence[OnnxDetector],
    *,
    from_scans: bool = False,
    forget_after_s: float = DEFAULT_FORGET_AFTER_S,
    duration_s: float = 0.0,
    batch: int = 1,
) -> DetectorCore:
    """Serve until ``stop`` is set (or ``duration_s`` passes); returns the core with its counters.

    One inference thread per detector in ``detectors`` (sessions of the same model): ONNX Runtime
    releases the GIL, so on a multi-core robot with many robots to serve, several single-threaded
    sessions in parallel beat one session spreading a batch-1 frame over all cores. Each thread takes
    up to ``batch`` robots' waiting tensors per model call (a batch model is needed for more than 1);
    it never waits to fill a batch, so a lone robot is served as fast as with ``batch`` 1.
    """
    if not detectors:
        raise ValueError("need at least one detector")
    check_batch(detectors, batch)
    detector = detectors[0]
    core = DetectorCore(detector)
    encoder = EncoderCore(detector.padding, forget_after_s=forget_after_s) if from_scans else None
    encoder_lock = threading.Lock()
    mailbox: LatestPerRobot[StackedTensor] = LatestPerRobot()
    for worker_detector in detectors:
        worker_detector.warmup(batch)

    def robot_of(sample: Any) -> str | None:
        try:
            return parse_key(str(sample.key_expr))[0]
        except ValueError as exc:
            core.reject("bad_key", str(exc))
            return None

    def on_tensor(sample: Any) -> None:
        robot_id = robot_of(sample)
        tensor = core.decode(payload_bytes(sample), robot_id) if robot_id is not None else None
        if tensor is not None and mailbox.put(tensor.robot_id, tensor):
            core.note_dropped()

    def on_scan(sample: Any) -> None:
        assert encoder is not None
        robot_id = robot_of(sample)
        if robot_id is None:
            return
        with encoder_lock:
            tensor = encoder.handle_payload(payload_bytes(sample), robot_id)
        if tensor is not None and core.accept(tensor) is not None and mailbox.put(tensor.robot_id, tensor):
            core.note_dropped()

    with open_session(settings) as session:
        key = wildcard_key(SCAN if from_scans else TENSOR)
        subscriber = session.declare_subscriber(key, on_scan if from_scans else on_tensor)
        token = declare_health(session, "detector")
        stats = StatsPublisher(session, "detector")
        log.info(
            "detector ready: %s (%s padding) on %s → detections", detector.model_id, detector.padding, key
        )
        publishers: dict[str, Any] = {}
        last_served: dict[str, float] = {}
        publishers_lock = threading.Lock()

        def forget_silent_robots(now: float) -> None:
            """Undeclare publishers of robots not served for ``forget_after_s``: no leak as fleets change."""
            with publishers_lock:
                for robot_id in [r for r, t in last_served.items() if now - t > forget_after_s]:
                    publishers.pop(robot_id).undeclare()
                    del last_served[robot_id]

        def publish(detections: Detections) -> None:
            robot_id = detections.robot_id
            with publishers_lock:
                publisher = publishers.get(robot_id)
                if publisher is None:
                    publisher = publishers[robot_id] = session.declare_publisher(detections_key(robot_id))
                last_served[robot_id] = time.monotonic()
            publisher.put(encode_message(detections))

        def serve(worker_detector: OnnxDetector) -> None:
            while not stop.is_set():
                taken = mailbox.take_many(batch, TAKE_TIMEOUT_S)
                if not taken:
                    continue
                try:
                    try:
                        results = core.detect_many([tensor for _, tensor in taken], worker_detector)
                    except Exception as exc:  # one failed model call must not end this worker
                        log.exception("inference failed for %s", [robot_id for robot_id, _ in taken])
                        for robot_id, tensor in taken:
                            core.reject("inference_error", f"{robot_id} seq {tensor.seq}: {exc}")
                        results = []
                    for detections in results:
                        publish(detections)
                finally:
                    for robot_id, _ in taken:  # only now: a robot's next tensor must not overtake this one
                        mailbox.release(robot_id)

        workers = [
            threading.Thread(target=serve, args=(d,), name=f"inference-{i}", daemon=True)
            for i, d in enumerate(detectors)
        ]
        for worker in workers:
            worker.start()
        started = last_summary = time.monotonic()
        try:
            while not stop.wait(1.0):
                now = time.monotonic()
                forget_silent_robots(now)
                counters: dict[str, object] = {**core.counters.to_dict(), "robots": len(publishers)}
                if encoder is not None:
                    with encoder_lock:
                        encoder.forget_silent()
                        counters["encoder"] = encoder.counters.to_dict()
                stats.publish(counters)
                if now - last_summary >= SUMMARY_EVERY_S:
                    last_summary = now
                    log.info("robots %d, %s", len(publishers), core.counters.to_dict())
                if duration_s and now - started >= duration_s:
                    break
        finally:
            stop.set()
            mailbox.close()
            for worker in workers:
                worker.join(10)
            stats.close()
            token.undeclare()
            subscriber.undeclare()
    return core


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="triscan-detector", description=__doc__.splitlines()[0])
    parser.add_argument(
        "--model", type=Path, default=None, help=f"ONNX model (default: ${MODEL_ENV} or {SHIPPED_MODEL.name})"
    )
    parser.add_argument("--conf", type=float, default=DEFAULT_CONF, help="score threshold")
    parser.add_argument("--iou", type=float, default=DEFAULT_IOU, help="NMS IoU threshold")
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="ONNX Runtime threads per worker (default: all cores / workers)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=1,
        help="parallel inference threads, each with its own session (fleets)",
    )
    parser.add_argument(
        "--batch",
        type=int,
        default=1,
        help="most robots' tensors per model call, each worker; above 1 needs a -batch model "
        f"(default model then: {SHIPPED_BATCH_MODEL.name})",
    )
    parser.add_argument(
        "--from-scans", action="store_true", help="encode scans here too (encoder + detector)"
    )
    add_service_arguments(parser, forget_after_s=DEFAULT_FORGET_AFTER_S)
    args = parser.parse_args(argv)
    configure_logging(args.verbose)
    if args.workers < 1:
        parser.error(f"--workers must be >= 1, got {args.workers}")
    if args.batch < 1:
        parser.error(f"--batch must be >= 1, got {args.batch}")  # before loading any model
    threads = args.threads or (max(1, (os.cpu_count() or 1) // args.workers) if args.workers > 1 else None)
    try:
        detectors = [
            OnnxDetector(
                args.model or default_model_path(batched=args.batch > 1),
                conf_threshold=args.conf,
                iou_threshold=args.iou,
                intra_op_threads=threads,
            )
            for _ in range(args.workers)
        ]
        check_batch(detectors, args.batch)
    except (FileNotFoundError, ValueError) as exc:
        log.error("cannot load the model: %s", exc)
        return 2
    run(
        settings_from_args(args),
        stop_event_on_signals(),
        detectors,
        from_scans=args.from_scans,
        forget_after_s=args.forget_after,
        duration_s=args.duration,
        batch=args.batch,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
