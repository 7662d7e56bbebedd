"""The occupancy-grid baseline the paper compares against, rebuilt for timing (Najem et al. style).

The paper's contrast is between its 64×384 three-scan raster and the common alternative: draw the
scan into a robot-centred square occupancy-grid image and run a stock YOLOv8n on it at 640×640
(846.5 ms against 47.8 ms on a Raspberry Pi 5, in the paper). This module rebuilds that alternative so
both can be timed on the same scans, with the same runtime and the same post-processing:

* :func:`rasterise_occupancy_grid`: a scan → ``uint8[640, 640, 3]`` image, robot at the centre,
  robot forward (REP-103 +x) pointing up the image and robot left (+y) pointing left, ``radius_m``
  (default ``R_MAX`` = 4 m, so 8 m across: 1.25 cm per pixel at 640) from the centre to each edge.
  Every valid return sets its pixel to 255 in all three channels; everything else is 0 (the
  simplest grid: occupied vs. not, no free-space ray casting, no map accumulation). Vectorised numpy.
* :func:`grid_model_onnx`: a YOLOv8n built from Ultralytics' ``yolov8n.yaml`` with ``nc = 4`` and
  **random initial weights** (no trained grid model exists in this project, and none is needed to
  time it: the graph and its cost do not depend on the weight values), exported once with
  Ultralytics' own ONNX exporter at ``imgsz`` exactly like the shipped triscan model, and cached.
* :class:`GridDetector`: that ONNX file in ONNX Runtime with the session options of
  :class:`common.inference.OnnxDetector`, decoded with this project's ``decode_yolov8`` + ``nms``.

Untrained weights put every class score far below the 0.25 threshold (YOLOv8's class-bias prior), so
the baseline's decode + NMS sees almost no candidates: if anything that flatters the baseline.
"""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
import time
from pathlib import Path
from typing import Final

import numpy as np
import onnxruntime as ort

from common.encoding import R_MAX_M, scan_points_xy
from common.inference import session_options
from common.model_spec import MAX_DETECTIONS
from common.postprocess import DEFAULT_CONF, DEFAULT_IOU, decode_yolov8, nms

log = logging.getLogger(__name__)

GRID_PX: Final[int] = 640
GRID_RADIUS_M: Final[float] = R_MAX_M
GRID_CLASSES: Final[int] = 4
OCCUPIED: Final[np.uint8] = np.uint8(255)
_NS_PER_MS: Final[float] = 1e6


def rasterise_occupancy_grid(
    ranges: np.ndarray,
    angle_min: float,
    angle_increment: float,
    range_min: float,
    range_max: float,
    *,
    size: int = GRID_PX,
    radius_m: float = GRID_RADIUS_M,
) -> np.ndarray:
    """One scan as a robot-centred ``uint8[size, size, 3]`` occupancy image (see the module docstring).

    Pixel ``(row, col)`` covers ``x ∈ (radius − (row + 1)·res, radius − row·res]`` and likewise ``y``
    along the columns, ``res = 2·radius / size``; returns outside the square are left out.
    """
    if size < 1 or radius_m <= 0.0:
        raise ValueError(f"need size >= 1 and radius_m > 0, got {size} and {radius_m}")
    points = scan_points_xy(ranges, angle_min, angle_increment, range_min, range_max)
    pixels_per_m = size / (2.0 * radius_m)
    rows = np.floor((radius_m - points[:, 0]) * pixels_per_m).astype(np.int64)
    cols = np.floor((radius_m - points[:, 1]) * pixels_per_m).astype(np.int64)
    inside = (rows >= 0) & (rows < size) & (cols >= 0) & (cols < size)
    image = np.zeros((size, size, 3), dtype=np.uint8)
    image[rows[inside], cols[inside]] = OCCUPIED
    return image


def grid_model_input(image: np.ndarray) -> np.ndarray:
    """HWC ``uint8`` image → ``float32[1, 3, H, W]`` in [0, 1] (the conversion triscan's tensor gets)."""
    return image.transpose(2, 0, 1)[None].astype(np.float32) / np.float32(255.0)


