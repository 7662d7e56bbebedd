"""The skeleton every triscan service runs in: one Zenoh session, a health token, counters, a stop.

A service is healthy while its Zenoh liveliness token ``triscan/@health/<service>/<pid>`` exists; the
token vanishes when the process exits or its session closes, which is how ``triscan up`` (and anyone
else) notices a dead peer without polling. Once a second it publishes its counters as JSON on
``triscan/@stats/<service>/<pid>``, which ``triscan status`` collects.

:class:`ServiceRuntime` does all of that, plus ``--duration`` and clean shutdown (every subscriber,
publisher and token undeclared, the session closed: a session left open with a callback subscriber
hangs the interpreter at exit). :class:`RobotPublishers` holds one publisher per robot, declared on
first use and forgotten with its robot, so a fleet that changes over time does not leak them; the
encoder's also announce each robot's tensors, and the simulator's each robot's scans
(:func:`announce_source`), which is how the processes that share a fleet know which robots' keys to
subscribe to. A
service's ``run`` is then: build its pure core, subscribe the core's handlers, and hand
:meth:`ServiceRuntime.serve` a housekeeping function that returns the counters to publish.
"""

from __future__ import annotations

import argparse
import contextlib
import inspect
import json
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from types import TracebackType
from typing import Any, NoReturn

from common.keys import SCAN, health_key, service_health_key, source_key, stats_key
from common.transport import (
    ZenohSettings,
    ZenohSetupError,
    add_zenoh_arguments,
    open_session,
    payload_bytes,
)
from services.shards import SETTLE_S

log = logging.getLogger(__name__)

STATS_PERIOD_S = 1.0
SUMMARY_PERIOD_S = 10.0  # a one-line summary in the log this often
EXIT_WITH_PARENT_ENV = "TRISCAN_EXIT_WITH_PARENT"
# "debug": the periodic summaries go to the debug log (``--verbose``), the one at the end stays. Set by
# ``triscan up``, whose own table says what the loop finds; a service started by hand keeps them.
PERIODIC_SUMMARY_ENV = "TRISCAN_PERIODIC_SUMMARY"
PARENT_POLL_S = 0.5
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
# argparse's exit code for refused arguments, and every service's for an input it cannot use (a
# model that does not load, a port in use): ``triscan up`` reports such a child once, never restarts it.
USAGE_EXIT = 2


class TerseArgumentParser(argparse.ArgumentParser):
    """A parser whose error is what is wrong and where the help is, two lines: argparse's full usage
    (twenty lines for ``triscan up``) would bury the one that matters."""

    def error(self, message: str) -> NoReturn:
        self.exit(USAGE_EXIT, f"{self.prog}: error: {message}\nusage: {self.prog} --help (every option)\n")


def periodic_summary_level() -> int:
    """The log level of a service's periodic summary line (:data:`PERIODIC_SUMMARY_ENV`)."""
    return logging.DEBUG if os.environ.get(PERIODIC_SUMMARY_ENV) == "debug" else logging.INFO


def service_parser(module: str, description: str) -> argparse.ArgumentParser:
    """The parser of ``python -m <module>``: usage and errors name the command as it is typed, and a
    flag must be spelt out (an abbreviation is an error, not a guess)."""
    return TerseArgumentParser(prog=f"python -m {module}", description=description, allow_abbrev=False)


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


def default_of(owner: Callable[..., Any], name: str) -> Any:
    """The default of parameter or dataclass field ``name`` of ``owner``: argparse reads it there
    instead of restating the number."""
    default = inspect.signature(owner).parameters[name].default
    if default is inspect.Parameter.empty:
        raise ValueError(f"{owner.__qualname__}'s {name} has no default")
    return default


def exit_code_of(main: Callable[[], int]) -> int:
    """Run a service's ``main`` as ``python -m`` does: a Zenoh session that cannot open as asked (a
    port in use, a bad config entry) or a missing file is one logged line and :data:`USAGE_EXIT`, not
    a traceback."""
    try:
        return main()
    except (ZenohSetupError, FileNotFoundError) as exc:
        log.debug("refused", exc_info=True)
        log.error("%s", exc)
        return USAGE_EXIT


def exit_process(code: int) -> NoReturn:
    """End a service's process with ``code`` once its ``main`` has returned, without Python's
    finalization.

    By then the service's Zenoh session is closed, but Zenoh's own threads may still need the GIL for
    a moment (to drop a callback they held). Python 3.11 unwinds a thread that asks for the GIL while
    the interpreter finalizes, and unwound through Rust frames that aborts the whole process ("FATAL:
    exception not rethrown", CPython gh-87135), so a clean stop would exit with SIGABRT now and then.
    Logs and the standard streams are flushed first; nothing else is left to run.
    """
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):  # a closed pipe or stream: nothing more to write
            stream.flush()
    os._exit(code)


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


