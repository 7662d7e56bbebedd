"""Simulated people at scan height: two legs with a walking gait, on paths through the room and the door.

A 2D LiDAR at about 0.17 m sees a person as two leg cross-sections (docs/people.md has the sources of
the sizes and the gait used here):

* each leg is a circle of 0.055–0.08 m radius (lower calf in trousers: the width real recordings show
  at scan height, docs/people.md); wide trousers and skirts widen it, up to 0.10 m;
* the legs stand ``step_width_m`` apart across the walking direction;
* walking at speed v, the cadence is ``CADENCE_BASE + CADENCE_GAIN·v`` steps/s, so a step is
  ``v / cadence`` long: 0.64 m and 2.0 steps/s at 1.3 m/s, shrinking to nothing as v → 0;
* each leg is planted for the stance share of the gait cycle (it stays put in the world while the
  body moves over it) and swings forward for the rest, the two legs half a cycle apart. A standing
  person's legs are still, side by side.

People follow polylines at their own speed, with smoothed turns and speed changes, may stop and stand
(beside the desk or the chair, say) and come in pairs and small groups. Some walk past outside the
room, in the passage between its door wall and the enclosure, where the robot sees them only through
the doorway: a person beyond a gap in a near wall is still a person. Like clutter they are
ray-cast in closed form rather than added to the PyBullet world: they move with every scan, and
PyBullet leaks memory on every body removed. Unlike clutter they are labelled (class ``person``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from services.simulator.clutter import ray_circle_distances
from services.simulator.scenario import OUTER_HALF_M, ROOM_HALF_M, WALL_THICKNESS_M, Scenario

PERSON_OBJECT_BASE = 100  # hit_object of leg j of person k: BASE + 2k + j (furniture 0.., wall -1, ...)
CADENCE_BASE = 1.0  # steps/s as v → 0
CADENCE_GAIN = 0.8  # steps/s per m/s
STANCE_SHARE = 0.6  # of the gait cycle, a leg on the ground
MAX_SPEED_MPS = 1.6
TIME_STEP_S = 0.02  # trajectories are sampled this finely and interpolated
SMOOTHING_S = 0.5  # window of the moving average that rounds corners and ramps speed
FURNITURE_CLEARANCE_M = 0.3  # a person's centre keeps this far from every footprint
ROBOT_CLEARANCE_M = 0.5  # and from the robot at the same instant
PEOPLE_CLEARANCE_M = 0.45  # and from everyone else not in their group
INSIDE_MARGIN_M = 0.25  # centres inside the room stay this far inside the walls
OUTSIDE_DEPTH_M = 0.8  # how far beyond the door a path may start or end
# Centres in the passage outside the door wall keep this far from the wall and from the enclosure.
PASSAGE_CLEARANCE_M = 0.3
PLACEMENT_TRIES = 30
BEHAVIOURS = ("cross", "door", "visit", "stand", "group", "pass")
BEHAVIOUR_SHARES = (0.25, 0.2, 0.15, 0.1, 0.15, 0.15)  # most people a robot meets are passing by


def leg_object(person: int, leg: int) -> int:
    """The ``hit_object`` value of a beam that stopped on ``leg`` (0 or 1) of person ``person``."""
    return PERSON_OBJECT_BASE + 2 * person + leg


@dataclass(frozen=True)
class Person:
    """One person over a robot motion: their centre's path sampled every ``TIME_STEP_S`` and their legs.

    ``phase`` is the gait cycle count integrated over the path, so the legs' swing follows the speed
    of the moment; ``leg_radius_m`` and ``step_width_m`` are this person's build.
    """

    centres: np.ndarray  # float64[T, 2]
    headings: np.ndarray  # float64[T]
    speeds: np.ndarray  # float64[T]
    phase: np.ndarray  # float64[T], gait cycles since t = 0
    leg_radius_m: float
    step_width_m: float

    def _at(self, t_s: float) -> tuple[np.ndarray, float, float, float]:
        i = min(max(t_s / TIME_STEP_S, 0.0), len(self.speeds) - 1.0)
        lo = math.floor(i)
        hi = min(lo + 1, len(self.speeds) - 1)
        w = i - lo
        centre = (1 - w) * self.centres[lo] + w * self.centres[hi]
        dh = (self.headings[hi] - self.headings[lo] + math.pi) % (2 * math.pi) - math.pi
        heading = float(self.headings[lo] + w * dh)
        speed = float((1 - w) * self.speeds[lo] + w * self.speeds[hi])
        phase = float((1 - w) * self.phase[lo] + w * self.phase[hi])
        return centre, heading, speed, phase

    def centre(self, t_s: float) -> tuple[float, float]:
        """The midpoint between the legs at ``t_s``: the person's position in the truth."""
        c, _, _, _ = self._at(t_s)
        return float(c[0]), float(c[1])

    def legs(self, t_s: float) -> list[tuple[float, float, float]]:
        """The two leg circles (x, y, radius) at ``t_s``."""
        centre, heading, speed, phase = self._at(t_s)
        step = speed / (CADENCE_BASE + CADENCE_GAIN * speed)
        forward = np.array([math.cos(heading), math.sin(heading)])
        left = np.array([-forward[1], forward[0]])
        out = []
        for leg, side in ((0, 1.0), (1, -1.0)):
            along = step * leg_offset((phase + 0.5 * leg) % 1.0)
            xy = centre + along * forward + side * (self.step_width_m / 2.0) * left
            out.append((float(xy[0]), float(xy[1]), self.leg_radius_m))
        return out


