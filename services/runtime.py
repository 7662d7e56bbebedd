"""What every service process does the same way: logging, stopping on signals, announcing itself.

A service is healthy while its Zenoh liveliness token ``triscan/@health/<service>/<pid>`` exists; the
token vanishes when the process exits or its session closes, which is how ``triscan up`` (and anyone
else) notices a dead peer without polling.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import threading
import time
from collections.abc import Mapping
from typing import Any

from common.transport import add_zenoh_arguments, health_key

STATS_PREFIX = "triscan/@stats"  # triscan/@stats/<service>/<pid>: JSON counters, once a second
STATS_PERIOD_S = 1.0

EXIT_WITH_PARENT_ENV = "TRISCAN_EXIT_WITH_PARENT"
PARENT_POLL_S = 0.5
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def add_service_arguments(parser: argparse.ArgumentParser, *, forget_after_s: float | None = None) -> None:
    """The flags every long-running service shares: ``--duration``, ``--verbose`` and Zenoh's, plus
    ``--forget-after`` (default ``forget_after_s``) for the services that keep state per robot."""
    if forget_after_s is not None:
        parser.add_argument(
            "--forget-after", type=float, default=forget_after_s, help="seconds of silence to forget a robot"
        )
    parser.add_argument(
        "--duration", type=float, default=0.0, metavar="S", help="stop after S seconds (0: run until stopped)"
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    add_zenoh_arguments(parser)


def configure_logging(verbose: bool = False) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO, format=LOG_FORMAT)


def stop_event_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM, so ``main`` can leave its loop and close the session.

    Only the main thread may install handlers; elsewhere (a test calling ``run`` in a thread) the
    caller passes its own event instead.
    """
    stop = threading.Event()

    def handler(signum: int, _frame: Any) -> None:
        logging.getLogger(__name__).info("signal %s: stopping", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    if os.environ.get(EXIT_WITH_PARENT_ENV) == "1":
        threading.Thread(target=_stop_when_orphaned, args=(stop, os.getppid()), daemon=True).start()
    return stop


def _stop_when_orphaned(stop: threading.Event, parent_pid: int) -> None:
    """Children of ``triscan up`` stop when the launcher is gone (even after a kill -9)."""
    while not stop.wait(PARENT_POLL_S):
        if os.getppid() != parent_pid:
            logging.getLogger(__name__).warning("launcher (pid %d) is gone: stopping", parent_pid)
            stop.set()


def declare_health(session: Any, service: str) -> Any:
    """Declare this process's liveliness token; keep the returned object alive while serving."""
    return session.liveliness().declare_token(health_key(service, str(os.getpid())))


def stats_key(service: str, instance: str) -> str:
    return f"{STATS_PREFIX}/{service}/{instance}"


class StatsPublisher:
    """Publishes a service's counters as JSON on ``triscan/@stats/<service>/<pid>``.

    JSON rather than msgpack so that ``z_sub`` or any dashboard can read them as they are; ``triscan
    status`` collects them from every running service.
    """

    def __init__(self, session: Any, service: str) -> None:
        self.service = service
        self._publisher = session.declare_publisher(stats_key(service, str(os.getpid())))
        self._last = 0.0

    def publish(self, counters: Mapping[str, object], *, force: bool = False) -> None:
        """Publish at most once per ``STATS_PERIOD_S`` (always with ``force``)."""
        now = time.monotonic()
        if not force and now - self._last < STATS_PERIOD_S:
            return
        self._last = now
        body = {"service": self.service, "pid": os.getpid(), "stamp_ns": time.time_ns(), **counters}
        self._publisher.put(json.dumps(body, sort_keys=True))

    def close(self) -> None:
        self._publisher.undeclare()
