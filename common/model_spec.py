"""What a triscan model is: its classes, colours, input and output shapes, files and metadata.

Everything that must agree between training, export, the detector, the wire messages, the viewer and
the pictures lives here, so adding a class or changing the input is an edit of this one file (the
class list and its colours below), and every other module imports these names instead of restating
them.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Final, Literal, get_args

from common.encoding import IMAGE_WIDTH, PADDINGS, RANGE_ROWS, STACK_DEPTH

CLASS_NAMES: Final[tuple[str, ...]] = ("chair", "box", "desk", "doorframe", "person")
NUM_CLASSES: Final[int] = len(CLASS_NAMES)
# The paper's classes: a data set without people, and the models trained on one, hold these only.
FURNITURE_CLASSES: Final[tuple[str, ...]] = CLASS_NAMES[:4]
PERSON: Final[str] = CLASS_NAMES[4]  # the class the paper left to future work
PERSON_ID: Final[int] = CLASS_NAMES.index(PERSON)
# A person's box is the disc of this radius about the midpoint of their legs: a walking person's legs
# stay within about 0.3 m of it (half a fast step; docs/people.md).
PERSON_FOOTPRINT_RADIUS_M: Final[float] = 0.3

Rgb = tuple[int, int, int]
# One palette for the viewer and the pictures. It avoids the pure and mixed channel colours (red,
# green, blue, yellow, cyan, magenta, white) that lit scan pixels take in the R/G/B raster, so a box
# or outline drawn over a scan is never mistaken for one.
CLASS_COLOURS: Final[tuple[Rgb, ...]] = (
    (255, 150, 30),  # chair: orange
    (180, 130, 255),  # box: lavender
    (255, 95, 170),  # desk: pink
    (215, 205, 130),  # doorframe: khaki
    (120, 230, 255),  # person: sky blue
)
UNKNOWN_CLASS_COLOUR: Final[Rgb] = (128, 128, 128)
assert len(CLASS_COLOURS) == NUM_CLASSES, "one colour per class"

# The network's input: the stacked tensor as HWC uint8 on the wire, NCHW float32 in the model.
TENSOR_SHAPE: Final[tuple[int, int, int]] = (RANGE_ROWS, IMAGE_WIDTH, STACK_DEPTH)
INPUT_SHAPE: Final[tuple[int, int, int, int]] = (1, STACK_DEPTH, RANGE_ROWS, IMAGE_WIDTH)
STRIDES: Final[tuple[int, ...]] = (8, 16, 32)  # YOLOv8's three detection scales
NUM_ANCHORS: Final[int] = sum((RANGE_ROWS // s) * (IMAGE_WIDTH // s) for s in STRIDES)  # 504
MAX_DETECTIONS: Final[int] = 300  # per frame: the detector's cap, the wire limit and Ultralytics' max_det

# ONNX metadata written by `triscan export` and read by the detector and the launcher.
META_PREFIX: Final[str] = "triscan."
META_PADDING: Final[str] = f"{META_PREFIX}padding"
META_INVALID: Final[str] = f"{META_PREFIX}invalid"
META_CLASSES: Final[str] = f"{META_PREFIX}classes"
META_BOX_GRID: Final[str] = f"{META_PREFIX}box_grid"
META_STACK_PERIOD: Final[str] = f"{META_PREFIX}stack_period_s"
# Degrees the model's raster is turned by (common.encoding, "Raster yaw"); absent: 0, the paper's.
META_RASTER_YAW: Final[str] = f"{META_PREFIX}raster_yaw_deg"

# Labels are whole pixels (a range row, a beam column): "pixel" rounds a model's box edges to them
# after NMS, which tightens small boxes at high IoU; "none" keeps the regressed edges, as every model
# exported before the key existed does.
BoxGrid = Literal["none", "pixel"]
BOX_GRIDS: Final[tuple[str, ...]] = get_args(BoxGrid)
DEFAULT_BOX_GRID: Final[BoxGrid] = "none"

# Files: <stem>.onnx (fp32), <stem>-int8.onnx, and each with a free batch axis as <...>-batch.onnx.
MODEL_PREFIX: Final[str] = "triscan-"
INT8_SUFFIX: Final[str] = "-int8"
BATCH_SUFFIX: Final[str] = "-batch"
MODELS_PACKAGE: Final[str] = "triscan_models"  # models/ once installed (pyproject.toml, docs/packaging.md)


def _models_dir() -> Path:
    """The shipped models: ``models/`` beside the code in a source checkout, else the installed package
    :data:`MODELS_PACKAGE`, so a non-editable install finds them from any directory. The checkout's own
    directory wins over an installed copy, so a checkout never runs another install's models."""
    beside = Path(__file__).resolve().parents[1] / "models"
    if (beside / "MODEL_CARD.json").is_file():  # the paper's card: triscan's models/, not a namesake
        return beside
    from importlib.resources import files

    try:
        installed = files(MODELS_PACKAGE)
    except ModuleNotFoundError:
        return beside  # neither: opening a model names the path it looked for
    return installed if isinstance(installed, Path) else beside


