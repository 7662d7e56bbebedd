"""Simulated people (gait, placement, labels), sensor profiles, and the data sets they make."""

from __future__ import annotations

import hashlib
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from common.encoding import ANGLE_COLUMNS
from common.model_spec import PERSON_FOOTPRINT_RADIUS_M
from services.simulator.labels import clip_to_field_of_view, label_scan
from services.simulator.people import (
    CADENCE_BASE,
    CADENCE_GAIN,
    INSIDE_MARGIN_M,
    PEOPLE_CLEARANCE_M,
    ROBOT_CLEARANCE_M,
    STANCE_SHARE,
    TIME_STEP_S,
    Person,
    _build,
    leg_object,
    people_distances,
    sample_people,
)
from services.simulator.scenario import PERSON, sample_scenario
from services.simulator.sensors import (
    DEFAULT_SPEC,
    PROFILES,
    RANDOM_PROFILE,
    draw_profile,
    profile,
    stack_stride,
)


def walker(speed: float = 1.3, duration_s: float = 6.0) -> Person:
    """A person walking along +x from (-3, 0) at ``speed`` from t = 0."""
    return _build([(-3.0, 0.0), (30.0, 0.0)], [speed], [0.0], -5.0, duration_s, 0.05, 0.16, 0.0)


def test_a_walking_legs_stance_stays_put_and_the_legs_alternate() -> None:
    person = walker()
    cadence = CADENCE_BASE + CADENCE_GAIN * 1.3
    cycle_s = 2.0 / cadence
    for leg in (0, 1):
        stances: list[list[float]] = [[]]
        for t in np.arange(1.0, 1.0 + 2 * cycle_s, 0.01):
            i = round(t / TIME_STEP_S)
            phase = (person.phase[i] + 0.5 * leg) % 1.0
            if 0.05 < phase < STANCE_SHARE - 0.05:  # well inside the stance
                stances[-1].append(person.legs(t)[leg][0])
            elif stances[-1]:
                stances.append([])
        stances = [run for run in stances if len(run) > 10]
        assert len(stances) >= 1
        for run in stances:
            assert max(run) - min(run) < 0.03, "a planted foot does not slide"
    # One stride (two steps) per cycle: each foot lands a stride ahead of where it stood.
    step = 1.3 / cadence
    assert step == pytest.approx(0.64, abs=0.01)
    a, b = person.legs(2.0), person.legs(2.0 + cycle_s)
    assert b[0][0] - a[0][0] == pytest.approx(1.3 * cycle_s, abs=0.05)
    assert abs(a[0][1] - a[1][1]) == pytest.approx(0.16)  # side by side across the walking direction


def test_a_standing_person_keeps_both_legs_still_side_by_side() -> None:
    person = _build([(0.5, 0.5)], [], [], 0.0, 4.0, 0.06, 0.18, 0.3)
    assert person.legs(0.0) == person.legs(3.9)
    (x0, y0, r0), (x1, y1, _) = person.legs(1.0)
    assert math.dist((x0, y0), (x1, y1)) == pytest.approx(0.18) and r0 == 0.06
    assert person.centre(2.0) == pytest.approx((0.5, 0.5))


@pytest.mark.parametrize("room_half_m", [2.0, 5.0])
def test_people_stay_walkable_and_clear_of_furniture_the_robot_and_each_other(room_half_m: float) -> None:
    rng = np.random.default_rng(3)
    robot = np.array([[-1.2, -1.2, 0.0]] * 50)
    inside_half = room_half_m - INSIDE_MARGIN_M
    seen = 0
    farthest = 0.0
    for index in range(6):
        scenario = sample_scenario(index, seed=21, room_half_m=room_half_m)
        for _ in range(8):
            people = sample_people(scenario, robot, 0.1, 5.0, 4, rng)
            assert len(people) <= 4
            seen += len(people)
            for k, person in enumerate(people):
                c = person.centres
                farthest = max(farthest, float(np.abs(c).max()))
                outside = np.any(np.abs(c) > inside_half + 1e-9, axis=1)
                normal = np.array([math.cos(scenario.door.yaw), math.sin(scenario.door.yaw)])
                assert np.all(c[outside] @ normal > inside_half - 0.02), "only the doorway leads out"
                for obj in scenario.objects:
                    assert np.all(obj.footprint.distance(c) >= 0.3 - 1e-9)
                assert np.hypot(*(c - robot[0, :2]).T).min() >= ROBOT_CLEARANCE_M
                for other in people[k + 1 :]:
                    gap = np.hypot(*(c - other.centres).T).min()
                    assert gap >= min(PEOPLE_CLEARANCE_M, 0.5) - 1e-9  # a companion walks 0.5-0.7 m aside
    assert seen > 20
    assert farthest > room_half_m - 1.0, "people use the whole room, an open-space one too"
    assert sample_people(sample_scenario(0, seed=21), robot, 0.1, 5.0, 0, rng) == []


