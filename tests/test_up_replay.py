"""``triscan up --headless --replay BAG``: a recorded drive through encoder, detector and visualizer.

The bag holds real simulated scans (``triscan sim-bag``, written by rosbags' MCAP writer). The test
joins the loop through the launcher's endpoint, as any app would, and checks that the replayed robot's
scans come back as detections, that the run ends by itself when the bag does (exit 0, well before
``--duration``), and that the ``.rrd`` holds the robot's entities.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import pytest

from common.keys import DETECTIONS, wildcard_key
from common.messages import Detections, decode_message
from common.transport import ZenohSettings, open_session, payload_bytes
from services.launcher import free_tcp_ports

rerun_chunk = pytest.importorskip("rerun.chunk")
pytest.importorskip("pybullet")

pytestmark = [pytest.mark.slow, pytest.mark.integration]

ROOT = Path(__file__).resolve().parents[1]
SCANS = 40  # 4 s at 10 Hz
ROBOT = "bagbot"
DURATION_S = 120  # a ceiling only: the run must end when the bag does


def test_up_replays_a_bag_through_the_loop_and_ends_with_it(tmp_path: Path) -> None:
    from services.sim_bag import write_sim_bag

    bag = write_sim_bag(tmp_path / "drive", SCANS)
    rrd = tmp_path / "replay.rrd"
    (port,) = free_tcp_ports(1)
    command = [
        sys.executable, "-m", "services.cli", "up", "--headless", "--replay", str(bag), "--robot", ROBOT,
        "--duration", str(DURATION_S), "--rrd", str(rrd), "--listen", f"tcp/127.0.0.1:{port}",
    ]  # fmt: skip
    detections: dict[tuple[str, int], Detections] = {}
    lock = threading.Lock()

    def on_detections(sample: Any) -> None:  # record only: assertions belong to the test thread
        message = decode_message(payload_bytes(sample), Detections)
        with lock:
            detections[(message.robot_id, message.seq)] = message

    started = time.monotonic()
    launcher = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    try:
        with open_session(ZenohSettings.loopback(None, [port])) as session:
            sub = session.declare_subscriber(wildcard_key(DETECTIONS), on_detections)
            output, _ = launcher.communicate(timeout=DURATION_S + 60)
            sub.undeclare()
    finally:
        if launcher.poll() is None:
            launcher.kill()
    elapsed = time.monotonic() - started
    text = output.decode(errors="replace")
    assert launcher.returncode == 0, text[-4000:]
    assert "replay finished" in text and "reached: stopping" not in text, text[-4000:]
    assert elapsed < DURATION_S / 2, f"the run took {elapsed:.0f} s: it did not end with the bag"
    assert "restarting" not in text, text[-4000:]

    with lock:
        answered = {seq for robot, seq in detections if robot == ROBOT}
        robots = {robot for robot, _ in detections}
    answerable = set(range(2, SCANS))  # the encoder's FIFO gives a tensor from the third scan on
    assert robots == {ROBOT}
    assert answered <= answerable
    assert len(answered) >= 0.9 * len(answerable), f"{len(answered)}/{len(answerable)} scans answered"
    assert sum(len(m.detections) for m in detections.values()) > 0  # real scans: the model finds things

    per_robot: dict[str, set[str]] = defaultdict(set)
    reader = rerun_chunk.RrdReader(rrd)
    reader.store()  # a complete file: the footer was written at the clean stop
    for chunk in reader.stream():
        parts = chunk.entity_path.strip("/").split("/")
        if len(parts) >= 3 and parts[0] == "robots":
            per_robot[parts[1]].add("/".join(parts[2:]))
    assert set(per_robot) == {ROBOT}
    for expected in ("scan", "raster", "raster/detections", "map/detections"):
        assert expected in per_robot[ROBOT], (expected, sorted(per_robot[ROBOT]))
