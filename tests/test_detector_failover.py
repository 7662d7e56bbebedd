"""Detector processes share a fleet over Zenoh liveliness: ``kill -9`` of one of three moves its robots,
and each of two receives only the tensors of the robots it serves.

The test publishes recorded tensors for a dozen robots at 10 Hz (the robots' stand-in of
``bench.fleet_capacity``), starts three ``services.detector --detectors 1`` processes on loopback,
waits until every robot is answered, kills the process serving the most robots with SIGKILL and
checks that its robots are answered again within 2 s, that no (robot, seq) is ever answered twice,
and that no robot goes unanswered. The robots announce their tensors, as the encoder does, so each
process subscribes to its own robots' only (services.shard_subscriptions).
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
from bench.harness import start_loopback_service
from common.keys import DETECTIONS, TENSOR, service_stats_key, tensor_key, wildcard_key
from common.messages import Detections, decode_message
from common.model_spec import SHIPPED_MODEL
from common.transport import ZenohSettings, open_session, payload_bytes
from services.encoder.core import EncoderCore
from services.launcher import free_tcp_ports, stop_processes
from services.runtime import announce_source
from services.shards import owner_of
from tests.support.scan_replay import replay_scans
from tests.support.waiting import wait_for

pytestmark = [pytest.mark.slow, pytest.mark.integration]

ROBOTS = [f"fleet{i:02d}" for i in range(12)]
DETECTORS = 3
RATE_HZ = 10.0
MOVE_WITHIN_S = 2.0


class Answers:
    """Every detections message received: count per (robot, seq) and arrival times per robot."""

    def __init__(self) -> None:
        self.count: Counter[tuple[str, int]] = Counter()
        self.arrivals: dict[str, list[tuple[float, int]]] = {robot: [] for robot in ROBOTS}
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

            owners = {robot: owner_of(robot, members.values()) for robot in ROBOTS}
            victim_pid, victim = max(members.items(), key=lambda m: list(owners.values()).count(m[1]))
            orphans = [robot for robot in ROBOTS if owners[robot] == victim]
            assert orphans, "rendezvous gave the victim no robot: a dozen robots over three should not"
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


def test_two_detector_processes_each_receive_only_the_tensors_of_the_robots_they_serve() -> None:
    """``--detectors 2``: every tensor reaches its robot's owner and no other process (``not_ours`` stays
    0), and every robot is answered by exactly one process."""
    test_port, port = free_tcp_ports(2)
    detector = start_loopback_service(
        "services.detector",
        port,
        [test_port],
        "--detectors",
        "2",
        *ONE_THREAD,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    stats: dict[int, dict[str, Any]] = {}  # pid → its newest counters
    lock = threading.Lock()

    def on_stats(sample: Any) -> None:
        body = json.loads(payload_bytes(sample))
        with lock:
            stats[int(body["pid"])] = body

    def newest() -> list[dict[str, Any]]:
        with lock:
            return list(stats.values())

    answers = Answers()
    try:
        with open_session(ZenohSettings.loopback(test_port)) as session:
            session.declare_subscriber(wildcard_key(DETECTIONS), answers)
            session.declare_subscriber(service_stats_key("detector"), on_stats)
            # Counters come once a launch's processes all serve, settled: no robot moves from here on.
            assert wait_for(lambda: len(stats) == 2, 90), f"detectors up: {list(stats)}"
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
            members = [s["shard"]["member"] for s in newest()]
            for body in newest():
                mine = [robot for robot in ROBOTS if owner_of(robot, members) == body["shard"]["member"]]
                assert mine, "rendezvous gave a process no robot: a dozen robots over two should not"
                assert body["not_ours"] == 0, body
                assert body["shard"]["subscribed_robots"] == len(mine), body
                assert body["robots"] == len(mine), body  # it answered its own robots, no other
            with answers.lock:
                twice = {key: n for key, n in answers.count.items() if n > 1}
            assert not twice, f"answered more than once: {twice}"
    finally:
        stop_processes({str(port): detector}, grace_s=20)