def test_most_sampled_people_walk_for_the_whole_motion() -> None:
    """People a robot meets are mostly passing by: over a 5 s motion most of a sampled person's time is
    spent walking, and a walker is already under way at the first scan (the real recordings' walkers)."""
    rng = np.random.default_rng(5)
    robot = np.array([[-1.2, -1.2, 0.0]] * 50)
    walking_share, moving_at_start = [], []
    for index in range(6):
        scenario = sample_scenario(index, seed=22)
        for _ in range(8):
            for person in sample_people(scenario, robot, 0.1, 5.0, 4, rng):
                walking_share.append(float(np.mean(person.speeds > 0.3)))
                moving_at_start.append(bool(person.speeds[: round(0.5 / TIME_STEP_S)].max() > 0.3))
    assert len(walking_share) > 40
    # Walks that started up to half the motion late and ended before it did gave 0.16 and 0.31.
    assert np.mean(walking_share) > 0.5, np.mean(walking_share)
    assert np.mean(moving_at_start) > 0.5, np.mean(moving_at_start)


def test_passers_by_walk_outside_the_door_wall_and_are_seen_only_through_the_doorway() -> None:
    """Some people walk past in the passage outside the door wall; a robot in the room sees their legs
    through the doorway and never through the wall, and sees them at all only some of the time."""
    from services.simulator.lidar import Lidar
    from services.simulator.scenario import OUTER_HALF_M, ROOM_HALF_M, WALL_THICKNESS_M
    from services.simulator.world import World

    scenario = sample_scenario(0, seed=0)
    room, half_door = scenario.room_half_m, scenario.door.width_m / 2.0
    normal = np.array([math.cos(scenario.door.yaw), math.sin(scenario.door.yaw)])
    along = np.array([-normal[1], normal[0]])
    robot = np.array([[0.0, 0.0, 0.0]] * 60)
    rng = np.random.default_rng(7)
    passers = [
        person
        for _ in range(60)
        for person in sample_people(scenario, robot, 0.1, 6.0, 4, rng)
        if (person.centres @ normal).min() > room + WALL_THICKNESS_M and np.ptp(person.centres @ along) > 1.0
    ]
    assert len(passers) >= 10, "some walk past along the wall, not just out of the door"
    for person in passers:
        assert (person.centres @ normal).max() <= room + OUTER_HALF_M - ROOM_HALF_M - 0.3 + 1e-9
    crossing = [p for p in passers if np.abs(p.centres @ along).min() < half_door]
    assert len(crossing) >= len(passers) // 2, "most pass the doorway while the robot looks"
    seen_at, hidden_at = 0, 0
    with World(scenario) as world:
        lidar = Lidar(world, rng=np.random.default_rng(0))
        for person in crossing[:4]:
            for t in np.arange(0.0, 6.0, 0.1):
                reading = lidar.scan((0.0, 0.0, scenario.door.yaw), people=(person,), t_s=float(t))
                on_legs = reading.hit_object >= leg_object(0, 0)
                if on_legs.sum() >= 2:
                    seen_at += 1
                    bearings = DEFAULT_SPEC.bearings_rad[on_legs]
                    ends = np.outer(reading.true_ranges[on_legs], [1.0, 1.0]) * np.column_stack(
                        [np.cos(bearings + scenario.door.yaw), np.sin(bearings + scenario.door.yaw)]
                    ) + np.asarray(reading.lidar_pose[:2])
                    # where each beam crosses the door wall's line it is inside the opening
                    cross = ends * ((room + WALL_THICKNESS_M / 2) / (ends @ normal))[:, None]
                    assert np.all(np.abs(cross @ along) < half_door + 0.02)
                else:
                    hidden_at += 1
    assert seen_at > 3 and hidden_at > 3


