"""``examples/publish_scans.py`` (a driver with only zenoh, msgpack and numpy) feeds a real detector, and
``examples/detect_in_process.py`` runs detection without Zenoh.

The example writes the Scan wire format by hand; this test decodes every scan it publishes with the
project's own validating decoder and checks that a ``services.detector --from-scans`` process answers
them, so the example cannot drift from the schema.

The example announces its robot's scans as the project's publishers do (a source token, then a lead
before the first scan), checked against :mod:`common.keys` and :func:`services.runtime.announce_lead_s`.
It waits for a subscriber before its first put. Connected to the test and the detector at
once it would start as soon as the test's subscriber matched, maybe before its link to the detector was
up, and its first scans would reach only the test. So it runs twice: once to the test alone (every scan
must decode), once to the detector alone (every scan from the third on must be answered).
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest

from bench.harness import start_loopback_service
from common.keys import DETECTIONS, SCAN, parse_source_key, topic_sources_key, wildcard_key
from common.messages import Detections, MessageError, Scan, decode_message
from common.transport import ZenohSettings, open_session, payload_bytes
from services.launcher import free_tcp_ports, stop_processes
from services.runtime import announce_lead_s
from tests.support.health import service_pids
from tests.support.waiting import wait_for

ROOT = Path(__file__).resolve().parents[1]
ROBOT = "exbot"
SCANS = 40
FURNITURE = {"chair", "box", "desk"}  # what the examples' stand-in room holds


def run_example(port: int, robot: str) -> None:
    example = subprocess.run(
        [
            sys.executable, str(ROOT / "examples" / "publish_scans.py"),
            "--connect", f"tcp/127.0.0.1:{port}", "--robot", robot, "--count", str(SCANS), "--rate", "20",
        ],
        capture_output=True, text=True, timeout=90,
    )  # fmt: skip
    assert example.returncode == 0, example.stdout + example.stderr


def test_detect_in_process_example_finds_the_stand_in_rooms_furniture() -> None:
    """Run as the README shows it; every line after the stack fills names what it found and where."""
    result = subprocess.run(
        [sys.executable, str(ROOT / "examples" / "detect_in_process.py")],
        capture_output=True, text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)},
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert [int(line.split()[0]) for line in lines] == list(range(2, 30))
    found = {word for line in lines for word in line.split() if word in FURNITURE}
    assert found == FURNITURE and all(" at (" in line and ") m" in line for line in lines[5:])


@pytest.mark.slow
@pytest.mark.integration
def test_publish_scans_example_writes_the_scan_wire_format() -> None:
    (test_port,) = free_tcp_ports(1)
    scans: list[Scan] = []
    bad: list[str] = []
    lock = threading.Lock()

    def on_scan(sample: Any) -> None:  # record only: assertions belong to the test thread
        try:
            scan = decode_message(payload_bytes(sample), Scan)
        except MessageError as exc:
            with lock:
                bad.append(str(exc))
            return
        with lock:
            scans.append(scan)

    sources: list[tuple[str, str, str]] = []

    def on_source(sample: Any) -> None:
        with lock:
            sources.append(parse_source_key(str(sample.key_expr)))

    with open_session(ZenohSettings.loopback(test_port)) as session:
        sub = session.declare_subscriber(wildcard_key(SCAN), on_scan)
        watch = session.liveliness().declare_subscriber(topic_sources_key(SCAN), on_source)
        run_example(test_port, ROBOT)
        assert wait_for(lambda: len(scans) + len(bad) >= SCANS, timeout=10), len(scans)
        assert wait_for(lambda: len(sources) == 2, timeout=10), sources  # declared, then undeclared
        watch.undeclare()
        sub.undeclare()
    with lock:
        assert [(topic, robot) for topic, robot, _ in sources] == [(SCAN, ROBOT)] * 2
        assert not bad, bad[:3]
        assert [s.seq for s in scans] == list(range(SCANS)) and {s.robot_id for s in scans} == {ROBOT}
        assert scans[0].ranges.shape == (360,) and scans[0].frame_id == "laser"
        assert all(s.odom is not None and s.odom.frame_id == "odom" for s in scans)  # the stand-in's pose


@pytest.mark.slow
@pytest.mark.integration
def test_publish_scans_example_gets_every_scan_answered_by_a_detector() -> None:
    test_port, detector_port = free_tcp_ports(2)
    # One process: with siblings, a robot's first scans may go by while the processes settle who owns it.
    detector = start_loopback_service(
        "services.detector", detector_port, [test_port], "--from-scans", "--detectors", "1"
    )
    answered: set[int] = set()
    classes: set[str] = set()
    lock = threading.Lock()

    def on_detections(sample: Any) -> None:
        message = decode_message(payload_bytes(sample), Detections)
        with lock:
            answered.add(message.seq)
            classes.update(d.class_name for d in message.detections)

    try:
        with open_session(ZenohSettings.loopback(test_port)) as session:
            sub = session.declare_subscriber(wildcard_key(DETECTIONS), on_detections)
            # Subscribed, and serving: its health token comes once it has settled which robots it serves.
            ready = lambda: detector_ready(session) and bool(service_pids(session, "detector"))  # noqa: E731
            assert wait_for(ready, timeout=60), "the detector never came up"
            run_example(detector_port, ROBOT)  # to the detector alone: its subscriber is the only match
            assert wait_for(lambda: SCANS - 1 in answered, timeout=20), sorted(answered)
            sub.undeclare()
    finally:
        stop_processes({"detector": detector}, grace_s=20)
    with lock:
        assert answered == set(range(2, SCANS))  # a tensor from the third scan on, every one answered
        assert classes == FURNITURE  # the stand-in room's furniture is found, and nothing else


def test_publish_scans_example_waits_the_project_s_lead_after_announcing() -> None:
    spec = importlib.util.spec_from_file_location("publish_scans", ROOT / "examples" / "publish_scans.py")
    assert spec is not None and spec.loader is not None
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    assert pytest.approx(announce_lead_s(SCAN)) == example.ANNOUNCE_LEAD_S


def detector_ready(session: Any) -> bool:
    """Some subscriber (the detector's) matches the example's key."""
    publisher = session.declare_publisher(f"triscan/{ROBOT}/scan")
    try:
        return bool(publisher.matching_status.matching)
    finally:
        publisher.undeclare()
