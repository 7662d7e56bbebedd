"""Differential-drive kinematics and the waypoint controller used for the dataset's short motions."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from common.encoding import wrap_angle
from services.simulator.robot import (
    DiffDriveLimits,
    follow_waypoints,
    integrate,
)

LIMITS = DiffDriveLimits()


def speeds(poses: np.ndarray, period: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Chord speed and yaw rate between consecutive poses: lower bounds of what the robot drove."""
    step = np.diff(poses, axis=0)
    linear = np.hypot(step[:, 0], step[:, 1]) / period
    angular = np.abs((step[:, 2] + np.pi) % (2 * np.pi) - np.pi) / period
    return linear, angular


# --- integrate --------------------------------------------------------------------------------------


def test_integrate_straight_line() -> None:
    x, y, yaw = integrate((1.0, 2.0, 0.5), 0.2, 0.0, 3.0)
    assert (x, y, yaw) == pytest.approx(
        (1.0 + 0.6 * math.cos(0.5), 2.0 + 0.6 * math.sin(0.5), 0.5), abs=1e-12
    )


def test_integrate_pure_rotation_wraps_yaw() -> None:
    assert integrate((0.3, -0.4, 0.5), 0.0, 1.0, 1.0) == pytest.approx((0.3, -0.4, 1.5), abs=1e-12)
    x, y, yaw = integrate((0.0, 0.0, 3.0), 0.0, 0.5, 1.0)
    assert (x, y) == (0.0, 0.0)
    assert yaw == pytest.approx(3.5 - 2 * math.pi, abs=1e-12)


def test_integrate_arc_matches_closed_form() -> None:
    v, w, dt, yaw0 = 0.1, 0.5, 2.0, 0.7
    radius = v / w
    x, y, yaw = integrate((1.0, 1.0, yaw0), v, w, dt)
    expected_x = 1.0 + radius * (math.sin(yaw0 + w * dt) - math.sin(yaw0))
    expected_y = 1.0 - radius * (math.cos(yaw0 + w * dt) - math.cos(yaw0))
    assert (x, y, yaw) == pytest.approx((expected_x, expected_y, yaw0 + w * dt), abs=1e-12)
    # Clockwise too.
    x, y, yaw = integrate((0.0, 0.0, 0.0), 0.2, -1.0, 1.0)
    assert (x, y, yaw) == pytest.approx((0.2 * math.sin(1.0), -0.2 * (1 - math.cos(1.0)), -1.0), abs=1e-12)


def test_integrate_full_circle_returns_home_and_splits_exactly() -> None:
    period = 4.0
    assert integrate((0.5, 0.5, 0.2), 0.2, 2 * math.pi / period, period) == pytest.approx(
        (0.5, 0.5, 0.2), abs=1e-12
    )
    one = integrate((0.0, 0.0, 0.3), 0.15, 0.8, 1.0)
    half = integrate(integrate((0.0, 0.0, 0.3), 0.15, 0.8, 0.5), 0.15, 0.8, 0.5)
    assert one == pytest.approx(half, abs=1e-12)


def test_integrate_tiny_turn_rate_is_continuous() -> None:
    straight = integrate((0.0, 0.0, 0.4), 0.2, 0.0, 1.0)
    for w in (1e-9, 1e-6, 2e-6, 1e-5):
        x, y, _ = integrate((0.0, 0.0, 0.4), 0.2, w, 1.0)
        radius = 0.2 / w
        exact = (radius * (math.sin(0.4 + w) - math.sin(0.4)), -radius * (math.cos(0.4 + w) - math.cos(0.4)))
        assert (x, y) == pytest.approx(straight[:2], abs=5e-6)
        if w >= 1e-5:  # the textbook form is itself inaccurate below this
            assert (x, y) == pytest.approx(exact, abs=1e-9)


def test_wrap_angle_range() -> None:
    angles = [wrap_angle(a) for a in np.linspace(-20, 20, 401)]
    assert all(-math.pi <= a < math.pi for a in angles)
    assert wrap_angle(math.pi) == pytest.approx(-math.pi)
    assert wrap_angle(2 * math.pi + 0.1) == pytest.approx(0.1)