def test_each_beam_names_the_leg_it_hit() -> None:
    person = _build([(2.0, 0.0)], [], [], 0.0, 1.0, 0.05, 0.2, 0.0)  # facing +x: legs at y = ±0.1
    rays = np.array([[math.cos(a), math.sin(a)] for a in np.radians([0.0, 2.9, -2.9, 45.0])])
    distances, legs = people_distances([person], (0.0, 0.0), rays, 0.0)
    assert math.isinf(distances[0]) and math.isinf(distances[3])  # between the legs; far off
    hit = {int(legs[1]), int(legs[2])}
    assert hit == {leg_object(0, 0), leg_object(0, 1)}
    assert distances[1] == pytest.approx(distances[2]) and 1.9 < distances[1] < 2.0


def test_a_person_is_labelled_by_the_footprint_about_their_legs() -> None:
    scenario = sample_scenario(0, seed=0)
    pose = (0.0, -1.0, 0.0)  # the person 1 m away at bearing 90°
    legs = ((-0.1, 0.0, 0.05), (0.1, 0.0, 0.05))
    bearings = DEFAULT_SPEC.bearings_rad
    ranges = np.full(len(bearings), np.inf)
    hits = np.full(len(bearings), -2, dtype=np.int16)
    seen = [91, 92, 93, 94, 95]  # beams on the leg at x = -0.1 m (5.7° left of the midpoint)
    hits[seen] = leg_object(0, 0)
    ranges[seen] = 0.96
    labels = label_scan(scenario, pose, bearings, ranges, hits, 3.5, "zero", (legs,))
    person = [label for label in labels if label.class_id == PERSON]
    assert len(person) == 1 and person[0].visible and person[0].beams_on_object == 5
    # The 0.3 m disc about the legs' midpoint, whichever leg the beams saw: ±17.46° and 0.7-1.3 m.
    half = math.degrees(math.asin(PERSON_FOOTPRINT_RADIUS_M))
    assert person[0].boxes_px == (
        (
            float(math.floor(90 - half + 0.5)),
            float(math.floor(0.7 * 63 / 4)),
            float(math.floor(90 + half + 0.5) + 1),
            float(math.floor(1.3 * 63 / 4) + 1),
        ),
    )
    hits[seen[1:]] = -2  # one beam is not enough
    labels = label_scan(scenario, pose, bearings, ranges, hits, 3.5, "zero", (legs,))
    assert not next(label for label in labels if label.class_id == PERSON).visible


def test_an_arc_is_clipped_to_the_sensors_field_of_view() -> None:
    spec = PROFILES["leg-tracker-180"]  # -90° … +90°
    bearings = spec.bearings_rad
    assert clip_to_field_of_view(0.0, -10.0, 10.0, bearings) == (-10.0, 10.0)
    lo, hi = clip_to_field_of_view(90.0, 80.0, 100.0, bearings)  # type: ignore[misc]
    assert lo == 80.0 and hi == pytest.approx(math.degrees(spec.angle_max))
    assert clip_to_field_of_view(180.0, 170.0, 190.0, bearings) is None
    assert clip_to_field_of_view(180.0, 170.0, 190.0, DEFAULT_SPEC.bearings_rad) == (170.0, 190.0)
    lo, hi = clip_to_field_of_view(275.0, 265.0, 285.0, bearings)  # type: ignore[misc]
    assert lo == pytest.approx(270.0, abs=0.5) and hi == 285.0  # -90° is 270°


def test_profiles_follow_their_datasheets_and_stack_at_the_trained_period() -> None:
    for name, spec in PROFILES.items():
        assert spec.rate_hz > 0 and spec.range_min < spec.range_max, name
        fov = math.degrees(spec.beams * spec.angle_increment)
        assert 179.0 < fov < 361.0, name
    assert PROFILES["lds-01"] == DEFAULT_SPEC
    assert PROFILES["ust-10lx"].beams == 1081 and math.degrees(PROFILES["ust-10lx"].angle_min) == -135.0
    assert stack_stride(40.0, 0.1) == 4 and stack_stride(10.0, 0.1) == 1 and stack_stride(5.5, 0.1) == 1
    assert stack_stride(15.0, 0.1) == 2
    rng = np.random.default_rng(0)
    drawn = {draw_profile(RANDOM_PROFILE, rng)[0] for _ in range(200)}
    assert drawn == set(PROFILES)
    with pytest.raises(ValueError, match=r"unknown sensor 'hokuyo'.*lds-01"):
        profile("hokuyo")
    with pytest.raises(ValueError, match="rate_hz"):
        replace(DEFAULT_SPEC, rate_hz=0.0)


