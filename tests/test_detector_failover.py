"""Detector processes share a fleet over Zenoh liveliness: ``kill -9`` of one of three moves its robots,
and each of two receives only the tensors (``--from-scans``: the scans) of the robots it serves.

The test publishes recorded tensors for a dozen robots at 10 Hz (the robots' stand-in of
``bench.fleet_capacity``), starts three ``services.detector --detectors 1`` processes on loopback,
waits until every robot is answered, kills the process serving the most robots with SIGKILL and
checks that its robots are answered again within 2 s, that no (robot, seq) is ever answered twice,
and that no robot goes unanswered. The robots announce their tensors, as the encoder does, so each
process subscribes to its own robots' only (services.shard_subscriptions). With ``--from-scans`` a
robot that announces nothing is served too, by the one process that holds the scans' wildcard.
"""

from __future__ import annotations

import json
import signal
import subprocess
import threading
import time
from collections import Counter
from typing import Any

import pytest
import zenoh

from bench.fleet_capacity import RecordedFrame
from bench.harness import recorded_scans, start_loopback_service
from common.keys import DETECTIONS, SCAN, TENSOR, scan_key, service_stats_key, tensor_key, wildcard_key
from common.messages import Detections, decode_message, encode_message
from common.model_spec import SHIPPED_MODEL
from common.transport import ZenohSettings, open_session, payload_bytes
from services.encoder.core import EncoderCore
from services.launcher import free_tcp_ports, stop_processes
from services.runtime import announce_lead_s, announce_source
from services.shard_subscriptions import UNANNOUNCED
from services.shards import BALANCE_SLACK, assign, owner_of
from tests.support.scan_replay import replay_scans
from tests.support.waiting import wait_for

pytestmark = [pytest.mark.slow, pytest.mark.integration]

ROBOTS = [f"fleet{i:02d}" for i in range(12)]
DETECTORS = 3
RATE_HZ = 10.0
MOVE_WITHIN_S = 2.0


class Answers:
    """Every detections message received: count per (robot, seq) and arrival times per robot."""

    def __init__(self, robots: list[str] = ROBOTS) -> None:
        self.count: Counter[tuple[str, int]] = Counter()
        self.arrivals: dict[str, list[tuple[float, int]]] = {robot: [] for robot in robots}
        self.lock = threading.Lock()

    def __call__(self, sample: Any) -> None:
        message = decode_message(payload_bytes(sample), Detections)
        with self.lock:
            self.count[(message.robot_id, message.seq)] += 1
            self.arrivals[message.robot_id].append((time.monotonic(), message.seq))

    def answered_since(self, robot: str, since: float) -> bool:
        with self.lock:
            return any(t >= since for t, _ in self.arrivals[robot])

    def first_since(self, robot: str, since: float) -> float:
        with self.lock:
            return min(t for t, _ in self.arrivals[robot] if t >= since)

    def has(self, robot: str, seq: int) -> bool:
        with self.lock:
            return self.count[(robot, seq)] > 0


class Fleet(threading.Thread):
    """Every robot publishes its next tensor each period until stopped; remembers the last seq sent."""

    def __init__(self, session: Any) -> None:
        super().__init__(daemon=True)
        encoder = EncoderCore("zero")
        tensors = [t for s in replay_scans("fleet", 12) if (t := encoder.push(s.scan)) is not None]
        self.frames = [RecordedFrame(tensor) for tensor in tensors]
        # BLOCK: a loaded host's publisher would otherwise drop a burst of a dozen 73 KB tensors, and the
        # tests check where tensors go, not how many survive the queue.
        block = zenoh.CongestionControl.BLOCK
        self.publishers = {
            robot: session.declare_publisher(tensor_key(robot), congestion_control=block) for robot in ROBOTS
        }
        self.sources = [announce_source(session, robot, TENSOR) for robot in ROBOTS]  # detectors subscribe
        self.halt = threading.Event()
        self.last_seq = -1
        self.sent = 0

    def run(self) -> None:
        period_ns = round(1e9 / RATE_HZ)
        tick = 0
        while not self.halt.wait(1.0 / RATE_HZ):
            frame = self.frames[tick % len(self.frames)]
            for robot, publisher in self.publishers.items():
                publisher.put(frame.payload(robot, tick, time.time_ns(), period_ns))
            self.last_seq = frame.seq(tick)
            self.sent += len(self.publishers)
            tick += 1


ONE_THREAD = ("--model", str(SHIPPED_MODEL), "--batch", "1", "--workers", "1", "--threads", "1")


