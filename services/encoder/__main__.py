"""``python -m services.encoder``: scans in on ``triscan/*/scan``, stacked tensors out on ``.../tensor``.

Runs on the robot next to the detector (base dependencies only: no torch, PyBullet or rerun). The
stream rules (first scans, gaps, restarts, silence) live in :mod:`services.encoder.core`; the session,
health, counters and shutdown in :class:`services.runtime.ServiceRuntime`. This module wires them.
"""

from __future__ import annotations

import logging
import threading

from common.encoding import INVALID_RULES, PADDINGS, InvalidRule, Padding
from common.keys import ALL_SCANS, tensor_key
from common.messages import encode_message
from common.transport import ZenohSettings, settings_from_args
from services.encoder.core import DEFAULT_FORGET_AFTER_S, EncoderCore
from services.runtime import (
    ServiceRuntime,
    add_service_arguments,
    configure_logging,
    exit_code_of,
    service_parser,
    stop_event_on_signals,
)

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m


def run(
    settings: ZenohSettings,
    stop: threading.Event,
    *,
    padding: Padding = "zero",
    invalid: InvalidRule = "sentinel",
    forget_after_s: float = DEFAULT_FORGET_AFTER_S,
    duration_s: float = 0.0,
    stack_period_s: float | None = None,
) -> EncoderCore:
    """Serve until ``stop`` is set (or ``duration_s`` passes); returns the core with its counters."""
    core = EncoderCore(padding, invalid=invalid, forget_after_s=forget_after_s, stack_period_s=stack_period_s)
    with ServiceRuntime("encoder", settings, stop, duration_s=duration_s) as runtime:
        tensors = runtime.robot_publishers(tensor_key)

        def on_scan(key: str, payload: bytes) -> None:
            tensor = core.handle_sample(key, payload)
            if tensor is not None:
                tensors.put(tensor.robot_id, encode_message(tensor))

        def housekeeping() -> dict[str, object]:
            tensors.forget(core.forget_silent())
            return core.snapshot()

        runtime.subscribe(ALL_SCANS, on_scan)
        log.info("encoder ready (padding %s, invalid returns %s): %s → tensor", padding, invalid, ALL_SCANS)
        runtime.serve(housekeeping)
    return core


def main(argv: list[str] | None = None) -> int:
    parser = service_parser("services.encoder", __doc__.splitlines()[0])
    parser.add_argument("--padding", choices=PADDINGS, default="zero", help="must match the detector's model")
    parser.add_argument(
        "--invalid",
        choices=INVALID_RULES,
        default="sentinel",
        help="invalid returns: sentinel row (paper) or empty; must match the detector's model",
    )
    parser.add_argument(
        "--stack-period-s",
        type=float,
        default=None,
        metavar="S",
        help="stack scans this far apart, as the detector's model was trained (its triscan.stack_period_s); "
        "default: consecutive scans",
    )
    add_service_arguments(parser, forget_after_s=DEFAULT_FORGET_AFTER_S)
    args = parser.parse_args(argv)
    if args.stack_period_s is not None and not args.stack_period_s > 0:
        parser.error(f"--stack-period-s must be positive, got {args.stack_period_s}")
    configure_logging(args.verbose)
    run(
        settings_from_args(args),
        stop_event_on_signals(),
        padding=args.padding,
        invalid=args.invalid,
        forget_after_s=args.forget_after,
        duration_s=args.duration,
        stack_period_s=args.stack_period_s,
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(exit_code_of(main))
