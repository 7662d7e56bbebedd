"""The data set generator: determinism, scenario-level splits, file formats, and the trainer's view."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from common.encoding import ScanStacker
from services.simulator.lidar import Lidar, LidarSpec
from services.simulator.scenario import Scenario
from services.simulator.world import World
from training.dataset import (
    DatasetConfig,
    generate_dataset,
    plan_motions,
    scans_of_motion,
    split_of_scenarios,
)


def tree_digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


@pytest.fixture(scope="module")
def small_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("ds") / "set"
    generate_dataset(DatasetConfig(out=out, scenarios=6, positions=2, seed=7, frame_stride=4), progress=False)
    return out


def test_same_seed_gives_byte_identical_files_whatever_the_worker_count(
    small_set: Path, tmp_path: Path
) -> None:
    again = tmp_path / "again"
    generate_dataset(
        DatasetConfig(out=again, scenarios=6, positions=2, seed=7, frame_stride=4, workers=2), progress=False
    )
    first, second = tree_digest(small_set), tree_digest(again)
    assert len(first) > 20 and first == second


def test_another_seed_gives_other_data(small_set: Path, tmp_path: Path) -> None:
    other = tmp_path / "other"
    generate_dataset(
        DatasetConfig(out=other, scenarios=6, positions=2, seed=8, frame_stride=4), progress=False
    )
    assert (other / "scenarios.jsonl").read_text() != (small_set / "scenarios.jsonl").read_text()


def test_splits_are_by_scenario_and_disjoint(small_set: Path) -> None:
    samples = [json.loads(line) for line in (small_set / "samples.jsonl").read_text().splitlines()]
    split_of = {}
    for sample in samples:
        split = sample["image"].split("/")[1]
        assert split_of.setdefault(sample["scenario"], split) == split, "a scenario appears in two splits"
    assert set(split_of.values()) == {"train", "val", "test"}
    # 85/10/5 at the paper's scale: 136/16/8 scenarios.
    assert [split_of_scenarios(160, 0).count(s) for s in ("train", "val", "test")] == [136, 16, 8]


def test_layout_and_summary_agree_with_the_files(small_set: Path) -> None:
    summary = json.loads((small_set / "summary.json").read_text())
    for split in ("train", "val", "test"):
        images = sorted((small_set / "images" / split).glob("*.png"))
        labels = sorted((small_set / "labels" / split).glob("*.txt"))
        assert [p.stem for p in images] == [p.stem for p in labels]
        assert summary["samples"][split] == len(images)
        boxes = [line.split()[0] for p in labels for line in p.read_text().splitlines()]
        counts = {name: boxes.count(str(i)) for i, name in enumerate(("chair", "box", "desk", "doorframe"))}
        assert summary["boxes_per_class"][split] == counts
    for line in (small_set / "labels" / "train").glob("*.txt"):
        for row in line.read_text().splitlines():
            cls, *coords = row.split()
            assert cls in {"0", "1", "2", "3"} and all(0.0 <= float(v) <= 1.0 for v in coords)
    yaml = (small_set / "data.yaml").read_text()
    assert "train: images/train" in yaml and "3: doorframe" in yaml and "path:" not in yaml
    scenarios = [json.loads(line) for line in (small_set / "scenarios.jsonl").read_text().splitlines()]
    assert [s["index"] for s in scenarios] == list(range(6))
    assert Scenario.from_json(scenarios[0]).to_json()["objects"] == scenarios[0]["objects"]


def test_refuses_to_overwrite_without_being_asked(small_set: Path) -> None:
    with pytest.raises(FileExistsError, match="overwrite"):
        generate_dataset(DatasetConfig(out=small_set, scenarios=1, positions=1), progress=False)


def test_config_rejects_nonsense() -> None:
    with pytest.raises(ValueError):
        DatasetConfig(out=Path("x"), scenarios=0)
    with pytest.raises(ValueError, match="padding"):
        DatasetConfig(out=Path("x"), padding="mirror")  # type: ignore[arg-type]


def test_trainer_reads_the_same_tensor_the_runtime_encoder_makes(small_set: Path, tmp_path: Path) -> None:
    """Ultralytics' own loader, given a PNG we wrote, yields exactly the run-time tensor (no BGR swap)."""
    from training.offline import configure_offline

    configure_offline(tmp_path / "yolo")
    from ultralytics.data.dataset import YOLODataset

    sample = json.loads((small_set / "samples.jsonl").read_text().splitlines()[0])
    scenario = Scenario.from_json(json.loads((small_set / "scenarios.jsonl").read_text().splitlines()[0]))
    assert sample["scenario"] == scenario.index == 0
    # Re-simulate that sample the way a robot would produce it: scans → ScanStacker, the run-time path.
    spec = LidarSpec()
    with World(scenario) as world:
        lidar = Lidar(world, spec, rng=np.random.default_rng(np.random.SeedSequence([7, 0, 2])))
        _, readings = scans_of_motion(lidar, plan_motions(scenario, 7, 2)[0])
    stacker = ScanStacker("zero")
    tensors = [
        stacker.push_scan(r.ranges, spec.angle_min, spec.angle_increment, spec.range_min, spec.range_max)
        for r in readings
    ]
    runtime_tensor = tensors[sample["frame"]]
    assert runtime_tensor is not None and runtime_tensor.any()

    split = sample["image"].split("/")[1]
    data = {"names": {0: "chair", 1: "box", 2: "desk", 3: "doorframe"}, "nc": 4, "channels": 3}
    dataset = YOLODataset(
        img_path=str(small_set / "images" / split),
        imgsz=384,
        augment=False,
        rect=True,
        pad=0.0,
        batch_size=1,
        stride=32,
        data=data,
    )
    index = [Path(f).name for f in dataset.im_files].index(Path(sample["image"]).name)
    trainer_tensor = dataset[index]["img"].numpy()  # CHW, as the network receives it
    assert trainer_tensor.shape == (3, 64, 384)
    assert np.array_equal(trainer_tensor, runtime_tensor.transpose(2, 0, 1))
