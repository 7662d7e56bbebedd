"""The live simulator's core: robots that drive around their own simulated rooms and scan, tick by tick.

The offline data set (``training/dataset.py``) drives short two-waypoint motions from sampled
positions; a live stream instead needs a robot that keeps moving for as long as the service runs. Each
:class:`SimulatedRobot` therefore owns one PyBullet :class:`World`, one scenario at a time and its own
random streams, and wanders: it picks a random free goal, plans a route to it over the scenario's free
grid (``free_grid_cells``, the same free space the data set samples from), drives it with the data
set's waypoint controller (``follow_waypoints``) and, on arrival, picks the next goal. Every
``scenario_period_s`` of *simulated* time it moves to a new world. Each tick yields the ``Scan`` the
encoder consumes and the ``GroundTruth`` (labels of README "Labels") a visualiser or evaluator compares with.

This module knows nothing about Zenoh or wall-clock time: the caller passes the stamp, so the same seed
gives the same scans whatever the host's speed, and tests can step it as fast as they like.
"""

from __future__ import annotations

import heapq
import logging
import math
from collections import deque
from types import TracebackType

import numpy as np

from common.encoding import PADDINGS, R_MAX_M, Padding, check_raster_yaw
from common.keys import validate_robot_id
from common.messages import GroundTruth, Odometry, Scan, TruthObject
from common.model_spec import CLASS_NAMES
from services.simulator.defaults import ROBOT_ID_PREFIX, SCAN_RATE_HZ, SCENARIO_PERIOD_S, SIM_SEED
from services.simulator.labels import Box, ObjectLabel, label_scan
from services.simulator.lidar import DEFAULT_SPEC, Lidar, LidarSpec
from services.simulator.people import Person, sample_live_people
from services.simulator.robot import Pose, follow_waypoints
from services.simulator.scenario import (
    PERSON,
    ROBOT_GRID_HALF_M,
    ROBOT_GRID_STEP_M,
    Rect,
    Scenario,
    free_grid_cells,
    sample_robot_positions,
    sample_scenario,
)
from services.simulator.world import World

log = logging.getLogger(__name__)

# Scenario ``robot_index * SCENARIOS_PER_ROBOT + k`` is robot's k-th world, so (seed, scenario_id) in a
# GroundTruth message names the world exactly (``sample_scenario(scenario_id, seed)``) and no two
# robots of a fleet ever share a world. At the default 30 s period a robot needs a year to run out.
SCENARIOS_PER_ROBOT = 1_000_000
HEADINGS_DEG = np.arange(0, 360, 45)  # start headings k·45°, as the data set (README, "The simulated world")
MIN_GOAL_DISTANCE_M = 0.5  # goals nearer than this make the robot spin more than it drives
CRUISE_MPS = 0.1  # the data set's motion speed, so live scans look like the training scans
TURN_RADPS = 1.5
WAYPOINT_TOLERANCE_M = 0.05
FRAME_ID = "laser"
PEOPLE_HORIZON_S = 60.0  # how far ahead people are planned when the world never changes
PERSON_FOOTPRINT_M = 0.4  # the square a person's truth object draws, around the midpoint of the legs
# 8-connected grid moves; a diagonal needs both orthogonal neighbours free so a route never cuts a corner.
_MOVES: tuple[tuple[int, int, float], ...] = tuple(
    (di, dj, math.hypot(di, dj)) for di in (-1, 0, 1) for dj in (-1, 0, 1) if (di, dj) != (0, 0)
)