def leg_offset(cycle: float) -> float:
    """A leg's fore-aft offset from the body centre in steps, at ``cycle`` ∈ [0, 1) of its gait cycle.

    Stance: it slides back at the body's speed (two steps per cycle), so it stays put in the world.
    Swing: it moves forward to the next footfall along a smoothstep, fastest mid-swing.
    """
    reach = STANCE_SHARE  # ± this many steps: a stance spans 2·STANCE_SHARE steps of body travel
    if cycle < STANCE_SHARE:
        return reach - 2.0 * cycle
    u = (cycle - STANCE_SHARE) / (1.0 - STANCE_SHARE)
    return -reach + 2.0 * reach * u * u * (3.0 - 2.0 * u)


def _smooth(values: np.ndarray, window: int) -> np.ndarray:
    """Moving average along axis 0 with edge padding (keeps the ends where they are)."""
    if window <= 1:
        return values
    pad = window // 2
    padded = np.concatenate([np.repeat(values[:1], pad, axis=0), values, np.repeat(values[-1:], pad, axis=0)])
    kernel = np.ones(window) / window
    if values.ndim == 1:
        return np.convolve(padded, kernel, mode="valid")[: len(values)]
    return np.stack(
        [np.convolve(padded[:, k], kernel, mode="valid")[: len(values)] for k in range(2)], axis=1
    )


def _build(
    points: Sequence[tuple[float, float]],
    speeds: Sequence[float],
    pauses: Sequence[float],
    start_s: float,
    duration_s: float,
    leg_radius_m: float,
    step_width_m: float,
    initial_heading: float,
) -> Person:
    """A person who waits ``start_s`` at ``points[0]``, then walks each leg i at ``speeds[i]`` and
    stands ``pauses[i]`` at point i + 1, standing at the last point once there."""
    times = np.arange(0.0, duration_s + TIME_STEP_S, TIME_STEP_S)
    # Knots in absolute time: before the first and after the last, np.interp holds the end points, so
    # a person stands until ``start_s``, and one with a negative start is already on the way at t = 0.
    knots_t = [start_s]
    knots_xy = [points[0]]
    t = start_s
    for i in range(1, len(points)):
        length = math.dist(points[i - 1], points[i])
        t += length / max(speeds[i - 1], 1e-3)
        knots_t.append(t)
        knots_xy.append(points[i])
        if pauses[i - 1] > 0:
            t += pauses[i - 1]
            knots_t.append(t)
            knots_xy.append(points[i])
    xy = np.asarray(knots_xy)
    kt = np.asarray(knots_t)
    raw = np.stack([np.interp(times, kt, xy[:, 0]), np.interp(times, kt, xy[:, 1])], axis=1)
    centres = _smooth(raw, round(SMOOTHING_S / TIME_STEP_S) | 1)
    velocity = np.gradient(centres, TIME_STEP_S, axis=0)
    speed = np.hypot(velocity[:, 0], velocity[:, 1])
    headings = np.empty(len(times))
    heading = initial_heading
    for i, (vx, vy) in enumerate(velocity):
        if speed[i] > 0.05:
            heading = math.atan2(vy, vx)
        headings[i] = heading
    cadence = CADENCE_BASE + CADENCE_GAIN * speed
    phase = np.concatenate([[0.0], np.cumsum(0.5 * cadence[:-1] * TIME_STEP_S)])
    return Person(centres, headings, speed, phase, leg_radius_m, step_width_m)


