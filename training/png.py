"""The data set's scan images as PNGs: a minimal, fast writer, and the reader that gives the tensor back.

The images are 64×384×3 and about 99 % zeros. Pillow spends most of its time choosing per-row
filters that buy nothing on such data; writing filter type 0 rows straight into zlib at level 1 is
three to four times faster and the files stay ~1.5 kB. Output depends only on zlib, so a seed gives
byte-identical files across Pillow versions. Any PNG reader (OpenCV in Ultralytics, Pillow) reads it.

Reading one back as the run-time tensor (:func:`read_tensor_png`) lives beside the writer because the
two must agree on the channel order (red plane = channel 0 = scan t−2); calibration, the export's
checks and the evaluation all read the data set through it.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from common.encoding import IMAGE_WIDTH, RANGE_ROWS, STACK_DEPTH
from training.onnx_model import ExportError

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
ZLIB_LEVEL = 1


def _chunk(tag: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)


def encode_rgb_png(image: np.ndarray) -> bytes:
    """PNG bytes of a ``uint8[H, W, 3]`` array, channel 0 stored as red."""
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected uint8[H, W, 3], got {image.dtype}{image.shape}")
    height, width, _ = image.shape
    rows = np.zeros((height, 1 + width * 3), dtype=np.uint8)  # leading 0 per row: filter type None
    rows[:, 1:] = image.reshape(height, -1)
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)  # 8-bit, colour type 2 (RGB)
    return (
        PNG_SIGNATURE
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", zlib.compress(rows.tobytes(), ZLIB_LEVEL))
        + _chunk(b"IEND", b"")
    )


def write_rgb_png(path: Path, image: np.ndarray) -> None:
    path.write_bytes(encode_rgb_png(image))


def read_tensor_png(path: Path) -> np.ndarray:
    """A data-set PNG as the run-time ``uint8[64, 384, 3]`` tensor (PNG red plane = channel 0 = t−2).

    Pillow returns planes in file order (R, G, B), which is the order :func:`encode_rgb_png` wrote them;
    OpenCV would return B, G, R and silently swap the oldest and newest scan. A PNG of another size is
    an :class:`~training.onnx_model.ExportError`, the one-line error of the commands that read them.
    """
    from PIL import Image

    with Image.open(path) as image:
        tensor = np.asarray(image.convert("RGB"), dtype=np.uint8)
    if tensor.shape != (RANGE_ROWS, IMAGE_WIDTH, STACK_DEPTH):
        raise ExportError(f"{path}: expected a {IMAGE_WIDTH}×{RANGE_ROWS} RGB image, got {tensor.shape}")
    return tensor
