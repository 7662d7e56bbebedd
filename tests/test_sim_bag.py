"""`triscan sim-bag`: a ROS 2 bag of simulated scans that triscan's replay reads back."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.cli import main
from services.sim_bag import DEFAULT_TOPIC, T0_NS
from services.simulator.defaults import SCAN_PERIOD_S

SCANS = 3


def test_sim_bag_writes_the_simulated_scans_at_the_simulator_rate(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from rosbags.highlevel import AnyReader

    from services.ros2_bridge.ros_types import LASER_SCAN, ros_types

    out = tmp_path / "drive"
    assert main(["sim-bag", "--scans", str(SCANS), "--out", str(out)]) == 0
    mcap = Path(capsys.readouterr().out.strip())
    assert mcap.parent == out and mcap.suffix == ".mcap"
    with AnyReader([out], default_typestore=ros_types("jazzy").store) as reader:
        assert [(c.topic, c.msgtype) for c in reader.connections] == [(DEFAULT_TOPIC, LASER_SCAN)]
        log_times = [timestamp for _, timestamp, _ in reader.messages()]
    assert log_times == [T0_NS + round(i * SCAN_PERIOD_S * 1e9) for i in range(SCANS)]
