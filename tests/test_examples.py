"""``examples/publish_scans.py`` (a driver with only zenoh, msgpack and numpy) feeds a real detector.

The example writes the Scan wire format by hand; this test decodes every scan it publishes with the
project's own validating decoder and checks that a ``services.detector --from-scans`` process answers
them, so the example cannot drift from the schema.
"""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest

from bench.harness import start_loopback_service
from common.keys import DETECTIONS, SCAN, wildcard_key
from common.messages import Detections, MessageError, Scan, decode_message
from common.transport import ZenohSettings, open_session, payload_bytes
from services.launcher import free_tcp_ports, stop_processes
from tests.waiting import wait_for

pytestmark = [pytest.mark.slow, pytest.mark.integration]

ROOT = Path(__file__).resolve().parents[1]
ROBOT = "exbot"
SCANS = 40


def test_publish_scans_example_is_valid_wire_format_and_gets_detections() -> None:
    test_port, detector_port = free_tcp_ports(2)
    detector = start_loopback_service("services.detector", detector_port, [test_port], "--from-scans")
    scans: list[Scan] = []
    bad: list[str] = []
    answered: set[int] = set()
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

    def on_detections(sample: Any) -> None:
        message = decode_message(payload_bytes(sample), Detections)
        with lock:
            answered.add(message.seq)

    try:
        with open_session(ZenohSettings.loopback(test_port)) as session:
            subs = [
                session.declare_subscriber(wildcard_key(SCAN), on_scan),
                session.declare_subscriber(wildcard_key(DETECTIONS), on_detections),
            ]
            assert wait_for(lambda: detector_ready(session), timeout=60), "the detector never subscribed"
            example = subprocess.run(
                [
                    sys.executable, str(ROOT / "examples" / "publish_scans.py"),
                    "--connect", f"tcp/127.0.0.1:{detector_port}", "--connect", f"tcp/127.0.0.1:{test_port}",
                    "--robot", ROBOT, "--count", str(SCANS), "--rate", "20",
                ],
                capture_output=True, text=True, timeout=60,
            )  # fmt: skip
            assert example.returncode == 0, example.stdout + example.stderr
            # The example waits for a subscriber before its first put, but the test's own scan subscriber
            # can match before the detector's link is up: the first scans may reach only the test. From
            # the first answered scan on, every one must be answered, to the last.
            assert wait_for(lambda: SCANS - 1 in answered, timeout=20), sorted(answered)
            for sub in subs:
                sub.undeclare()
    finally:
        stop_processes({"detector": detector}, grace_s=20)
    with lock:
        assert not bad, bad[:3]
        assert [s.seq for s in scans] == list(range(SCANS)) and {s.robot_id for s in scans} == {ROBOT}
        assert scans[0].ranges.shape == (360,) and scans[0].frame_id == "laser"
        first = min(answered)
        assert answered == set(range(first, SCANS)), sorted(answered)  # no gap once the link is up
        assert len(answered) >= SCANS // 2, f"only {len(answered)} of {SCANS} scans answered"


def detector_ready(session: Any) -> bool:
    """Some subscriber (the detector's) matches the example's key."""
    publisher = session.declare_publisher(f"triscan/{ROBOT}/scan")
    try:
        return bool(publisher.matching_status.matching)
    finally:
        publisher.undeclare()
