"""Seeded generator of YOLO data sets from the simulated room (README, "The simulated world" and "Labels").

Per scenario: build the world, draw up to M robot positions, let the robot drive a short motion from
each while the LiDAR scans at 10 Hz, and turn every three consecutive scans into one sample — the
stacked RGB tensor as a PNG plus the labels of its middle scan. Splits are made by scenario, never by
frame, because neighbouring frames are near-duplicates and would leak between train and test.

Every scenario owns its random streams (derived from ``[seed, index]``), so the output is byte-for-byte
the same for a seed whatever the number of workers or the order they finish in.

Domain randomisation makes the simulated LiDAR look like real ones: each scenario draws its own range
noise σ, dropout rate and spurious-return rate from the configured ranges, and each motion may hold
non-target clutter (poles, wall stubs) that is never labelled. Labels stay those of the
true geometry. The defaults are the paper's clean setting, and they reproduce its data set exactly:
the randomisation draws from streams of their own.
"""

from __future__ import annotations

import json
import logging
import math
import multiprocessing
import shutil
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from common.encoding import (
    INVALID_RULES,
    PADDINGS,
    R_MAX_M,
    InvalidRule,
    Padding,
    ScanStacker,
    check_raster_yaw,
)
from common.model_spec import CLASS_NAMES, FURNITURE_CLASSES
from services.simulator.clutter import Clutter, sample_clutter
from services.simulator.defaults import SCAN_PERIOD_S
from services.simulator.labels import ObjectLabel, label_scan, yolo_lines
from services.simulator.lidar import Lidar, LidarReading
from services.simulator.people import Person, sample_people
from services.simulator.robot import follow_waypoints
from services.simulator.scenario import (
    Scenario,
    check_open_space,
    check_share,
    door_watch_cells,
    room_half_of,
    sample_robot_positions,
    sample_scenario,
    sample_waypoints,
)
from services.simulator.sensors import (
    DEFAULT_PROFILE,
    DEFAULT_SPEC,
    LidarSpec,
    check_sensor,
    draw_profile,
    stack_stride,
)
from services.simulator.world import World
from training.png import write_rgb_png

log = logging.getLogger(__name__)

SPLITS = ("train", "val", "test")
SPLIT_FRACTIONS = (0.85, 0.10, 0.05)
HEADINGS_DEG = np.arange(0, 360, 45)
STATIONARY_SHARE = 0.5  # of the motions with people, those where the robot stands still