def wait_for_service(session: Any, service: str, timeout_s: float = 30.0) -> None:
    """Block until an instance of ``service`` holds its health token, wired and serving (a detector then
    subscribes to the tensors of every robot announced from here on); ``TimeoutError`` after
    ``timeout_s``. A bench that feeds the encoder scans waits so before its robots' first tensors."""
    deadline = time.monotonic() + timeout_s
    pattern = service_health_key(service)
    while not any(reply.ok is not None for reply in session.liveliness().get(pattern, timeout=1.0)):
        if time.monotonic() > deadline:
            raise TimeoutError(f"no {service} came up within {timeout_s:.0f} s")
        time.sleep(0.05)


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


ANNOUNCE_LEAD_S = 0.1
"""How long after announcing a robot :class:`RobotPublishers` holds its first sample back: the source
token's way to the subscriber that serves the robot and that subscriber's way back take milliseconds
on one network, and a sample published before it arrives is lost. A robot streaming at its own rate
is announced with its first scan, a few scan periods before its first tensor, and never waits."""


def announce_lead_s(topic: str) -> float:
    """How long a robot's first ``topic`` sample waits after its announcement: :data:`ANNOUNCE_LEAD_S`,
    and for a scan :data:`services.shards.SETTLE_S` more, since one process serves the scans of robots
    with no token and the owner of an announced robot takes its scans only once every process has
    seen its token (:mod:`services.shard_subscriptions`)."""
    return ANNOUNCE_LEAD_S + (SETTLE_S if topic == SCAN else 0.0)


def announce_source(session: Any, robot_id: str, topic: str) -> Any:
    """Declare that this session publishes ``topic`` for ``robot_id`` (a liveliness token on
    :func:`common.keys.source_key`); returns the token, to undeclare when the robot's samples stop.

    The processes that share a fleet subscribe only to the tensors (or scans) of announced robots they
    serve, so whoever puts tensors (the encoder through :class:`RobotPublishers`, a test, a bench)
    announces each robot first, then waits for a subscriber (:func:`common.transport.wait_for_subscriber`).
    Whoever puts scans announces them too and holds the first for :func:`announce_lead_s`; scans that
    nobody announces are all served by one process (:mod:`services.shard_subscriptions`)."""
    return session.liveliness().declare_token(source_key(topic, robot_id, str(session.zid())))


class RobotPublishers:
    """One Zenoh publisher per robot on ``key_of(robot_id)``, declared on first use.

    Thread-safe (Zenoh callbacks and inference threads both publish). A robot not published for
    ``forget_after_s`` is forgotten by :meth:`forget_silent`, and :meth:`forget` drops the ones a
    core has forgotten itself, so publishers live exactly as long as their robot. With
    ``announce_topic`` (the topic ``key_of`` builds keys of) every robot's publisher comes with its
    source token (:func:`announce_source`), declared by :meth:`announce` or the first :meth:`put` and
    undeclared with the publisher, and a robot's first samples wait until :func:`announce_lead_s`
    after the announcement.
    """

    def __init__(
        self, session: Any, key_of: Callable[[str], str], *, announce_topic: str | None = None
    ) -> None:
        self._session = session
        self._key_of = key_of
        self._announce_topic = announce_topic
        self._publishers: dict[str, Any] = {}
        self._tokens: dict[str, Any] = {}
        self._last_put: dict[str, float] = {}
        self._held_until: dict[str, float] = {}  # announced robots whose lead has not passed yet
        self._lock = threading.Lock()

    def __len__(self) -> int:
        with self._lock:
            return len(self._publishers)

    def _declare(self, robot_id: str, now: float) -> Any:
        """The robot's publisher, declared (and announced) if new; call with the lock held."""
        publisher = self._publishers.get(robot_id)
        if publisher is None:
            publisher = self._publishers[robot_id] = self._session.declare_publisher(self._key_of(robot_id))
            self._last_put[robot_id] = now  # forget_silent counts the silence from here
            if self._announce_topic is not None:
                self._tokens[robot_id] = announce_source(self._session, robot_id, self._announce_topic)
                self._held_until[robot_id] = now + announce_lead_s(self._announce_topic)
        return publisher

    def announce(self, robot_id: str) -> None:
        """Declare the robot's publisher (and source token) ahead of its first :meth:`put`."""
        with self._lock:
            self._declare(robot_id, time.monotonic())

    def put(self, robot_id: str, payload: bytes) -> None:
        now = time.monotonic()
        with self._lock:
            publisher = self._declare(robot_id, now)
            self._last_put[robot_id] = now
            held_until = self._held_until.get(robot_id) if self._held_until else None
            if held_until is not None and held_until <= now:
                del self._held_until[robot_id]
        if held_until is not None and held_until > now:
            time.sleep(held_until - now)  # once per robot, and only when it was announced just now
        publisher.put(payload)

    def forget(self, robot_ids: Iterable[str]) -> None:
        with self._lock:
            for robot_id in robot_ids:
                publisher = self._publishers.pop(robot_id, None)
                token = self._tokens.pop(robot_id, None)
                self._last_put.pop(robot_id, None)
                self._held_until.pop(robot_id, None)
                if token is not None:
                    token.undeclare()
                if publisher is not None:
                    publisher.undeclare()

    def forget_silent(self, forget_after_s: float, now: float | None = None) -> list[str]:
        """Undeclare the publishers of robots silent for ``forget_after_s``; returns their ids."""
        now = time.monotonic() if now is None else now
        with self._lock:
            silent = [robot_id for robot_id, t in self._last_put.items() if now - t > forget_after_s]
        self.forget(silent)
        return silent

    def close(self) -> None:
        with self._lock:
            robot_ids = list(self._publishers)
        self.forget(robot_ids)


