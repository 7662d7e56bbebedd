"""Which robots' tensors a detector process subscribes to: the announced robots it owns, and how that
set changes as members join and leave and robots' sources come and go; then the same over Zenoh."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

from common.keys import TENSOR, tensor_key
from common.transport import ZenohSettings, open_session
from services.runtime import announce_source
from services.shard_subscriptions import OwnedRobots, OwnedSubscriptions, robots_to_subscribe
from services.shards import owner_of
from tests.support.waiting import wait_for

ROBOTS = [f"robot{i:03d}" for i in range(60)]
ME, OTHER, THIRD = "a1f3", "0be2", "9c77"


def announced(plan: OwnedRobots, robots: list[str], source: str = "enc1") -> None:
    for robot_id in robots:
        plan.source_up(robot_id, source)


def owned_by(member: str, members: list[str], robots: list[str] = ROBOTS) -> set[str]:
    return {robot_id for robot_id in robots if owner_of(robot_id, members) == member}


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


def test_a_leaver_s_robots_come_back_and_nothing_else_moves() -> None:
    plan = OwnedRobots(ME)
    plan.set_members([ME, OTHER, THIRD])
    announced(plan, ROBOTS)
    before = plan.wanted()
    plan.set_members([ME, OTHER])  # THIRD died
    subscribe, unsubscribe = plan.diff(before)
    assert unsubscribe == []
    assert set(subscribe) == owned_by(ME, [ME, OTHER]) - before
    assert all(owner_of(robot_id, [ME, OTHER, THIRD]) == THIRD for robot_id in subscribe) and subscribe


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
    theirs = sorted(owned_by(OTHER, [ME, OTHER]))[0]
    plan.source_up(theirs, "enc1")
    assert plan.wanted() == frozenset()
    plan.set_members([ME])  # its owner left: the robot is still announced, so it is taken over
    assert plan.wanted() == {theirs}


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