@dataclass(frozen=True)
class DatasetConfig:
    """What ``triscan dataset`` was asked for; written into the summary so a set can be remade."""

    out: Path
    scenarios: int = 160
    positions: int = 90
    seed: int = 0
    padding: Padding = "zero"
    frame_stride: int = 1  # keep every k-th three-scan window of a motion (1 = all, as the paper)
    workers: int = 1
    invalid: InvalidRule = "sentinel"  # where invalid returns go in the raster (common.encoding)
    # Domain randomisation: each scenario draws σ, dropout and spurious rates uniformly from these.
    noise_sigma_m: tuple[float, float] = (DEFAULT_SPEC.noise_sigma_m, DEFAULT_SPEC.noise_sigma_m)
    dropout_rate: tuple[float, float] = (0.0, 0.0)
    spurious_rate: tuple[float, float] = (0.0, 0.0)
    clutter: int = 0  # at most this many unlabelled clutter items per motion
    people: int = 0  # at most this many people per motion (0: the paper's four classes only)
    sensor: str = DEFAULT_PROFILE  # a profile of services.simulator.sensors, or "random" per scenario
    # Degrees every scan is turned by before binning, labels too (common.encoding); 0: the paper's raster.
    raster_yaw_deg: float = 0.0
    # Share of scenarios whose walls move out to an open-space room (services.simulator.scenario).
    open_space: float = 0.0
    # Share of motions where the robot watches the doorway from close by while someone passes outside.
    door_watch: float = 0.0

    def __post_init__(self) -> None:
        if self.scenarios < 1 or self.positions < 1 or self.frame_stride < 1 or self.workers < 1:
            raise ValueError("scenarios, positions, frame_stride and workers must all be >= 1")
        if self.padding not in PADDINGS:
            raise ValueError(f"padding must be one of {PADDINGS}, got {self.padding!r}")
        if self.invalid not in INVALID_RULES:
            raise ValueError(f"invalid must be one of {INVALID_RULES}, got {self.invalid!r}")
        for name, upper in (("noise_sigma_m", 0.5), ("dropout_rate", 1.0), ("spurious_rate", 1.0)):
            lo, hi = getattr(self, name)
            if not 0.0 <= lo <= hi <= upper:
                raise ValueError(f"{name} must be a range 0 <= low <= high <= {upper}, got {lo}..{hi}")
        if self.clutter < 0:
            raise ValueError(f"clutter must be >= 0, got {self.clutter}")
        if self.people < 0:
            raise ValueError(f"people must be >= 0, got {self.people}")
        check_sensor(self.sensor)
        check_open_space(self.open_space)
        check_share(self.door_watch, "door-watch")
        if self.door_watch > 0.0 and self.people == 0:
            raise ValueError("door watching needs people (--people N): someone has to pass the door")
        object.__setattr__(self, "raster_yaw_deg", check_raster_yaw(self.raster_yaw_deg))  # a ValueError

    @property
    def classes(self) -> tuple[str, ...]:
        """The classes this set labels: the paper's four, and ``person`` once people walk in it."""
        return CLASS_NAMES if self.people > 0 else FURNITURE_CLASSES

    def summary_fields(self) -> dict[str, object]:
        """The configuration as summary.json records it. Options the paper's set does not use are
        written only when set, so that set's summary stays byte for byte what it always was."""
        fields = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(self).items()}
        for key in ("out", "workers"):
            fields.pop(key)
        if self.people == 0:
            fields.pop("people")
        if self.sensor == DEFAULT_PROFILE:
            fields.pop("sensor")
        if self.raster_yaw_deg == 0.0:
            fields.pop("raster_yaw_deg")
        if self.open_space == 0.0:
            fields.pop("open_space")
        if self.door_watch == 0.0:
            fields.pop("door_watch")
        return fields


def scenario_sensor(config: DatasetConfig, index: int) -> str:
    """The sensor profile of scenario ``index``: the configured one, or for ``random`` one drawn from
    the scenario's own stream (``[seed, index, 5]``)."""
    rng = np.random.default_rng(np.random.SeedSequence([config.seed, index, 5]))
    return draw_profile(config.sensor, rng)[0]


def scenario_lidar_spec(config: DatasetConfig, index: int) -> LidarSpec:
    """The sensor of scenario ``index``: its profile's geometry and rate, with σ, dropout and spurious
    rates drawn from the config's ranges.

    Its own stream (``[seed, index, 3]``): the paper's fixed setting draws the same values every
    time, so the defaults rebuild the clean data set unchanged.
    """
    _, base = draw_profile(scenario_sensor(config, index), np.random.default_rng(0))
    rng = np.random.default_rng(np.random.SeedSequence([config.seed, index, 3]))
    return replace(
        base,
        noise_sigma_m=float(rng.uniform(*config.noise_sigma_m)),
        dropout_rate=float(rng.uniform(*config.dropout_rate)),
        spurious_rate=float(rng.uniform(*config.spurious_rate)),
    )


@dataclass
class ScenarioResult:
    """What one scenario contributed: its split, sample count, boxes per class and per-sample poses."""

    index: int
    split: str
    samples: int = 0
    boxes_per_class: list[int] = field(default_factory=lambda: [0] * len(CLASS_NAMES))  # cut to the set's
    sample_records: list[dict[str, object]] = field(default_factory=list)
    scenario_json: dict[str, object] = field(default_factory=dict)
    positions: int = 0


