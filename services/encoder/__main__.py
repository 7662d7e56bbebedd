"""``python -m services.encoder``: scans in on ``triscan/*/scan``, stacked tensors out on ``.../tensor``.

Runs on the robot next to the detector (base dependencies only: no torch, PyBullet or rerun). The
stream rules (first scans, gaps, restarts, silence) live in :mod:`services.encoder.core`; the session,
health, counters and shutdown in :class:`services.runtime.ServiceRuntime`. This module wires them.
``--encoders N`` starts N-1 more processes; all live encoder processes share the robots
(:mod:`services.shards`), as the detector's do, each subscribed to the scans of the announced robots
it serves, one of them also to the scans of robots that announce nothing
(:mod:`services.shard_subscriptions`). Each announces the robots whose tensors it publishes
(:func:`services.runtime.announce_source`), from a robot's first scan on: the detector processes
subscribe to the tensors of the announced robots they serve.
"""

from __future__ import annotations

import logging
import math
import subprocess
import sys
import threading
from typing import Any

from common.encoding import INVALID_RULES, PADDINGS, InvalidRule, Padding
from common.keys import SCAN, TENSOR, parse_key, scan_key, tensor_key
from common.messages import encode_message
from common.transport import ZenohSettings, payload_bytes, settings_from_args
from services.encoder.core import DEFAULT_FORGET_AFTER_S, EncoderCore
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

PROCESSES_FLAG = "--encoders"


def run(
    settings: ZenohSettings,
    stop: threading.Event,
    *,
    padding: Padding = "zero",
    invalid: InvalidRule = "sentinel",
    forget_after_s: float = DEFAULT_FORGET_AFTER_S,
    duration_s: float = 0.0,
    stack_period_s: float | None = None,
    raster_yaw_deg: float = 0.0,
    siblings: Siblings | None = None,
    processes: int = 1,
) -> EncoderCore:
    """Serve until ``stop`` is set (or ``duration_s`` passes); returns the core with its counters.

    Like the detector, the process stacks the scans of its share of the robots among the live
    encoder processes (:mod:`services.shards`); a robot that moves here starts a fresh
    FIFO, so its first tensor comes three scans later and none is sent twice. As the detector's, it
    serves once ``processes`` encoders are live and settled.
    """
    core = EncoderCore(
        padding,
        invalid=invalid,
        forget_after_s=forget_after_s,
        stack_period_s=stack_period_s,
        raster_yaw_deg=raster_yaw_deg,
    )
    with ServiceRuntime("encoder", settings, stop, duration_s=duration_s) as runtime:
        tensors = runtime.robot_publishers(tensor_key, announce_topic=TENSOR)
        shards = ShardMembership(runtime.session, "encoder")
        not_ours = 0

        def on_scan(sample: Any) -> None:
            nonlocal not_ours
            key = str(sample.key_expr)
            try:
                robot_id: str | None = parse_key(key)[0]
            except ValueError:
                robot_id = None  # the core refuses and counts it
            if robot_id is not None and not owns(robot_id):  # another process's robot: no payload copy
                not_ours += 1
                return
            if robot_id is not None:  # from its first scan: its detector subscribes before its first tensor
                tensors.announce(robot_id)
            tensor = core.handle_sample(key, payload_bytes(sample))
            if tensor is not None:
                tensors.put(tensor.robot_id, encode_message(tensor))

        scans = OwnedSubscriptions(
            runtime.session, shards.me, SCAN, scan_key, on_scan, unannounced=on_scan, view=shards.view
        )
        owns = scans.owns(shards.view)

        def housekeeping() -> dict[str, object]:
            tensors.forget(core.forget_silent())
            tensors.forget_silent(forget_after_s)  # robots announced whose scans the core refused
            if siblings is not None:
                siblings.restart_dead()
            shard = shards.log_changes(forget_after_s)
            scans.set_members(shards.view.members)  # a missed membership change heals here
            shard.update(scans.counters(forget_after_s))
            return {**core.snapshot(), "not_ours": not_ours, "shard": shard}

        try:
            shards.join(scans.set_members)
            shards.wait_settled(processes, stop)
            scans.start()  # once settled: a robot it subscribes to is one it serves
            scans.wait_serving(stop)
            log.info("encoder %s ready (padding %s, invalid returns %s, raster yaw %g): its robots' scans → "
                     "tensor", shards.me[:8], padding, invalid, core.raster_yaw_deg)  # fmt: skip
            runtime.serve(housekeeping)
        finally:
            scans.close()
            shards.leave()
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
    parser.add_argument(
        "--raster-yaw",
        type=float,
        default=0.0,
        metavar="DEG",
        help="turn scans by DEG before binning, as the detector's model was trained (its "
        "triscan.raster_yaw_deg); default 0, the paper's raster",
    )
    add_processes_argument(parser, PROCESSES_FLAG, "1; more, here or on other hosts, share the robots")
    add_service_arguments(parser, forget_after_s=DEFAULT_FORGET_AFTER_S)
    argv = sys.argv[1:] if argv is None else argv
    args = parser.parse_args(argv)
    if args.stack_period_s is not None and not args.stack_period_s > 0:
        parser.error(f"--stack-period-s must be positive, got {args.stack_period_s}")
    if not math.isfinite(args.raster_yaw):
        parser.error(f"--raster-yaw must be finite, got {args.raster_yaw}")
    configure_logging(args.verbose)
    if args.encoders is not None and args.encoders < 1:
        parser.error(f"{PROCESSES_FLAG} must be >= 1, got {args.encoders}")
    processes = args.encoders or 1
    siblings = None
    if processes > 1 and not args.sibling:
        commands = sibling_commands("services.encoder", argv, PROCESSES_FLAG, processes)
        siblings = Siblings(commands, lambda command: subprocess.Popen(command, env=child_environment()))
        siblings.start()
    try:
        run(
            settings_from_args(args),
            stop_event_on_signals(),
            padding=args.padding,
            invalid=args.invalid,
            forget_after_s=args.forget_after,
            duration_s=args.duration,
            stack_period_s=args.stack_period_s,
            raster_yaw_deg=args.raster_yaw,
            siblings=siblings,
            processes=processes,
        )
    finally:
        if siblings is not None:
            siblings.stop()
    return 0


if __name__ == "__main__":
    exit_process(exit_code_of(main))
