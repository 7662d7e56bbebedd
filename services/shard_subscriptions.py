"""A process sharing a fleet subscribes only to the robots it serves, so no other robot's data reaches it.

Subscribed to a wildcard, every process of a shard set would receive every robot's tensor (or scan)
and drop all but its own share: Zenoh transport work and a Python callback for each of them, in every
process. Instead, whoever publishes a topic announces each robot with a liveliness token
(:func:`services.runtime.announce_source`), and each process subscribes to the key of every announced
robot that :func:`services.shards.assign` gives it among the live members (an even share, worked out
from the members and the announced robots alike by every process).

Scans also come from code that announces nothing (a user's driver, an older build). Exactly one
member serves those: the owner of the pseudo-robot :data:`UNANNOUNCED`, which moves on a join or a
death like any robot. It alone holds the wildcard subscriber and drops the announced robots' scans
from it before their payload is copied (their owners receive them on their own keys). A robot's
announcement reaches the members at slightly different times, so while it changed within
``settle_s`` a member serves the robot only if it owns both the robot and :data:`UNANNOUNCED`
(:meth:`OwnedRobots.serving_ids`): the old server gives it up at once and the new one takes it
after ``settle_s``, as :class:`services.shards.ShardView` does when the members change.

:class:`OwnedRobots` is the pure part: members, announced sources and this member in, the robots to
subscribe, whether to hold the wildcard and the change since the last look out.
:class:`OwnedSubscriptions` is the Zenoh side: a liveliness watch on the sources, one subscriber per
owned robot and the wildcard where it belongs, declared and undeclared by a thread of its own, so
Zenoh's callbacks only note a change and never declare anything.

A robot is subscribed as soon as this member is its owner among the members it sees (not only once
:class:`services.shards.ShardView` has settled): the subscription is then in place by the time the
view settles, and the service's own ``owns`` check keeps a scan from being answered twice meanwhile.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Collection, Iterable
from typing import Any, Final

from common.keys import parse_key, parse_source_key, topic_sources_key, wildcard_key
from services.shards import SETTLE_S, Rankings, ShardView, assign, owner_of

log = logging.getLogger(__name__)

REFRESH_S: Final[float] = 1.0  # the thread also compares wanted and declared this often, unprompted

GONE_TOLERATED: Final[float] = 0.1
"""Robots whose tokens went stay in the even share (:class:`OwnedRobots`) until the next robot is
announced or member changes, or until more than one, and more than this share of those shared, are
gone: a fleet that only shrinks is shared out again too."""

UNANNOUNCED: Final[str] = "@unannounced"
"""The pseudo-robot whose owner serves every robot with no source token: ``@`` keeps it apart from
every robot id (:func:`common.keys.validate_robot_id` refuses it)."""


def robots_to_subscribe(
    members: Iterable[str], sources: Iterable[str], me: str, rankings: Rankings | None = None
) -> frozenset[str]:
    """The announced robots (``sources``) whose owner among ``members`` (and ``me``) is ``me``."""
    owners = assign(sources, frozenset(members) | {me}, rankings=rankings)
    return frozenset(robot_id for robot_id, owner in owners.items() if owner == me)


def holds_wildcard(members: Iterable[str], me: str) -> bool:
    """Whether ``me`` is the member among ``members`` that serves the unannounced robots."""
    return owner_of(UNANNOUNCED, frozenset(members) | {me}) == me


class OwnedRobots:
    """Which robots one member subscribes to, kept up to date from member and source changes.

    Pure and thread-safe. A robot is announced while at least one source holds its token (two
    encoders do during a handover). The robots shared out (:meth:`shared`; with a ``view``, that
    view is told of them) are the announced ones as of the last change that moves robots: a member
    joining or leaving, a robot announced, or more robots gone than :data:`GONE_TOLERATED` allows.
    A robot whose token goes moves nobody else by itself, so a token that flaps (a publisher in a
    crash loop) cannot keep another robot in transit, unserved, for as long as it flaps; every member
    sees the same token events in the same order, so every member shares out the same set. The
    owners are worked out only when asked for after a change, and the weights are kept
    (:class:`services.shards.Rankings`), so a fleet coming up token by token stays cheap. Every
    robot counts as just changed for ``settle_s`` after this member starts watching the sources
    (:meth:`watching`), since its tokens arrive a little later than another member's may have.
    """

    def __init__(
        self, me: str, *, settle_s: float = SETTLE_S, now: float | None = None, view: ShardView | None = None
    ) -> None:
        self.me = me
        self.settle_s = settle_s
        self.view = view
        self._rankings = Rankings()
        self._started = time.monotonic() if now is None else now
        self._members: frozenset[str] = frozenset({me})
        self._sources: dict[str, set[str]] = {}  # robot id → the sources announcing it
        self._shared: frozenset[str] = frozenset()  # the robots the owners are worked out for
        self._owned: frozenset[str] | None = frozenset()  # of those, this member's; None: to work out
        self._changed: dict[str, float] = {}  # robot id → when it was last announced or unannounced
        self._lock = threading.Lock()

    def set_members(self, members: Iterable[str]) -> None:
        """The live members (this one is always among them)."""
        current = frozenset(members) | {self.me}
        with self._lock:
            if current == self._members:
                return
            self._members = current
            self._owned = None
            self._share(None)

    def _share(self, now: float | None) -> None:
        """Share out the robots announced now (the lock is held), and tell the view."""
        announced = frozenset(self._sources)
        if announced != self._shared:
            self._shared = announced
            self._owned = None
        if self.view is not None:
            self.view.set_robots(self._shared, now)

    def shared(self) -> frozenset[str]:
        """The robots shared out among the members now (see the class docstring)."""
        with self._lock:
            return self._shared

    def watching(self, now: float | None = None) -> None:
        """This member starts watching the sources ``now``."""
        with self._lock:
            self._started = time.monotonic() if now is None else now

    def watched(self, now: float | None = None) -> bool:
        """Whether this member has watched the sources for ``settle_s``: every token up before it
        started has arrived, and it serves the robots it owns as the other members see them."""
        now = time.monotonic() if now is None else now
        with self._lock:
            return now - self._started >= self.settle_s

    def source_up(self, robot_id: str, source: str, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        with self._lock:
            sources = self._sources.setdefault(robot_id, set())
            sources.add(source)
            if len(sources) == 1:
                self._changed[robot_id] = now
                self._share(now)

    def source_down(self, robot_id: str, source: str, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        with self._lock:
            sources = self._sources.get(robot_id)
            if sources is None:
                return
            sources.discard(source)
            if not sources:
                del self._sources[robot_id]
                self._changed[robot_id] = now
                gone = len(self._shared) - sum(1 for r in self._shared if r in self._sources)
                if gone > max(1, int(GONE_TOLERATED * len(self._shared))):
                    self._share(now)

    def announced(self, robot_id: str) -> bool:
        """Whether a source holds ``robot_id``'s token (its scans reach its owner on its own key)."""
        return robot_id in self._sources  # one dict lookup: asked for every scan on the wildcard

    def holds_wildcard(self) -> bool:
        """Whether this member subscribes to every robot's key (it serves the unannounced robots)."""
        with self._lock:
            return holds_wildcard(self._members, self.me)

    def serving_ids(self, robot_id: str, now: float | None = None) -> tuple[str, ...]:
        """The ids whose owner serves ``robot_id`` now: the robot's own while it is announced,
        :data:`UNANNOUNCED` while it is not, and both for ``settle_s`` after either changed (a member
        serves it then only if it owns both, so the one that served it stops at once and the other
        takes over once every member has seen the change)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            changed = self._changed.get(robot_id, self._started)
            if now - changed < self.settle_s:
                return robot_id, UNANNOUNCED
            self._changed.pop(robot_id, None)
            return (robot_id,) if robot_id in self._sources else (UNANNOUNCED,)

    def wanted(self) -> frozenset[str]:
        """The robots to subscribe to now: those this member owns that are still announced."""
        with self._lock:
            if self._owned is None:
                self._owned = robots_to_subscribe(self._members, self._shared, self.me, self._rankings)
                self._rankings.retain(self._shared)
            return frozenset(r for r in self._owned if r in self._sources)

    def diff(self, subscribed: Collection[str], now: float | None = None) -> tuple[list[str], list[str]]:
        """(subscribe, unsubscribe): what to change to get from the robots ``subscribed`` now to
        :meth:`wanted` (against what is declared, so a declaration that failed is tried again)."""
        self._forget_settled(time.monotonic() if now is None else now)
        wanted, current = self.wanted(), frozenset(subscribed)
        return sorted(wanted - current), sorted(current - wanted)

    def _forget_settled(self, now: float) -> None:
        """Drop the change times older than ``settle_s`` (a fleet that comes and goes does not leak)."""
        with self._lock:
            for robot_id in [r for r, changed in self._changed.items() if now - changed >= self.settle_s]:
                del self._changed[robot_id]


def serves(plan: OwnedRobots, view: ShardView, robot_id: str, now: float | None = None) -> bool:
    """Whether this member serves ``robot_id``'s samples now, announced or not: it owns, settled in
    ``view``, every id of :meth:`OwnedRobots.serving_ids`."""
    now = time.monotonic() if now is None else now
    return all(view.owns(served_as, now) for served_as in plan.serving_ids(robot_id, now))


class OwnedSubscriptions:
    """The Zenoh side of :class:`OwnedRobots`: ``callback`` gets the samples of the robots this member
    owns, one subscriber on ``key_of(robot_id)`` each; with ``unannounced``, the member that serves
    the unannounced robots also holds a subscriber on ``topic``'s wildcard, and ``unannounced`` gets
    its samples of robots that no source announces. ``view`` (the service's
    :class:`services.shards.ShardView`) learns the announced robots, which it shares evenly.

    :meth:`start` declares the liveliness watch on ``topic``'s sources (its history gives the robots
    already announced) and starts the thread that declares and undeclares subscribers;
    :meth:`set_members` is fed by the service's :class:`services.shards.ShardMembership`; :meth:`close`
    undeclares everything.
    """

    def __init__(
        self,
        session: Any,
        me: str,
        topic: str,
        key_of: Callable[[str], str],
        callback: Callable[[Any], None],
        *,
        unannounced: Callable[[Any], None] | None = None,
        view: ShardView | None = None,
    ) -> None:
        self.topic = topic
        self.plan = OwnedRobots(me, view=view)
        self.skipped_announced = 0  # announced robots' samples the wildcard received and dropped
        self._session = session
        self._key_of = key_of
        self._callback = callback
        self._unannounced = unannounced
        self._heard: dict[str, float] = {}  # unannounced robot → when the wildcard last passed it on
        self._subscribers: dict[str, Any] = {}  # only the thread touches it while it runs
        self._wildcard: Any = None  # likewise
        self._count = 0
        self._wake = threading.Event()
        self._applied = threading.Event()  # the thread has declared what the plan wanted at least once
        self._closing = threading.Event()
        self._watch: Any = None
        self._thread: threading.Thread | None = None

    def __len__(self) -> int:
        """How many robots' keys this process subscribes to."""
        return self._count

    def set_members(self, members: Iterable[str]) -> None:
        self.plan.set_members(members)
        self._wake.set()

    def owns(self, view: ShardView) -> Callable[[str], bool]:
        """The ``owns`` check of a service that serves announced and unannounced robots (:func:`serves`)."""
        return lambda robot_id: serves(self.plan, view, robot_id)

    def counters(self, forget_after_s: float) -> dict[str, object]:
        """For the service's ``shard`` counters; forgets unannounced robots silent for ``forget_after_s``."""
        counters: dict[str, object] = {"subscribed_robots": self._count}
        if self._unannounced is not None:
            now = time.monotonic()
            for robot_id, heard in list(self._heard.items()):
                if now - heard > forget_after_s:
                    self._heard.pop(robot_id, None)
            counters.update(
                wildcard=self._wildcard is not None,
                unannounced_robots=len(self._heard),
                skipped_announced=self.skipped_announced,
            )
        return counters

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

        self.plan.watching()
        self._thread = threading.Thread(target=self._run, name="shard-subscriptions", daemon=True)
        self._thread.start()
        self._watch = self._session.liveliness().declare_subscriber(
            topic_sources_key(self.topic), on_source, history=True
        )
        self._wake.set()

    def wait_serving(self, stop: threading.Event) -> bool:
        """Block until the subscriptions are declared and, with ``unannounced``, the member has watched
        the sources for ``settle_s`` (until then it serves no robot as unannounced): a service declares
        its health token after this, so a peer that waits for the token is served from its first
        sample. False if ``stop`` is set first."""
        while not (self._applied.is_set() and (self._unannounced is None or self.plan.watched())):
            if stop.wait(0.05):
                return False
        return True

    def _on_wildcard(self, sample: Any) -> None:
        """A sample on the wildcard: an announced robot's is dropped before its payload is copied."""
        assert self._unannounced is not None
        try:
            robot_id: str | None = parse_key(str(sample.key_expr))[0]
        except ValueError:
            robot_id = None  # the service refuses and counts it
        if robot_id is not None:
            if self.plan.announced(robot_id):
                self.skipped_announced += 1
                self._heard.pop(robot_id, None)
                return
            self._heard[robot_id] = time.monotonic()
        self._unannounced(sample)

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
        wildcard = self._unannounced is not None and self.plan.holds_wildcard()
        if self._wildcard is not None and not wildcard:
            self._wildcard.undeclare()
            self._wildcard = None
            self._heard.clear()
            log.info("%s: no longer serves the unannounced robots", self.topic)
        for robot_id in subscribe:
            key = self._key_of(robot_id)
            self._subscribers[robot_id] = self._session.declare_subscriber(key, self._callback)
        if wildcard and self._wildcard is None:
            self._wildcard = self._session.declare_subscriber(wildcard_key(self.topic), self._on_wildcard)
            log.info("%s: serves the unannounced robots (%s)", self.topic, wildcard_key(self.topic))
        self._count = len(self._subscribers)
        self._applied.set()
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
        for subscriber in [*self._subscribers.values(), *([self._wildcard] if self._wildcard else [])]:
            subscriber.undeclare()
        self._subscribers.clear()
        self._wildcard = None
        self._count = 0
