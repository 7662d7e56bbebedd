"""Several processes of one service share a fleet: which process serves which robot, with no coordinator.

Every process of a service (the detector, the encoder) holds a Zenoh liveliness token
``triscan/@shards/<service>/<member>`` (the member is its Zenoh id, unique across hosts) and watches the
others'. Each works out every robot's owner from what it sees, so every process that sees the same
things picks the same owners and nothing has to be agreed on:

* **Announced robots** (their publisher holds a source token: :mod:`services.shard_subscriptions`) are
  shared by bounded-load rendezvous hashing (:func:`assign`): each robot goes to the live member that
  weighs it highest (:func:`weight`) unless that member already holds its share, ``ceil(robots /
  members)`` plus :data:`BALANCE_SLACK`, and then to the next. Plain rendezvous hashing leaves the
  busiest of 16 processes with half as many robots again as the mean, and a fleet server fails at its
  busiest process; a bounded share keeps every process within a robot or two of the mean. The price
  is that a robot coming can move a robot or so besides itself, and a member's death a few of the
  survivors' robots besides the dead one's (a robot going moves nobody by itself:
  :class:`services.shard_subscriptions.OwnedRobots` says which robots are shared out).
* **Any other robot** (and :data:`services.shard_subscriptions.UNANNOUNCED`) goes to the member that
  weighs it highest (:func:`owner_of`): about 1/N of the robots move when a member joins, only the
  leaver's when one leaves.

Views of the members and of the announced robots are not updated everywhere at the same instant, so
:class:`ShardView` gives robots up at once and takes new ones only after ``settle_s``: a robot counts
as this process's only if this process owned it in every view it held over the last ``settle_s``.
Two processes then serve one robot at once only if one of them learns of a change more than
``settle_s`` after the other, and a joiner or a survivor takes a robot over ``settle_s`` after it
learns of the change. A robot newly shared out is the exception: the views from before it was are
no constraint on it, since no member subscribed to its samples then. A killed process's connections
are closed by its OS, so its token vanishes
within milliseconds; a host that vanishes from the network is noticed after Zenoh's transport lease
instead.

:class:`ShardMembership` is the Zenoh side: it declares the token and feeds a view from a liveliness
subscriber. :func:`sibling_commands` starts the other processes of a ``--detectors N`` (or
``--encoders N``) launch.
"""

from __future__ import annotations

import argparse
import hashlib
import logging
import sys
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any, Final

from common.keys import parse_shard_key, shard_key, shard_members_key
from common.transport import ZenohSettings, add_zenoh_arguments, settings_from_args

log = logging.getLogger(__name__)

SETTLE_S: Final[float] = 0.5
"""How long a process waits before serving a robot it gained (see the module docstring): far above the
milliseconds a liveliness change takes to reach every peer of one network, far below the 2 s in which
a dead process's robots must be served again."""

BALANCE_SLACK: Final[int] = 1
"""Robots a member may hold beyond an even share (:func:`assign`). With none, every member is within
one robot of the others, but about two robots move whenever one joins a fleet of hundreds; with one,
about one moves, and the busiest member holds at most two more than the least busy."""

COALESCE_S: Final[float] = 0.05
"""A view changed again within this of its start is changed in place rather than followed by a new
one: a fleet's tokens arrive in bursts (a start, an encoder restart), and a view a token makes
costs an assignment and a look on every sample until it has settled. A state that lasted less than
this never grants a robot anyway (``settle_s`` is ten times longer); what it costs is that this
process takes the burst's last state as begun up to this much earlier, well inside the margin
``settle_s`` keeps for peers that learn of a change later."""

SIBLINGS_TIMEOUT_S: Final[float] = 60.0  # a launch's other processes load their models meanwhile
MAX_LOGGED: Final[int] = 8  # robot ids named in one ownership-change log line


