"""LiDAR geometry, noise and rate (:class:`LidarSpec`) and the named profiles of the sensors robots carry.

Pure data, importable without PyBullet: the CLI lists the profiles and the encoder's stacking rule reads
their rates. The geometry follows ROS ``sensor_msgs/LaserScan``: beam i has bearing
``angle_min + i·angle_increment``, counter-clockwise from the sensor's forward axis (REP-103), so a
sensor with a narrower field of view starts at a negative ``angle_min`` and leaves the columns behind
it dark. Sources of each profile's figures are in docs/sensors.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Final

import numpy as np


@dataclass(frozen=True)
class LidarSpec:
    """Sensor geometry, rate and noise. Defaults: LDS-01 on a TurtleBot3 Burger, as the paper simulates it."""

    beams: int = 360
    angle_min: float = 0.0
    angle_increment: float = 2.0 * math.pi / 360
    range_min: float = 0.12
    range_max: float = 3.5
    noise_sigma_m: float = 0.015
    dropout_rate: float = 0.0  # share of beams that come back invalid (inf)
    spurious_rate: float = 0.0  # share of beams that come back short, at U(range_min, true range)
    mount_offset_x_m: float = -0.03  # the LDS-01 sits 3 cm behind the robot centre
    mount_height_m: float = 0.173
    rate_hz: float = 10.0  # scans per second

    def __post_init__(self) -> None:
        if self.beams < 1:
            raise ValueError(f"beams must be positive, got {self.beams}")
        if not 0.0 <= self.range_min < self.range_max:
            raise ValueError(f"need 0 <= range_min < range_max, got {self.range_min}, {self.range_max}")
        if self.noise_sigma_m < 0.0:
            raise ValueError(f"noise_sigma_m must be >= 0, got {self.noise_sigma_m}")
        for name in ("dropout_rate", "spurious_rate"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if not self.rate_hz > 0.0:
            raise ValueError(f"rate_hz must be positive, got {self.rate_hz}")

    @property
    def bearings_rad(self) -> np.ndarray:
        """float64[beams]: bearing of each beam in the sensor frame, CCW from forward."""
        return self.angle_min + np.arange(self.beams) * self.angle_increment

    @property
    def angle_max(self) -> float:
        """Bearing of the last beam, as ``LaserScan.angle_max`` defines it."""
        return self.angle_min + (self.beams - 1) * self.angle_increment

    @property
    def full_circle(self) -> bool:
        """Whether the beams cover all 360° (one increment closes the circle)."""
        return self.beams * self.angle_increment >= 2.0 * math.pi - 1e-9

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz


DEFAULT_SPEC: Final[LidarSpec] = LidarSpec()


def _fov(
    beams: int, step_deg: float, start_deg: float, rate_hz: float, range_m: tuple[float, float]
) -> LidarSpec:
    """A profile from a datasheet's terms: beam count, step, first bearing, rate and range limits."""
    return replace(
        DEFAULT_SPEC,
        beams=beams,
        angle_min=math.radians(start_deg),
        angle_increment=math.radians(step_deg),
        range_min=range_m[0],
        range_max=range_m[1],
        rate_hz=rate_hz,
        mount_offset_x_m=0.0,
    )


# Datasheet geometry of the sensors indoor robots carry (docs/sensors.md has the sources). The two
# "leg-tracker" profiles are the geometries of the real development recordings in shared/real.
PROFILES: Final[dict[str, LidarSpec]] = {
    "lds-01": DEFAULT_SPEC,
    "rplidar-a1": _fov(360, 1.0, 0.0, 5.5, (0.15, 12.0)),
    "rplidar-a2": _fov(800, 0.45, 0.0, 10.0, (0.15, 12.0)),
    "rplidar-a3": _fov(1600, 0.225, 0.0, 10.0, (0.2, 25.0)),
    "ydlidar-x4": _fov(720, 0.5, 0.0, 7.0, (0.12, 10.0)),
    "urg-04lx": _fov(683, 360 / 1024, -120.0, 10.0, (0.02, 5.6)),
    "ust-10lx": _fov(1081, 0.25, -135.0, 40.0, (0.06, 10.0)),
    "tim571": _fov(811, 1 / 3, -135.0, 15.0, (0.05, 25.0)),
    "leg-tracker-180": _fov(512, 360 / 1024, -90.0, 7.5, (0.02, 5.6)),
    "leg-tracker-270": _fov(768, 360 / 1024, -135.0, 7.5, (0.02, 11.0)),
}
DEFAULT_PROFILE: Final[str] = "lds-01"
RANDOM_PROFILE: Final[str] = "random"  # `--sensor random`: a profile drawn per scenario
SENSOR_CHOICES: Final[tuple[str, ...]] = (*PROFILES, RANDOM_PROFILE)


def profile(name: str) -> LidarSpec:
    """The named profile; an unknown name says which ones exist."""
    try:
        return PROFILES[name]
    except KeyError:
        raise ValueError(f"unknown sensor {name!r}: use one of {', '.join(SENSOR_CHOICES)}") from None


def check_sensor(name: str) -> str:
    """``name`` if it is a profile or ``random``, else the error :func:`profile` gives."""
    if name != RANDOM_PROFILE:
        profile(name)
    return name


def draw_profile(name: str, rng: np.random.Generator) -> tuple[str, LidarSpec]:
    """``name``'s profile, or for ``random`` one drawn uniformly from every named profile."""
    if name == RANDOM_PROFILE:
        name = list(PROFILES)[int(rng.integers(0, len(PROFILES)))]
    return name, profile(name)


def stack_stride(rate_hz: float, stack_period_s: float) -> int:
    """Every how many scans of a ``rate_hz`` sensor to stack so that stacked scans lie about
    ``stack_period_s`` apart: 4 for a 40 Hz sensor and a 0.1 s model, 1 for any sensor slower than
    the model's period (its scans are stacked as they come)."""
    return max(1, round(stack_period_s * rate_hz))
