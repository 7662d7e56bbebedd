"""``triscan up --snapshot DIR``: the loop's newest frame as pictures, for a machine without a display.

Every ``SNAPSHOT_PERIOD_S`` the launcher calls :meth:`LiveFrames.write`, which draws, per robot, the
newest frame whose tensor, detections and truth have all arrived: ``<robot>_raster.png`` (the tensor
the detector read, with the label boxes of its middle scan solid and the model's boxes dashed,
:mod:`training.raster_picture`) and ``<robot>_map.png`` (the world from above with the tensor's hits,
:mod:`training.map_picture`). Files are replaced whole (written beside, then renamed), so a viewer
never reads half a picture.

Pairing follows :mod:`services.run_summary`: the detections of seq t belong to the tensor of seq t,
whose boxes are those of the middle scan t-1; the truth of t-1 gives the labels and the pose, the truth
of t must carry the tensor's stamp. The world is rebuilt from the truth's ``scenario_id`` and the
simulator's seed (``sample_scenario``), as the simulator built it.
"""

from __future__ import annotations

import functools
import os
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

from PIL import Image

from common.messages import Detections, GroundTruth, StackedTensor
from services.simulator.scenario import Scenario, sample_scenario
from training.dataset_sample import LabelBox, Sample
from training.map_picture import draw_map_picture
from training.raster_picture import DetectedBox, draw_raster_picture

SNAPSHOT_PERIOD_S = 5.0
SNAPSHOT_ROBOTS = 4  # drawn per period (the first by name): drawing runs in the launcher's own loop
KEPT = 16  # tensors and truths kept per robot to pair with detections a few scans late
RASTER_SCALE = 3
T = TypeVar("T")


@dataclass
class _Robot:
    tensors: OrderedDict[int, StackedTensor] = field(default_factory=OrderedDict)
    truths: OrderedDict[int, GroundTruth] = field(default_factory=OrderedDict)
    newest: tuple[StackedTensor, Detections, GroundTruth] | None = None
    drawn_seq: int | None = None


def _keep(items: OrderedDict[int, T], seq: int, item: T) -> None:
    items[seq] = item
    items.move_to_end(seq)
    while len(items) > KEPT:
        items.popitem(last=False)


class LiveFrames:
    """The newest complete frame per robot, drawn on demand; :meth:`update` may be called from threads."""

    def __init__(self, seed: int) -> None:
        self.seed = seed
        self._robots: dict[str, _Robot] = {}
        self._lock = threading.Lock()

    def update(self, message: StackedTensor | Detections | GroundTruth) -> None:
        with self._lock:
            robot = self._robots.setdefault(message.robot_id, _Robot())
            if isinstance(message, StackedTensor):
                _keep(robot.tensors, message.seq, message)
            elif isinstance(message, GroundTruth):
                _keep(robot.truths, message.seq, message)
            else:
                tensor, newest = robot.tensors.get(message.seq), robot.truths.get(message.seq)
                middle = robot.truths.get(message.seq - 1)
                if tensor is None or newest is None or middle is None:
                    return
                if tensor.stamp_ns == message.scan_stamp_ns == newest.stamp_ns:
                    robot.newest = (tensor, message, middle)

    def write(self, out_dir: Path) -> list[Path]:
        """Draw each robot's newest frame not drawn yet (at most ``SNAPSHOT_ROBOTS``); the paths written."""
        with self._lock:
            todo = [
                (robot_id, robot.newest)
                for robot_id, robot in sorted(self._robots.items())
                if robot.newest is not None and robot.newest[1].seq != robot.drawn_seq
            ][:SNAPSHOT_ROBOTS]
            for robot_id, frame in todo:
                self._robots[robot_id].drawn_seq = frame[1].seq
        out_dir.mkdir(parents=True, exist_ok=True)
        written = []
        for robot_id, (tensor, detections, truth) in todo:
            sample = self._sample(tensor, truth)
            found = [DetectedBox(d.class_id, *d.box_px, d.score) for d in detections.detections]
            for kind, picture in (
                ("raster", draw_raster_picture(sample, RASTER_SCALE, found)),
                ("map", draw_map_picture(sample)),
            ):
                written.append(_replace_png(picture, out_dir / f"{robot_id}_{kind}.png"))
        return written

    def _sample(self, tensor: StackedTensor, truth: GroundTruth) -> Sample:
        """The frame as a data-set sample: what the pictures draw (frame: the middle scan's seq)."""
        labels = tuple(LabelBox(obj.class_id, *obj.box_px) for obj in truth.objects if obj.box_px is not None)
        return Sample(
            name=f"{tensor.robot_id} seq {truth.seq}",
            image_path=Path(f"{tensor.robot_id}_raster.png"),
            split="live",
            tensor=tensor.tensor,
            boxes=labels,
            lidar_pose=truth.lidar_pose,
            scenario=_scenario(truth.scenario_id, self.seed),
            position=0,
            frame=truth.seq,
            padding=tensor.padding,
        )


@functools.lru_cache(maxsize=64)
def _scenario(index: int, seed: int) -> Scenario:
    return sample_scenario(index, seed)


def _replace_png(picture: Image.Image, path: Path) -> Path:
    partial = path.with_name(f".{path.name}.partial")
    picture.save(partial, format="PNG")
    os.replace(partial, path)
    return path
