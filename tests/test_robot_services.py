"""The robot's processes for real: encoder and detector (and ``--from-scans``) over Zenoh on loopback.

A replayer session in the test publishes simulated scans of two robots on their real keys; the
services run as separate ``python -m`` processes, and the test reads their detections back. No part
is mocked; multicast is off and every endpoint is explicit.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from bench.harness import start_loopback_service
from common.keys import DETECTIONS, TENSOR, scan_key, service_stats_key, wildcard_key
from common.messages import Detections, StackedTensor, decode_message, encode_message
from common.model_spec import SHIPPED_BATCH_MODEL, SHIPPED_MODEL
from common.transport import ZenohSettings, open_session, payload_bytes, wait_for_subscriber
from services.launcher import free_tcp_ports
from tests.support.scan_replay import replay_scans
from tests.support.waiting import wait_for

ROOT = Path(__file__).resolve().parents[1]
SCANS_PER_ROBOT = 40
ROBOTS = ("alpha", "bravo")
PROBE = "probe"


pytestmark = [pytest.mark.slow, pytest.mark.integration]


def start_service(module: str, port: int, connect: list[int], *extra: str) -> subprocess.Popen[bytes]:
    # One detector process: lockstep needs every scan of a robot from its first in the process that
    # serves it, and the probe robot cannot tell when a launch's other processes serve theirs
    # (processes sharing a fleet: tests/test_detector_failover.py).
    one = ("--detectors", "1") if module == "services.detector" else ()
    return start_loopback_service(
        module, port, connect, *extra, *one, stdout=subprocess.PIPE, stderr=subprocess.STDOUT
    )


def stop_all(processes: list[subprocess.Popen[bytes]]) -> list[str]:
    for p in processes:
        p.terminate()
    logs = []
    for p in processes:
        out, _ = p.communicate(timeout=20)
        logs.append(out.decode(errors="replace"))
        assert p.returncode == 0, out.decode(errors="replace")[-3000:]
    return logs


class Collector:
    """Decoded messages per robot, filled from a Zenoh callback."""

    def __init__(self, kind: type) -> None:
        self.kind = kind
        self.by_robot: dict[str, list[Any]] = defaultdict(list)
        self.lock = threading.Lock()

    def __call__(self, sample: Any) -> None:
        message = decode_message(payload_bytes(sample), self.kind)
        with self.lock:
            self.by_robot[message.robot_id].append(message)

    def has(self, robot_id: str, seq: int) -> bool:
        with self.lock:
            return any(m.seq == seq for m in self.by_robot[robot_id])

    def count(self) -> int:
        with self.lock:
            return sum(len(v) for v in self.by_robot.values())


@pytest.fixture(scope="module")
def replay() -> dict[str, list]:
    return {
        robot: [r.scan for r in replay_scans(robot, SCANS_PER_ROBOT, scenario_index=i)]
        for i, robot in enumerate(ROBOTS)
    }


def prime_pipeline(session: Any, scans: list, detections: Collector, timeout: float = 60.0) -> None:
    """Publish a probe robot's scans until its detections come back: every link is up.

    Peers that start together may first miss each other and connect on Zenoh's retry a few seconds
    later; whatever is published before that is (correctly) lost. The probe robot has its own FIFO,
    so it does not disturb the robots under test.
    """
    publisher = session.declare_publisher(scan_key(PROBE))
    deadline = time.monotonic() + timeout
    seq = 0
    while not detections.by_robot.get(PROBE):
        assert time.monotonic() < deadline, "the pipeline never answered the probe robot"
        scan = scans[seq % len(scans)].model_copy(update={"robot_id": PROBE, "seq": seq, "stamp_ns": seq + 1})
        publisher.put(encode_message(scan))
        seq += 1
        time.sleep(0.1)
    publisher.undeclare()
    with detections.lock:
        del detections.by_robot[PROBE]


def publish_in_lockstep(session: Any, replay: dict[str, list], detections: Collector) -> None:
    """Scan t of every robot, then wait for their detections of seq t before scan t+1.

    Lockstep makes the expected output exact on any machine, however slow: every tensor must come
    back as detections, none dropped as stale (dropping is the core's business, tested there).
    """
    publishers = {robot: session.declare_publisher(scan_key(robot)) for robot in replay}
    for t in range(SCANS_PER_ROBOT):
        for robot, scans in replay.items():
            publishers[robot].put(encode_message(scans[t]))
        if t >= 2:
            assert wait_for(lambda t=t: all(detections.has(robot, t) for robot in replay), 30), (
                f"no detections for seq {t}"
            )


@pytest.fixture
def ports() -> Iterator[list[int]]:
    yield free_tcp_ports(3)


@pytest.mark.parametrize(
    "detector_args",
    [("--threads", "1"), ("--threads", "1", "--batch", "4")],
    ids=["batch-1-model", "batch-model"],
)
def test_encoder_and_detector_processes_serve_two_robots_without_cross_talk(
    replay: dict[str, list], ports: list[int], detector_args: tuple[str, ...]
) -> None:
    test_port, encoder_port, detector_port = ports
    encoder = start_service("services.encoder", encoder_port, [test_port, detector_port])
    detector = start_service("services.detector", detector_port, [test_port, encoder_port], *detector_args)
    tensors, detections = Collector(StackedTensor), Collector(Detections)
    try:
        with open_session(ZenohSettings.loopback(test_port)) as session:
            subs = [
                session.declare_subscriber(wildcard_key(TENSOR), tensors),
                session.declare_subscriber(wildcard_key(DETECTIONS), detections),
            ]
            wait_for_subscriber(session, scan_key(ROBOTS[0]))
            wait_for_subscriber(session, "triscan/anyone/tensor")
            prime_pipeline(session, replay[ROBOTS[0]], detections)
            with tensors.lock:
                tensors.by_robot.pop(PROBE, None)
            publish_in_lockstep(session, replay, detections)
            expected_tensors = len(ROBOTS) * (SCANS_PER_ROBOT - 2)
            assert wait_for(lambda: tensors.count() >= expected_tensors, 30), tensors.count()
            for sub in subs:
                sub.undeclare()
    finally:
        stop_all([encoder, detector])
    for robot in ROBOTS:
        got = tensors.by_robot[robot]
        # Every tensor holds three consecutive scans of its own robot, in order: no FIFO is shared.
        assert [t.scan_seqs for t in got] == [(s - 2, s - 1, s) for s in range(2, SCANS_PER_ROBOT)]
        stamps = {s.seq: s.stamp_ns for s in replay[robot]}
        assert all(t.scan_stamps_ns == tuple(stamps[q] for q in t.scan_seqs) for t in got)
        dets = detections.by_robot[robot]
        assert [d.seq for d in dets] == list(range(2, SCANS_PER_ROBOT))
        assert all(d.scan_stamp_ns == stamps[d.seq] for d in dets)
        assert sum(len(d.detections) for d in dets) > 0


def test_detector_from_scans_with_two_workers_serves_in_order_and_forgets_silent_robots(
    replay: dict[str, list], ports: list[int]
) -> None:
    test_port, detector_port, _ = ports
    extra = ("--from-scans", "--threads", "1", "--workers", "2", "--forget-after", "2")
    detector = start_service("services.detector", detector_port, [test_port], *extra)
    detections = Collector(Detections)
    stats: list[dict[str, Any]] = []
    try:
        with open_session(ZenohSettings.loopback(test_port)) as session:
            subs = [
                session.declare_subscriber(wildcard_key(DETECTIONS), detections),
                session.declare_subscriber(
                    service_stats_key("detector"), lambda s: stats.append(json.loads(payload_bytes(s)))
                ),
            ]
            wait_for_subscriber(session, scan_key(ROBOTS[1]))
            prime_pipeline(session, replay[ROBOTS[1]], detections)
            publish_in_lockstep(session, {ROBOTS[1]: replay[ROBOTS[1]]}, detections)

            # Silent for longer than --forget-after: its FIFO and its publisher are gone, nothing leaks.
            def forgotten() -> bool:  # the probe robot and the one under test
                last = stats[-1] if stats else {}
                return last.get("robots") == 0 and last["encoder"]["forgotten_robots"] >= 2

            assert wait_for(forgotten, 30), stats[-1:]
            for sub in subs:
                sub.undeclare()
    finally:
        stop_all([detector])
    # Two inference workers, yet one robot's detections come out in order, one per tensor.
    assert [d.seq for d in detections.by_robot[ROBOTS[1]]] == list(range(2, SCANS_PER_ROBOT))


def test_detector_refuses_a_batch_its_model_cannot_run() -> None:
    fixed = SHIPPED_MODEL
    result = subprocess.run(
        [sys.executable, "-m", "services.detector", "--batch", "4", "--model", str(fixed), "--no-multicast"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 2
    assert "free batch axis" in result.stderr and SHIPPED_BATCH_MODEL.name in result.stderr