MODELS_DIR: Final[Path] = _models_dir()
MODEL_ENV: Final[str] = "TRISCAN_MODEL"
# Each shipped network's files and card (MODEL_CARD.json) share one directory: the paper's YOLOv8n in
# models/ itself, the pico with 12 DFL bins in models/yolov8p-dfl12/, the five-class people preview in
# models/yolov8p-relu-dfl12/. The default is the 12-bin pico:
# it meets every accuracy goal on unseen worlds in fp32 and INT8 and runs faster than YOLOv8n
# (models/yolov8p-dfl12/MODEL_CARD.md).
SHIPPED_DIR: Final[Path] = MODELS_DIR / "yolov8p-dfl12"
SHIPPED_STEM: Final[str] = "triscan-yolov8p-dfl12-zero"
SHIPPED_FP32_MODEL: Final[Path] = SHIPPED_DIR / f"{SHIPPED_STEM}.onnx"
SHIPPED_INT8_MODEL: Final[Path] = SHIPPED_DIR / f"{SHIPPED_STEM}{INT8_SUFFIX}.onnx"
SHIPPED_CHECKPOINT: Final[Path] = SHIPPED_DIR / f"{SHIPPED_STEM}.pt"
# The paper's network as trained here (YOLOv8n, same data): Ultralytics `predict` on this checkpoint
# is "the paper's runtime" the speed goals are measured against, whatever network is the default.
PAPER_CHECKPOINT: Final[Path] = MODELS_DIR / "triscan-yolov8n-zero.pt"
# What the detector runs when given no model: the file the card recommends (INT8 only where it is
# faster and within half a point of fp32's mAP@0.5 everywhere measured). tests/test_shipped_model.py
# holds the two to agreement, so a re-exported card that recommends fp32 cannot ship beside this.
SHIPPED_MODEL: Final[Path] = SHIPPED_INT8_MODEL


def model_stem(network: str, padding: str, invalid: str = "sentinel") -> str:
    """``triscan-yolov8p-zero``: the file stem that names the network, the padding and, when it is not
    the paper's sentinel row, the invalid-return rule (``triscan-yolov8p-zero-invalid-empty``), so two
    models of one network that read scans differently never share a file name."""
    return f"{MODEL_PREFIX}{network}-{padding}" + ("" if invalid == "sentinel" else f"-invalid-{invalid}")


def network_of_stem(stem: str) -> str:
    """``triscan-yolov8p-zero-int8`` → ``yolov8p``, ``triscan-yolov8p-relu-zero`` → ``yolov8p-relu``: the
    network a model file names (:func:`model_stem`), everything between the prefix and the padding."""
    parts = stem.removeprefix(MODEL_PREFIX).split("-")
    padding_at = next((i for i, part in enumerate(parts) if part in PADDINGS), 0)
    if not stem.startswith(MODEL_PREFIX) or padding_at == 0:
        raise ValueError(f"{stem!r} is not a triscan model stem ({MODEL_PREFIX}<network>-<padding>…)")
    return "-".join(parts[:padding_at])


NETWORK_TITLES: Final[dict[str, str]] = {
    "yolov8n": "YOLOv8n",
    "yolov8p": "YOLOv8p (pico: YOLOv8 at width 0.125)",
    "yolov8p-relu": "YOLOv8p-ReLU (pico with ReLU instead of SiLU)",
    "yolov8p-dfl12": "YOLOv8p-DFL12 (pico with 12 DFL bins: a box branch three quarters as wide)",
    "yolov8p-relu-dfl12": "YOLOv8p-ReLU-DFL12 (pico with ReLU and 12 DFL bins)",
    "yolov8p-dfl8": "YOLOv8p-DFL8 (pico with 8 DFL bins: a box branch half as wide)",
    "yolov8p-relu-dfl8": "YOLOv8p-ReLU-DFL8 (pico with ReLU and 8 DFL bins)",
}


def network_title(network: str) -> str:
    return NETWORK_TITLES.get(network, network)


def batch_variant_path(model_path: Path) -> Path:
    """Where the free-batch-axis copy of a model goes: ``<stem>-batch.onnx`` beside it."""
    return model_path.with_name(f"{model_path.stem}{BATCH_SUFFIX}{model_path.suffix}")


SHIPPED_BATCH_MODEL: Final[Path] = batch_variant_path(SHIPPED_MODEL)


def default_model_path(batched: bool = False) -> Path:
    """``$TRISCAN_MODEL`` if set, else the shipped model (its batch variant when ``batched``)."""
    if os.environ.get(MODEL_ENV):
        return Path(os.environ[MODEL_ENV])
    return SHIPPED_BATCH_MODEL if batched else SHIPPED_MODEL


def file_sha256(path: Path) -> str:
    """Hex SHA-256 of a file: model ids, the card and the batch variants name weights by it."""
    with path.open("rb") as handle:
        return hashlib.file_digest(handle, "sha256").hexdigest()


def file_model_id(path: Path) -> str:
    """``<stem>@<12 hex of sha256>``: names the exact weights, so a result can be traced to its file."""
    return f"{path.stem}@{file_sha256(path)[:12]}"
