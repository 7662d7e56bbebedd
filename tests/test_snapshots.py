"""``triscan up --snapshot``: the newest complete frame per robot, drawn from the loop's messages."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from common.messages import StackedTensor
from common.model_spec import CLASS_COLOURS
from services.bag_replay import ReplayConfig
from services.launcher import UpConfig
from tests.test_run_summary import MS, detection, detections, truth, truth_object
from training.raster_picture import RASTER_ORIGIN
from training.snapshots import RASTER_SCALE, LiveFrames


def tensor(seq: int, robot: str = "robot0") -> StackedTensor:
    pixels = np.zeros((64, 384, 3), np.uint8)
    pixels[30, 100:120, :] = 255
    return StackedTensor(
        robot_id=robot,
        seq=seq,
        stamp_ns=100 * seq * MS,
        tensor=pixels,
        padding="zero",
        scan_seqs=(seq - 2, seq - 1, seq),
        scan_stamps_ns=(100 * (seq - 2) * MS, 100 * (seq - 1) * MS, 100 * seq * MS),
    )


def test_the_newest_paired_frame_is_drawn_once_with_the_models_boxes(tmp_path: Path) -> None:
    frames = LiveFrames(seed=1)
    box = (98.0, 26.0, 122.0, 34.0)
    for seq in (4, 5):
        frames.update(truth(seq, [truth_object(1, box)]))
    frames.update(tensor(5))
    frames.update(detections(5, [detection(1, box, 0.8)]))
    written = frames.write(tmp_path)
    assert sorted(p.name for p in written) == ["robot0_map.png", "robot0_raster.png"]
    raster = np.asarray(Image.open(tmp_path / "robot0_raster.png").convert("RGB"))
    ox, oy = RASTER_ORIGIN
    left, bottom = ox + round(box[0] * RASTER_SCALE), oy + round(box[3] * RASTER_SCALE) - 1
    under = raster[bottom + 2 : bottom + 15, left : left + 60]  # the model's tag, under its box
    assert np.all(under == np.array(CLASS_COLOURS[1]), axis=-1).any()
    assert frames.write(tmp_path) == []  # nothing new: nothing redrawn
    assert not list(tmp_path.glob(".*partial"))


def test_a_frame_without_its_tensor_or_with_another_stamp_is_not_drawn(tmp_path: Path) -> None:
    frames = LiveFrames(seed=1)
    frames.update(truth(4, []))
    frames.update(truth(5, [], stamp_ms=12345))  # another stream's scan 5
    frames.update(tensor(5))
    frames.update(detections(5, []))
    frames.update(detections(7, []))  # no tensor, no truth
    assert frames.write(tmp_path) == []


def test_snapshots_need_the_simulator() -> None:
    with pytest.raises(ValueError, match="--snapshot"):
        UpConfig(snapshot_dir=Path("x"), replay=ReplayConfig(bags=(Path("b.bag"),)))
