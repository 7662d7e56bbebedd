"""The live simulator: its seeded core driven tick by tick, and the real service over a loopback Zenoh.

The core tests check what a consumer of the streams relies on (seq and stamp bookkeeping, ranges that
match the sensor description, truth that belongs to its scan) and what keeps the simulation honest (the
robot moves, never enters furniture or leaves the room, worlds change on schedule, seeds reproduce).
The end-to-end test runs ``python -m services.simulator`` as a separate process, exactly as deployed.
"""

from __future__ import annotations

import math
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from common.keys import scan_key, truth_key
from common.messages import GroundTruth, Scan, decode_message, encode_message
from common.model_spec import CLASS_NAMES
from common.transport import ZenohSettings, open_session, payload_bytes
from services.simulator.fleet import SCENARIOS_PER_ROBOT, SimulatedFleet
from services.simulator.lidar import DEFAULT_SPEC
from services.simulator.robot import DiffDriveLimits
from services.simulator.scenario import (
    BOX_CLEARANCE_M,
    DOORFRAME,
    LEG_CLEARANCE_M,
    ROBOT_GRID_HALF_M,
    Scenario,
    sample_scenario,
)

ROOT = Path(__file__).resolve().parents[1]
# The controller passes an intermediate waypoint within 5 cm and steers along gentle arcs, so the robot
# centre may stray a few centimetres from the straight grid segments it was planned on.
PATH_SLACK_M = 0.04


def clearance_violations(scenario: Scenario, xy: np.ndarray) -> list[str]:
    """Why a robot centre at ``xy`` would not be in free space (empty list: it is)."""
    problems = []
    if np.any(np.abs(xy) > ROBOT_GRID_HALF_M + PATH_SLACK_M):
        problems.append(f"{xy} is outside the free area of the room")
    for obj in scenario.objects:
        if obj.footprint.distance(xy) <= 0.0:
            problems.append(f"{xy} is inside the footprint of {CLASS_NAMES[obj.class_id]}")
        needed = (LEG_CLEARANCE_M if obj.has_legs else BOX_CLEARANCE_M) - PATH_SLACK_M
        for solid in obj.solid_rects():
            if solid.distance(xy) < needed:
                problems.append(f"{xy} is {solid.distance(xy):.3f} m from {CLASS_NAMES[obj.class_id]}")
    return problems


def test_scan_and_truth_fields_follow_the_sensor_and_the_tick() -> None:
    with SimulatedFleet(robots=1, seed=3, scenario_period_s=30.0, rate_hz=10.0) as fleet:
        ticks = [fleet.step(stamp_ns=1_000 + 7 * i) for i in range(5)]
    for i, [(scan, truth)] in enumerate(ticks):
        assert scan.robot_id == truth.robot_id == "robot0"
        assert scan.seq == truth.seq == i
        assert scan.stamp_ns == truth.stamp_ns == 1_000 + 7 * i
        assert scan.ranges.dtype == np.float32 and scan.ranges.shape == (DEFAULT_SPEC.beams,)
        assert (scan.angle_min, scan.angle_increment) == (
            DEFAULT_SPEC.angle_min,
            DEFAULT_SPEC.angle_increment,
        )
        assert (scan.range_min, scan.range_max) == (DEFAULT_SPEC.range_min, DEFAULT_SPEC.range_max)
        assert scan.frame_id == "laser"
        finite = scan.ranges[np.isfinite(scan.ranges)]
        assert len(finite) > DEFAULT_SPEC.beams // 2  # inside a 4 m room most beams hit a wall
        assert np.all((finite >= DEFAULT_SPEC.range_min) & (finite <= DEFAULT_SPEC.range_max))
        scenario = sample_scenario(truth.scenario_id, 3)  # (seed, scenario_id) names the world exactly
        assert [o.class_id for o in truth.objects] == [0, 1, 2, DOORFRAME]
        for obj in truth.objects:
            footprint = scenario.footprint_of(obj.class_id)
            np.testing.assert_allclose(obj.corners_xy, footprint.corners(), atol=1e-6)
            assert obj.center_xy == pytest.approx(footprint.center)
            assert obj.visible == (obj.box_px is not None)
        assert any(obj.visible for obj in truth.objects)
        x, y, yaw = truth.robot_pose
        assert truth.lidar_pose == pytest.approx((x - 0.03 * math.cos(yaw), y - 0.03 * math.sin(yaw), yaw))
        # Both survive the wire unchanged.
        assert decode_message(encode_message(scan), Scan) == scan
        assert decode_message(encode_message(truth), GroundTruth) == truth


def test_robot_wanders_within_free_space_and_within_its_limits() -> None:
    rate_hz = 10.0
    limits = DiffDriveLimits()
    with SimulatedFleet(robots=1, seed=5, scenario_period_s=40.0, rate_hz=rate_hz) as fleet:
        robot = fleet.robots[0]
        poses, scenario_ids = [], []
        for i in range(1_200):  # three worlds, 40 s each
            _, truth = fleet.step(stamp_ns=i)[0]
            poses.append(truth.robot_pose)
            scenario_ids.append(truth.scenario_id)
            problems = clearance_violations(robot.scenario, np.asarray(truth.robot_pose[:2]))
            assert not problems, f"tick {i}: {problems}"
    poses_arr, ids = np.asarray(poses), np.asarray(scenario_ids)
    assert len(set(scenario_ids)) == 3
    for scenario_id in set(scenario_ids):
        in_world = poses_arr[ids == scenario_id]
        chords = np.hypot(*np.diff(in_world[:, :2], axis=0).T)
        turns = np.abs((np.diff(in_world[:, 2]) + np.pi) % (2 * np.pi) - np.pi)
        assert chords.max() <= limits.max_linear_mps / rate_hz + 1e-9
        assert turns.max() <= limits.max_angular_radps / rate_hz + 1e-9
        assert chords.sum() > 1.0, "the robot should drive about, not sit still"
        assert np.ptp(in_world[:, 0]) + np.ptp(in_world[:, 1]) > 0.5, "it should reach new places"