class FreeGrid:
    """The scenario's free cells (``free_grid_cells``) as a boolean grid, with shortest routes over it.

    Consecutive route cells are neighbours on the 0.1 m grid, i.e. at most 0.14 m apart. A segment that
    short between two free cells cannot reach furniture: every free cell keeps 0.22 m from each leg and
    0.175 m from the box, and a chair or desk footprint (≥ 0.32 m across) can only be clipped at a
    corner, where a leg stands. Driving the route therefore never crosses an obstacle.
    """

    def __init__(self, scenario: Scenario) -> None:
        self.cells = free_grid_cells(scenario)  # float64[K, 2]
        self.size = round(2 * ROBOT_GRID_HALF_M / ROBOT_GRID_STEP_M) + 1
        ij = self._index_of(self.cells)
        self.free = np.zeros((self.size, self.size), dtype=bool)
        self.free[ij[:, 0], ij[:, 1]] = True

    def _index_of(self, points: np.ndarray) -> np.ndarray:
        scaled = (np.asarray(points, dtype=np.float64) + ROBOT_GRID_HALF_M) / ROBOT_GRID_STEP_M
        return np.clip(np.rint(scaled).astype(np.int64), 0, self.size - 1)

    def point_of(self, cell: tuple[int, int]) -> tuple[float, float]:
        return (
            cell[0] * ROBOT_GRID_STEP_M - ROBOT_GRID_HALF_M,
            cell[1] * ROBOT_GRID_STEP_M - ROBOT_GRID_HALF_M,
        )

    def nearest_free_cell(self, xy: tuple[float, float]) -> tuple[int, int] | None:
        if len(self.cells) == 0:
            return None
        nearest = self.cells[int(np.argmin(np.hypot(*(self.cells - np.asarray(xy)).T)))]
        i, j = self._index_of(nearest)
        return int(i), int(j)

    def _passable(self, i: int, j: int, di: int, dj: int) -> bool:
        ni, nj = i + di, j + dj
        if not (0 <= ni < self.size and 0 <= nj < self.size and self.free[ni, nj]):
            return False
        return di == 0 or dj == 0 or bool(self.free[i + di, j] and self.free[i, j + dj])

    def routes_from(
        self, start: tuple[int, int]
    ) -> tuple[np.ndarray, dict[tuple[int, int], tuple[int, int]]]:
        """Dijkstra from ``start``: route length (m, inf if unreachable) per cell and each cell's parent."""
        distance = np.full((self.size, self.size), np.inf)
        distance[start] = 0.0
        parent: dict[tuple[int, int], tuple[int, int]] = {}
        queue: list[tuple[float, tuple[int, int]]] = [(0.0, start)]
        while queue:
            d, (i, j) = heapq.heappop(queue)
            if d > distance[i, j]:
                continue
            for di, dj, step in _MOVES:
                if not self._passable(i, j, di, dj):
                    continue
                nd = d + step * ROBOT_GRID_STEP_M
                if nd < distance[i + di, j + dj] - 1e-12:
                    distance[i + di, j + dj] = nd
                    parent[(i + di, j + dj)] = (i, j)
                    heapq.heappush(queue, (nd, (i + di, j + dj)))
        return distance, parent


def _route_cells(
    parent: dict[tuple[int, int], tuple[int, int]], start: tuple[int, int], goal: tuple[int, int]
) -> list[tuple[int, int]]:
    """The cells from ``start`` (excluded) to ``goal``, keeping only the corners of the route.

    Cells in the middle of a straight run are dropped: the path is the same, and the controller then
    drives each straight run at cruise speed instead of aiming at every cell.
    """
    cells = [goal]
    while cells[-1] != start:
        cells.append(parent[cells[-1]])
    cells.reverse()  # start ... goal
    corners = []
    for before, here, after in zip(cells, cells[1:], cells[2:], strict=False):
        if (here[0] - before[0], here[1] - before[1]) != (after[0] - here[0], after[1] - here[1]):
            corners.append(here)
    corners.append(goal)
    return corners


def _whole_box(boxes: tuple[Box, ...]) -> Box | None:
    """The one box a truth object carries: with ``wrap`` padding an object near the seam has two
    copies, the widest of which shows it whole (the first one on a tie)."""
    if not boxes:
        return None
    return max(boxes, key=lambda box: box[2] - box[0])


