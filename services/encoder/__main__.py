"""``python -m services.encoder``: scans in on ``triscan/*/scan``, stacked tensors out on ``.../tensor``.

Runs on the robot next to the detector (base dependencies only: no torch, PyBullet or rerun). The
stream rules (first scans, gaps, restarts, silence) live in :mod:`services.encoder.core`.
"""

from __future__ import annotations

import argparse
import logging
import threading
import time
from typing import Any

from common.encoding import PADDINGS, Padding
from common.keys import SCAN, parse_key, tensor_key, wildcard_key
from common.messages import encode_message
from common.transport import (
    ZenohSettings,
    open_session,
    payload_bytes,
    settings_from_args,
)
from services.encoder.core import DEFAULT_FORGET_AFTER_S, EncoderCore
from services.runtime import (
    StatsPublisher,
    add_service_arguments,
    configure_logging,
    declare_health,
    stop_event_on_signals,
)

log = logging.getLogger("triscan.encoder")

HOUSEKEEPING_S = 1.0
SUMMARY_EVERY_S = 10.0


def run(
    settings: ZenohSettings,
    stop: threading.Event,
    *,
    padding: Padding = "zero",
    forget_after_s: float = DEFAULT_FORGET_AFTER_S,
    duration_s: float = 0.0,
) -> EncoderCore:
    """Serve until ``stop`` is set (or ``duration_s`` passes); returns the core with its counters."""
    core = EncoderCore(padding, forget_after_s=forget_after_s)
    lock = threading.Lock()  # the core is not thread-safe; Zenoh may call back from several threads
    with open_session(settings) as session:
        publishers: dict[str, Any] = {}

        def on_scan(sample: Any) -> None:
            try:
                robot_id, _ = parse_key(str(sample.key_expr))
            except ValueError as exc:
                with lock:
                    core.counters.received += 1
                    core.counters.rejected["bad_key"] += 1
                log.warning("scan on an unusable key: %s", exc)
                return
            with lock:
                tensor = core.handle_payload(payload_bytes(sample), robot_id)
                if tensor is None:
                    return
                publisher = publishers.get(robot_id)
                if publisher is None:
                    publisher = publishers[robot_id] = session.declare_publisher(tensor_key(robot_id))
            publisher.put(encode_message(tensor))

        subscriber = session.declare_subscriber(wildcard_key(SCAN), on_scan)
        token = declare_health(session, "encoder")
        stats = StatsPublisher(session, "encoder")
        log.info("encoder ready (padding %s): %s → tensor", padding, wildcard_key(SCAN))
        started = last_summary = time.monotonic()
        while not stop.wait(HOUSEKEEPING_S):
            now = time.monotonic()
            with lock:
                for robot_id in core.forget_silent():
                    publisher = publishers.pop(robot_id, None)
                    if publisher is not None:
                        publisher.undeclare()
                counters = core.counters.to_dict()
                robots = len(core.robot_ids)
            stats.publish({**counters, "robots": robots})
            if now - last_summary >= SUMMARY_EVERY_S:
                log.info("robots %d, %s", len(publishers), counters)
                last_summary = now
            if duration_s and now - started >= duration_s:
                break
        stats.close()
        token.undeclare()
        subscriber.undeclare()
    return core


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="triscan-encoder", description=__doc__.splitlines()[0])
    parser.add_argument("--padding", choices=PADDINGS, default="zero", help="must match the detector's model")
    add_service_arguments(parser, forget_after_s=DEFAULT_FORGET_AFTER_S)
    args = parser.parse_args(argv)
    configure_logging(args.verbose)
    run(
        settings_from_args(args),
        stop_event_on_signals(),
        padding=args.padding,
        forget_after_s=args.forget_after,
        duration_s=args.duration,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
