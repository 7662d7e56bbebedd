"""``python -m services.tracker``: detections in on ``triscan/*/detections``, tracks out on ``.../tracks``.

A service of its own rather than a stage inside the detector: the detector's threads belong to the
network (its batch cap and workers are timed against the cores it has), the tracker keeps state per
robot that must survive a detector restart, and a consumer that wants only detections pays nothing for
it (its cost: ``python -m bench.tracking``). The rules live in :mod:`services.tracker.core`; this
module wires them to Zenoh through :class:`services.runtime.ServiceRuntime`.
"""

from __future__ import annotations

import logging
import threading
import time

from common.keys import ALL_DETECTIONS, tracks_key
from common.messages import encode_message
from common.transport import ZenohSettings, settings_from_args
from services.runtime import (
    ServiceRuntime,
    add_service_arguments,
    configure_logging,
    exit_process,
    service_parser,
    stop_event_on_signals,
)
from services.tracker import add_tracker_arguments, tracker_config
from services.tracker.core import DEFAULT_FORGET_AFTER_S, TrackerConfig, TrackerCore

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m


def run(
    settings: ZenohSettings,
    stop: threading.Event,
    *,
    forget_after_s: float = DEFAULT_FORGET_AFTER_S,
    duration_s: float = 0.0,
    config: TrackerConfig | None = None,
) -> TrackerCore:
    """Serve until ``stop`` is set (or ``duration_s`` passes); returns the core with its counters.

    Track ids start at the wall clock in milliseconds, so a restarted tracker never hands out an id it
    handed out before (it would have to have opened more than a thousand tracks a second).
    """
    core = TrackerCore(config, first_track_id=time.time_ns() // 1_000_000, forget_after_s=forget_after_s)
    with ServiceRuntime("tracker", settings, stop, duration_s=duration_s) as runtime:
        publishers = runtime.robot_publishers(tracks_key)

        def on_detections(key: str, payload: bytes) -> None:
            tracks = core.handle_sample(key, payload)
            if tracks is not None:
                publishers.put(tracks.robot_id, encode_message(tracks))

        def housekeeping() -> dict[str, object]:
            publishers.forget(core.forget_silent())
            return core.snapshot()

        runtime.subscribe(ALL_DETECTIONS, on_detections)
        log.info("tracker ready: %s → tracks", ALL_DETECTIONS)
        runtime.serve(housekeeping)
    return core


def main(argv: list[str] | None = None) -> int:
    parser = service_parser("services.tracker", __doc__.splitlines()[0])
    add_service_arguments(parser, forget_after_s=DEFAULT_FORGET_AFTER_S)
    add_tracker_arguments(parser)
    args = parser.parse_args(argv)
    configure_logging(args.verbose)
    run(
        settings_from_args(args),
        stop_event_on_signals(),
        forget_after_s=args.forget_after,
        duration_s=args.duration,
        config=tracker_config(args),
    )
    return 0


if __name__ == "__main__":
    exit_process(main())