SampleHandler = Callable[[str, bytes], object]  # the return value, if any, is ignored


class ServiceRuntime:
    """A service's Zenoh side and lifetime: use as ``with ServiceRuntime(...) as runtime:``.

    Entering opens the session and the stats publisher; :meth:`ready` (called by :meth:`serve`, or by a
    service with a loop of its own once it is wired) declares the health token, so the token means
    "subscribed and serving": a peer that waits for it never publishes into the gap before the
    service's subscriptions exist. Leaving undeclares everything declared through it and closes the
    session, in that order, however the block ends.
    """

    def __init__(
        self, service: str, settings: ZenohSettings, stop: threading.Event, *, duration_s: float = 0.0
    ) -> None:
        self.service = service
        self.settings = settings
        self.stop = stop
        self.duration_s = duration_s
        self.session: Any = None
        self._session_cm: Any = None
        self._declared: list[Any] = []  # subscribers and publishers, undeclared in reverse order
        self._robot_publishers: list[RobotPublishers] = []
        self._stats: StatsPublisher | None = None
        self._health: Any = None
        self._started = time.monotonic()

    def __enter__(self) -> ServiceRuntime:
        self._session_cm = open_session(self.settings)
        self.session = self._session_cm.__enter__()
        try:
            self._stats = StatsPublisher(self.session, self.service)
        except BaseException:
            self._session_cm.__exit__(None, None, None)
            raise
        self._started = time.monotonic()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        try:
            if self._health is not None:
                self._health.undeclare()  # first: peers see the service go before its parts do
            if self._stats is not None:
                self._stats.close()
            for publishers in self._robot_publishers:
                publishers.close()
            for entity in reversed(self._declared):
                entity.undeclare()
        finally:
            self._session_cm.__exit__(exc_type, exc, tb)

    def ready(self) -> None:
        """Declare the health token (once): the service is wired and serving."""
        if self._health is None:
            self._health = declare_health(self.session, self.service)

    def subscribe(self, key: str, handler: SampleHandler) -> None:
        """Call ``handler(key, payload)`` for every sample on ``key`` (a pattern)."""

        def on_sample(sample: Any) -> None:
            handler(str(sample.key_expr), payload_bytes(sample))

        self._declared.append(self.session.declare_subscriber(key, on_sample))

    def subscribe_samples(self, key: str, callback: Callable[[Any], None]) -> None:
        """Call ``callback(sample)`` with the raw ``zenoh.Sample`` (for services that read attachments)."""
        self._declared.append(self.session.declare_subscriber(key, callback))

    def keep(self, entity: Any) -> Any:
        """Undeclare ``entity`` (a publisher, a liveliness token) when the service stops; returns it."""
        self._declared.append(entity)
        return entity

    def robot_publishers(
        self, key_of: Callable[[str], str], *, announce_topic: str | None = None
    ) -> RobotPublishers:
        publishers = RobotPublishers(self.session, key_of, announce_topic=announce_topic)
        self._robot_publishers.append(publishers)
        return publishers

    @property
    def elapsed_s(self) -> float:
        return time.monotonic() - self._started

    def should_stop(self) -> bool:
        """The stop event is set or ``duration_s`` (when > 0) has passed."""
        return self.stop.is_set() or (self.duration_s > 0.0 and self.elapsed_s >= self.duration_s)

    def publish_stats(self, counters: Mapping[str, object], *, force: bool = False) -> None:
        """Publish counters (at most once per ``STATS_PERIOD_S``, always with ``force``)."""
        assert self._stats is not None, "use ServiceRuntime in a with block"
        self._stats.publish(counters, force=force)

    def serve(
        self, housekeeping: Callable[[], Mapping[str, object]], period_s: float = STATS_PERIOD_S
    ) -> None:
        """Until :meth:`should_stop`: every ``period_s`` run ``housekeeping`` and publish what it returns.

        The counters also go to the log every ``SUMMARY_PERIOD_S`` and once at the end.
        """
        self.ready()
        last_summary = time.monotonic()
        counters: Mapping[str, object] = {}
        while not self.stop.wait(period_s):
            counters = housekeeping()
            self.publish_stats(counters)
            now = time.monotonic()
            if now - last_summary >= SUMMARY_PERIOD_S:
                log.log(periodic_summary_level(), "%s: %s", self.service, counters)
                last_summary = now
            if self.should_stop():
                break
        log.info("%s stopping after %.1f s: %s", self.service, self.elapsed_s, counters or housekeeping())