def test_world_changes_on_schedule_and_seq_runs_on() -> None:
    with SimulatedFleet(robots=1, seed=2, scenario_period_s=1.0, rate_hz=10.0) as fleet:
        truths = [fleet.step(stamp_ns=i)[0][1] for i in range(25)]
    assert [t.seq for t in truths] == list(range(25))
    assert [t.scenario_id for t in truths] == [0] * 10 + [1] * 10 + [2] * 5
    # A new world places the robot afresh (a teleport, which the robot's own motion can never do).
    jump = np.hypot(*np.subtract(truths[10].robot_pose[:2], truths[9].robot_pose[:2]))
    assert jump > 0.0


def test_zero_period_keeps_the_first_world() -> None:
    with SimulatedFleet(robots=1, seed=2, scenario_period_s=0.0, rate_hz=50.0) as fleet:
        assert {fleet.step(stamp_ns=i)[0][1].scenario_id for i in range(60)} == {0}


def test_robots_are_independent() -> None:
    with SimulatedFleet(robots=2, seed=4, rate_hz=10.0, robot_id_prefix="bot") as fleet:
        assert fleet.robot_ids == ["bot0", "bot1"]
        for i in range(3):
            (scan0, truth0), (scan1, truth1) = fleet.step(stamp_ns=i)
            assert (scan0.robot_id, scan1.robot_id) == ("bot0", "bot1")
            assert scan0.seq == scan1.seq == i
        assert truth0.scenario_id == 0 and truth1.scenario_id == SCENARIOS_PER_ROBOT
        assert not np.array_equal(scan0.ranges, scan1.ranges)


def test_same_seed_same_streams_other_seed_other_streams() -> None:
    def payloads(seed: int) -> list[bytes]:
        with SimulatedFleet(robots=2, seed=seed, scenario_period_s=1.0, rate_hz=10.0) as fleet:
            return [encode_message(m) for i in range(15) for pair in fleet.step(stamp_ns=i) for m in pair]

    first = payloads(7)
    assert payloads(7) == first
    assert payloads(8) != first


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError):
        SimulatedFleet(robots=0)
    with pytest.raises(ValueError):
        SimulatedFleet(rate_hz=0.0)
    with pytest.raises(ValueError):
        SimulatedFleet(robot_id_prefix="a/b")


# --- end to end: the service process on a loopback Zenoh ------------------------------------------


def wait_until_listening(port: int, process: subprocess.Popen[Any], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise AssertionError(f"simulator exited early with {process.returncode}")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise AssertionError(f"simulator did not listen on port {port} within {timeout_s} s")


@pytest.mark.slow
@pytest.mark.integration
def test_service_publishes_scans_and_truth_over_zenoh(tmp_path: Path, free_port: Callable[[], int]) -> None:
    port = free_port()
    log_path = tmp_path / "simulator.log"
    command = [sys.executable, "-m", "services.simulator", "--robots", "2", "--rate", "20", "--duration", "3"]
    command += ["--listen", f"tcp/127.0.0.1:{port}", "--no-multicast"]
    received: dict[str, list[Any]] = {"scan": [], "truth": []}
    lock = threading.Lock()

    def on_sample(topic: str) -> Any:
        def callback(sample: Any) -> None:
            message = decode_message(payload_bytes(sample), Scan if topic == "scan" else GroundTruth)
            with lock:
                received[topic].append((str(sample.key_expr), message))

        return callback

    with log_path.open("w") as log_file:
        process = subprocess.Popen(command, cwd=ROOT, stdout=log_file, stderr=subprocess.STDOUT)
        try:
            wait_until_listening(port, process, timeout_s=30.0)
            with open_session(ZenohSettings.loopback(None, [port])) as session:
                subscribers = [
                    session.declare_subscriber("triscan/*/scan", on_sample("scan")),
                    session.declare_subscriber("triscan/*/truth", on_sample("truth")),
                ]
                returncode = process.wait(timeout=60.0)
                for subscriber in subscribers:
                    subscriber.undeclare()
        finally:
            if process.poll() is None:
                process.kill()
                process.wait()
    output = log_path.read_text()
    assert returncode == 0, output
    assert "scans published" in output, output
    with lock:
        scans, truths = list(received["scan"]), list(received["truth"])
    for robot_id in ("robot0", "robot1"):
        robot_scans = [m for key, m in scans if key == scan_key(robot_id)]
        robot_truths = [m for key, m in truths if key == truth_key(robot_id)]
        assert all(m.robot_id == robot_id for m in robot_scans + robot_truths)
        assert len(robot_scans) >= 5, f"{robot_id}: only {len(robot_scans)} scans arrived\n{output}"
        seqs = [m.seq for m in robot_scans]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), f"{robot_id}: gaps in {seqs}"
        stamps = [m.stamp_ns for m in robot_scans]
        assert stamps == sorted(stamps) and abs(stamps[-1] / 1e9 - time.time()) < 120.0
        scan_by_seq = {m.seq: m for m in robot_scans}
        assert robot_truths
        for truth in robot_truths:
            if truth.seq in scan_by_seq:
                assert truth.stamp_ns == scan_by_seq[truth.seq].stamp_ns
        assert {t.seq for t in robot_truths} & set(scan_by_seq)
