"""``python -m services.detector``: tensors in on ``triscan/*/tensor``, detections out on ``.../detections``.

The robot's perception process (base dependencies only: numpy, onnxruntime, zenoh, msgpack, pydantic).
``--from-scans`` runs the encoder in the same process and subscribes to ``triscan/*/scan`` instead,
saving one hop and one serialisation on a Raspberry Pi. Zenoh callbacks only decode and drop the
tensor into a newest-per-robot mailbox; one inference thread drains it, so the detector never falls
behind (see :mod:`services.detector.core`).
"""

from __future__ import annotations

import argparse
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any

from common.inference import DEFAULT_CONF, DEFAULT_IOU, OnnxDetector
from common.keys import SCAN, TENSOR, detections_key, parse_key, wildcard_key
from common.messages import StackedTensor, encode_message
from common.transport import (
    ZenohSettings,
    add_zenoh_arguments,
    open_session,
    payload_bytes,
    settings_from_args,
)
from services.detector.core import DetectorCore, LatestPerRobot
from services.encoder.core import DEFAULT_FORGET_AFTER_S, EncoderCore
from services.runtime import configure_logging, declare_health, stop_event_on_signals

log = logging.getLogger("triscan.detector")

MODEL_ENV = "TRISCAN_MODEL"
SHIPPED_MODEL = Path(__file__).resolve().parents[2] / "models" / "triscan-yolov8n-zero.onnx"
TAKE_TIMEOUT_S = 0.5
SUMMARY_EVERY_S = 10.0


def default_model_path() -> Path:
    """``$TRISCAN_MODEL`` if set, else the model shipped in the repository's ``models/``."""
    return Path(os.environ[MODEL_ENV]) if os.environ.get(MODEL_ENV) else SHIPPED_MODEL


def run(
    settings: ZenohSettings,
    stop: threading.Event,
    detector: OnnxDetector,
    *,
    from_scans: bool = False,
    forget_after_s: float = DEFAULT_FORGET_AFTER_S,
    duration_s: float = 0.0,
) -> DetectorCore:
    """Serve until ``stop`` is set (or ``duration_s`` passes); returns the core with its counters."""
    core = DetectorCore(detector)
    encoder = EncoderCore(detector.padding, forget_after_s=forget_after_s) if from_scans else None
    encoder_lock = threading.Lock()
    mailbox: LatestPerRobot[StackedTensor] = LatestPerRobot()
    detector.warmup()

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
        publishers: dict[str, Any] = {}
        key = wildcard_key(SCAN if from_scans else TENSOR)
        subscriber = session.declare_subscriber(key, on_scan if from_scans else on_tensor)
        token = declare_health(session, "detector")
        log.info(
            "detector ready: %s (%s padding) on %s → detections", detector.model_id, detector.padding, key
        )
        started = last_summary = last_housekeeping = time.monotonic()
        try:
            while not stop.is_set():
                item = mailbox.take(TAKE_TIMEOUT_S)
                if item is not None:
                    robot_id, tensor = item
                    detections = core.detect(tensor)
                    publisher = publishers.get(robot_id)
                    if publisher is None:
                        publisher = publishers[robot_id] = session.declare_publisher(detections_key(robot_id))
                    publisher.put(encode_message(detections))
                now = time.monotonic()
                if now - last_housekeeping >= 1.0:
                    last_housekeeping = now
                    if encoder is not None:
                        with encoder_lock:
                            encoder.forget_silent()
                if now - last_summary >= SUMMARY_EVERY_S:
                    last_summary = now
                    log.info("robots %d, %s", len(publishers), core.counters.to_dict())
                if duration_s and now - started >= duration_s:
                    break
        finally:
            mailbox.close()
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
        "--threads", type=int, default=None, help="ONNX Runtime intra-op threads (default: all)"
    )
    parser.add_argument(
        "--from-scans", action="store_true", help="encode scans here too (encoder + detector)"
    )
    parser.add_argument(
        "--forget-after",
        type=float,
        default=DEFAULT_FORGET_AFTER_S,
        help="--from-scans: seconds to forget a robot",
    )
    parser.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: never)")
    parser.add_argument("--verbose", "-v", action="store_true")
    add_zenoh_arguments(parser)
    args = parser.parse_args(argv)
    configure_logging(args.verbose)
    try:
        detector = OnnxDetector(
            args.model or default_model_path(),
            conf_threshold=args.conf,
            iou_threshold=args.iou,
            intra_op_threads=args.threads,
        )
    except (FileNotFoundError, ValueError) as exc:
        log.error("cannot load the model: %s", exc)
        return 2
    run(
        settings_from_args(args),
        stop_event_on_signals(),
        detector,
        from_scans=args.from_scans,
        forget_after_s=args.forget_after,
        duration_s=args.duration,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
