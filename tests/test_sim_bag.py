"""`triscan sim-bag`: a ROS 2 bag of simulated scans that triscan's replay reads back."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.cli import main
from services.sim_bag import DEFAULT_TOPIC, RECORDED_SCANS_ENV, T0_NS, recorded_scans
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


def test_recorded_scans_are_read_back_from_the_folder_that_names_them_without_simulating(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(RECORDED_SCANS_ENV, str(tmp_path))
    simulated = recorded_scans(4, seed=3)
    assert len(list(tmp_path.iterdir())) == 1

    import services.simulator.fleet as fleet

    def no_simulator(*args: object, **kwargs: object) -> None:
        raise AssertionError("the recorded file should have been read")

    monkeypatch.setattr(fleet, "SimulatedFleet", no_simulator)
    assert recorded_scans(4, seed=3) == simulated
    with pytest.raises(AssertionError, match="recorded file"):
        recorded_scans(4, seed=4)  # other arguments: another file, so it simulates
