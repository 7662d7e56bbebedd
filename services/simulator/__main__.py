"""``python -m services.simulator``: publish simulated LiDAR scans and ground truth over Zenoh in real time.

The simulation itself lives in :mod:`services.simulator.fleet` and knows no clock and no network;
this module only adds the two: a tick schedule on the monotonic clock and one Zenoh publisher per robot
and key (``triscan/<robot_id>/scan``, ``triscan/<robot_id>/truth``), each robot's scans announced
(:func:`services.runtime.announce_source`). ``run`` takes plain settings and
a stop event, so it can be called from a test or a launcher; ``main`` is the only place that parses
flags and installs signal handlers.

Ticks are scheduled at ``start + n/rate`` rather than "sleep one period after the work", so the rate
does not drift with the time a tick takes. A tick that starts late is published at once; ticks that
were missed entirely are skipped, not caught up in a burst, because a burst of stale scans is worse
for a downstream detector than a gap.
"""

from __future__ import annotations

import argparse
import logging
import math
import threading
import time
from collections.abc import Sequence

from common.encoding import PADDINGS
from common.keys import SCAN, scan_key, truth_key, validate_robot_id
from common.messages import encode_message
from common.transport import ZenohSettings, settings_from_args
from services.runtime import (
    SUMMARY_PERIOD_S,
    ServiceRuntime,
    add_service_arguments,
    announce_lead_s,
    configure_logging,
    exit_code_of,
    exit_process,
    periodic_summary_level,
    service_parser,
    stop_event_on_signals,
)
from services.simulator.defaults import (
    ROBOT_ID_PREFIX,
    ROBOTS,
    SCAN_RATE_HZ,
    SCENARIO_PERIOD_S,
    SIM_PEOPLE,
    SIM_SEED,
)
from services.simulator.fleet import SimulatedFleet
from services.simulator.sensors import DEFAULT_PROFILE, PROFILES, profile

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m


class RateSummary:
    """Counts published scans per robot and logs one line every ``period_s`` (and once at the end)."""

    def __init__(self, robot_ids: Sequence[str], period_s: float = SUMMARY_PERIOD_S) -> None:
        self.period_s = period_s
        self.total = dict.fromkeys(robot_ids, 0)
        self._since_last = dict.fromkeys(robot_ids, 0)
        self.skipped_ticks = 0
        self._last_log = time.monotonic()

    def count(self, robot_id: str) -> None:
        self.total[robot_id] += 1
        self._since_last[robot_id] += 1

    def maybe_log(self, *, force: bool = False) -> None:
        now = time.monotonic()
        elapsed = now - self._last_log
        if not force and elapsed < self.period_s:
            return
        rates = ", ".join(
            f"{robot_id} {count} ({count / max(elapsed, 1e-9):.1f} Hz)"
            for robot_id, count in self._since_last.items()
        )
        log.log(
            logging.INFO if force else periodic_summary_level(),
            "last %.1f s: scans published %s; skipped ticks so far %d",
            elapsed,
            rates,
            self.skipped_ticks,
        )
        self._since_last = dict.fromkeys(self._since_last, 0)
        self._last_log = now