class SimulatedRobot:
    """One robot wandering in its own sequence of scenarios; :meth:`step` scans and moves one tick.

    Random streams, all derived from ``(seed, scenario index)`` so a world always plays out the same:
    ``[seed, index, 3]`` start pose and goals, ``[seed, index, 4]`` LiDAR noise, ``[seed, index, 7]``
    people (the data set uses streams 1, 2, 5 and 6 of the same scenario, so the live stream never
    replays a training motion). With ``people`` > 0, that many people walk about each world: they are
    planned with the robot's route for the world's whole period, so they keep clear of the robot.
    """

    def __init__(
        self,
        robot_id: str,
        robot_index: int,
        seed: int,
        rate_hz: float,
        ticks_per_scenario: int | None,
        padding: Padding = "zero",
        spec: LidarSpec = DEFAULT_SPEC,
        people: int = 0,
        raster_yaw_deg: float = 0.0,
    ) -> None:
        self.robot_id = validate_robot_id(robot_id)
        # Truth boxes are given in the raster of the model the loop runs: turned by its yaw.
        self.raster_yaw_deg = check_raster_yaw(raster_yaw_deg)
        if people < 0:
            raise ValueError(f"people must be >= 0, got {people}")
        self.people_count = people
        self.people: tuple[Person, ...] = ()
        self._people_origin_seq = 0
        if robot_index < 0:
            raise ValueError(f"robot_index must be >= 0, got {robot_index}")
        if rate_hz <= 0.0:
            raise ValueError(f"rate_hz must be positive, got {rate_hz}")
        if ticks_per_scenario is not None and ticks_per_scenario < 1:
            raise ValueError(f"ticks_per_scenario must be >= 1 or None, got {ticks_per_scenario}")
        if padding not in PADDINGS:
            raise ValueError(f"padding must be one of {PADDINGS}, got {padding!r}")
        self.robot_index = robot_index
        self.seed = seed
        self.period_s = 1.0 / rate_hz
        self.ticks_per_scenario = ticks_per_scenario
        self.padding: Padding = padding
        self.spec = spec
        self._bearings_rad = spec.bearings_rad
        self.seq = 0  # seq of the next scan; never reset, not even by a scenario change
        self.scenario_number = 0
        self._planned: deque[Pose] = deque()  # poses of the coming ticks, oldest first
        self._pose: Pose = (0.0, 0.0, 0.0)
        self.world = World(None)
        try:
            self._enter_scenario(0)
        except Exception:
            self.world.close()
            raise

    @property
    def pose(self) -> Pose:
        """The robot's pose (x, y, yaw in the world frame) at its next scan."""
        return self._pose

    @property
    def scenario(self) -> Scenario:
        assert self.world.scenario is not None
        return self.world.scenario

    def close(self) -> None:
        self.world.close()

    def _enter_scenario(self, k: int) -> None:
        """Load this robot's k-th world and drop the robot on a random free cell, heading k·45°."""
        index = self.robot_index * SCENARIOS_PER_ROBOT + k
        scenario = sample_scenario(index, self.seed)
        self.world.load(scenario)
        self.grid = FreeGrid(scenario)
        self.lidar = Lidar(
            self.world, self.spec, rng=np.random.default_rng(np.random.SeedSequence([self.seed, index, 4]))
        )
        self.rng = np.random.default_rng(np.random.SeedSequence([self.seed, index, 3]))
        start = sample_robot_positions(scenario, 1, self.rng)
        if len(start) == 0:  # pragma: no cover - sample_scenario always leaves free space
            raise RuntimeError(f"scenario {index} has no free cell for the robot")
        heading = math.radians(float(self.rng.choice(HEADINGS_DEG)))
        self._pose = (float(start[0, 0]), float(start[0, 1]), heading)
        self._planned.clear()
        self.scenario_number = k
        self.people = ()
        if self.people_count > 0:
            self._people_rng = np.random.default_rng(np.random.SeedSequence([self.seed, index, 7]))
            self._plan_people()
        log.debug("%s: scenario %d, start pose %s", self.robot_id, index, self._pose)

    def _plan_people(self) -> None:
        """Plan the robot's route for the coming period, then people who walk about clear of it."""
        ticks = self.ticks_per_scenario or round(PEOPLE_HORIZON_S / self.period_s)
        pose = self._planned[-1] if self._planned else self._pose
        while len(self._planned) < ticks:
            more = self._plan_next_goal(pose)
            if not more:
                break
            self._planned.extend(more)
            pose = more[-1]
        route = np.array([self._pose, *self._planned])
        self.people = tuple(
            sample_live_people(
                self.scenario,
                route,
                self.period_s,
                ticks * self.period_s,
                self.people_count,
                self._people_rng,
            )
        )
        self._people_origin_seq = self.seq
        self._people_until_seq = self.seq + ticks

    def _plan_next_goal(self, pose: Pose | None = None) -> deque[Pose]:
        """Poses of the ticks that drive from ``pose`` (here by default) to a new random reachable goal
        (empty: stay put)."""
        pose = self._pose if pose is None else pose
        start = self.grid.nearest_free_cell(pose[:2])
        if start is None:  # pragma: no cover - see _enter_scenario
            return deque()
        distance, parent = self.grid.routes_from(start)
        reachable = np.argwhere(np.isfinite(distance) & (distance > 0.0))
        if len(reachable) == 0:
            log.debug("%s: no reachable free cell from %s, staying put", self.robot_id, start)
            return deque()
        points = (reachable * ROBOT_GRID_STEP_M - ROBOT_GRID_HALF_M) - np.asarray(pose[:2])
        far = reachable[np.hypot(points[:, 0], points[:, 1]) >= MIN_GOAL_DISTANCE_M]
        candidates = far if len(far) else reachable
        goal_i, goal_j = candidates[self.rng.integers(0, len(candidates))]
        goal = (int(goal_i), int(goal_j))
        waypoints = [self.grid.point_of(cell) for cell in _route_cells(parent, start, goal)]
        start_xy = self.grid.point_of(start)
        if math.hypot(start_xy[0] - pose[0], start_xy[1] - pose[1]) > WAYPOINT_TOLERANCE_M:
            waypoints.insert(0, start_xy)  # back onto the grid first: the hops are only safe between cells
        # Generous: the route at cruise speed, plus a half turn in place at every corner.
        budget_s = 1.5 * float(distance[goal]) / CRUISE_MPS + len(waypoints) * math.pi / TURN_RADPS + 5.0
        poses = follow_waypoints(
            pose,
            waypoints,
            cruise_mps=CRUISE_MPS,
            turn_radps=TURN_RADPS,
            scan_period_s=self.period_s,
            max_duration_s=budget_s,
            waypoint_tolerance_m=WAYPOINT_TOLERANCE_M,
        )
        return deque((float(x), float(y), float(yaw)) for x, y, yaw in poses[1:])

    def _advance(self) -> None:
        if not self._planned:
            self._planned = self._plan_next_goal()
        if self._planned:
            self._pose = self._planned.popleft()

    def step(self, stamp_ns: int) -> tuple[Scan, GroundTruth]:
        """Scan from the current pose, label it, then drive one tick (1/rate_hz seconds)."""
        if self.ticks_per_scenario is not None:
            k = self.seq // self.ticks_per_scenario
            if k != self.scenario_number:
                self._enter_scenario(k)
        if self.people_count > 0 and self.seq >= self._people_until_seq:
            self._plan_people()  # a world that never changes gets people for the next period
        t_s = (self.seq - self._people_origin_seq) * self.period_s
        reading = self.lidar.scan(self._pose, t_s=t_s, people=self.people)
        labels = label_scan(
            self.scenario,
            reading.lidar_pose,
            self._bearings_rad,
            reading.true_ranges,
            reading.hit_object,
            min(self.spec.range_max, R_MAX_M),
            self.padding,
            reading.people_legs,
            self.raster_yaw_deg,
        )
        people = iter(range(len(self.people)))
        scan = Scan(
            robot_id=self.robot_id,
            seq=self.seq,
            stamp_ns=stamp_ns,
            angle_min=self.spec.angle_min,
            angle_increment=self.spec.angle_increment,
            range_min=self.spec.range_min,
            range_max=self.spec.range_max,
            ranges=reading.ranges,
            frame_id=FRAME_ID,
            odom=Odometry(x_m=self._pose[0], y_m=self._pose[1], yaw_rad=self._pose[2], stamp_ns=stamp_ns),
        )
        truth = GroundTruth(
            robot_id=self.robot_id,
            seq=self.seq,
            stamp_ns=stamp_ns,
            scenario_id=self.scenario.index,
            robot_pose=self._pose,
            lidar_pose=reading.lidar_pose,
            objects=[
                self._person_object(label, next(people), t_s)
                if label.class_id == PERSON
                else self._truth_object(label)
                for label in labels
            ],
        )
        self.seq += 1
        self._advance()
        return scan, truth

    def _truth_object(self, label: ObjectLabel) -> TruthObject:
        footprint = self.scenario.footprint_of(label.class_id)
        box = _whole_box(label.boxes_px) if label.visible else None
        return TruthObject(
            class_id=label.class_id,
            class_name=CLASS_NAMES[label.class_id],
            corners_xy=footprint.corners().astype(np.float32),
            center_xy=(float(footprint.center[0]), float(footprint.center[1])),
            yaw_rad=float(footprint.yaw),
            visible=box is not None,
            box_px=box,
        )

    def _person_object(self, label: ObjectLabel, index: int, t_s: float) -> TruthObject:
        """A person's truth: the midpoint of the legs, facing the way they walk."""
        person = self.people[index]
        centre = person.centre(t_s)
        heading = float(person._at(t_s)[1])
        square = Rect(centre, (PERSON_FOOTPRINT_M, PERSON_FOOTPRINT_M), heading)
        box = _whole_box(label.boxes_px) if label.visible else None
        return TruthObject(
            class_id=PERSON,
            class_name=CLASS_NAMES[PERSON],
            corners_xy=square.corners().astype(np.float32),
            center_xy=centre,
            yaw_rad=heading,
            visible=box is not None,
            box_px=box,
        )