def split_of_scenarios(scenarios: int, seed: int) -> list[str]:
    """Assign each scenario index to train/val/test (85/10/5 %), shuffled by the seed.

    Val and test get at least one scenario each once there are three or more, so tiny sets still
    exercise every split.
    """
    n_val = round(scenarios * SPLIT_FRACTIONS[1])
    n_test = round(scenarios * SPLIT_FRACTIONS[2])
    if scenarios >= 3:
        n_val, n_test = max(n_val, 1), max(n_test, 1)
    order = np.random.default_rng(np.random.SeedSequence([seed, 0x5B1])).permutation(scenarios)
    splits = ["train"] * scenarios
    for rank, index in enumerate(order):
        if rank < n_test:
            splits[index] = "test"
        elif rank < n_test + n_val:
            splits[index] = "val"
    return splits


@dataclass(frozen=True)
class Motion:
    """One robot position of a scenario and the short drive made from it (README, "The simulated world")."""

    start_xy: tuple[float, float]
    heading_rad: float
    waypoints: list[tuple[float, float]]
    # The robot stands in front of the doorway, facing it, while someone passes outside (--door-watch).
    door_watch: bool = False


@dataclass(frozen=True)
class Sample:
    """One example: the run-time tensor of scans t-2, t-1, t and the labels of scan t-1."""

    name: str
    position: int
    frame: int
    tensor: np.ndarray  # uint8[64, 384, 3], built by the run-time ScanStacker
    labels: list[ObjectLabel]
    lidar_pose: tuple[float, float, float]  # true pose of the sensor at scan t-1
    people_legs: tuple[tuple[tuple[float, float, float], ...], ...] = ()  # each person's legs at t-1


def plan_motions(scenario: Scenario, seed: int, positions: int, door_watch: float = 0.0) -> list[Motion]:
    """Draw every position, heading and waypoint pair of a scenario from its own motion stream.

    A share ``door_watch`` of the motions is then replaced, from a stream of its own (so the others
    stay as they were), by a robot standing 0.6–1.6 m in front of the doorway and facing it within
    45° (:func:`door_watch_cells`): the real recordings' hard case, a walker seen beyond a near wall
    only through a narrow opening.
    """
    rng = np.random.default_rng(np.random.SeedSequence([seed, scenario.index, 1]))
    motions = []
    for start in sample_robot_positions(scenario, positions, rng):
        heading = math.radians(float(rng.choice(HEADINGS_DEG)))
        waypoints = sample_waypoints(scenario, start, rng)
        motions.append(Motion((float(start[0]), float(start[1])), heading, waypoints))
    if door_watch <= 0.0:
        return motions
    watch_rng = np.random.default_rng(np.random.SeedSequence([seed, scenario.index, 7]))
    cells = door_watch_cells(scenario)
    for index, motion in enumerate(motions):
        if watch_rng.random() >= door_watch or not len(cells):
            continue
        x, y = cells[watch_rng.integers(0, len(cells))]
        heading = scenario.door.yaw + math.radians(float(watch_rng.uniform(-45.0, 45.0)))
        # The drive moves with the start, so the motion lasts about as long as it did (its first turn
        # differs); the robot stands still through it (a door watch is a waiting robot's view).
        dx, dy = x - motion.start_xy[0], y - motion.start_xy[1]
        waypoints = [(float(wx + dx), float(wy + dy)) for wx, wy in motion.waypoints]
        motions[index] = Motion((float(x), float(y)), heading, waypoints, door_watch=True)
    return motions


def stacked_period_s(spec: LidarSpec) -> float:
    """Time between the scans a model stacks from this sensor: the simulator's scan period for a fast
    sensor (every k-th scan of it, as the encoder picks them), the sensor's own for a slower one."""
    return stack_stride(spec.rate_hz, SCAN_PERIOD_S) / spec.rate_hz