# --- follow_waypoints --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("start", "waypoints"),
    [
        ((0.0, 0.0, 0.0), [(0.2, 0.3), (0.0, 0.5)]),
        ((0.5, -0.5, math.pi / 4), [(0.3, -0.5), (0.6, -0.2)]),  # first waypoint behind: turn in place
        ((-1.0, 1.0, -3.0), [(-1.0, 1.25), (-1.2, 1.2)]),
    ],
)
def test_follow_waypoints_reaches_them_within_limits(
    start: tuple[float, float, float], waypoints: list[tuple[float, float]]
) -> None:
    poses = follow_waypoints(start, waypoints)
    assert poses.dtype == np.float64 and poses.shape[1] == 3
    assert tuple(poses[0]) == pytest.approx(start)
    assert 10 < len(poses) < 200  # a few seconds at 10 Hz, not the 30 s cap
    assert math.hypot(*(poses[-1, :2] - waypoints[-1])) <= 0.02
    # Intermediate waypoints are passed within 5 cm (plus one tick of travel between samples).
    for wx, wy in waypoints[:-1]:
        assert np.min(np.hypot(poses[:, 0] - wx, poses[:, 1] - wy)) <= 0.05 + 0.1 * 0.1
    linear, angular = speeds(poses)
    assert np.all(linear <= 0.1 + 1e-12)  # cruise speed
    assert np.all(angular <= 1.5 + 1e-12)  # turn rate
    assert np.all(np.abs(poses[:, 2]) <= math.pi)


def test_follow_waypoints_turns_in_place_when_facing_away() -> None:
    poses = follow_waypoints((0.0, 0.0, 0.0), [(-0.3, 0.0)])
    linear, angular = speeds(poses)
    # Heading error π: it spins at 1.5 rad/s without moving until the error is below 0.35 rad,
    # which takes (π − 0.35) / 1.5 ≈ 1.9 s, then drives off.
    first_move = int(np.flatnonzero(linear > 0.0)[0])
    assert first_move >= 18
    assert np.all(poses[: first_move + 1, :2] == 0.0)
    assert abs(wrap_angle(poses[first_move, 2] - math.pi)) <= 0.35 + 0.15
    assert np.max(angular) == pytest.approx(1.5, rel=1e-9)
    assert poses[-1, 0] == pytest.approx(-0.3, abs=0.02)


def test_follow_waypoints_slows_down_on_final_approach() -> None:
    poses = follow_waypoints((0.0, 0.0, 0.0), [(0.6, 0.0)])
    linear, _ = speeds(poses)
    assert linear[:20].max() == pytest.approx(0.1, rel=1e-6)  # cruising
    assert linear[-3:].max() < 0.06  # creeping in
    assert poses[-1, 0] == pytest.approx(0.6, abs=0.02)
    assert abs(poses[-1, 1]) < 1e-9  # a straight line stays straight


def test_follow_waypoints_never_exceeds_the_burger_limits() -> None:
    poses = follow_waypoints(
        (0.0, 0.0, 0.0), [(0.0, 1.0), (1.0, 1.0), (0.0, 0.0)], cruise_mps=1.0, turn_radps=10.0
    )
    linear, angular = speeds(poses)
    assert np.all(linear <= LIMITS.max_linear_mps + 1e-12)
    assert np.all(angular <= LIMITS.max_angular_radps + 1e-12)
    # The requested speeds are far above the limits, so the clipped ones must actually be reached.
    assert linear.max() > 0.21
    assert angular.max() > 2.8


def test_follow_waypoints_stops_at_the_time_cap(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="services.simulator.robot"):
        poses = follow_waypoints((0.0, 0.0, 0.0), [(3.0, 0.0)], max_duration_s=1.0)
    assert len(poses) == 11  # t = 0, 0.1, …, 1.0 s
    assert poses[-1, 0] == pytest.approx(0.1, abs=1e-9)
    assert "did not reach" in caplog.text


def test_follow_waypoints_is_deterministic_and_tick_spaced() -> None:
    a = follow_waypoints((0.1, 0.2, 1.0), [(0.4, 0.0), (0.2, -0.3)])
    b = follow_waypoints((0.1, 0.2, 1.0), [(0.4, 0.0), (0.2, -0.3)])
    assert a.tobytes() == b.tobytes()
    # Halving the scan period samples the same kind of path twice as densely.
    fine = follow_waypoints((0.1, 0.2, 1.0), [(0.4, 0.0), (0.2, -0.3)], scan_period_s=0.05, substeps=5)
    assert len(fine) == pytest.approx(2 * len(a), abs=2)
    np.testing.assert_allclose(fine[::2][: len(a) - 1], a[: len(a) - 1], atol=1e-12)


def test_follow_waypoints_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError):
        follow_waypoints((0.0, 0.0, 0.0), [])
    with pytest.raises(ValueError):
        follow_waypoints((0.0, 0.0, 0.0), [(1.0, 0.0)], substeps=0)


def test_limits_clip_commands_to_a_burger() -> None:
    limits = DiffDriveLimits()
    assert limits.clip(1.0, -10.0) == (0.22, -2.84)
    assert limits.clip(-1.0, 0.5) == (-0.22, 0.5)
    assert limits.clip(0.1, 0.3) == (0.1, 0.3)