def grid_model_onnx(cache_dir: Path, imgsz: int = GRID_PX, seed: int = 0) -> Path:
    """The untrained YOLOv8n (nc=4) grid model as fixed-shape ONNX at ``imgsz``, exported once and cached.

    The cache key is the image size, the seed of the random initialisation and the Ultralytics
    version; a file being written is renamed into place only when complete, so an interrupted export
    never leaves a broken cache entry.
    """
    from training.offline import configure_offline

    configure_offline()
    import torch
    import ultralytics
    import yaml
    from ultralytics import YOLO
    from ultralytics.nn.tasks import yaml_model_load

    cache_dir = Path(cache_dir)
    key = f"nc{GRID_CLASSES}-untrained-seed{seed}-{imgsz}px-ultralytics{ultralytics.__version__}"
    target = cache_dir / f"grid-yolov8n-{key}.onnx"
    if target.is_file():
        log.info("grid model: cached %s", target)
        return target
    cache_dir.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="triscan-grid-", dir=cache_dir) as scratch:
        config = yaml_model_load("yolov8n.yaml")
        config["nc"] = GRID_CLASSES
        for derived in ("yaml_file", "scale"):  # re-derived from the file name ("…v8n…" → scale n)
            config.pop(derived, None)
        model_yaml = Path(scratch) / "yolov8n-grid.yaml"
        model_yaml.write_text(yaml.safe_dump(config, sort_keys=False))
        torch.manual_seed(seed)
        yolo = YOLO(str(model_yaml), task="detect")
        # A model built from a YAML file is exported into the working directory: make that the scratch.
        # Ultralytics logs its export banner at INFO: keep it out of the benchmark's printed table.
        ultralytics_log = logging.getLogger("ultralytics")
        level = ultralytics_log.level
        ultralytics_log.setLevel(logging.WARNING)
        try:
            with contextlib.chdir(scratch):
                exported = yolo.export(
                    format="onnx",
                    imgsz=imgsz,
                    batch=1,
                    dynamic=False,
                    simplify=True,
                    nms=False,
                    device="cpu",
                    verbose=False,
                )
                exported = Path(exported).resolve()
        finally:
            ultralytics_log.setLevel(level)
        os.replace(exported, target)
    log.info("grid model: exported %s in %.1f s", target, time.perf_counter() - started)
    return target


class GridDetector:
    """The grid model in ONNX Runtime, post-processed with this project's decode + NMS."""

    def __init__(
        self,
        model_path: Path,
        *,
        intra_op_threads: int,
        conf_threshold: float = DEFAULT_CONF,
        iou_threshold: float = DEFAULT_IOU,
    ) -> None:
        self._session = ort.InferenceSession(  # the options OnnxDetector uses for the triscan model
            str(model_path),
            sess_options=session_options(intra_op_threads),
            providers=["CPUExecutionProvider"],
        )
        model_input = self._session.get_inputs()[0]
        self._input_name = model_input.name
        self._output_names = [self._session.get_outputs()[0].name]
        self.size = int(model_input.shape[-1])
        self.conf_threshold = conf_threshold
        self.iou_threshold = iou_threshold

    def detect_boxes(
        self, image: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[float, float, float]]:
        """Boxes (xyxy pixels), scores, class ids and ``(preprocess, inference, postprocess)`` in ms."""
        t0 = time.perf_counter_ns()
        model_input = grid_model_input(image)
        t1 = time.perf_counter_ns()
        output = self._session.run(self._output_names, {self._input_name: model_input})[0]
        t2 = time.perf_counter_ns()
        boxes, scores, class_ids = decode_yolov8(output, self.conf_threshold, num_classes=GRID_CLASSES)
        keep = nms(boxes, scores, class_ids, self.iou_threshold, MAX_DETECTIONS)
        boxes = np.clip(boxes[keep], np.float32(0.0), np.float32(self.size))
        t3 = time.perf_counter_ns()
        stages = ((t1 - t0) / _NS_PER_MS, (t2 - t1) / _NS_PER_MS, (t3 - t2) / _NS_PER_MS)
        return boxes, scores[keep], class_ids[keep], stages