def scans_of_motion(
    lidar: Lidar,
    motion: Motion,
    scenario: Scenario | None = None,
    clutter: int = 0,
    clutter_rng: np.random.Generator | None = None,
    people: int = 0,
    people_rng: np.random.Generator | None = None,
) -> tuple[np.ndarray, list[LidarReading]]:
    """Drive one motion and keep the scans a model stacks (:func:`stacked_period_s` apart), among up to
    ``clutter`` clutter items and ``people`` people. With people, a share of motions keeps the robot
    standing where it starts, as a robot waiting for people to pass does."""
    poses, kept = _scans_of_motion(lidar, motion, scenario, clutter, clutter_rng, people, people_rng, None)
    return poses, [reading for _, reading in kept]


def _scans_of_motion(
    lidar: Lidar,
    motion: Motion,
    scenario: Scenario | None,
    clutter: int,
    clutter_rng: np.random.Generator | None,
    people: int,
    people_rng: np.random.Generator | None,
    keep: Callable[[int], bool] | None,
) -> tuple[np.ndarray, list[tuple[int, LidarReading]]]:
    """:func:`scans_of_motion`, ray-casting only the ticks ``keep`` accepts (all when ``None``)."""
    period_s = stacked_period_s(lidar.spec)
    poses = follow_waypoints((*motion.start_xy, motion.heading_rad), motion.waypoints, scan_period_s=period_s)
    items: tuple[Clutter, ...] = ()
    if clutter > 0:
        if scenario is None or clutter_rng is None:
            raise ValueError("clutter needs the scenario and a generator to place it")
        items = tuple(sample_clutter(scenario, poses, len(poses) * period_s, clutter, clutter_rng))
    walkers: tuple[Person, ...] = ()
    if people > 0:
        if scenario is None or people_rng is None:
            raise ValueError("people need the scenario and a generator to place them")
        # A door watch stands still here, after its clutter was placed about the drive it does not
        # make: moved earlier, the same command would make another set. It always has people.
        if people_rng.random() < STATIONARY_SHARE or motion.door_watch:
            poses = np.repeat(poses[:1], len(poses), axis=0)
        walkers = tuple(
            sample_people(
                scenario, poses, period_s, len(poses) * period_s, people, people_rng,
                first_behaviour="pass" if motion.door_watch else None,
            )
        )  # fmt: skip
    return poses, [
        (t, lidar.scan(tuple(pose), items, t * period_s, walkers))
        for t, pose in enumerate(poses)
        if keep is None or keep(t)
    ]


def _window_ticks(frame_stride: int) -> Callable[[int], bool] | None:
    """The ticks whose scans a sample uses: all for strides below 3, else the three of each window."""
    if frame_stride < 3:
        return None
    return lambda t: t % frame_stride < 3