def weight(member: str, robot_id: str) -> int:
    """The rendezvous weight of ``member`` for ``robot_id``: the same in every process and on every host
    (Python's ``hash`` is salted per process, so it would not do)."""
    digest = hashlib.blake2b(f"{member}/{robot_id}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "big")


def owner_of(robot_id: str, members: Iterable[str]) -> str | None:
    """The member that serves ``robot_id``: the highest weight, ties to the larger id; None if none."""
    return max(members, key=lambda member: (weight(member, robot_id), member), default=None)


class Rankings:
    """Each robot's members from highest weight to lowest, kept for the member sets in use.

    :func:`assign` runs for every change of the members or the announced robots, hundreds of times
    while a fleet comes up; the weights it ranks by never change, so they are hashed once per (member
    set, robot). Not thread-safe: each owner guards its own.
    """

    KEPT_MEMBER_SETS: Final[int] = 4  # a view window rarely holds more than two

    def __init__(self) -> None:
        self._rankings: dict[frozenset[str], dict[str, tuple[str, ...]]] = {}
        self._order: dict[str, tuple[int, str]] = {}

    def ranking(self, robot_id: str, members: frozenset[str]) -> tuple[str, ...]:
        """``members`` by :func:`owner_of`'s preference for ``robot_id``, its owner first."""
        table = self._rankings.get(members)
        if table is None:
            if len(self._rankings) >= self.KEPT_MEMBER_SETS:
                del self._rankings[next(iter(self._rankings))]
            table = self._rankings[members] = {}
        ranked = table.get(robot_id)
        if ranked is None:
            ranked = table[robot_id] = tuple(
                sorted(members, key=lambda member: (weight(member, robot_id), member), reverse=True)
            )
        return ranked

    def order(self, robot_id: str) -> tuple[int, str]:
        """Where ``robot_id`` comes in :func:`assign`'s pass: a hash, so no id prefix goes first."""
        key = self._order.get(robot_id)
        if key is None:
            key = self._order[robot_id] = (weight("", robot_id), robot_id)
        return key

    def retain(self, robots: frozenset[str]) -> None:
        """Keep only what is kept for ``robots`` (a changing fleet does not leak)."""
        for robot_id in [r for r in self._order if r not in robots]:
            del self._order[robot_id]
        for table in self._rankings.values():
            for robot_id in [r for r in table if r not in robots]:
                del table[robot_id]


def assign(
    robots: Iterable[str],
    members: Iterable[str],
    *,
    slack: int = BALANCE_SLACK,
    rankings: Rankings | None = None,
) -> dict[str, str]:
    """Every robot's owner among ``members`` by bounded-load rendezvous hashing (module docstring).

    The robots are taken in the order of their hash; each goes to the highest-weighing member that
    holds fewer than ``ceil(len(robots) / len(members)) + slack``. The result depends only on the two
    sets, so every process that sees them computes it alike; empty if there are no members.
    """
    ranks = Rankings() if rankings is None else rankings
    everyone = frozenset(members)
    fleet = sorted(set(robots), key=ranks.order)
    if not everyone:
        return {}
    share = -(-len(fleet) // len(everyone)) + slack
    load = dict.fromkeys(everyone, 0)
    owners: dict[str, str] = {}
    for robot_id in fleet:
        for member in ranks.ranking(robot_id, everyone):
            if load[member] < share:
                load[member] += 1
                owners[robot_id] = member
                break
    return owners


class _View:
    """What one member saw from ``since``: the live members and the announced robots; the owners of
    those robots are worked out on first use and kept while the view is."""

    __slots__ = ("members", "owners", "robots", "since")

    def __init__(self, since: float, members: frozenset[str], robots: frozenset[str]) -> None:
        self.since = since
        self.members = members
        self.robots = robots
        self.owners: dict[str, str] | None = None

    def owner(self, robot_id: str, rankings: Rankings) -> str | None:
        if robot_id not in self.robots:
            return owner_of(robot_id, self.members)
        if self.owners is None:
            self.owners = assign(self.robots, self.members, rankings=rankings)
        return self.owners.get(robot_id)


class ShardView:
    """Which robots one member serves, from the members and announced robots it has seen over time.

    Pure: the Zenoh side calls :meth:`set_members` and :meth:`set_robots` on every change and the
    service asks :meth:`owns` for each sample; ``now`` (``time.monotonic`` by default) is injectable
    for tests. Thread-safe.
    """

    def __init__(self, me: str, *, settle_s: float = SETTLE_S, now: float | None = None) -> None:
        self.me = me
        self.settle_s = settle_s
        started = time.monotonic() if now is None else now
        # Every view that may still matter, oldest first. The first lacks this member: a process that
        # has just joined serves nothing until it has settled.
        self._views: list[_View] = [_View(started, frozenset(), frozenset())]
        self._rankings = Rankings()
        self._owned_cache: dict[str, bool] = {}  # filled only while settled, emptied by a change
        self._seen: dict[str, float] = {}  # robot id → when last asked about
        self._logged: set[str] = set()  # robots owned at the last :meth:`changes`
        self._lock = threading.Lock()
        self.set_members((), started)

    @property
    def members(self) -> frozenset[str]:
        with self._lock:
            return self._views[-1].members

    def set_members(self, members: Iterable[str], now: float | None = None) -> None:
        """The live members as of ``now`` (this member is always among them while it runs)."""
        current = frozenset(members) | {self.me}
        with self._lock:
            self._add_view(now, current, self._views[-1].robots)

    def set_robots(self, robots: Iterable[str], now: float | None = None) -> None:
        """The robots to share evenly as of ``now`` (:func:`assign`; :class:`OwnedRobots
        <services.shard_subscriptions.OwnedRobots>` says which)."""
        current = frozenset(robots)
        with self._lock:
            self._add_view(now, self._views[-1].members, current)

    def _add_view(self, now: float | None, members: frozenset[str], robots: frozenset[str]) -> None:
        last = self._views[-1]
        if members == last.members and robots == last.robots:
            return
        now = time.monotonic() if now is None else now
        if len(self._views) > 1 and now - last.since < COALESCE_S:  # a burst (COALESCE_S)
            self._views[-1] = _View(last.since, members, robots)
        else:
            self._views.append(_View(now, members, robots))
        self._owned_cache.clear()
        self._prune(now)

    def _prune(self, now: float) -> None:
        """Drop views that ended more than ``settle_s`` ago (the one current then stays), and what
        was kept for robots none of the others holds."""
        horizon = now - self.settle_s
        dropped = False
        while len(self._views) > 1 and self._views[1].since <= horizon:
            del self._views[0]
            dropped = True
        if dropped:
            self._rankings.retain(frozenset().union(*(view.robots for view in self._views)))

    def owns(self, robot_id: str, now: float | None = None) -> bool:
        """Whether this member serves ``robot_id`` now: its owner in every view of the last ``settle_s``."""
        now = time.monotonic() if now is None else now
        with self._lock:
            self._seen[robot_id] = now
            return self._owns(robot_id, now)

    def _owns(self, robot_id: str, now: float) -> bool:
        cached = self._owned_cache.get(robot_id)
        if cached is not None:
            return cached
        self._prune(now)
        views = self._views
        if robot_id in views[-1].robots:
            # Shared out: the views from before it was are no constraint. Until a member sees its
            # token it subscribes to no sample of it, and the member that serves unannounced robots
            # hands it over only after settle_s (services.shard_subscriptions.serves): so it is
            # served from the moment its owner sees it, not settle_s later.
            views = [view for view in views if robot_id in view.robots]
        owned = all(view.owner(robot_id, self._rankings) == self.me for view in views)
        if len(self._views) == 1:  # settled: the answer holds until the next change
            self._owned_cache[robot_id] = owned
        return owned

    def forget_silent(self, forget_after_s: float, now: float | None = None) -> list[str]:
        """Forget robots not asked about for ``forget_after_s`` (a changing fleet does not leak)."""
        now = time.monotonic() if now is None else now
        with self._lock:
            silent = [robot_id for robot_id, seen in self._seen.items() if now - seen > forget_after_s]
            for robot_id in silent:
                del self._seen[robot_id]
                self._owned_cache.pop(robot_id, None)
                self._logged.discard(robot_id)
        return silent

    def settled(self, now: float | None = None) -> bool:
        """Whether the member set has not changed for ``settle_s``: every robot's owner serves it."""
        now = time.monotonic() if now is None else now
        with self._lock:
            self._prune(now)
            return len(self._views) == 1

    def changes(self, now: float | None = None) -> tuple[list[str], list[str]]:
        """(gained, lost) among the robots seen, since the last call: what the service logs."""
        now = time.monotonic() if now is None else now
        with self._lock:  # asking here is not hearing from a robot: ``_seen`` stays as it was
            owned = {robot_id for robot_id in self._seen if self._owns(robot_id, now)}
            gained, lost = sorted(owned - self._logged), sorted(self._logged - owned)
            self._logged = owned
        return gained, lost

    def snapshot(self) -> dict[str, object]:
        """For the service's counters: this member, how many it sees and how many robots it serves."""
        with self._lock:
            members = len(self._views[-1].members)
            return {"member": self.me, "members": members, "robots_served": len(self._logged)}


class ShardMembership:
    """The Zenoh side of a :class:`ShardView`: this process's token and a watch on the others'.

    :meth:`join` declares the token (once the service is wired and able to serve) and starts the
    liveliness subscriber, whose history gives the members already up; its ``on_members`` hears of
    every change too (:class:`services.shard_subscriptions.OwnedSubscriptions`). :meth:`log_changes`
    (the service's housekeeping) logs the robots gained and lost.
    """

    def __init__(self, session: Any, service: str, *, settle_s: float = SETTLE_S) -> None:
        self.service = service
        self._session = session
        self.me = str(session.zid())
        self.view = ShardView(self.me, settle_s=settle_s)
        self._members: set[str] = set()
        self._lock = threading.Lock()
        self._token: Any = None
        self._subscriber: Any = None

    def join(self, on_members: Callable[[frozenset[str]], None] | None = None) -> None:
        import zenoh

        def on_change(sample: Any) -> None:
            try:
                service, member = parse_shard_key(str(sample.key_expr))
            except ValueError:
                return
            if service != self.service:
                return
            with self._lock:
                if sample.kind == zenoh.SampleKind.PUT:
                    self._members.add(member)
                else:
                    self._members.discard(member)
                members = set(self._members)
            self.view.set_members(members)
            if on_members is not None:
                on_members(frozenset(members | {self.me}))
            log.info("%s processes sharing the fleet: %d (%s)", self.service, len(members | {self.me}),
                     ", ".join(sorted(m[:8] for m in members | {self.me})))  # fmt: skip

        self._token = self._session.liveliness().declare_token(shard_key(self.service, self.me))
        self._subscriber = self._session.liveliness().declare_subscriber(
            shard_members_key(self.service), on_change, history=True
        )

    def owns(self, robot_id: str) -> bool:
        return self.view.owns(robot_id)

    def wait_settled(
        self, members: int, stop: threading.Event, timeout_s: float = SIBLINGS_TIMEOUT_S
    ) -> bool:
        """Block until at least ``members`` processes are live and the set has settled (a launch's
        processes then start serving their shares together instead of handing robots over as each
        one comes up); False after ``timeout_s`` or once ``stop`` is set."""
        deadline = time.monotonic() + timeout_s
        while not (len(self.view.members) >= members and self.view.settled()):
            if stop.wait(0.05):
                return False
            if time.monotonic() > deadline:
                log.warning("%s: %d of %d processes up after %.0f s: serving anyway", self.service,
                            len(self.view.members), members, timeout_s)  # fmt: skip
                return False
        return True

    def log_changes(self, forget_after_s: float) -> dict[str, object]:
        """Log the robots this process took over or handed over since the last call; its counters."""
        self.view.forget_silent(forget_after_s)
        gained, lost = self.view.changes()
        for verb, robots in (("now serves", gained), ("handed over", lost)):
            if robots:
                names = ", ".join(robots[:MAX_LOGGED]) + (" …" if len(robots) > MAX_LOGGED else "")
                log.info("%s %s %s %d robot(s): %s", self.service, self.me[:8], verb, len(robots), names)
        return self.view.snapshot()

    def leave(self) -> None:
        """Undeclare the token (the others take the robots over) and the watch."""
        for entity in (self._token, self._subscriber):
            if entity is not None:
                entity.undeclare()
        self._token = self._subscriber = None


SIBLING_FLAG: Final[str] = "--sibling"  # marks a process started by :func:`sibling_commands`


def add_processes_argument(parser: argparse.ArgumentParser, flag: str, default_help: str) -> None:
    """``--detectors N`` / ``--encoders N``: how many processes of this service share the fleet; and the
    hidden flag of the processes a launch starts itself, which start none."""
    parser.add_argument(
        flag,
        type=int,
        default=None,
        metavar="N",
        help=f"processes of this service sharing the robots, this one included (default: {default_help})",
    )
    parser.add_argument(SIBLING_FLAG, action="store_true", help=argparse.SUPPRESS)


def sibling_commands(
    module: str, argv: Sequence[str], flag: str, count: int, extra: Sequence[str] = ()
) -> list[list[str]]:
    """The command lines of the ``count - 1`` other processes of a ``flag N`` launch of ``module``.

    Each runs ``module`` with this process's own flags and ``extra``, ``flag count`` (its share of the
    cores, and how many processes to wait for before serving) and :data:`SIBLING_FLAG` (it starts no
    process itself). It joins the
    network through this process: it connects to this process's endpoints and to its ``--connect``
    peers, and listens where this process does but on a port of its own (0: the OS picks), so that a
    peer which knows only this process's endpoint learns the others' through Zenoh's gossip and sends
    them their robots' samples directly.
    """
    strip = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    add_zenoh_arguments(strip)
    strip.add_argument(flag)
    zenoh_args, rest = strip.parse_known_args(list(argv))
    settings = settings_from_args(zenoh_args)
    here = tuple(endpoint.replace("0.0.0.0", "127.0.0.1") for endpoint in settings.listen)
    sibling = ZenohSettings(
        mode=settings.mode,
        connect=(*here, *settings.connect),
        listen=tuple(endpoint.rsplit(":", 1)[0] + ":0" for endpoint in settings.listen),
        multicast_scouting=settings.multicast_scouting,
        config_file=settings.config_file,
        cfg=settings.cfg,
    )
    command = [sys.executable, "-m", module, *rest, *extra, flag, str(count), SIBLING_FLAG, *sibling.to_cli()]
    return [list(command) for _ in range(count - 1)]


class Siblings:
    """The other processes of a ``--detectors N`` launch: started, restarted when one dies, stopped.

    A sibling that dies has its robots taken over by the others within :data:`SETTLE_S`; the restart
    brings the share back.
    """

    def __init__(self, commands: Sequence[Sequence[str]], popen: Callable[[list[str]], Any]) -> None:
        self._commands = [list(c) for c in commands]
        self._popen = popen
        self.processes: list[Any] = []

    def start(self) -> None:
        self.processes = [self._popen(command) for command in self._commands]

    def restart_dead(self) -> int:
        """Restart siblings that exited; returns how many."""
        restarted = 0
        for index, process in enumerate(self.processes):
            if process.poll() is not None:
                log.warning("sibling pid %d exited with %s: restarting it", process.pid, process.returncode)
                self.processes[index] = self._popen(self._commands[index])
                restarted += 1
        return restarted

    def stop(self, grace_s: float = 5.0) -> None:
        from services.launcher import stop_processes

        stop_processes({str(p.pid): p for p in self.processes}, grace_s)
