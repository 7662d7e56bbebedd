"""One sample of a ``triscan dataset`` data set, read back and checked: what ``triscan show`` draws.

A sample is spread over five files (its PNG, its YOLO label lines, a line of samples.jsonl with the
LiDAR pose, a line of scenarios.jsonl with the room, and summary.json with the padding), and data sets
get copied, trimmed and hand-edited. :func:`load_sample` gathers them into one :class:`Sample` and
names the file and line of anything missing or malformed, so the pictures never have to guess.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from common.encoding import ANGLE_COLUMNS, IMAGE_WIDTH, PAD_COLUMNS, RANGE_ROWS
from common.model_spec import CLASS_NAMES
from services.simulator.scenario import Scenario
from training.onnx_export import dataset_raster_yaw

Pose = tuple[float, float, float]


@dataclass(frozen=True)
class LabelBox:
    """One YOLO label line in raster pixels (continuous coordinates, x2/y2 exclusive)."""

    class_id: int
    x1: float
    y1: float
    x2: float
    y2: float


@dataclass(frozen=True)
class Sample:
    """Everything the two pictures need about one sample, read and checked from the data set."""

    name: str
    image_path: Path
    split: str
    tensor: np.ndarray  # uint8[64, 384, 3]: channel 0 = t-2, 1 = t-1, 2 = t
    boxes: tuple[LabelBox, ...]
    lidar_pose: Pose  # of the middle scan t-1, world frame
    scenario: Scenario
    position: int
    frame: int
    padding: str
    people_legs: tuple[tuple[tuple[float, float, float], ...], ...] = ()  # world frame, at scan t-1
    raster_yaw_deg: float = 0.0  # degrees the set turned its scans by (common.encoding)


def _read_jsonl(path: Path) -> list[dict[str, Any]]:
    """Every record of a JSON-lines file; a bad line is named (file:line), as sets get hand-edited."""
    if not path.is_file():
        raise FileNotFoundError(f"data set file {path} is missing (is this a `triscan dataset` output?)")
    records = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}:{number}: not valid JSON ({exc.msg})") from exc
    return records


def _select_record(
    records: list[dict[str, Any]], samples_path: Path, sample: str | None, index: int
) -> dict[str, Any]:
    """Find the sample by image path (``images/train/x.png``), file name or stem; else by line index."""
    if not records:
        raise ValueError(f"{samples_path} lists no samples")
    if sample is None:
        if not 0 <= index < len(records):
            raise ValueError(
                f"sample index {index} is out of range: {samples_path} has {len(records)} samples "
                f"(valid: 0..{len(records) - 1})"
            )
        return records[index]
    wanted = sample.strip().replace("\\", "/")
    for record in records:
        image = str(record.get("image", ""))
        if wanted in (image, Path(image).name, Path(image).stem):
            return record
    examples = ", ".join(Path(str(r.get("image", ""))).stem for r in records[:3])
    raise ValueError(
        f"sample {sample!r} is not in {samples_path} ({len(records)} samples, e.g. {examples}); "
        "give an image path like images/train/<name>.png, a file name or a stem"
    )


def _read_tensor(image_path: Path) -> np.ndarray:
    """The PNG as the uint8[64, 384, 3] tensor, in file channel order (R = t-2, as written)."""
    if not image_path.is_file():
        raise FileNotFoundError(f"sample image {image_path} is missing")
    with Image.open(image_path) as image:
        if image.mode != "RGB" or image.size != (IMAGE_WIDTH, RANGE_ROWS):
            raise ValueError(
                f"{image_path} is {image.mode} {image.size[0]}x{image.size[1]}, "
                f"expected RGB {IMAGE_WIDTH}x{RANGE_ROWS}"
            )
        return np.asarray(image, dtype=np.uint8).copy()


def _read_boxes(label_path: Path) -> tuple[LabelBox, ...]:
    """YOLO lines ``cls xc yc w h`` (normalised by 384 and 64) back to raster-pixel boxes."""
    if not label_path.is_file():
        raise FileNotFoundError(f"label file {label_path} is missing")
    boxes = []
    for number, line in enumerate(label_path.read_text().splitlines(), start=1):
        fields = line.split()
        if not fields:
            continue
        try:
            if len(fields) != 5:
                raise ValueError(f"{len(fields)} fields")
            class_id = int(fields[0])
            xc, yc, w, h = (float(v) for v in fields[1:])
        except ValueError as exc:
            raise ValueError(f"{label_path}:{number}: expected 'cls xc yc w h', got {line!r}") from exc
        if not 0 <= class_id < len(CLASS_NAMES):
            raise ValueError(
                f"{label_path}:{number}: class {class_id} is not one of 0..{len(CLASS_NAMES) - 1}"
            )
        boxes.append(
            LabelBox(
                class_id,
                (xc - w / 2) * IMAGE_WIDTH,
                (yc - h / 2) * RANGE_ROWS,
                (xc + w / 2) * IMAGE_WIDTH,
                (yc + h / 2) * RANGE_ROWS,
            )
        )
    return tuple(boxes)


def _padding_of(dataset_dir: Path, tensor: np.ndarray) -> str:
    """The set's padding mode from summary.json; an old set without one is judged from its pixels."""
    summary = dataset_dir / "summary.json"
    if summary.is_file():
        padding = json.loads(summary.read_text()).get("config", {}).get("padding")
        if isinstance(padding, str):
            return padding
    pad = tensor[:, ANGLE_COLUMNS:]
    if not pad.any():
        return "zero"
    return "wrap" if np.array_equal(pad, tensor[:, :PAD_COLUMNS]) else "unknown"


