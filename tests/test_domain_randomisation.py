"""Domain randomisation: LiDAR imperfections, unlabelled clutter, and the data sets they make.

The clean default must stay the paper's data set byte for byte; the randomised one must differ only
where the sensor does, and its labels must remain those of the true geometry.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from services.simulator.clutter import (
    CLUTTER_OBJECT,
    Pole,
    WallStub,
    ray_circle_distances,
    ray_rect_distances,
    sample_clutter,
)
from services.simulator.lidar import DEFAULT_SPEC, Lidar
from services.simulator.scenario import Rect, sample_scenario
from services.simulator.world import World
from training.dataset import (
    DatasetConfig,
    Motion,
    generate_dataset,
    plan_motions,
    scans_of_motion,
    scenario_lidar_spec,
)


def unit_rays(degrees: list[float]) -> np.ndarray:
    rad = np.radians(degrees)
    return np.stack([np.cos(rad), np.sin(rad)], axis=1)


def test_ray_circle_distance_by_hand() -> None:
    circles = np.array([[2.0, 0.0, 0.5], [0.0, 3.0, 0.1]])
    d = ray_circle_distances((0.0, 0.0), unit_rays([0.0, 90.0, 180.0, 45.0]), circles)
    assert d[0] == pytest.approx(1.5)
    assert d[1] == pytest.approx(2.9)
    assert math.isinf(d[2]) and math.isinf(d[3])


def test_ray_rect_distance_by_hand_including_rotation() -> None:
    square = Rect((2.0, 0.0), (1.0, 1.0), 0.0)
    diamond = Rect((0.0, -2.0), (math.sqrt(2) / 2, math.sqrt(2) / 2), math.pi / 4)  # corner at y = -1.5
    d = ray_rect_distances((0.0, 0.0), unit_rays([0.0, -90.0, 90.0]), [square, diamond])
    assert d[0] == pytest.approx(1.5)
    assert d[1] == pytest.approx(1.5)
    assert math.isinf(d[2])


def test_clutter_keeps_off_furniture_and_the_robot_path() -> None:
    scenario = sample_scenario(3, seed=11)
    rng = np.random.default_rng(5)
    robot_path = np.array([[-1.2, -1.2], [-1.1, -1.2], [-1.0, -1.15]])
    kinds = set()
    for _ in range(200):
        for item in sample_clutter(scenario, robot_path, 3.0, 3, rng):
            kinds.add(type(item))
            path = item.path(3.0)
            assert np.all(np.abs(path) <= 2.0)
            for obj in scenario.objects:
                assert np.all(obj.footprint.distance(path) > item.extent_m)
            gaps = np.hypot(*(path[:, None, :] - robot_path[None]).transpose(2, 0, 1))
            assert gaps.min() >= 0.35
    assert kinds == {Pole, WallStub}
    assert sample_clutter(scenario, robot_path, 3.0, 0, rng) == []


def test_scan_merges_clutter_as_unlabelled_hits() -> None:
    with World(None) as world:  # the closed, empty room
        lidar = Lidar(world, replace(DEFAULT_SPEC, noise_sigma_m=0.0), rng=np.random.default_rng(0))
        pole = Pole((1.0, 0.0), 0.02)
        plain = lidar.scan((0.0, 0.0, 0.0))
        seen = lidar.scan((0.0, 0.0, 0.0), (pole,))
    ahead = 0  # beam 0 points along +x from the sensor, 3 cm behind the robot centre
    assert seen.hit_object[ahead] == CLUTTER_OBJECT
    assert seen.true_ranges[ahead] == pytest.approx(1.0 + 0.03 - 0.02, abs=1e-9)
    assert seen.ranges[ahead] == pytest.approx(1.01, abs=1e-6)
    changed = seen.hit_object != plain.hit_object
    assert 1 <= changed.sum() <= 3 and np.all(seen.hit_object[changed] == CLUTTER_OBJECT)
    np.testing.assert_array_equal(seen.ranges[~changed], plain.ranges[~changed])


def test_people_distances_follow_time() -> None:
    from services.simulator.people import _build, people_distances

    person = _build([(1.0, 0.0), (1.0, 20.0)], [1.0], [0.0], 0.0, 4.0, 0.05, 0.2, math.pi / 2)
    rays = unit_rays([0.0, 3.0, -3.0])
    assert np.isfinite(people_distances([person], (0.0, 0.0), rays, 0.0)[0]).any()
    assert np.isinf(people_distances([person], (0.0, 0.0), rays, 3.0)[0]).all()  # walked 3 m away


def test_dropouts_and_spurious_returns_leave_the_noise_stream_alone() -> None:
    pose = (0.0, 0.0, 0.3)
    with World(None) as world:
        clean = Lidar(world, DEFAULT_SPEC, rng=np.random.default_rng(4)).scan(pose)
        faulty_spec = replace(DEFAULT_SPEC, dropout_rate=0.2, spurious_rate=0.1)
        faulty = Lidar(world, faulty_spec, rng=np.random.default_rng(4)).scan(pose)
        again = Lidar(world, faulty_spec, rng=np.random.default_rng(4)).scan(pose)
    np.testing.assert_array_equal(faulty.ranges, again.ranges)  # seeded
    dropped = np.isinf(faulty.ranges) & np.isfinite(clean.ranges)
    short = np.isfinite(faulty.ranges) & (faulty.ranges < clean.ranges - 1e-6)
    untouched = ~dropped & ~short
    assert 0.12 < dropped.mean() < 0.3
    assert 0.03 < short.mean() < 0.17
    np.testing.assert_array_equal(faulty.ranges[untouched], clean.ranges[untouched])
    assert np.all(faulty.ranges[short] >= DEFAULT_SPEC.range_min)
    np.testing.assert_array_equal(faulty.true_ranges, clean.true_ranges)  # truth never degrades


def test_rates_outside_zero_one_are_refused() -> None:
    with pytest.raises(ValueError, match="dropout_rate"):
        replace(DEFAULT_SPEC, dropout_rate=1.5)
    with pytest.raises(ValueError, match="dropout_rate must be a range"):
        DatasetConfig(out=Path("x"), dropout_rate=(0.2, 0.1))


def test_scenario_sensors_are_drawn_from_the_ranges_and_default_to_the_paper() -> None:
    clean = DatasetConfig(out=Path("x"))
    assert scenario_lidar_spec(clean, 5) == DEFAULT_SPEC
    config = DatasetConfig(
        out=Path("x"), noise_sigma_m=(0.01, 0.03), dropout_rate=(0.0, 0.1), spurious_rate=(0.0, 0.01)
    )
    specs = [scenario_lidar_spec(config, i) for i in range(40)]
    sigmas = np.array([s.noise_sigma_m for s in specs])
    assert sigmas.min() >= 0.01 and sigmas.max() <= 0.03 and sigmas.std() > 0.003
    assert all(0.0 <= s.dropout_rate <= 0.1 and 0.0 <= s.spurious_rate <= 0.01 for s in specs)
    assert specs[3] == scenario_lidar_spec(config, 3)


def test_motion_with_clutter_is_reproducible_and_labels_ignore_clutter() -> None:
    scenario = sample_scenario(0, seed=21)
    motion: Motion = plan_motions(scenario, 21, 1)[0]
    with World(scenario) as world:
        runs = []
        for _ in range(2):
            lidar = Lidar(world, DEFAULT_SPEC, rng=np.random.default_rng(1))
            _, readings = scans_of_motion(lidar, motion, scenario, 3, np.random.default_rng(9))
            runs.append(readings)
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a.ranges, b.ranges)
    with pytest.raises(ValueError, match="clutter needs"):
        scans_of_motion(lidar, motion, None, 2, None)


@pytest.fixture(scope="module")
def clean_and_randomised(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("dr")
    base = {"scenarios": 4, "positions": 3, "seed": 13, "frame_stride": 6}
    clean, randomised = root / "clean", root / "dr"
    generate_dataset(DatasetConfig(out=clean, **base), progress=False)
    generate_dataset(
        DatasetConfig(
            out=randomised,
            noise_sigma_m=(0.01, 0.03),
            dropout_rate=(0.05, 0.1),
            spurious_rate=(0.0, 0.01),
            clutter=3,
            **base,
        ),
        progress=False,
    )
    return clean, randomised


def test_randomised_set_records_its_settings_and_keeps_true_geometry_labels(
    clean_and_randomised: tuple[Path, Path],
) -> None:
    clean, randomised = clean_and_randomised
    summary = json.loads((randomised / "summary.json").read_text())
    assert summary["config"]["dropout_rate"] == [0.05, 0.1] and summary["config"]["clutter"] == 3
    records = [json.loads(line) for line in (randomised / "scenarios.jsonl").read_text().splitlines()]
    assert all(0.05 <= r["lidar"]["dropout_rate"] <= 0.1 for r in records)
    # Same worlds, same motions: the sample list is the same and every label file is identical.
    assert (clean / "samples.jsonl").read_text() == (randomised / "samples.jsonl").read_text()
    for label in sorted((clean / "labels").rglob("*.txt")):
        assert label.read_text() == (randomised / label.relative_to(clean)).read_text()
    # ...while the scans differ, and dropouts light the sentinel row.
    from training.png import read_tensor_png

    differing, sentinel_gain = 0, 0
    for image in sorted((clean / "images").rglob("*.png")):
        a, b = read_tensor_png(image), read_tensor_png(randomised / image.relative_to(clean))
        differing += int(not np.array_equal(a, b))
        sentinel_gain += int(b[63].sum()) - int(a[63].sum())
    assert differing > 0 and sentinel_gain > 0


def test_open_space_rooms_move_only_the_walls_and_rebuild_from_their_record() -> None:
    from services.simulator.scenario import (
        OPEN_SPACE_HALF_M,
        ROOM_HALF_M,
        Scenario,
        room_half_of,
        sample_scenario,
    )

    assert {room_half_of(7, i, 0.0) for i in range(50)} == {ROOM_HALF_M}
    assert all(OPEN_SPACE_HALF_M[0] <= room_half_of(7, i, 1.0) <= OPEN_SPACE_HALF_M[1] for i in range(50))
    halves = [room_half_of(7, i, 0.5) for i in range(200)]
    assert 0.3 < np.mean([h == ROOM_HALF_M for h in halves]) < 0.7
    with pytest.raises(ValueError, match="open-space share"):
        room_half_of(7, 0, 1.5)
    paper, open_room = sample_scenario(3, 7), sample_scenario(3, 7, 5.0)
    assert open_room.objects == paper.objects and open_room.door.width_m == paper.door.width_m
    assert open_room.room_half_m == 5.0 and open_room.door.frame.center != paper.door.frame.center
    assert "room_half_m" not in paper.to_json()["door"]  # the paper's records stay as they were
    assert Scenario.from_json(open_room.to_json()) == open_room
    with pytest.raises(ValueError, match="half-width"):
        sample_scenario(3, 7, 1.5)


def test_named_and_written_imperfections_make_the_same_sensor() -> None:
    from services.simulator.lidar import NAMED_IMPERFECTIONS, with_imperfections

    worst = with_imperfections("drop10+sigma3+spur1")
    assert (worst.noise_sigma_m, worst.dropout_rate, worst.spurious_rate) == (0.03, 0.10, 0.01)
    assert with_imperfections("sigma=0.03, dropout=0.1,spurious=0.01") == worst
    assert with_imperfections("clean") == DEFAULT_SPEC
    assert with_imperfections("drop5").noise_sigma_m == DEFAULT_SPEC.noise_sigma_m  # only what is named
    assert set(NAMED_IMPERFECTIONS) == {"clean", "sigma3", "drop5", "drop5+sigma3", "drop10+sigma3+spur1"}
    for bad in ("bogus", "sigma=abc", "dropout=1.5", "colour=3"):
        with pytest.raises(ValueError):
            with_imperfections(bad)


def test_fresh_worlds_under_a_condition_keep_their_labels_and_change_their_scans() -> None:
    from services.simulator.lidar import with_imperfections
    from training.evaluate import fresh_samples

    clean = list(fresh_samples(2024, 1, 3, "zero", 6))
    noisy = list(fresh_samples(2024, 1, 3, "zero", 6, spec=with_imperfections("drop10+sigma3+spur1")))
    assert [s.name for s in clean] == [s.name for s in noisy] and len(clean) > 2
    for a, b in zip(clean, noisy, strict=True):
        np.testing.assert_array_equal(a.boxes, b.boxes)
        np.testing.assert_array_equal(a.classes, b.classes)
    assert (
        sum(int(b.tensor[63].sum()) - int(a.tensor[63].sum()) for a, b in zip(clean, noisy, strict=True)) > 0
    )


def test_fresh_open_space_worlds_keep_their_furniture_and_reach_past_the_full_scale() -> None:
    from services.simulator.sensors import profile
    from training.evaluate import FreshWorlds, fresh_samples

    long_range = profile("ust-10lx")  # 30 m: the open room's walls show, on the sentinel row past 4 m
    room = list(fresh_samples(2024, 1, 3, "zero", 6, spec=long_range))
    hall = list(fresh_samples(2024, 1, 3, "zero", 6, spec=long_range, open_space=1.0))
    assert [s.name for s in room] == [s.name for s in hall] and len(room) > 2
    sentinel = [int((s.tensor[63] > 0).sum()) for s in (*room, *hall)]
    assert sum(sentinel[len(room) :]) > 5 * sum(sentinel[: len(room)])
    for a, b in zip(room, hall, strict=True):  # the same furniture, labelled alike; the doorway moved
        np.testing.assert_array_equal(a.boxes[a.classes < 3], b.boxes[b.classes < 3])
    assert FreshWorlds(7, 2, 3, 15, open_space=0.5).source("clean").endswith(",open_space=0.5,noise=clean")


def test_fresh_worlds_with_clutter_are_the_same_worlds_with_unlabelled_things_in_them() -> None:
    from training.evaluate import FreshWorlds, fresh_samples

    plain = list(fresh_samples(2024, 1, 3, "zero", 6))
    cluttered = list(fresh_samples(2024, 1, 3, "zero", 6, clutter=3))
    assert [s.name for s in plain] == [s.name for s in cluttered] and len(plain) > 2
    changed = [not np.array_equal(a.tensor, b.tensor) for a, b in zip(plain, cluttered, strict=True)]
    assert any(changed)  # clutter returns where there were none
    # clutter is never labelled: it can hide furniture, never add a box
    assert all(len(b.boxes) <= len(a.boxes) for a, b in zip(plain, cluttered, strict=True))
    assert FreshWorlds(7, 2, 3, 15, clutter=3).source("clean") == (
        "fresh:seed=7,scenarios=2,positions=3,clutter=3,noise=clean"
    )
    assert "clutter" not in FreshWorlds(7, 2, 3, 15).source("clean")  # earlier grids keep their names
    with pytest.raises(ValueError, match="clutter must be >= 0"):
        FreshWorlds(7, 2, 3, 15, clutter=-1)


@pytest.mark.slow
def test_eval_scores_every_model_under_every_condition_on_the_same_worlds(tmp_path: Path) -> None:
    """`triscan eval --model A --model B --noise clean drop5`: one grid, identical worlds per cell."""
    from common.model_spec import SHIPPED_FP32_MODEL, SHIPPED_INT8_MODEL
    from services.cli import main as cli_main
    from training.offline import configure_offline

    configure_offline(tmp_path / "yolo")
    import onnx

    from training.onnx_model import set_metadata

    fp32, int8 = SHIPPED_FP32_MODEL, SHIPPED_INT8_MODEL
    # the same network declaring the other invalid-return rule: it must be fed tensors made that way
    relabelled = onnx.load(fp32)
    set_metadata(relabelled, {"triscan.invalid": "empty"})
    empty_rule = tmp_path / "triscan-empty-rule.onnx"
    onnx.save(relabelled, empty_rule)
    out = tmp_path / "grid"
    argv = ["eval", "--model", str(fp32), "--model", str(int8), "--fresh", "1", "--positions", "3"]
    argv += ["--model", str(empty_rule)]
    assert cli_main([*argv, "--seed", "4242", "--noise", "clean", "dropout=0.1", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    # each model's own box rounding: the shipped model's card says `pixel`, and the copy keeps it
    assert summary["worlds"]["clutter"] == 0 and set(summary["box_grid"].values()) == {"pixel"}
    assert list(summary["results"]) == ["clean", "dropout=0.1"]
    cells = [cell for row in summary["results"].values() for cell in row.values()]
    assert len(cells) == 6 and len({cell["images"] for cell in cells}) == 1 and cells[0]["images"] > 0
    summary_images = cells[0]["images"]  # the same worlds, with or without clutter
    assert list(summary["results"]["dropout=0.1"]) == [fp32.stem, int8.stem, empty_rule.stem]
    for condition in ("clean", "dropout=0.1"):
        for stem in (fp32.stem, int8.stem, empty_rule.stem):
            metrics = json.loads((out / condition / stem / "metrics.json").read_text())
            assert metrics["source"].endswith(f"noise={condition}") and metrics["model_id"].startswith(stem)
    # several conditions need simulated worlds; a bad condition fails before anything is simulated
    assert cli_main(["eval", "--model", str(fp32), "--data", str(tmp_path), "--noise", "clean", "drop5"]) == 2
    assert cli_main([*argv, "--noise", "clean", "bogus", "--out", str(tmp_path / "bad")]) == 2
    assert cli_main(["eval", "--model", str(fp32), "--data", str(tmp_path), "--clutter", "2"]) == 2
    one = ["eval", "--model", str(fp32), "--fresh", "1", "--positions", "3", "--seed", "4242"]
    assert cli_main([*one, "--clutter", "2", "--box-grid", "none", "--out", str(tmp_path / "clutter")]) == 0
    metrics = json.loads((tmp_path / "clutter" / "metrics.json").read_text())
    assert ",clutter=2,noise=clean" in metrics["source"] and metrics["images"] == summary_images
    assert metrics["box_grid"] == "none"  # asked for, over the model's own `pixel`
    # a data set of the other rule is refused, not silently misread
    (tmp_path / "summary.json").write_text(json.dumps({"config": {"invalid": "sentinel"}}))
    assert cli_main(["eval", "--model", str(empty_rule), "--data", str(tmp_path)]) == 2
    assert not (tmp_path / "bad").exists()


def test_fresh_worlds_are_encoded_with_the_models_invalid_rule() -> None:
    """Under dropouts the sentinel rule lights row 63 where the empty rule leaves the columns dark."""
    from common.encoding import SENTINEL_ROW
    from services.simulator.lidar import with_imperfections
    from training.evaluate import fresh_samples

    drop10 = with_imperfections("dropout=0.1")
    sentinel = list(fresh_samples(77, 1, 3, "zero", 6, spec=drop10))
    empty = list(fresh_samples(77, 1, 3, "zero", 6, spec=drop10, invalid="empty"))
    assert [s.name for s in sentinel] == [s.name for s in empty] and sentinel
    assert all(int(s.tensor[SENTINEL_ROW].sum()) > 0 for s in sentinel)
    for a, b in zip(sentinel, empty, strict=True):
        assert int(b.tensor[SENTINEL_ROW].sum()) < int(a.tensor[SENTINEL_ROW].sum())
        np.testing.assert_array_equal(a.boxes, b.boxes)
