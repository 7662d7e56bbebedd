"""``examples/subscribe_tracks.py`` (only zenoh and msgpack) reads the tracker's real wire format."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from common.keys import tracks_key
from common.messages import encode_message
from common.transport import ZenohSettings, open_session
from services.launcher import free_tcp_ports
from services.tracker.core import TrackerCore
from tests.test_tracker_core import drive

pytestmark = [pytest.mark.slow, pytest.mark.integration]

ROOT = Path(__file__).resolve().parents[1]


def test_subscribe_tracks_example_prints_confirmed_tracks_with_ids_and_velocities() -> None:
    frames = drive(TrackerCore(), 10)  # a still chair and a walking person, seen from a moving robot
    (port,) = free_tcp_ports(1)
    with open_session(ZenohSettings.loopback(port)) as session:
        example = subprocess.Popen(
            [sys.executable, str(ROOT / "examples" / "subscribe_tracks.py"),
             "--connect", f"tcp/127.0.0.1:{port}", "--count", "3"],
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        )  # fmt: skip
        publisher = session.declare_publisher(tracks_key("r1"))
        deadline = time.monotonic() + 60
        while example.poll() is None and time.monotonic() < deadline:
            for tracks in frames[-3:]:
                publisher.put(encode_message(tracks))
            time.sleep(0.2)
        out, _ = example.communicate(timeout=10)
    assert example.returncode == 0, out
    chair = next(t for t in frames[-1].tracks if t.class_name == "chair")
    lines = [line for line in out.splitlines() if line.startswith("r1 #")]
    assert len(lines) == 3, out
    assert f"#{chair.track_id} chair confirmed" in lines[-1] and "[odom]" in lines[-1]
    assert "person confirmed" in lines[-1] and "m/s" in lines[-1]