def load_sample(dataset_dir: Path, *, sample: str | None = None, index: int = 0) -> Sample:
    """Read one sample (image, labels, pose, scenario) from a data set written by ``training.dataset``.

    Raises ``FileNotFoundError`` naming the missing file and ``ValueError`` for an unknown sample, an
    index out of range or a malformed file: ``triscan show`` reports both as one clear line.
    """
    dataset_dir = Path(dataset_dir)
    if not dataset_dir.is_dir():
        raise FileNotFoundError(f"data set directory {dataset_dir} does not exist")
    samples_path = dataset_dir / "samples.jsonl"
    scenarios_path = dataset_dir / "scenarios.jsonl"
    record = _select_record(_read_jsonl(samples_path), samples_path, sample, index)
    try:
        image_rel = Path(str(record["image"]))
        scenario_index = int(record["scenario"])
        pose = tuple(float(v) for v in record["lidar_pose"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{samples_path}: malformed sample record {record!r}") from exc
    if len(pose) != 3:
        raise ValueError(f"{samples_path}: lidar_pose of {image_rel} must be [x, y, yaw], got {pose}")
    scenario_record = next(
        (r for r in _read_jsonl(scenarios_path) if int(r.get("index", -1)) == scenario_index), None
    )
    if scenario_record is None:
        raise ValueError(f"scenario {scenario_index} of sample {image_rel} is not in {scenarios_path}")
    if len(image_rel.parts) < 3 or image_rel.parts[0] != "images":
        raise ValueError(f"{samples_path}: image path {image_rel} is not images/<split>/<name>.png")
    split = image_rel.parts[1]
    label_path = dataset_dir / "labels" / Path(*image_rel.parts[1:]).with_suffix(".txt")
    tensor = _read_tensor(dataset_dir / image_rel)
    return Sample(
        name=image_rel.stem,
        image_path=dataset_dir / image_rel,
        split=str(scenario_record.get("split", split)),
        tensor=tensor,
        boxes=_read_boxes(label_path),
        lidar_pose=(pose[0], pose[1], pose[2]),
        scenario=Scenario.from_json(scenario_record),
        position=int(record.get("position", -1)),
        frame=int(record.get("frame", -1)),
        padding=_padding_of(dataset_dir, tensor),
        people_legs=_people_legs(record, samples_path),
        raster_yaw_deg=dataset_raster_yaw(dataset_dir),
    )


def _people_legs(
    record: dict[str, Any], samples_path: Path
) -> tuple[tuple[tuple[float, float, float], ...], ...]:
    """Each person's leg circles of a sample record (none in a set without people)."""
    try:
        return tuple(
            tuple((float(x), float(y), float(r)) for x, y, r in legs)
            for legs in record.get("people_legs", [])
        )
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{samples_path}: malformed people_legs in {record.get('image')!r}") from exc
