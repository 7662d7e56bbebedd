"""Sharding a fleet over live processes: plain rendezvous hashing for robots nobody announces, an even
share for the announced ones (bounded-load rendezvous), determinism, how few robots move on a change,
and the settle rule that keeps two processes from serving one robot at once."""

from __future__ import annotations

import math
import random
import subprocess
import sys
from collections import Counter

import pytest

from services.shards import BALANCE_SLACK, Rankings, ShardView, assign, owner_of, sibling_commands, weight

ROBOTS = [f"robot{i:04d}" for i in range(3000)]
MEMBERS = ["a1f3", "0be2", "9c77", "d401"]


def assignment(members: list[str]) -> dict[str, str | None]:
    return {robot: owner_of(robot, members) for robot in ROBOTS}


def test_weights_are_the_same_in_another_process() -> None:
    """Python's hash is salted per process; the assignment must not be."""
    code = "from services.shards import weight; print(weight('a1f3', 'robot0007'))"
    other = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert int(other.stdout) == weight("a1f3", "robot0007")


def test_owner_does_not_depend_on_the_order_members_are_seen_in() -> None:
    assert assignment(MEMBERS) == assignment(list(reversed(MEMBERS)))
    assert owner_of("robot0001", []) is None


@pytest.mark.parametrize("count", [2, 3, 4])
def test_robots_are_shared_evenly(count: int) -> None:
    shares = Counter(assignment(MEMBERS[:count]).values())
    expected = len(ROBOTS) / count
    assert set(shares) == set(MEMBERS[:count])
    assert all(abs(share - expected) < 0.1 * expected for share in shares.values()), shares


def test_a_leaving_member_moves_only_its_own_robots() -> None:
    before, after = assignment(MEMBERS), assignment(MEMBERS[:-1])
    moved = {robot for robot in ROBOTS if before[robot] != after[robot]}
    assert moved == {robot for robot in ROBOTS if before[robot] == MEMBERS[-1]}


def test_a_joining_member_takes_robots_only_for_itself_and_about_its_share() -> None:
    before, after = assignment(MEMBERS[:3]), assignment(MEMBERS)
    moved = [robot for robot in ROBOTS if before[robot] != after[robot]]
    assert all(after[robot] == MEMBERS[3] for robot in moved)
    assert abs(len(moved) - len(ROBOTS) / 4) < 0.1 * len(ROBOTS) / 4


def test_a_new_member_serves_nothing_until_it_has_settled() -> None:
    view = ShardView("a1f3", settle_s=0.5, now=0.0)
    view.set_members(["a1f3"], now=0.0)
    assert not view.owns("robot0001", now=0.2)
    assert view.owns("robot0001", now=0.6)  # alone: every robot, once settled


def test_robots_are_given_up_at_once_and_taken_only_after_settling() -> None:
    """A robot that moves is served by nobody for ``settle_s``, never by two."""
    old = ShardView("a1f3", settle_s=0.5, now=-10.0)
    old.set_members(["a1f3"], now=-10.0)
    new = ShardView("0be2", settle_s=0.5, now=0.0)
    new.set_members(["a1f3", "0be2"], now=0.0)
    old.set_members(["a1f3", "0be2"], now=0.01)  # the join reaches the old member a little later
    moving = [robot for robot in ROBOTS[:200] if owner_of(robot, ["a1f3", "0be2"]) == "0be2"]
    assert moving
    for t in (0.0, 0.2, 0.49, 0.51, 1.0):
        for robot in moving:
            assert not (old.owns(robot, now=max(t, 0.01)) and new.owns(robot, now=t))
    assert all(new.owns(robot, now=0.6) for robot in moving)
    assert not any(old.owns(robot, now=0.6) for robot in moving)


def test_a_dead_members_robots_are_taken_over_after_settling() -> None:
    survivor = ShardView("a1f3", settle_s=0.5, now=-10.0)
    survivor.set_members(["a1f3", "0be2"], now=-10.0)
    orphans = [robot for robot in ROBOTS[:200] if owner_of(robot, ["a1f3", "0be2"]) == "0be2"]
    assert not any(survivor.owns(robot, now=0.0) for robot in orphans)
    survivor.set_members(["a1f3"], now=0.0)
    assert not any(survivor.owns(robot, now=0.3) for robot in orphans)
    assert all(survivor.owns(robot, now=0.5) for robot in orphans)


