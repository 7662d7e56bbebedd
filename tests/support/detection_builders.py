"""Wire detections built from pixel boxes through the detector's own conversion, for tests."""

from __future__ import annotations

import numpy as np

from common.messages import Detection
from common.postprocess import detections_from_boxes


def one_detection(box_xyxy: tuple[float, ...] | np.ndarray, score: float, class_id: int) -> Detection:
    """One ``Detection`` from one ``(x1, y1, x2, y2)`` box in raster pixels."""
    return detections_from_boxes(
        np.asarray(box_xyxy, dtype=np.float64).reshape(1, 4), np.array([score]), np.array([class_id])
    )[0]