def simulate_samples(
    world: World,
    scenario: Scenario,
    motions: list[Motion],
    seed: int,
    padding: Padding,
    frame_stride: int = 1,
    *,
    spec: LidarSpec = DEFAULT_SPEC,
    clutter: int = 0,
    invalid: InvalidRule = "sentinel",
    people: int = 0,
    raster_yaw_deg: float = 0.0,
) -> Iterator[Sample]:
    """Simulate one scenario and yield its samples, tensors made exactly as on the robot.

    Scans go through :class:`ScanStacker`, the FIFO the encoder service runs, so training, evaluation
    and deployment share one code path from ranges to tensor. ``spec`` is the scenario's sensor
    (noise, dropouts, spurious returns); ``clutter`` the most unlabelled clutter items per motion.
    ``raster_yaw_deg`` turns tensors and labels alike (:mod:`common.encoding`); the samples' poses and
    people stay in the world frame.
    """
    world.load(scenario)
    lidar = Lidar(world, spec, rng=np.random.default_rng(np.random.SeedSequence([seed, scenario.index, 2])))
    clutter_rng = np.random.default_rng(np.random.SeedSequence([seed, scenario.index, 4]))
    people_rng = np.random.default_rng(np.random.SeedSequence([seed, scenario.index, 6]))
    label_range = min(spec.range_max, R_MAX_M)  # past the raster's full scale a return is no box
    for p_index, motion in enumerate(motions):
        # With a frame stride of 3 or more, the windows a sample needs are disjoint: only their scans
        # are cast (the stacker then holds exactly the three scans of each sample when it is made).
        _, kept = _scans_of_motion(
            lidar, motion, scenario, clutter, clutter_rng, people, people_rng, _window_ticks(frame_stride)
        )
        readings = dict(kept)
        stacker = ScanStacker(padding, invalid, raster_yaw_deg)
        for t, reading in kept:
            tensor = stacker.push_scan(
                reading.ranges, spec.angle_min, spec.angle_increment, spec.range_min, spec.range_max
            )
            if tensor is None or (t - 2) % frame_stride:
                continue
            middle = readings[t - 1]
            labels = label_scan(
                scenario,
                middle.lidar_pose,
                spec.bearings_rad,
                middle.true_ranges,
                middle.hit_object,
                label_range,
                padding,
                middle.people_legs,
                stacker.raster_yaw_deg,
            )
            name = f"s{scenario.index:04d}_p{p_index:03d}_f{t:03d}"
            yield Sample(name, p_index, t, tensor, labels, middle.lidar_pose, middle.people_legs)


_WORLD: World | None = None


def _world() -> World:
    """One PyBullet world per worker process, reused across its scenarios."""
    global _WORLD
    if _WORLD is None:
        _WORLD = World()
    return _WORLD


def generate_scenario(index: int, split: str, config: DatasetConfig) -> ScenarioResult:
    """Simulate scenario ``index`` and write its samples; safe to run in any process, in any order."""
    scenario = sample_scenario(index, config.seed, room_half_of(config.seed, index, config.open_space))
    result = ScenarioResult(index=index, split=split, scenario_json=scenario.to_json())
    image_dir = config.out / "images" / split
    label_dir = config.out / "labels" / split
    motions = plan_motions(scenario, config.seed, config.positions, config.door_watch)
    result.positions = len(motions)
    spec = scenario_lidar_spec(config, index)
    lidar_record: dict[str, object] = {
        "noise_sigma_m": spec.noise_sigma_m,
        "dropout_rate": spec.dropout_rate,
        "spurious_rate": spec.spurious_rate,
    }
    if config.sensor != DEFAULT_PROFILE:
        lidar_record["sensor"] = scenario_sensor(config, index)
    result.scenario_json["lidar"] = lidar_record
    samples = simulate_samples(
        _world(),
        scenario,
        motions,
        config.seed,
        config.padding,
        config.frame_stride,
        spec=spec,
        clutter=config.clutter,
        invalid=config.invalid,
        people=config.people,
        raster_yaw_deg=config.raster_yaw_deg,
    )
    for sample in samples:
        write_rgb_png(image_dir / f"{sample.name}.png", sample.tensor)
        lines = yolo_lines(sample.labels)
        (label_dir / f"{sample.name}.txt").write_text("".join(f"{line}\n" for line in lines))
        for label in sample.labels:
            result.boxes_per_class[label.class_id] += len(label.boxes_px)
        result.samples += 1
        record: dict[str, object] = {
            "image": f"images/{split}/{sample.name}.png",
            "scenario": index,
            "position": sample.position,
            "frame": sample.frame,
            "lidar_pose": [round(v, 6) for v in sample.lidar_pose],
        }
        if config.people > 0:  # world-frame leg circles (x, y, r) of each person at scan t-1
            record["people_legs"] = [
                [[round(v, 4) for v in leg] for leg in legs] for legs in sample.people_legs
            ]
        result.sample_records.append(record)
    return result


def _generate_task(task: tuple[int, str, DatasetConfig]) -> ScenarioResult:
    return generate_scenario(*task)