def run(
    settings: ZenohSettings, fleet: SimulatedFleet, stop: threading.Event, duration_s: float = 0.0
) -> int:
    """Publish ``fleet``'s scans and truth until ``stop`` is set or ``duration_s`` (> 0) has passed."""
    period_s = 1.0 / fleet.rate_hz
    with ServiceRuntime("simulator", settings, stop, duration_s=duration_s) as runtime:
        # Announced: the detector processes that share a fleet each subscribe to the robots they serve.
        scans = runtime.robot_publishers(scan_key, announce_topic=SCAN)
        truths = runtime.robot_publishers(truth_key)
        for robot_id in fleet.robot_ids:
            scans.announce(robot_id)
        summary = RateSummary(fleet.robot_ids)
        log.info(
            "publishing %d robot(s) at %.1f Hz: %s",
            len(fleet.robot_ids),
            fleet.rate_hz,
            ", ".join(scan_key(robot_id) for robot_id in fleet.robot_ids),
        )
        runtime.ready()
        start = time.monotonic() + announce_lead_s(SCAN)  # the first scans wait for the robots' owners
        tick = 0  # index of the next tick; it is due at start + tick * period_s
        try:
            while not runtime.should_stop():
                now = time.monotonic()
                due = start + tick * period_s
                if now < due:
                    stop.wait(min(due - now, SUMMARY_PERIOD_S))
                    continue
                missed = math.floor((now - due) / period_s)
                if missed > 0:
                    log.debug("%d tick(s) late: skipping them", missed)
                    summary.skipped_ticks += missed
                    tick += missed
                for scan, truth in fleet.step(time.time_ns()):
                    scans.put(scan.robot_id, encode_message(scan))
                    truths.put(truth.robot_id, encode_message(truth))
                    summary.count(scan.robot_id)
                tick += 1
                summary.maybe_log()
                runtime.publish_stats(
                    {
                        "published": sum(summary.total.values()),
                        "skipped_ticks": summary.skipped_ticks,
                        "robots": len(fleet.robot_ids),
                    }
                )
        finally:
            summary.maybe_log(force=True)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = service_parser(
        "services.simulator", "Publish simulated LiDAR scans and ground truth over Zenoh in real time."
    )
    parser.add_argument(
        "--robots", type=int, default=ROBOTS, help=f"number of simulated robots (default: {ROBOTS})"
    )
    parser.add_argument(
        "--rate",
        type=float,
        default=None,
        metavar="HZ",
        help=f"scans per second per robot (default: the sensor's; the LDS-01's is {SCAN_RATE_HZ:g})",
    )
    parser.add_argument(
        "--sensor",
        default=DEFAULT_PROFILE,
        choices=list(PROFILES),
        metavar="NAME",
        help=f"the simulated LiDAR: one of {', '.join(PROFILES)} (docs/sensors.md)",
    )
    parser.add_argument(
        "--people",
        type=int,
        default=SIM_PEOPLE,
        metavar="N",
        help=f"people walking about each robot's room (default: {SIM_PEOPLE}; 0: furniture only)",
    )
    parser.add_argument("--seed", type=int, default=SIM_SEED, help="seed of worlds, motion and noise")
    parser.add_argument(
        "--scenario-period",
        type=float,
        default=SCENARIO_PERIOD_S,
        metavar="S",
        help="seconds of simulated time per world (0: never change)",
    )
    parser.add_argument(
        "--padding", choices=PADDINGS, default="zero", help="padding the ground-truth boxes are given for"
    )
    parser.add_argument(
        "--raster-yaw", type=float, default=0.0, metavar="DEG",
        help="raster yaw the ground-truth boxes are given for (the model's triscan.raster_yaw_deg)",
    )  # fmt: skip
    parser.add_argument("--robot-prefix", default=ROBOT_ID_PREFIX, help="robot ids are PREFIX0, PREFIX1, ...")
    add_service_arguments(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.robots < 1:
        parser.error("--robots must be >= 1")
    if args.rate is not None and not (args.rate > 0.0 and math.isfinite(args.rate)):
        parser.error("--rate must be a positive number")
    if args.people < 0:
        parser.error("--people must be >= 0")
    spec = profile(args.sensor)
    if args.duration < 0.0 or args.scenario_period < 0.0:
        parser.error("--duration and --scenario-period must be >= 0")
    try:
        validate_robot_id(f"{args.robot_prefix}0")
    except ValueError as exc:
        parser.error(f"--robot-prefix: {exc}")
    configure_logging(args.verbose)
    try:
        settings = settings_from_args(args)
        fleet = SimulatedFleet(
            robots=args.robots,
            seed=args.seed,
            scenario_period_s=args.scenario_period,
            rate_hz=args.rate if args.rate is not None else spec.rate_hz,
            robot_id_prefix=args.robot_prefix,
            padding=args.padding,
            spec=spec,
            people=args.people,
            raster_yaw_deg=args.raster_yaw,
        )
    except (ValueError, FileNotFoundError) as exc:
        log.error("%s", exc)
        return 2
    with fleet:
        return run(settings, fleet, stop_event_on_signals(), duration_s=args.duration)


if __name__ == "__main__":
    exit_process(exit_code_of(main))
