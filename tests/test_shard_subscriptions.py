"""Which robots' tensors a detector process subscribes to: the announced robots it owns, and how that
set changes as members join and leave and robots' sources come and go; which member serves the scans
of robots that announce nothing, and how a robot's announcement moves it without a scan served twice;
then the same over Zenoh."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import pytest

from common.keys import SCAN, TENSOR, scan_key, tensor_key
from common.transport import ZenohSettings, open_session
from services.runtime import announce_source
from services.shard_subscriptions import (
    UNANNOUNCED,
    OwnedRobots,
    OwnedSubscriptions,
    holds_wildcard,
    robots_to_subscribe,
    serves,
)
from services.shards import ShardView, assign, owner_of
from tests.support.waiting import wait_for

ROBOTS = [f"robot{i:03d}" for i in range(60)]
ME, OTHER, THIRD = "a1f3", "0be2", "9c77"


def announced(plan: OwnedRobots, robots: list[str], source: str = "enc1") -> None:
    for robot_id in robots:
        plan.source_up(robot_id, source)


def owned_by(member: str, members: list[str], robots: list[str] = ROBOTS) -> set[str]:
    """The robots ``member`` serves when ``robots`` are announced: its even share."""
    return {robot_id for robot_id, owner in assign(robots, members).items() if owner == member}


def test_alone_a_member_subscribes_to_every_announced_robot_and_nothing_else() -> None:
    plan = OwnedRobots(ME)
    assert plan.diff([]) == ([], [])
    announced(plan, ROBOTS[:3])
    assert plan.wanted() == frozenset(ROBOTS[:3])
    assert plan.diff([]) == (ROBOTS[:3], [])
    assert plan.diff(ROBOTS[:3]) == ([], [])


def test_the_members_share_the_announced_robots_without_overlap_or_gap() -> None:
    members = [ME, OTHER, THIRD]
    plans = {member: OwnedRobots(member) for member in members}
    for plan in plans.values():
        plan.set_members(members)
        announced(plan, ROBOTS)
    wanted = {member: plan.wanted() for member, plan in plans.items()}
    assert sum(len(robots) for robots in wanted.values()) == len(ROBOTS)
    assert frozenset().union(*wanted.values()) == frozenset(ROBOTS)
    assert all(robots for robots in wanted.values())  # sixty robots leave nobody idle
    assert wanted[ME] == robots_to_subscribe(members, ROBOTS, ME) == owned_by(ME, members)


def test_a_joiner_takes_its_robots_and_the_old_owner_gives_exactly_those_up() -> None:
    plan = OwnedRobots(ME)
    announced(plan, ROBOTS)
    subscribed, _ = plan.diff([])
    plan.set_members([ME, OTHER])
    subscribe, unsubscribe = plan.diff(subscribed)
    assert subscribe == []
    assert set(unsubscribe) == owned_by(OTHER, [ME, OTHER]) and unsubscribe


def test_a_leaver_s_robots_are_shared_out_and_few_others_move() -> None:
    plan = OwnedRobots(ME)
    plan.set_members([ME, OTHER, THIRD])
    announced(plan, ROBOTS)
    before = plan.wanted()
    plan.set_members([ME, OTHER])  # THIRD died
    subscribe, unsubscribe = plan.diff(before)
    assert set(subscribe) - set(unsubscribe) == owned_by(ME, [ME, OTHER]) - before
    orphans = owned_by(THIRD, [ME, OTHER, THIRD])
    taken = [robot_id for robot_id in subscribe if robot_id in orphans]
    assert len(taken) >= len(orphans) // 2 - 2  # about half the orphans come here
    others = [robot_id for robot_id in [*subscribe, *unsubscribe] if robot_id not in orphans]
    assert len(others) <= 4, others  # a robot or two evens the shares out, not a reshuffle


def test_a_robot_stays_subscribed_until_its_last_source_goes() -> None:
    plan = OwnedRobots(ME)
    plan.source_up("r1", "enc1")
    plan.source_up("r1", "enc2")  # an encoder handover: both hold the robot for a while
    plan.source_down("r1", "enc1")
    assert plan.wanted() == {"r1"}
    plan.source_down("r1", "enc2")
    assert plan.wanted() == frozenset()
    assert plan.diff(["r1"]) == ([], ["r1"])
    plan.source_down("r1", "enc2")  # a repeated or unknown withdrawal changes nothing
    plan.source_down("never", "enc1")
    assert plan.wanted() == frozenset()


def test_a_robot_announced_while_another_member_owns_it_is_not_subscribed_here() -> None:
    plan = OwnedRobots(ME)
    plan.set_members([ME, OTHER])
    theirs = next(r for r in ROBOTS if owned_by(OTHER, [ME, OTHER], [r]))  # when it is the only robot
    plan.source_up(theirs, "enc1")
    assert plan.wanted() == frozenset()
    plan.set_members([ME])  # its owner left: the robot is still announced, so it is taken over
    assert plan.wanted() == {theirs}


SETTLE_S = 0.5
LONG_AGO = -10.0


def member(me: str, members: list[str], now: float = LONG_AGO) -> tuple[OwnedRobots, ShardView]:
    """A member's plan and view, both settled on ``members`` since ``now``; the plan tells the view of
    the announced robots, as the services wire them."""
    view = ShardView(me, settle_s=SETTLE_S, now=now)
    view.set_members(members, now=now)
    plan = OwnedRobots(me, settle_s=SETTLE_S, now=now, view=view)
    plan.set_members(members)
    return plan, view


def pushes_another(fleet: list[str], members: list[str]) -> tuple[str, list[str]]:
    """A robot whose arrival moves robots of ``fleet`` between ``members``, and those robots."""
    before = assign(fleet, members)
    for i in range(1000):
        newcomer = f"flaky{i}"
        after = assign([*fleet, newcomer], members)
        moved = [r for r in fleet if after[r] != before[r]]
        if moved:
            return newcomer, moved
    raise AssertionError("no robot moves another")


def test_a_token_that_flaps_moves_no_other_robot_and_leaves_none_unserved() -> None:
    """A publisher in a crash loop announces and withdraws its robot every 0.3 s. Were every change
    shared out at once, a robot its arrival moves would change owner faster than ``settle_s`` and be
    served by nobody for as long as it flaps."""
    members = [ME, OTHER]
    fleet = ROBOTS[:21]
    flaky, moved = pushes_another(fleet, members)
    everyone = {m: member(m, members) for m in members}
    for plan, _ in everyone.values():
        for robot_id in fleet:
            plan.source_up(robot_id, "sim", now=LONG_AGO)
    owners = assign([*fleet, flaky], members)  # its first arrival moves them, once
    up = False
    for tick in range(100):  # ten seconds: up 0.3 s, down 0.3 s
        t = 0.1 * tick
        if tick % 3 == 0:
            up = not up
            for k, (plan, _) in enumerate(everyone.values()):
                change = plan.source_up if up else plan.source_down
                change(flaky, "crashing", now=t + 0.005 * k)
        if t >= 0.6:  # the first arrival has settled
            for robot_id in moved:
                assert served_by(everyone, robot_id, now=t + 0.01) == [owners[robot_id]], (t, robot_id)


def test_a_fleet_that_shrinks_is_shared_out_again_and_forgets_its_robots() -> None:
    """Robots that go move nobody one by one, but once more than a tenth of the shared ones are gone
    the rest are shared out evenly again; what was kept for the gone ones is dropped."""
    members = [ME, OTHER, THIRD]
    plan, view = member(ME, members)
    for robot_id in ROBOTS:
        plan.source_up(robot_id, "sim", now=0.0)
    assert plan.shared() == frozenset(ROBOTS)
    plan.source_down(ROBOTS[0], "sim", now=1.0)
    assert plan.shared() == frozenset(ROBOTS)  # one gone: nothing moves
    for robot_id in ROBOTS[1:30]:
        plan.source_down(robot_id, "sim", now=1.0)
    remaining = ROBOTS[30:]
    shared = plan.shared()
    assert shared >= frozenset(remaining) and len(shared - set(remaining)) <= max(1, len(shared) // 10)
    mine = owned_by(ME, members, sorted(shared))
    assert plan.wanted() == mine & set(remaining)
    assert {r for r in remaining if view.owns(r, now=5.0)} == mine & set(remaining)
    assert set(view._rankings._order) <= shared  # the gone robots' weights are dropped


def test_a_burst_of_tokens_makes_few_views() -> None:
    """A thousand robots announced within a fifth of a second (a start, an encoder restart): views
    changed again within ``COALESCE_S`` are changed in place, so a sample looks at a handful of
    views, not a thousand, and the view settles half a second after the burst."""
    plan, view = member(ME, [ME, OTHER])
    robots = [f"robot{i:04d}" for i in range(1000)]
    for i, robot_id in enumerate(robots):
        plan.source_up(robot_id, "sim", now=0.0002 * i)
    assert len(view._views) <= 6, len(view._views)
    assert not view.settled(now=0.3) and view.settled(now=0.75)
    mine = owned_by(ME, [ME, OTHER], robots)
    assert {r for r in robots if view.owns(r, now=0.75)} == mine


def test_exactly_one_member_holds_the_wildcard_and_another_takes_it_when_it_goes() -> None:
    members = [ME, OTHER, THIRD]
    holders = [m for m in members if holds_wildcard(members, m)]
    assert holders == [owner_of(UNANNOUNCED, members)]
    survivors = [m for m in members if m != holders[0]]
    assert [m for m in survivors if holds_wildcard(survivors, m)] == [owner_of(UNANNOUNCED, survivors)]
    assert holds_wildcard([], ME)  # alone, a member serves every robot that announces nothing


def test_a_robot_is_served_as_its_own_while_announced_and_as_the_unannounced_while_not() -> None:
    plan = OwnedRobots(ME, settle_s=SETTLE_S, now=LONG_AGO)
    assert plan.serving_ids("r1", now=0.0) == (UNANNOUNCED,)
    plan.source_up("r1", "sim", now=0.0)
    assert plan.announced("r1") and not plan.announced("r2")
    assert plan.serving_ids("r1", now=0.4) == ("r1", UNANNOUNCED)  # others may not have seen the token yet
    assert plan.serving_ids("r1", now=0.5) == ("r1",)
    plan.source_down("r1", "sim", now=1.0)
    assert plan.serving_ids("r1", now=1.2) == ("r1", UNANNOUNCED)
    assert plan.serving_ids("r1", now=1.5) == (UNANNOUNCED,)


def test_every_robot_counts_as_just_changed_until_the_member_has_watched_the_sources_for_settle_s() -> None:
    plan = OwnedRobots(ME, settle_s=SETTLE_S, now=LONG_AGO)
    plan.watching(now=0.0)  # the tokens already up arrive a moment later
    assert plan.serving_ids("r1", now=0.3) == ("r1", UNANNOUNCED) and not plan.watched(now=0.3)
    assert plan.serving_ids("r1", now=0.6) == (UNANNOUNCED,) and plan.watched(now=0.6)


def test_each_robot_announced_or_not_is_served_by_exactly_the_member_that_receives_it() -> None:
    members = [ME, OTHER, THIRD]
    everyone = {m: member(m, members) for m in members}
    loud, quiet = ROBOTS[:40], ROBOTS[40:]
    for plan, _ in everyone.values():
        for robot_id in loud:
            plan.source_up(robot_id, "sim", now=LONG_AGO)
    for robot_id in ROBOTS:
        servers = [m for m, (plan, view) in everyone.items() if serves(plan, view, robot_id, now=0.0)]
        receivers = [
            m
            for m, (plan, _) in everyone.items()
            if robot_id in plan.wanted() or (plan.holds_wildcard() and not plan.announced(robot_id))
        ]
        assert servers == receivers and len(servers) == 1, (robot_id, servers, receivers)
    holder = owner_of(UNANNOUNCED, members)
    assert all(serves(*everyone[holder], robot_id, now=0.0) for robot_id in quiet)


Members = dict[str, tuple[OwnedRobots, ShardView]]


def two_members() -> tuple[str, str, Members, str]:
    """(the member that holds the wildcard, the other one, both settled, a robot the other one owns)."""
    members = [ME, OTHER]
    holder = owner_of(UNANNOUNCED, members)
    owner = next(m for m in members if m != holder)
    assert holder is not None
    robot_id = next(r for r in ROBOTS if owned_by(owner, members, [r]))  # announced alone
    return holder, owner, {m: member(m, members) for m in members}, robot_id


def served_by(everyone: Members, robot_id: str, now: float) -> list[str]:
    return [m for m, (plan, view) in everyone.items() if serves(plan, view, robot_id, now=now)]


@pytest.mark.parametrize("holder_learns_first", [True, False])
def test_a_robot_that_becomes_announced_moves_to_its_owner_and_is_never_served_twice(
    holder_learns_first: bool,
) -> None:
    holder, owner, everyone, robot_id = two_members()
    assert served_by(everyone, robot_id, now=0.0) == [holder]
    first, second = (holder, owner) if holder_learns_first else (owner, holder)
    everyone[first][0].source_up(robot_id, "sim", now=1.0)
    everyone[second][0].source_up(robot_id, "sim", now=1.05)  # the token reaches it a little later
    for now in (1.0, 1.02, 1.05, 1.3, 1.5, 1.54):
        assert len(served_by(everyone, robot_id, now)) <= 1, now
    assert served_by(everyone, robot_id, now=1.56) == [owner]
    assert robot_id in everyone[owner][0].wanted()  # on its own key, which the owner subscribes to


@pytest.mark.parametrize("holder_learns_first", [True, False])
def test_a_robot_whose_last_source_goes_moves_to_the_wildcard_and_is_never_served_twice(
    holder_learns_first: bool,
) -> None:
    holder, owner, everyone, robot_id = two_members()
    for plan, _ in everyone.values():
        plan.source_up(robot_id, "sim", now=0.0)
    assert served_by(everyone, robot_id, now=1.0) == [owner]
    first, second = (holder, owner) if holder_learns_first else (owner, holder)
    everyone[first][0].source_down(robot_id, "sim", now=2.0)
    everyone[second][0].source_down(robot_id, "sim", now=2.05)
    for now in (2.0, 2.02, 2.05, 2.3, 2.5, 2.54):
        assert len(served_by(everyone, robot_id, now)) <= 1, now
    assert served_by(everyone, robot_id, now=2.56) == [holder]
    assert robot_id not in everyone[owner][0].wanted()


def test_when_the_wildcard_s_member_dies_another_takes_the_unannounced_robots_after_settling() -> None:
    members = [ME, OTHER, THIRD]
    everyone = {m: member(m, members) for m in members}
    holder = owner_of(UNANNOUNCED, members)
    survivors = [m for m in members if m != holder]
    heir = owner_of(UNANNOUNCED, survivors)
    quiet = ROBOTS[:5]
    for robot_id in quiet:
        assert served_by(everyone, robot_id, now=0.0) == [holder]
    del everyone[holder]
    for plan, view in everyone.values():
        plan.set_members(survivors)
        view.set_members(survivors, now=1.0)
    assert [m for m, (plan, _) in everyone.items() if plan.holds_wildcard()] == [heir]  # subscribes at once
    assert not any(served_by(everyone, robot_id, now=1.3) for robot_id in quiet)  # serves after settling
    assert all(served_by(everyone, robot_id, now=1.5) == [heir] for robot_id in quiet)


def test_the_zenoh_side_subscribes_to_an_announced_robot_and_drops_it_when_its_source_goes(
    free_port: Callable[[], int],
) -> None:
    port = free_port()
    received: list[str] = []
    lock = threading.Lock()

    def on_sample(sample: Any) -> None:
        with lock:
            received.append(str(sample.key_expr))

    with (
        open_session(ZenohSettings.loopback(port)) as detector,
        open_session(ZenohSettings.loopback(None, [port])) as encoder,
    ):
        subscriptions = OwnedSubscriptions(detector, str(detector.zid()), TENSOR, tensor_key, on_sample)
        subscriptions.start()
        try:
            mine = encoder.declare_publisher(tensor_key("r1"))
            token = announce_source(encoder, "r1", TENSOR)
            assert wait_for(lambda: mine.matching_status.matching, 10)
            assert wait_for(lambda: len(subscriptions) == 1, 10)
            unannounced = encoder.declare_publisher(tensor_key("r2"))
            mine.put(b"x")
            unannounced.put(b"y")  # nobody subscribes to a robot nobody announced
            assert wait_for(lambda: received == [tensor_key("r1")], 10)
            assert not unannounced.matching_status.matching
            token.undeclare()
            assert wait_for(lambda: not mine.matching_status.matching, 10)
            assert wait_for(lambda: len(subscriptions) == 0, 10)
            mine.undeclare()
            unannounced.undeclare()
        finally:
            subscriptions.close()


def test_the_zenoh_side_hands_unannounced_robots_to_the_wildcard_and_announced_ones_to_their_key(
    free_port: Callable[[], int],
) -> None:
    port = free_port()
    mine: list[str] = []
    theirs: list[str] = []
    lock = threading.Lock()

    def collect(into: list[str]) -> Callable[[Any], None]:
        def on_sample(sample: Any) -> None:
            with lock:
                into.append(str(sample.key_expr))

        return on_sample

    with (
        open_session(ZenohSettings.loopback(port)) as detector,
        open_session(ZenohSettings.loopback(None, [port])) as robots,
    ):
        subscriptions = OwnedSubscriptions(
            detector, str(detector.zid()), SCAN, scan_key, collect(mine), unannounced=collect(theirs)
        )
        subscriptions.start()  # alone: it owns every announced robot and serves the unannounced ones
        try:
            loud = robots.declare_publisher(scan_key("r1"))
            token = announce_source(robots, "r1", SCAN)
            quiet = robots.declare_publisher(scan_key("r2"))
            assert wait_for(lambda: len(subscriptions) == 1, 10)
            assert wait_for(lambda: subscriptions.counters(60.0)["wildcard"], 10)
            assert wait_for(lambda: quiet.matching_status.matching, 10)
            loud.put(b"x")
            quiet.put(b"y")
            assert wait_for(lambda: mine == [scan_key("r1")] and theirs == [scan_key("r2")], 10), (
                mine,
                theirs,
            )
            assert wait_for(lambda: subscriptions.counters(60.0)["skipped_announced"] == 1, 10)
            assert subscriptions.counters(60.0)["unannounced_robots"] == 1
            token.undeclare()
            assert wait_for(lambda: len(subscriptions) == 0, 10)
            loud.put(b"z")  # no longer announced: the wildcard passes it on
            assert wait_for(lambda: theirs == [scan_key("r2"), scan_key("r1")], 10), theirs
            for entity in (loud, quiet):
                entity.undeclare()
        finally:
            subscriptions.close()
