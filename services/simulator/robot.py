"""Kinematic TurtleBot3-Burger-like drive (README, "The simulated world"): no physics body, only poses.

The robot never collides with anything and has no collision shape, so LiDAR rays never hit it; scan
positions are sampled in free space by the scenario code, and the short motions between two nearby
waypoints stay there. Poses are ``(x, y, yaw)`` tuples in the world frame (REP-103: x forward,
y left, yaw counter-clockwise, radians, wrapped to [-π, π)).

Motion is integrated exactly along arcs rather than with Euler steps, so a pose sequence is a true
unicycle trajectory and its chord lengths never exceed ``v·dt`` (the speed limit test relies on that).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from common.encoding import wrap_angle

log = logging.getLogger(__name__)

Pose = tuple[float, float, float]  # (x m, y m, yaw rad)

TURN_IN_PLACE_RAD = 0.35  # above this heading error the robot stops and turns before driving
STEERING_GAIN = 2.0  # rad/s of turn rate per rad of heading error while driving
TURN_GAIN = 3.0  # same, while turning in place (saturates at turn_radps for most errors)
APPROACH_GAIN = 1.0  # m/s per m of distance on the final approach (slows inside 0.1 m at cruise 0.1)
MIN_APPROACH_MPS = 0.03  # keeps the final approach from crawling asymptotically


@dataclass(frozen=True)
class DiffDriveLimits:
    """Velocity limits of a TurtleBot3 Burger (ROBOTIS e-manual)."""

    max_linear_mps: float = 0.22
    max_angular_radps: float = 2.84

    def clip(self, v: float, w: float) -> tuple[float, float]:
        """Saturate a command; the simulator and the controller both go through here so neither can
        produce a trajectory a real Burger could not drive."""
        v_max, w_max = self.max_linear_mps, self.max_angular_radps
        return min(max(v, -v_max), v_max), min(max(w, -w_max), w_max)


def integrate(pose: Pose, v: float, w: float, dt: float) -> Pose:
    """Pose after driving at constant (v, w) for dt seconds, exactly (an arc, or a line when w = 0).

    Written as chord length ``v·dt·sin(φ/2)/(φ/2)`` along the mean heading (φ = w·dt), which equals the
    textbook ``v/w·(sin(θ+φ) − sin θ)`` form but stays accurate as w → 0 instead of dividing by it.
    """
    x, y, yaw = pose
    half_turn = 0.5 * w * dt
    # sin(h)/h is accurate in floating point down to the smallest h; only h = 0 needs its limit.
    chord = v * dt * (math.sin(half_turn) / half_turn if half_turn != 0.0 else 1.0)
    heading = yaw + half_turn
    return (x + chord * math.cos(heading), y + chord * math.sin(heading), wrap_angle(yaw + w * dt))


def _waypoint_command(
    pose: Pose,
    target: tuple[float, float],
    *,
    final: bool,
    cruise_mps: float,
    turn_radps: float,
) -> tuple[float, float]:
    """Turn-then-drive controller toward one waypoint; returns the unclipped (v, w).

    Turning in place above TURN_IN_PLACE_RAD keeps the robot from orbiting a waypoint inside its
    turning circle; below it, proportional steering bends the path smoothly. Only the last waypoint is
    approached slowly, so intermediate ones are driven through at cruise speed.
    """
    x, y, yaw = pose
    dx, dy = target[0] - x, target[1] - y
    error = wrap_angle(math.atan2(dy, dx) - yaw)
    if abs(error) > TURN_IN_PLACE_RAD:
        return 0.0, math.copysign(min(turn_radps, TURN_GAIN * abs(error)), error)
    v = cruise_mps
    if final:
        v = min(cruise_mps, max(MIN_APPROACH_MPS, APPROACH_GAIN * math.hypot(dx, dy)))
    return v, STEERING_GAIN * error


def follow_waypoints(
    start_pose: Pose,
    waypoints: Sequence[tuple[float, float]],
    *,
    cruise_mps: float = 0.1,
    turn_radps: float = 1.5,
    scan_period_s: float = 0.1,
    substeps: int = 10,
    max_duration_s: float = 30.0,
    waypoint_tolerance_m: float = 0.05,
    goal_tolerance_m: float = 0.02,
    limits: DiffDriveLimits | None = None,
) -> np.ndarray:
    """Drive through ``waypoints`` in order and return the pose at every scan tick, float64[T, 3].

    Row 0 is ``start_pose``; row i is the pose i·scan_period_s later. The robot is controlled
    ``substeps`` times per tick and stops for good once within ``goal_tolerance_m`` of the last
    waypoint; the rows end with the first tick at which it has stopped, or at ``max_duration_s``
    (logged as a warning) if it has not arrived. Intermediate waypoints count as passed within
    ``waypoint_tolerance_m``. Everything is deterministic: no randomness, fixed time steps.
    """
    if not waypoints:
        raise ValueError("follow_waypoints needs at least one waypoint")
    if scan_period_s <= 0.0 or substeps < 1 or max_duration_s < 0.0:
        raise ValueError("need scan_period_s > 0, substeps >= 1, max_duration_s >= 0")
    if cruise_mps <= 0.0 or turn_radps <= 0.0:
        raise ValueError("cruise_mps and turn_radps must be positive")
    limits = limits or DiffDriveLimits()
    dt = scan_period_s / substeps
    ticks = math.floor(max_duration_s / scan_period_s + 1e-9)
    pose: Pose = (float(start_pose[0]), float(start_pose[1]), wrap_angle(float(start_pose[2])))
    targets = [(float(wx), float(wy)) for wx, wy in waypoints]
    current = 0
    arrived = False
    poses = [pose]
    for _ in range(ticks):
        for _ in range(substeps):
            # Skip every waypoint already reached (several may be within tolerance of the same spot).
            while not arrived:
                final = current == len(targets) - 1
                tolerance = goal_tolerance_m if final else waypoint_tolerance_m
                if math.hypot(targets[current][0] - pose[0], targets[current][1] - pose[1]) > tolerance:
                    break
                if final:
                    arrived = True
                else:
                    current += 1
            if arrived:
                break
            v, w = _waypoint_command(
                pose,
                targets[current],
                final=current == len(targets) - 1,
                cruise_mps=cruise_mps,
                turn_radps=turn_radps,
            )
            pose = integrate(pose, *limits.clip(v, w), dt)
        poses.append(pose)
        if arrived:
            break
    if not arrived:
        log.warning(
            "robot did not reach waypoint %d of %d in %.1f s", current + 1, len(targets), max_duration_s
        )
    return np.asarray(poses, dtype=np.float64)