def test_quick_changes_need_every_view_of_the_window() -> None:
    """A robot owned in the current view but not in one held within ``settle_s`` is not served yet."""
    view = ShardView("a1f3", settle_s=0.5, now=-10.0)
    view.set_members(["a1f3", "0be2"], now=-10.0)
    view.set_members(["a1f3"], now=0.0)
    view.set_members(["a1f3", "9c77"], now=0.3)
    robot = next(
        r
        for r in ROBOTS
        if owner_of(r, ["a1f3", "0be2"]) == "0be2" and owner_of(r, ["a1f3", "9c77"]) == "a1f3"
    )
    assert not view.owns(robot, now=0.4)  # the view that ended at 0.0 did not give it here
    assert view.owns(robot, now=0.51)


def test_changes_log_gains_and_losses_and_silent_robots_are_forgotten() -> None:
    view = ShardView("a1f3", settle_s=0.5, now=-10.0)
    view.set_members(["a1f3"], now=-10.0)
    for robot in ROBOTS[:20]:
        assert view.owns(robot, now=0.0)
    gained, lost = view.changes(now=0.0)
    assert gained == ROBOTS[:20] and lost == []
    view.set_members(["a1f3", "0be2"], now=1.0)
    gained, lost = view.changes(now=1.0)
    assert gained == [] and lost == [r for r in ROBOTS[:20] if owner_of(r, ["a1f3", "0be2"]) == "0be2"]
    view.changes(now=8.0)  # logging the changes is not hearing from the robots
    assert view.forget_silent(5.0, now=10.0) == ROBOTS[:20]
    assert view.snapshot() == {"member": "a1f3", "members": 2, "robots_served": 0}


SIXTEEN = [f"{random.Random(seed).getrandbits(64):016x}" for seed in range(16)]  # Zenoh ids


@pytest.mark.parametrize("robots", [1, 15, 16, 17, 350, 700])
def test_announced_robots_are_shared_evenly_whatever_the_order_they_are_seen_in(robots: int) -> None:
    fleet = ROBOTS[:robots]
    owners = assign(fleet, SIXTEEN)
    assert sorted(owners) == sorted(fleet)
    loads = Counter(owners.values())
    assert max(loads.values()) <= math.ceil(robots / 16) + BALANCE_SLACK, loads
    shuffled = list(fleet)
    random.Random(1).shuffle(shuffled)
    assert assign(shuffled, list(reversed(SIXTEEN)), rankings=Rankings()) == owners
    assert assign(fleet, []) == {}


def test_the_even_share_holds_the_busiest_process_well_below_plain_rendezvous() -> None:
    """What the even share is for: a fleet server fails at its busiest process."""
    fleet = ROBOTS[:350]
    plain = Counter(owner_of(robot, SIXTEEN) for robot in fleet)
    even = Counter(assign(fleet, SIXTEEN).values())
    assert max(even.values()) <= 23 < max(plain.values())  # 350 / 16 is 21.9


def test_with_room_to_spare_every_robot_goes_to_its_rendezvous_owner() -> None:
    fleet = ROBOTS[:500]
    assert assign(fleet, MEMBERS, slack=len(fleet)) == {robot: owner_of(robot, MEMBERS) for robot in fleet}


def test_a_robot_joining_or_leaving_moves_about_one_other() -> None:
    """Robots come and go one at a time; each move costs the moved robot up to ``settle_s`` unserved."""
    rankings = Rankings()
    before: dict[str, str] = {}
    moved = 0
    for count in range(1, 301):
        after = assign(ROBOTS[:count], SIXTEEN, rankings=rankings)
        moved += sum(1 for robot, owner in before.items() if after[robot] != owner)
        before = after
    assert moved <= 1.5 * 300, moved  # 1.2 a join when written
    leaving = assign(ROBOTS[1:300], SIXTEEN, rankings=rankings)
    assert sum(1 for robot, owner in leaving.items() if before[robot] != owner) <= 6