def _digest(root: Path) -> str:
    files = sorted(p for p in root.rglob("*") if p.is_file())
    text = "".join(f"{hashlib.sha256(p.read_bytes()).hexdigest()}  ./{p.relative_to(root)}\n" for p in files)
    return hashlib.sha256(text.encode()).hexdigest()


@pytest.mark.slow
def test_the_papers_set_is_byte_for_byte_what_it_was(tmp_path: Path) -> None:
    """`--people 0` with the LDS-01: the same files as the generator made before people and sensor
    profiles existed (this digest was taken from that generator's output)."""
    from training.dataset import DatasetConfig, generate_dataset

    generate_dataset(DatasetConfig(out=tmp_path, scenarios=3, positions=2, seed=0), progress=False)
    assert _digest(tmp_path) == "44748fe6b4a8317bd77f6be49905a88613543d042dad59dd5f88997b0d1aadff"


@pytest.mark.slow
def test_a_set_with_people_and_random_sensors(tmp_path: Path) -> None:
    import json

    from training.dataset import DatasetConfig, generate_dataset

    config = DatasetConfig(
        out=tmp_path / "a", scenarios=6, positions=4, seed=5, frame_stride=5, people=4, sensor="random",
        open_space=0.5, door_watch=0.3,
    )  # fmt: skip
    summary = generate_dataset(config, progress=False)
    assert (
        "nc: 5" in (tmp_path / "a" / "data.yaml").read_text()
        and "  4: person" in (tmp_path / "a" / "data.yaml").read_text()
    )
    boxes = summary["boxes_per_class"]
    assert isinstance(boxes, dict) and sum(split["person"] for split in boxes.values()) > 10
    sensors = [json.loads(line)["lidar"]["sensor"] for line in (tmp_path / "a" / "scenarios.jsonl").open()]
    assert len(set(sensors)) >= 3 and set(sensors) <= set(PROFILES)
    config_json = json.loads((tmp_path / "a" / "summary.json").read_text())["config"]
    assert config_json["people"] == 4 and config_json["sensor"] == "random"
    assert config_json["open_space"] == 0.5 and config_json["door_watch"] == 0.3
    records = [json.loads(line) for line in (tmp_path / "a" / "scenarios.jsonl").open()]
    rooms = [record["door"].get("room_half_m", 2.0) for record in records]
    assert min(rooms) == 2.0 < max(rooms), "a share of the rooms are open spaces"
    again = replace(config, out=tmp_path / "b", workers=2)
    generate_dataset(again, progress=False)
    assert _digest(tmp_path / "a") == _digest(tmp_path / "b"), "the same whatever the worker count"
    # A narrow field of view leaves its dark columns unlabelled.
    for line in (tmp_path / "a" / "scenarios.jsonl").open():
        record = json.loads(line)
        spec = PROFILES[record["lidar"]["sensor"]]
        if spec.full_circle:
            continue
        first = math.degrees(spec.angle_min) % ANGLE_COLUMNS
        last = math.degrees(spec.angle_max) % ANGLE_COLUMNS
        for label in (tmp_path / "a" / "labels").glob(f"*/s{record['index']:04d}_*.txt"):
            for row in label.read_text().splitlines():
                _, xc, _, w, _ = (float(v) for v in row.split())
                for x in ((xc - w / 2) * 384 + 0.5, (xc + w / 2) * 384 - 0.5):
                    inside = (first <= x <= 360.0) or (0.0 <= x <= last + 1.0)
                    assert inside, (label, row, first, last)
    # The evaluator reads a five-class set: a person's box crosses the seam only where it reaches it.
    from training.evaluate import PERSON_ID, dataset_samples

    people = []
    for split in ("train", "val", "test"):
        for sample in dataset_samples(tmp_path / "a", split):
            assert sample.crosses_seam is not None and len(sample.crosses_seam) == len(sample.classes)
            labels = zip(sample.boxes, sample.classes, sample.crosses_seam, strict=True)
            people += [(box, crosses) for box, class_id, crosses in labels if class_id == PERSON_ID]
    assert len(people) > 10
    assert all(box[0] <= 0.0 or box[2] >= ANGLE_COLUMNS for box, crosses in people if crosses)