def test_killing_one_of_three_detectors_moves_its_robots_within_two_seconds() -> None:
    test_port, *ports = free_tcp_ports(1 + DETECTORS)
    args = ("--detectors", "1", *ONE_THREAD)
    detectors = {
        port: start_loopback_service(
            "services.detector",
            port,
            [test_port, *(p for p in ports if p != port)],
            *args,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        for port in ports
    }
    members: dict[int, str] = {}  # pid → Zenoh id, from each detector's own stats

    def on_stats(sample: Any) -> None:
        body = json.loads(payload_bytes(sample))
        members[int(body["pid"])] = body["shard"]["member"]

    answers = Answers()
    try:
        with open_session(ZenohSettings.loopback(test_port)) as session:
            session.declare_subscriber(wildcard_key(DETECTIONS), answers)
            session.declare_subscriber(service_stats_key("detector"), on_stats)
            fleet = Fleet(session)
            fleet.start()
            started = time.monotonic()
            assert wait_for(lambda: len(members) == DETECTORS, 90), f"detectors up: {members}"
            assert wait_for(lambda: all(answers.answered_since(r, started) for r in ROBOTS), 60)

            owners = assign(ROBOTS, members.values())
            victim_pid, victim = max(members.items(), key=lambda m: list(owners.values()).count(m[1]))
            orphans = [robot for robot in ROBOTS if owners[robot] == victim]
            assert orphans, "the victim has no robot: a dozen robots over three should not allow it"
            steady = time.monotonic()
            assert wait_for(lambda: all(answers.answered_since(r, steady) for r in ROBOTS), 10)

            victim_process = next(p for p in detectors.values() if p.pid == victim_pid)
            victim_process.send_signal(signal.SIGKILL)
            killed = time.monotonic()
            assert wait_for(lambda: all(answers.answered_since(r, killed) for r in ROBOTS), 10), "starved"
            moved_after = {robot: answers.first_since(robot, killed) - killed for robot in orphans}
            assert max(moved_after.values()) < MOVE_WITHIN_S, moved_after
            settled = time.monotonic()
            assert wait_for(lambda: all(answers.answered_since(r, settled) for r in ROBOTS), 10), "starved"

            fleet.halt.set()
            fleet.join()
            last = fleet.last_seq  # each robot's newest tensor is always served by its owner
            assert wait_for(lambda: all(answers.has(robot, last) for robot in ROBOTS), 10)
            with answers.lock:
                twice = {key: n for key, n in answers.count.items() if n > 1}
            assert not twice, f"answered more than once: {twice}"
    finally:
        stop_processes({str(p): process for p, process in detectors.items()}, grace_s=20)


class NewestStats:
    """Each detector process's newest counters (a stats subscriber's callback)."""

    def __init__(self) -> None:
        self.by_pid: dict[int, dict[str, Any]] = {}
        self.lock = threading.Lock()

    def __call__(self, sample: Any) -> None:
        body = json.loads(payload_bytes(sample))
        with self.lock:
            self.by_pid[int(body["pid"])] = body

    def newest(self) -> list[dict[str, Any]]:
        with self.lock:
            return list(self.by_pid.values())


def two_detectors(port: int, test_port: int, *extra: str) -> subprocess.Popen[bytes]:
    """``services.detector --detectors 2`` (one thread each), connected to the test on ``test_port``."""
    return start_loopback_service(
        "services.detector",
        port,
        [test_port],
        *extra,
        "--detectors",
        "2",
        *ONE_THREAD,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )


def test_two_detector_processes_each_receive_only_the_tensors_of_the_robots_they_serve() -> None:
    """``--detectors 2``: every tensor reaches its robot's owner and no other process (``not_ours`` stays
    0), and every robot is answered by exactly one process."""
    test_port, port = free_tcp_ports(2)
    detector = two_detectors(port, test_port)
    stats = NewestStats()
    newest = stats.newest

    answers = Answers()
    try:
        with open_session(ZenohSettings.loopback(test_port)) as session:
            session.declare_subscriber(wildcard_key(DETECTIONS), answers)
            session.declare_subscriber(service_stats_key("detector"), stats)
            # Counters come once a launch's processes all serve, settled: no robot moves from here on.
            assert wait_for(lambda: len(newest()) == 2, 90), f"detectors up: {newest()}"
            fleet = Fleet(session)  # announces every robot
            for publisher in fleet.publishers.values():  # each robot's owner has subscribed
                assert wait_for(lambda p=publisher: p.matching_status.matching, 30)
            fleet.start()
            started = time.monotonic()
            assert wait_for(lambda: all(answers.answered_since(r, started) for r in ROBOTS), 60)
            fleet.halt.set()
            fleet.join()
            # Each tensor reaches exactly one process: the counts add up to the tensors sent.
            assert wait_for(lambda: sum(int(s["received"]) for s in newest()) == fleet.sent, 10), (
                f"{fleet.sent} sent, received {[int(s['received']) for s in newest()]}"
            )
            owners = assign(ROBOTS, [s["shard"]["member"] for s in newest()])
            for body in newest():
                mine = [robot for robot in ROBOTS if owners[robot] == body["shard"]["member"]]
                assert abs(len(mine) - len(ROBOTS) / 2) <= BALANCE_SLACK, owners  # an even share
                assert body["not_ours"] == 0, body
                assert body["shard"]["subscribed_robots"] == len(mine), body
                assert body["robots"] == len(mine), body  # it answered its own robots, no other
            with answers.lock:
                twice = {key: n for key, n in answers.count.items() if n > 1}
            assert not twice, f"answered more than once: {twice}"
    finally:
        stop_processes({str(port): detector}, grace_s=20)


QUIET = "quiet00"  # a robot whose publisher announces nothing (a user's driver)
SCAN_TICKS = 20  # scans each robot sends at least


class ScanFleet(threading.Thread):
    """Every robot publishes its next scan each period until stopped, the first ``first_s`` from now;
    ``ROBOTS`` announce their scans as the project's publishers do, :data:`QUIET` does not."""

    def __init__(self, session: Any) -> None:
        super().__init__(daemon=True)
        self.scans = recorded_scans(12)
        block = zenoh.CongestionControl.BLOCK
        self.publishers = {
            robot: session.declare_publisher(scan_key(robot), congestion_control=block)
            for robot in [*ROBOTS, QUIET]
        }
        self.sources = [announce_source(session, robot, SCAN) for robot in ROBOTS]
        self.halt = threading.Event()
        self.first_s = 0.0
        self.ticks = 0

    def run(self) -> None:
        if self.halt.wait(self.first_s):
            return
        while True:
            scan = self.scans[self.ticks % len(self.scans)]
            for robot, publisher in self.publishers.items():
                update = {"robot_id": robot, "seq": self.ticks, "stamp_ns": time.time_ns()}
                publisher.put(encode_message(scan.model_copy(update=update)))
            self.ticks += 1
            if self.halt.wait(1.0 / RATE_HZ):
                return


def test_two_from_scans_processes_receive_only_their_announced_robots_scans_and_one_serves_the_rest() -> None:
    """``--from-scans --detectors 2``: an announced robot's scans reach its owner and no other process's
    subscriber (``not_ours`` stays 0), a robot that announces nothing is served by the process that
    owns :data:`UNANNOUNCED`, and no scan is answered twice."""
    test_port, port = free_tcp_ports(2)
    detector = two_detectors(port, test_port, "--from-scans")
    stats = NewestStats()
    newest = stats.newest

    answers = Answers([*ROBOTS, QUIET])
    try:
        with open_session(ZenohSettings.loopback(test_port)) as session:
            session.declare_subscriber(wildcard_key(DETECTIONS), answers)
            session.declare_subscriber(service_stats_key("detector"), stats)
            assert wait_for(lambda: len(newest()) == 2, 90), f"detectors up: {newest()}"
            fleet = ScanFleet(session)  # announces ROBOTS
            # Each announced robot's owner has subscribed to its key, so has seen its token.
            subscribed = lambda: sum(int(s["shard"]["subscribed_robots"]) for s in newest()) == len(ROBOTS)  # noqa: E731
            assert wait_for(subscribed, 30), newest()
            fleet.first_s = announce_lead_s(SCAN)  # as the project's publishers wait after announcing
            fleet.start()
            started = time.monotonic()
            assert wait_for(lambda: all(answers.answered_since(r, started) for r in [*ROBOTS, QUIET]), 60)
            assert wait_for(lambda: fleet.ticks >= SCAN_TICKS, 30)
            fleet.halt.set()
            fleet.join()
            last = fleet.ticks - 1  # each robot's newest scan is always answered, by one process
            assert wait_for(lambda: all(answers.has(robot, last) for robot in [*ROBOTS, QUIET]), 10)
            sent, announced = fleet.ticks * len(fleet.publishers), fleet.ticks * len(ROBOTS)

            def counted() -> tuple[int, int]:
                """(scans into the processes' encoders, announced scans the wildcard dropped), all told."""
                bodies = newest()
                received = sum(int(body["encoder"]["received"]) for body in bodies)
                return received, sum(int(body["shard"]["skipped_announced"]) for body in bodies)

            # Each scan reaches exactly one process's encoder: the counts add up to the scans sent.
            assert wait_for(lambda: counted() == (sent, announced), 10), f"{sent}, {announced}: {counted()}"
            members = [s["shard"]["member"] for s in newest()]
            holder = owner_of(UNANNOUNCED, members)
            owners = assign(ROBOTS, members)
            for body in newest():
                shard = body["shard"]
                mine = [robot for robot in ROBOTS if owners[robot] == shard["member"]]
                holds = shard["member"] == holder
                assert abs(len(mine) - len(ROBOTS) / 2) <= BALANCE_SLACK, owners  # an even share
                assert body["not_ours"] == 0, body
                assert shard["subscribed_robots"] == len(mine), body
                assert shard["wildcard"] is holds and shard["unannounced_robots"] == int(holds), body
                # The wildcard's process received every announced scan there too, and dropped it unread.
                assert shard["skipped_announced"] == (fleet.ticks * len(ROBOTS) if holds else 0), body
                assert body["robots"] == len(mine) + int(holds), body  # its own robots, no other
            with answers.lock:
                twice = {key: n for key, n in answers.count.items() if n > 1}
            assert not twice, f"answered more than once: {twice}"
    finally:
        stop_processes({str(port): detector}, grace_s=20)