class SimulatedFleet:
    """``robots`` independent robots (``robot0``, ``robot1``, …) stepped together, one world each.

    ``scenario_period_s`` ≤ 0 keeps every robot in its first world for good.
    """

    def __init__(
        self,
        robots: int = 1,
        seed: int = SIM_SEED,
        scenario_period_s: float = SCENARIO_PERIOD_S,
        rate_hz: float = SCAN_RATE_HZ,
        robot_id_prefix: str = ROBOT_ID_PREFIX,
        padding: Padding = "zero",
        spec: LidarSpec = DEFAULT_SPEC,
        people: int = 0,
        raster_yaw_deg: float = 0.0,
    ) -> None:
        if robots < 1:
            raise ValueError(f"robots must be >= 1, got {robots}")
        if rate_hz <= 0.0 or not math.isfinite(rate_hz):
            raise ValueError(f"rate_hz must be positive, got {rate_hz}")
        self.rate_hz = rate_hz
        self.seed = seed
        ticks = None if scenario_period_s <= 0.0 else max(1, round(scenario_period_s * rate_hz))
        self.robots: list[SimulatedRobot] = []
        try:
            for index in range(robots):
                robot_id = validate_robot_id(f"{robot_id_prefix}{index}")
                self.robots.append(
                    SimulatedRobot(
                        robot_id, index, seed, rate_hz, ticks, padding, spec, people, raster_yaw_deg
                    )
                )
        except Exception:
            self.close()
            raise

    @property
    def robot_ids(self) -> list[str]:
        return [robot.robot_id for robot in self.robots]

    def step(self, stamp_ns: int) -> list[tuple[Scan, GroundTruth]]:
        """One tick of every robot, in robot order; all scans of a tick carry ``stamp_ns``."""
        return [robot.step(stamp_ns) for robot in self.robots]

    def close(self) -> None:
        for robot in self.robots:
            robot.close()

    def __enter__(self) -> SimulatedFleet:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