def people_distances(
    people: Sequence[Person], sensor_xy: tuple[float, float], directions: np.ndarray, t_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """First-hit distance of every beam on any leg at ``t_s`` (``inf`` where none) and the
    :func:`leg_object` of the leg each beam hit (undefined where none)."""
    circles = np.array([c for person in people for c in person.legs(t_s)], dtype=np.float64).reshape(-1, 3)
    if len(circles) == 0:
        return np.full(len(directions), np.inf), np.zeros(len(directions), dtype=np.int16)
    per_leg = np.stack(
        [ray_circle_distances(sensor_xy, directions, circles[k : k + 1]) for k in range(len(circles))], axis=1
    )
    nearest = per_leg.argmin(axis=1)
    return per_leg.min(axis=1), (PERSON_OBJECT_BASE + nearest).astype(np.int16)


# --- placement -------------------------------------------------------------------------------------


def _passage(room_half_m: float) -> tuple[float, float, float]:
    """The centres' band in the passage outside the door wall: nearest and farthest distance from the
    room's centre across the wall, and the reach along it either side of the door."""
    near = room_half_m + WALL_THICKNESS_M + PASSAGE_CLEARANCE_M
    far = room_half_m + OUTER_HALF_M - ROOM_HALF_M - PASSAGE_CLEARANCE_M
    return near, far, room_half_m + WALL_THICKNESS_M


def _allowed(points: np.ndarray, scenario: Scenario) -> np.ndarray:
    """Which centres are walkable: inside the room, in the doorway's corridor, or in the passage
    outside the door wall."""
    room = scenario.room_half_m
    inside_half = room - INSIDE_MARGIN_M
    inside = np.all(np.abs(points) <= inside_half, axis=1)
    normal, along = scenario.door.axes
    out = points @ normal
    side = np.abs(points @ along)
    corridor = (out >= inside_half - 0.01) & (out <= room + OUTSIDE_DEPTH_M)
    in_door = corridor & (side <= scenario.door.width_m / 2.0 - 0.17)
    beyond = (out >= room + 0.25) & (out <= room + OUTSIDE_DEPTH_M) & (side <= 0.8)
    near, far, reach = _passage(room)
    passage = (out >= near - 1e-9) & (out <= far + 1e-9) & (side <= reach)
    clear = np.ones(len(points), dtype=bool)
    for obj in scenario.objects:
        clear &= obj.footprint.distance(points) >= FURNITURE_CLEARANCE_M
    return (inside | in_door | beyond | passage) & clear


def _free_point(scenario: Scenario, rng: np.random.Generator) -> tuple[float, float]:
    lim = scenario.room_half_m - INSIDE_MARGIN_M
    return float(rng.uniform(-lim, lim)), float(rng.uniform(-lim, lim))


def _door_points(
    scenario: Scenario, rng: np.random.Generator
) -> tuple[tuple[float, float], tuple[float, float]]:
    """A point just outside the door and one in the doorway, both on one line across it."""
    normal, along = scenario.door.axes
    offset = float(rng.uniform(-1.0, 1.0)) * max(scenario.door.width_m / 2.0 - 0.2, 0.0)
    room = scenario.room_half_m
    outside = normal * (room + float(rng.uniform(0.4, OUTSIDE_DEPTH_M - 0.05))) + along * offset
    doorway = normal * room + along * offset
    return (float(outside[0]), float(outside[1])), (float(doorway[0]), float(doorway[1]))


def _passing_walk(
    scenario: Scenario, duration_s: float, rng: np.random.Generator
) -> tuple[list[tuple[float, float]], list[float], list[float]]:
    """A walk along the passage outside the door wall, from a random spot to one end and back and
    forth until ``duration_s`` is filled, so that it crosses the doorway's view at least once."""
    normal, along = scenario.door.axes
    near, far, reach = _passage(scenario.room_half_m)
    offset = float(rng.uniform(-reach, reach))
    heading = 1.0 if rng.random() < 0.5 else -1.0

    def at(side: float) -> tuple[float, float]:
        point = normal * float(rng.uniform(near, far)) + along * side
        return float(point[0]), float(point[1])

    points, speeds, pauses = [at(offset)], [], []
    walked, speed = 0.0, _walking_speed(rng)
    while walked < (duration_s + 2.0) * speed:
        end = heading * reach * float(rng.uniform(0.6, 1.0))
        points.append(at(end))
        walked += math.dist(points[-2], points[-1])
        speeds.append(speed)
        pauses.append(float(rng.uniform(0.3, 1.5)) if rng.random() < 0.2 else 0.0)
        heading = -heading
    return points, speeds, pauses


def _beside_furniture(scenario: Scenario, rng: np.random.Generator) -> tuple[float, float]:
    """A standing spot 0.35–0.55 m off the desk's or the chair's footprint, where people stop."""
    candidates = [o for o in scenario.objects if o.has_legs] or list(scenario.objects)
    obj = candidates[int(rng.integers(0, len(candidates)))]
    rect = obj.footprint
    angle = float(rng.uniform(0.0, 2.0 * math.pi))
    reach = float(np.hypot(*rect.size)) / 2.0 + float(rng.uniform(0.35, 0.55))
    return (rect.center[0] + reach * math.cos(angle), rect.center[1] + reach * math.sin(angle))


@dataclass(frozen=True)
class _Plan:
    points: list[tuple[float, float]]
    speeds: list[float]
    pauses: list[float]
    start_s: float


def _walking_speed(rng: np.random.Generator) -> float:
    """Mostly a normal walk (0.8–1.6 m/s), sometimes a stroll (0.3–0.8 m/s)."""
    return float(rng.uniform(0.8, MAX_SPEED_MPS)) if rng.random() < 0.7 else float(rng.uniform(0.3, 0.8))


def _fill(
    points: list[tuple[float, float]],
    scenario: Scenario,
    duration_s: float,
    rng: np.random.Generator,
    *,
    pause_share: float,
    pauses_s: tuple[float, float],
    beside_share: float,
) -> tuple[list[tuple[float, float]], list[float], list[float]]:
    """Extend a walk from ``points[-1]`` spot to spot (free floor, or beside the desk or the chair for
    ``beside_share`` of the spots) along walkable straight legs until ``duration_s`` is filled, each leg
    at its own walking speed, with a pause of ``pauses_s`` at ``pause_share`` of the spots. Walks end
    early only where no walkable spot is found (the person then stands there)."""
    points = list(points)
    speeds: list[float] = []
    pauses: list[float] = []
    elapsed = 0.0
    while elapsed < duration_s + 2.0:
        for _ in range(PLACEMENT_TRIES):
            beside = rng.random() < beside_share
            target = _beside_furniture(scenario, rng) if beside else _free_point(scenario, rng)
            if _segment_walkable(points[-1], target, scenario):
                break
        else:
            break
        speed = _walking_speed(rng)
        pause = float(rng.uniform(*pauses_s)) if rng.random() < pause_share else 0.0
        elapsed += math.dist(points[-1], target) / speed + pause
        points.append(target)
        speeds.append(speed)
        pauses.append(pause)
    return points, speeds, pauses


def _plan(behaviour: str, scenario: Scenario, duration_s: float, rng: np.random.Generator) -> _Plan:
    """One person's plan for a robot motion. Walkers are under way from the motion's first scan and
    walk for all of it: people a robot meets are mostly passing by, and what their legs do between
    the stacked scans is the cue the network reads."""
    start = float(rng.uniform(-2.0, 0.0))
    if behaviour == "stand":
        spot = _beside_furniture(scenario, rng) if rng.random() < 0.6 else _free_point(scenario, rng)
        return _Plan([spot], [], [], 0.0)
    if behaviour == "visit":  # walk to the desk or chair, stop a while there (or stay), then go on
        spot = _beside_furniture(scenario, rng)
        stays = rng.random() < 0.3
        points = [_free_point(scenario, rng), spot]
        speeds, pauses = [_walking_speed(rng)], [duration_s if stays else float(rng.uniform(0.5, 3.0))]
        if not stays:
            points, more_speeds, more_pauses = _fill(
                points, scenario, duration_s, rng, pause_share=0.2, pauses_s=(0.5, 2.0), beside_share=0.3
            )
            speeds, pauses = speeds + more_speeds, pauses + more_pauses
        return _Plan(points, speeds, pauses, start)
    if behaviour == "door":  # in through the doorway and on about the room, or the same walk out
        outside, doorway = _door_points(scenario, rng)
        points, speeds, pauses = _fill(
            [outside, doorway],
            scenario,
            duration_s,
            rng,
            pause_share=0.1,
            pauses_s=(0.5, 2.0),
            beside_share=0.2,
        )
        speeds, pauses = [_walking_speed(rng), *speeds], [0.0, *pauses]
        if rng.random() < 0.5:
            points, speeds, pauses = points[::-1], speeds[::-1], [*pauses[-2::-1], 0.0]
        return _Plan(points, speeds, pauses, start)
    if behaviour == "pass":  # walks past outside the room, seen only through the doorway
        return _Plan(*_passing_walk(scenario, duration_s, rng), start)
    # cross: walks across the room from spot to spot, now and then stopping briefly
    points, speeds, pauses = _fill(
        [_free_point(scenario, rng)],
        scenario,
        duration_s,
        rng,
        pause_share=0.2,
        pauses_s=(0.5, 2.0),
        beside_share=0.0,
    )
    return _Plan(points, speeds, pauses, start)


def _fits(
    person: Person,
    scenario: Scenario,
    robot_xy: np.ndarray,
    robot_dt_s: float,
    others: Sequence[Person],
) -> bool:
    """Walkable everywhere, never closer than the clearances to the robot or to anyone placed."""
    centres = person.centres
    if not np.all(_allowed(centres, scenario)):
        return False
    t = np.arange(len(centres)) * TIME_STEP_S
    index = np.minimum(np.round(t / robot_dt_s).astype(int), len(robot_xy) - 1)
    if np.any(np.hypot(*(centres - robot_xy[index]).T) < ROBOT_CLEARANCE_M):
        return False
    return all(np.all(np.hypot(*(centres - other.centres).T) >= PEOPLE_CLEARANCE_M) for other in others)


def _build_plan(plan: _Plan, duration_s: float, rng: np.random.Generator, lateral_m: float = 0.0) -> Person:
    points = plan.points
    if lateral_m and len(points) > 1:  # walk beside a companion: the same path, offset to one side
        shifted = []
        for i, point in enumerate(points):
            a, b = points[max(i - 1, 0)], points[min(i + 1, len(points) - 1)]
            d = np.subtract(b, a)
            n = np.array([-d[1], d[0]]) / max(float(np.hypot(*d)), 1e-9)
            shifted.append((point[0] + lateral_m * n[0], point[1] + lateral_m * n[1]))
        points = shifted
    radius = float(rng.uniform(0.055, 0.08)) if rng.random() < 0.85 else float(rng.uniform(0.08, 0.10))
    return _build(
        points,
        plan.speeds,
        plan.pauses,
        plan.start_s,
        duration_s,
        leg_radius_m=radius,
        step_width_m=float(rng.uniform(0.12, 0.22)) + 2 * (radius - 0.065),
        initial_heading=float(rng.uniform(-math.pi, math.pi)),
    )


def sample_people(
    scenario: Scenario,
    robot_path: np.ndarray,
    robot_dt_s: float,
    duration_s: float,
    max_people: int,
    rng: np.random.Generator,
    first_behaviour: str | None = None,
) -> list[Person]:
    """Between 0 and ``max_people`` people for one robot motion (``robot_path``: float64[T, ≥2], one row
    every ``robot_dt_s``). Someone who does not fit after a few draws is left out, so a crowded room
    gets fewer people; a group that does not fit whole loses its later members. With
    ``first_behaviour`` at least one person is tried, and the first one behaves so."""
    if max_people <= 0:
        return []
    if first_behaviour is not None and first_behaviour not in BEHAVIOURS:
        raise ValueError(f"behaviour must be one of {BEHAVIOURS}, got {first_behaviour!r}")
    wanted = int(rng.integers(0, max_people + 1))
    if first_behaviour is not None:
        wanted = max(wanted, 1)
    robot_xy = np.asarray(robot_path, dtype=np.float64)[:, :2]
    placed: list[Person] = []
    while len(placed) < wanted:
        behaviour = str(rng.choice(BEHAVIOURS, p=BEHAVIOUR_SHARES))
        if first_behaviour is not None and not placed:
            behaviour = first_behaviour
        size = int(rng.integers(2, 4)) if behaviour == "group" else 1
        size = min(size, wanted - len(placed))
        group: list[Person] = []
        for _ in range(PLACEMENT_TRIES):
            plan = _plan("cross" if behaviour == "group" else behaviour, scenario, duration_s, rng)
            leader = _build_plan(plan, duration_s, rng)
            if not _fits(leader, scenario, robot_xy, robot_dt_s, placed):
                continue
            group = [leader]
            for member in range(1, size):
                side = 1.0 if member % 2 else -1.0
                follower = _build_plan(plan, duration_s, rng, lateral_m=side * float(rng.uniform(0.5, 0.7)))
                if _fits(follower, scenario, robot_xy, robot_dt_s, placed + group):
                    group.append(follower)
            break
        if not group:
            break
        placed.extend(group)
    return placed


def _segment_walkable(a: tuple[float, float], b: tuple[float, float], scenario: Scenario) -> bool:
    """Whether a straight walk from ``a`` to ``b`` keeps to walkable centres (every 5 cm)."""
    steps = max(2, int(math.dist(a, b) / 0.05) + 1)
    points = np.linspace(a, b, steps)
    return bool(np.all(_allowed(points, scenario)))


def _wander(scenario: Scenario, duration_s: float, rng: np.random.Generator) -> _Plan:
    """A long walk for the live simulator: from spot to spot (free floor, beside the desk or the chair,
    out of the door and back in), standing a while at some, until ``duration_s`` is filled."""
    if rng.random() < 0.3:
        outside, doorway = _door_points(scenario, rng)
        first, speeds, pauses = [outside, doorway], [_walking_speed(rng)], [0.0]
    else:
        first, speeds, pauses = [_free_point(scenario, rng)], [], []
    points, more_speeds, more_pauses = _fill(
        first, scenario, duration_s, rng, pause_share=0.35, pauses_s=(1.0, 6.0), beside_share=0.3
    )
    return _Plan(points, speeds + more_speeds, pauses + more_pauses, float(rng.uniform(-2.0, 0.0)))


def sample_live_people(
    scenario: Scenario,
    robot_path: np.ndarray,
    robot_dt_s: float,
    duration_s: float,
    count: int,
    rng: np.random.Generator,
) -> list[Person]:
    """Up to ``count`` people who keep walking about the room for ``duration_s`` (the live simulator's
    world period), clear of the robot's planned path and of each other; one who cannot be placed after
    a few draws is left out."""
    robot_xy = np.asarray(robot_path, dtype=np.float64)[:, :2]
    placed: list[Person] = []
    for _ in range(count):
        for _ in range(PLACEMENT_TRIES):
            person = _build_plan(_wander(scenario, duration_s, rng), duration_s, rng)
            if _fits(person, scenario, robot_xy, robot_dt_s, placed):
                placed.append(person)
                break
    return placed