def test_the_live_simulator_has_people_walking_and_labels_them() -> None:
    from services.simulator.fleet import SimulatedFleet

    with SimulatedFleet(1, people=3, scenario_period_s=20.0) as fleet:
        steps = [fleet.step(k * 100_000_000)[0] for k in range(120)]
    people = [[o for o in truth.objects if o.class_id == PERSON] for _, truth in steps]
    assert all(len(p) == len(fleet.robots[0].people) for p in people) and len(people[0]) >= 1
    assert sum(o.visible for p in people for o in p) > 20
    first, last = people[0][0].center_xy, people[-1][0].center_xy
    assert math.dist(first, last) > 0.3, "people walk"
    robot = np.array([truth.robot_pose[:2] for _, truth in steps])
    for k in range(len(steps)):
        for person in people[k]:
            assert math.dist(person.center_xy, robot[k]) >= ROBOT_CLEARANCE_M - 0.05


def test_the_live_simulator_scans_with_a_profile() -> None:
    from services.simulator.fleet import SimulatedFleet

    spec = PROFILES["ust-10lx"]
    with SimulatedFleet(1, rate_hz=spec.rate_hz, spec=spec) as fleet:
        scan, truth = fleet.step(0)[0]
    assert len(scan.ranges) == spec.beams and scan.angle_min == pytest.approx(spec.angle_min)
    assert not any(o.class_id == PERSON for o in truth.objects)


@pytest.mark.parametrize("room_half_m", [2.0, 4.5])
def test_a_door_watch_stands_the_robot_close_in_front_of_the_doorway_facing_it(room_half_m: float) -> None:
    """``--door-watch``: the robot stands 0.6-1.6 m inside the door wall, within 0.5 m of the door's
    centre line and facing out within 45 degrees, and someone passes outside; the other motions of the
    scenario are the ones it had without door watching."""
    from training.dataset import plan_motions

    scenario = sample_scenario(3, seed=1, room_half_m=room_half_m)
    plain = plan_motions(scenario, 1, 12)
    assert plan_motions(scenario, 1, 12, door_watch=0.0) == plain
    mixed = plan_motions(scenario, 1, 12, door_watch=0.5)
    watching = [m for m in mixed if m.door_watch]
    assert 0 < len(watching) < len(mixed)
    assert all(m == p for m, p in zip(mixed, plain, strict=True) if not m.door_watch)
    normal = np.array([math.cos(scenario.door.yaw), math.sin(scenario.door.yaw)])
    along = np.array([-normal[1], normal[0]])
    for motion, before in zip(plan_motions(scenario, 1, 12, door_watch=1.0), plain, strict=True):
        assert motion.door_watch
        shift = np.subtract(motion.start_xy, before.start_xy)
        moved = np.subtract(motion.waypoints, before.waypoints)
        np.testing.assert_allclose(moved, [shift] * len(before.waypoints))  # the drive moves along
        start = np.asarray(motion.start_xy)
        assert 0.6 - 1e-9 <= room_half_m - start @ normal <= 1.6 + 1e-9
        assert abs(start @ along) <= 0.5 + 1e-9
        facing = math.remainder(motion.heading_rad - scenario.door.yaw, math.tau)
        assert abs(facing) <= math.radians(45.0) + 1e-9
    robot = np.array([[*watching[0].start_xy, watching[0].heading_rad]] * 60)
    rng = np.random.default_rng(3)
    for _ in range(5):
        first, *_ = sample_people(scenario, robot, 0.1, 6.0, 2, rng, first_behaviour="pass")
        assert (first.centres @ normal).min() > room_half_m, "the first person walks outside the door wall"
    with pytest.raises(ValueError, match="behaviour"):
        sample_people(scenario, robot, 0.1, 6.0, 2, rng, first_behaviour="dance")


def test_door_watching_needs_people() -> None:
    from training.dataset import DatasetConfig

    with pytest.raises(ValueError, match="needs people"):
        DatasetConfig(out=Path("x"), door_watch=0.1)
    with pytest.raises(ValueError, match="door-watch share"):
        DatasetConfig(out=Path("x"), people=2, door_watch=1.5)
