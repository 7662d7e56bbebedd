"""A process sharing a fleet subscribes only to the robots it serves, so no other robot's data reaches it.

Subscribed to a wildcard, every process of a shard set would receive every robot's tensor and drop
all but its own share: Zenoh transport work and a Python callback for each of them, in every process.
Instead, whoever publishes tensors announces each robot with a liveliness token
(:func:`services.runtime.announce_source`), and each process subscribes to the key of every announced
robot that rendezvous hashing (:func:`services.shards.owner_of`) gives it among the live members.

:class:`OwnedRobots` is the pure part: members, announced sources and this member in, the robots to
subscribe and the change since the last look out. :class:`OwnedSubscriptions` is the Zenoh side: a
liveliness watch on the sources and one subscriber per owned robot, declared and undeclared by a
thread of its own, so Zenoh's callbacks only note a change and never declare anything.

A robot is subscribed as soon as this member is its owner among the members it sees (not only once
:class:`services.shards.ShardView` has settled): the subscription is then in place by the time the
view settles, and the service's own ``owns`` check keeps a scan from being answered twice meanwhile.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Collection, Iterable
from typing import Any, Final

from common.keys import parse_source_key, topic_sources_key
from services.shards import owner_of

log = logging.getLogger(__name__)

REFRESH_S: Final[float] = 1.0  # the thread also compares wanted and declared this often, unprompted


def robots_to_subscribe(members: Iterable[str], sources: Iterable[str], me: str) -> frozenset[str]:
    """The announced robots (``sources``) whose owner among ``members`` (and ``me``) is ``me``."""
    everyone = frozenset(members) | {me}
    return frozenset(robot_id for robot_id in sources if owner_of(robot_id, everyone) == me)


class OwnedRobots:
    """Which robots one member subscribes to, kept up to date from member and source changes.

    Pure and thread-safe. A robot is announced while at least one source holds its token (two
    encoders do during a handover). Owners are worked out again for every robot only when the members
    change; a robot announced or gone costs one owner lookup, so a fleet coming up token by token
    stays cheap.
    """

    def __init__(self, me: str) -> None:
        self.me = me
        self._members: frozenset[str] = frozenset({me})
        self._sources: dict[str, set[str]] = {}  # robot id → the sources announcing it
        self._owned: set[str] = set()  # announced robots this member owns
        self._lock = threading.Lock()

    def set_members(self, members: Iterable[str]) -> None:
        """The live members (this one is always among them)."""
        current = frozenset(members) | {self.me}
        with self._lock:
            if current == self._members:
                return
            self._members = current
            self._owned = set(robots_to_subscribe(current, self._sources, self.me))

    def source_up(self, robot_id: str, source: str) -> None:
        with self._lock:
            sources = self._sources.setdefault(robot_id, set())
            if not sources and owner_of(robot_id, self._members) == self.me:
                self._owned.add(robot_id)
            sources.add(source)

    def source_down(self, robot_id: str, source: str) -> None:
        with self._lock:
            sources = self._sources.get(robot_id)
            if sources is None:
                return
            sources.discard(source)
            if not sources:
                del self._sources[robot_id]
                self._owned.discard(robot_id)

    def wanted(self) -> frozenset[str]:
        """The robots to subscribe to now."""
        with self._lock:
            return frozenset(self._owned)

    def diff(self, subscribed: Collection[str]) -> tuple[list[str], list[str]]:
        """(subscribe, unsubscribe): what to change to get from the robots ``subscribed`` now to
        :meth:`wanted` (against what is declared, so a declaration that failed is tried again)."""
        wanted, current = self.wanted(), frozenset(subscribed)
        return sorted(wanted - current), sorted(current - wanted)


class OwnedSubscriptions:
    """The Zenoh side of :class:`OwnedRobots`: ``callback`` gets the samples of the robots this member
    owns, one subscriber on ``key_of(robot_id)`` each.

    :meth:`start` declares the liveliness watch on ``topic``'s sources (its history gives the robots
    already announced) and starts the thread that declares and undeclares subscribers;
    :meth:`set_members` is fed by the service's :class:`services.shards.ShardMembership`; :meth:`close`
    undeclares everything.
    """

    def __init__(
        self, session: Any, me: str, topic: str, key_of: Callable[[str], str], callback: Callable[[Any], None]
    ) -> None:
        self.topic = topic
        self.plan = OwnedRobots(me)
        self._session = session
        self._key_of = key_of
        self._callback = callback
        self._subscribers: dict[str, Any] = {}  # only the thread touches it while it runs
        self._count = 0
        self._wake = threading.Event()
        self._closing = threading.Event()
        self._watch: Any = None
        self._thread: threading.Thread | None = None

    def __len__(self) -> int:
        """How many robots' keys this process subscribes to."""
        return self._count

    def set_members(self, members: Iterable[str]) -> None:
        self.plan.set_members(members)
        self._wake.set()

    def start(self) -> None:
        import zenoh

        def on_source(sample: Any) -> None:
            try:
                topic, robot_id, source = parse_source_key(str(sample.key_expr))
            except ValueError:
                return
            if topic != self.topic:
                return
            if sample.kind == zenoh.SampleKind.PUT:
                self.plan.source_up(robot_id, source)
            else:
                self.plan.source_down(robot_id, source)
            self._wake.set()

        self._thread = threading.Thread(target=self._run, name="shard-subscriptions", daemon=True)
        self._thread.start()
        self._watch = self._session.liveliness().declare_subscriber(
            topic_sources_key(self.topic), on_source, history=True
        )

    def _run(self) -> None:
        while not self._closing.is_set():
            self._wake.wait(REFRESH_S)
            self._wake.clear()
            if self._closing.is_set():
                return
            try:
                self._apply()
            except Exception:  # a failed declaration is retried at the next change or refresh
                log.exception("could not update the %s subscriptions", self.topic)

    def _apply(self) -> None:
        subscribe, unsubscribe = self.plan.diff(self._subscribers.keys())
        for robot_id in unsubscribe:  # give robots up before taking others
            subscriber = self._subscribers.pop(robot_id, None)
            if subscriber is not None:
                subscriber.undeclare()
        for robot_id in subscribe:
            key = self._key_of(robot_id)
            self._subscribers[robot_id] = self._session.declare_subscriber(key, self._callback)
        self._count = len(self._subscribers)
        if subscribe or unsubscribe:
            log.debug("%s subscriptions: +%d -%d, %d in all", self.topic, len(subscribe), len(unsubscribe),
                      self._count)  # fmt: skip

    def close(self) -> None:
        """Stop the thread, then undeclare the watch and every subscriber."""
        self._closing.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join()
        if self._watch is not None:
            self._watch.undeclare()
            self._watch = None
        for subscriber in self._subscribers.values():
            subscriber.undeclare()
        self._subscribers.clear()
        self._count = 0