def test_a_dead_member_s_robots_move_and_few_of_the_survivors_robots_do() -> None:
    fleet = ROBOTS[:450]
    before, after = assign(fleet, SIXTEEN), assign(fleet, SIXTEEN[1:])
    survivors_moved = [r for r in fleet if before[r] != SIXTEEN[0] and after[r] != before[r]]
    assert len(survivors_moved) <= 0.05 * len(fleet), len(survivors_moved)


def test_the_view_shares_the_announced_robots_evenly_and_the_others_by_rendezvous() -> None:
    view = ShardView("a1f3", settle_s=0.5, now=-10.0)
    view.set_members(MEMBERS, now=-10.0)
    announced = ROBOTS[:40]
    view.set_robots(announced, now=-10.0)
    mine = {robot for robot, owner in assign(announced, MEMBERS).items() if owner == "a1f3"}
    assert {robot for robot in announced if view.owns(robot, now=0.0)} == mine
    quiet = ROBOTS[40:200]
    assert {r for r in quiet if view.owns(r, now=0.0)} == {r for r in quiet if owner_of(r, MEMBERS) == "a1f3"}


@pytest.mark.parametrize("first", ["a1f3", "0be2"])
def test_a_robot_coming_moves_others_without_serving_any_twice(first: str) -> None:
    """A newly announced robot can move robots besides itself: the old owner gives them up at once,
    the new one takes them after ``settle_s``, whichever member learns of it first."""
    members = ["a1f3", "0be2"]
    views = {m: ShardView(m, settle_s=0.5, now=-10.0) for m in members}
    fleet = ROBOTS[:21]
    for view in views.values():
        view.set_members(members, now=-10.0)
        view.set_robots(fleet, now=-10.0)
    before = assign(fleet, members)

    def pushes_others(robot: str) -> bool:
        return any(assign([*fleet, robot], members)[r] != owner for r, owner in before.items())

    newcomer = next(r for r in ROBOTS[21:] if pushes_others(r))
    after = assign([*fleet, newcomer], members)
    moving = [r for r in fleet if before[r] != after[r]]
    second = next(m for m in members if m != first)
    views[first].set_robots([*fleet, newcomer], now=0.0)
    for robot in moving:  # the other member has not heard of the newcomer yet
        assert sum(view.owns(robot, now=0.02) for view in views.values()) <= 1, robot
    # The newcomer's owner serves it at once: no member subscribed to it before it was announced.
    if after[newcomer] == first:
        assert views[first].owns(newcomer, now=0.02)
    views[second].set_robots([*fleet, newcomer], now=0.05)
    assert views[after[newcomer]].owns(newcomer, now=0.05)
    for t in (0.05, 0.3, 0.5, 0.54):
        for robot in [*moving, newcomer]:
            assert sum(view.owns(robot, now=t) for view in views.values()) <= 1, (robot, t)
    for robot in [*fleet, newcomer]:
        assert [m for m, view in views.items() if view.owns(robot, now=0.6)] == [after[robot]]


def test_siblings_join_through_this_process_and_run_one_process_each() -> None:
    argv = ["--model", "m.onnx", "--detectors", "3", "--listen", "tcp/0.0.0.0:7447", "-e", "tcp/enc:7447"]
    commands = sibling_commands("services.detector", argv, "--detectors", 3, ("--batch", "4"))
    assert len(commands) == 2
    command = commands[0]
    assert command[1:5] == ["-m", "services.detector", "--model", "m.onnx"]
    assert command[command.index("--detectors") + 1] == "3" and command.count("--detectors") == 1
    assert "--sibling" in command  # it starts no process of its own
    assert command[command.index("--listen") + 1] == "tcp/0.0.0.0:0"  # a port of its own
    assert command[command.index("--batch") + 1] == "4"
    connects = [command[i + 1] for i, arg in enumerate(command) if arg == "--connect"]
    assert connects == ["tcp/127.0.0.1:7447", "tcp/enc:7447"]
