"""What every service process does the same way: logging, stopping on signals, announcing itself.

A service is healthy while its Zenoh liveliness token ``triscan/@health/<service>/<pid>`` exists; the
token vanishes when the process exits or its session closes, which is how ``triscan up`` (and anyone
else) notices a dead peer without polling.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
from typing import Any

from common.transport import health_key

EXIT_WITH_PARENT_ENV = "TRISCAN_EXIT_WITH_PARENT"
PARENT_POLL_S = 0.5
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


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
