"""The simulator's defaults, importable without PyBullet (the CLI and the launcher read them)."""

from __future__ import annotations

from typing import Final

ROBOTS: Final[int] = 1  # robots the simulator (and `triscan up`) runs unless told otherwise
SCAN_RATE_HZ: Final[float] = 10.0  # the LDS-01's rate, and every scan period of the simulation
SCAN_PERIOD_S: Final[float] = 1.0 / SCAN_RATE_HZ
SIM_SEED: Final[int] = 1  # the shipped models were trained on seed 0's worlds: seed 1 shows them unseen ones
SCENARIO_PERIOD_S: Final[float] = 30.0  # seconds of simulated time per world in the live simulator
ROBOT_ID_PREFIX: Final[str] = "robot"  # robot ids are robot0, robot1, ...
SIM_PEOPLE: Final[int] = 3  # people walking about each live robot's room: the loop shows them by default