def _results(config: DatasetConfig, splits: list[str]) -> Iterator[ScenarioResult]:
    tasks = [(i, splits[i], config) for i in range(config.scenarios)]
    if config.workers == 1:
        yield from map(_generate_task, tasks)
        return
    # fork would copy a parent's PyBullet client; spawn gives each worker a clean interpreter.
    with multiprocessing.get_context("spawn").Pool(config.workers) as pool:
        yield from pool.imap(_generate_task, tasks)


def _prepare_out_dir(out: Path, overwrite: bool) -> None:
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise FileExistsError(f"{out} is not empty; pass --overwrite to replace it")
        for child in ("images", "labels"):
            shutil.rmtree(out / child, ignore_errors=True)
        for name in ("data.yaml", "scenarios.jsonl", "samples.jsonl", "summary.json"):
            (out / name).unlink(missing_ok=True)
    for kind in ("images", "labels"):
        for split in SPLITS:
            (out / kind / split).mkdir(parents=True, exist_ok=True)


def _data_yaml(config: DatasetConfig) -> str:
    names = "\n".join(f"  {i}: {name}" for i, name in enumerate(config.classes))
    yaw = f", raster yaw {config.raster_yaw_deg!r}" if config.raster_yaw_deg else ""  # the paper's: none
    # No "path:" key: Ultralytics then resolves the splits next to this file, so the set can be moved.
    return (
        f"# triscan data set: seed {config.seed}, {config.scenarios} scenarios, padding {config.padding}, "
        f"invalid {config.invalid}{yaw}\n"
        "train: images/train\nval: images/val\ntest: images/test\n"
        f"nc: {len(config.classes)}\nnames:\n{names}\n"
    )


def generate_dataset(
    config: DatasetConfig, *, overwrite: bool = False, progress: bool = True
) -> dict[str, object]:
    """Write the whole data set under ``config.out`` and return its summary (also in ``summary.json``)."""
    _prepare_out_dir(config.out, overwrite)
    splits = split_of_scenarios(config.scenarios, config.seed)
    started = time.perf_counter()
    samples = {s: 0 for s in SPLITS}
    scenarios = {s: 0 for s in SPLITS}
    classes = config.classes
    boxes = {s: [0] * len(classes) for s in SPLITS}
    results = _results(config, splits)
    if progress:
        from tqdm import tqdm

        results = tqdm(results, total=config.scenarios, unit="scenario", desc="triscan dataset")
    with (
        (config.out / "scenarios.jsonl").open("w") as scen_file,
        (config.out / "samples.jsonl").open("w") as smp_file,
    ):
        for result in results:
            scenarios[result.split] += 1
            samples[result.split] += result.samples
            boxes[result.split] = [
                a + b
                for a, b in zip(boxes[result.split], result.boxes_per_class[: len(classes)], strict=True)
            ]
            record = {
                "split": result.split,
                "positions": result.positions,
                "samples": result.samples,
                **result.scenario_json,
            }
            scen_file.write(json.dumps(record, sort_keys=True) + "\n")
            for sample in result.sample_records:
                smp_file.write(json.dumps(sample, sort_keys=True) + "\n")
    elapsed = time.perf_counter() - started
    (config.out / "data.yaml").write_text(_data_yaml(config))
    summary: dict[str, object] = {
        "config": config.summary_fields(),
        "scenarios": scenarios,
        "samples": samples,
        "boxes_per_class": {s: dict(zip(classes, boxes[s], strict=True)) for s in SPLITS},
    }
    # Timing is reported, not stored: summary.json must be identical between two runs of one seed.
    (config.out / "summary.json").write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")
    total = sum(samples.values())
    log.info(
        "wrote %d samples from %d scenarios in %.1f s (%.0f samples/s, %d workers)",
        total,
        config.scenarios,
        elapsed,
        total / max(elapsed, 1e-9),
        config.workers,
    )
    return {**summary, "elapsed_s": elapsed, "samples_per_s": total / max(elapsed, 1e-9)}
