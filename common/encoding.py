"""Three-frame RGB scan encoding of the paper, and its inverse (README, "The encoding").

A 2D scan (bearings θ, ranges ρ) becomes a sparse binary image: 64 range rows × 360 one-degree angle
columns, padded to 384 columns so the width is a multiple of YOLO's stride 32. The last three images,
stacked as channels (0 = scan t−2, 1 = t−1, 2 = t), are the detector's input: motion shows up as
colour, and no pose alignment or occupancy grid is needed.

Conventions, fixed here once for every process:

* Bearings are counter-clockwise from the sensor's forward axis (ROS REP-103: x forward, y left).
* Column ``a = floor(deg(θ) + 0.5) mod 360``: rounding half up, so 359.5° lands in column 0.
* Raster yaw ``Y`` (degrees, a model's property like its padding; 0 for the paper's models): a model
  with yaw ``Y`` sees every scan turned by ``Y``, column ``a = floor(deg(θ) + Y + 0.5) mod 360``. With
  ``Y = 180`` the 0°/360° seam lies behind the robot instead of on its heading, where the people in
  front of it walk (docs/encoding-and-simulator.md). Pixels and boxes are in the turned (raster)
  frame; :func:`raster_to_laser_bearing_deg` turns their bearings back to the laser frame.
* Row ``r = floor(clip(ρ · 63 / R_MAX, 0, 63))`` with ``R_MAX = 4.0`` m; row 0 is nearest.
* Invalid returns (inf, NaN, below ``range_min``, above ``range_max``) become ``R_MAX`` (row 63):
  they are kept, not dropped, because "nothing seen along this bearing" is information too. That is
  the paper's rule (``invalid="sentinel"``, the default). ``invalid="empty"`` leaves an invalid
  beam's pixel dark instead: a real sensor's dropouts then add no isolated pixels to row 63, at the
  price of no longer telling "nothing within range" from "no beam here". A model is trained for one
  rule and carries it in its metadata, like its padding.
* Continuous pixel coordinates (what label and detection boxes use) put column ``a`` on
  ``[a, a + 1)`` and row ``r`` on ``[r, r + 1)``; so pixel ``u`` is bearing ``u − 0.5`` degrees and
  pixel ``v`` is range ``v · R_MAX / 63`` metres.
"""

from __future__ import annotations

import functools
import math
from collections import deque
from typing import Literal, Protocol, get_args

import numpy as np

RANGE_ROWS = 64
ANGLE_COLUMNS = 360
IMAGE_WIDTH = 384  # 360 + 24 padding columns: divisible by the YOLO stride 32
PAD_COLUMNS = IMAGE_WIDTH - ANGLE_COLUMNS
R_MAX_M = 4.0
SENTINEL_ROW = RANGE_ROWS - 1
ROW_SCALE = (RANGE_ROWS - 1) / R_MAX_M  # rows per metre: 63 / 4
HIT = np.uint8(255)
MAX_ABS_ANGLE_RAD = 1000.0  # ~160 turns: far beyond any real angle_min, far below float trouble
STACK_DEPTH = 3

Padding = Literal["zero", "wrap"]
PADDINGS: tuple[str, ...] = get_args(Padding)
InvalidRule = Literal["sentinel", "empty"]
INVALID_RULES: tuple[str, ...] = get_args(InvalidRule)


class ScanError(ValueError):
    """A scan that cannot be encoded (wrong shapes or nonsensical sensor parameters)."""


def _check_scan(
    ranges: np.ndarray, angle_min: float, angle_increment: float, range_min: float, range_max: float
) -> np.ndarray:
    values = np.asarray(ranges)
    if values.ndim != 1:
        raise ScanError(f"ranges must be one-dimensional, got shape {values.shape}")
    if values.size == 0:
        raise ScanError("ranges is empty: a scan needs at least one beam")
    if not np.issubdtype(values.dtype, np.floating) and not np.issubdtype(values.dtype, np.integer):
        raise ScanError(f"ranges must be numeric, got dtype {values.dtype}")
    for name, value in (
        ("angle_min", angle_min),
        ("angle_increment", angle_increment),
        ("range_min", range_min),
        ("range_max", range_max),
    ):
        if not math.isfinite(value):
            raise ScanError(f"{name} must be finite, got {value}")
    if angle_increment == 0.0:
        raise ScanError("angle_increment must be non-zero")
    # Finite is not enough: a bearing of 1e300 rad overflows when converted to a column. No sensor
    # reports angles beyond a few turns, nor steps of more than a full turn between beams.
    if abs(angle_min) > MAX_ABS_ANGLE_RAD or abs(angle_increment) > 2 * math.pi:
        raise ScanError(
            f"angle_min {angle_min} or angle_increment {angle_increment} is beyond any sensor "
            f"(|angle_min| <= {MAX_ABS_ANGLE_RAD:g} rad, |angle_increment| <= 2*pi)"
        )
    if not 0.0 <= range_min < range_max:
        raise ScanError(f"need 0 <= range_min < range_max, got {range_min} and {range_max}")
    return values.astype(np.float64, copy=False)


def beam_bearings_rad(angle_min: float, angle_increment: float, beams: int) -> np.ndarray:
    """Bearing of each beam, as ROS ``LaserScan`` defines it: ``angle_min + i · angle_increment``."""
    return angle_min + angle_increment * np.arange(beams, dtype=np.float64)


def check_raster_yaw(yaw_deg: float) -> float:
    """A raster yaw in degrees, checked (finite) and taken mod 360 into ``[0, 360)``."""
    try:
        value = float(yaw_deg)
    except (TypeError, ValueError):
        raise ScanError(f"raster yaw must be a number of degrees, got {yaw_deg!r}") from None
    if not math.isfinite(value):
        raise ScanError(f"raster yaw must be finite, got {yaw_deg!r}")
    turned = value % 360.0
    return 0.0 if turned == 360.0 else turned  # a tiny negative yaw rounds up to 360.0


def raster_to_laser_bearing_deg(bearing_deg: np.ndarray | float, yaw_deg: float) -> np.ndarray:
    """Laser-frame bearings (degrees, not wrapped) of raster-frame ones: the raster yaw undone."""
    return np.asarray(bearing_deg, dtype=np.float64) - yaw_deg


def angle_columns(bearings_rad: np.ndarray, yaw_deg: float = 0.0) -> np.ndarray:
    """Column of each bearing turned by the raster yaw: ``round(deg(θ) + Y) mod 360``, rounding half up."""
    return (np.floor(np.degrees(bearings_rad) + yaw_deg + 0.5).astype(np.int64)) % ANGLE_COLUMNS


@functools.lru_cache(maxsize=64)
def beam_columns(angle_min: float, angle_increment: float, beams: int, yaw_deg: float = 0.0) -> np.ndarray:
    """Column of each beam of a sensor (read-only), computed once per sensor geometry and raster yaw.

    A sensor sends the same angles with every scan, so the encoder looks its columns up instead of
    recomputing them per scan; a fleet of mixed sensors holds one entry per geometry.
    """
    columns = angle_columns(beam_bearings_rad(angle_min, angle_increment, beams), yaw_deg)
    columns.flags.writeable = False
    return columns


def valid_returns(ranges: np.ndarray, range_min: float, range_max: float) -> np.ndarray:
    """``bool[N]``: finite returns within ``[range_min, range_max]``."""
    values = np.asarray(ranges, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        return np.isfinite(values) & (values >= range_min) & (values <= range_max)


def check_invalid_rule(invalid: str) -> InvalidRule:
    if invalid not in INVALID_RULES:
        raise ScanError(f"invalid must be one of {INVALID_RULES}, got {invalid!r}")
    return invalid  # type: ignore[return-value]


def range_rows(ranges_m: np.ndarray) -> np.ndarray:
    """Row of each (already sanitised) range: ``floor(clip(ρ · 63 / R_MAX, 0, 63))``."""
    return np.floor(np.clip(ranges_m * ROW_SCALE, 0.0, SENTINEL_ROW)).astype(np.int64)


def scan_hits(
    ranges: np.ndarray,
    angle_min: float,
    angle_increment: float,
    range_min: float,
    range_max: float,
    invalid: InvalidRule = "sentinel",
    raster_yaw_deg: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns (``int64[K]`` each) of the pixels one scan lights in its ``[64, 360]`` raster.

    A scan lights at most one pixel per beam, a few hundred of the raster's 23,040: the stacker
    keeps these instead of whole rasters. ``invalid`` and ``raster_yaw_deg`` as in :func:`encode_scan`.
    """
    values = _check_scan(ranges, angle_min, angle_increment, range_min, range_max)
    check_invalid_rule(invalid)
    yaw = check_raster_yaw(raster_yaw_deg)
    cols = beam_columns(float(angle_min), float(angle_increment), values.size, yaw)
    valid = valid_returns(values, range_min, range_max)
    rows = range_rows(np.where(valid, values, R_MAX_M))  # an invalid return reads R_MAX: the sentinel row
    if invalid == "empty":
        return rows[valid], cols[valid]
    return rows, cols


def encode_scan(
    ranges: np.ndarray,
    angle_min: float,
    angle_increment: float,
    range_min: float,
    range_max: float,
    invalid: InvalidRule = "sentinel",
    raster_yaw_deg: float = 0.0,
) -> np.ndarray:
    """Rasterise one scan to ``uint8[64, 360]`` (255 where hit).

    Any beam count and field of view works: each beam is binned by its own bearing, several beams
    may share a column (denser sensors) and columns no beam points at stay 0 (narrower sensors).
    ``invalid`` says where an invalid return goes: the sentinel row (the paper) or nowhere.
    ``raster_yaw_deg`` turns the scan before binning (module docstring; 0: the paper's raster).
    """
    rows, cols = scan_hits(ranges, angle_min, angle_increment, range_min, range_max, invalid, raster_yaw_deg)
    raster = np.zeros((RANGE_ROWS, ANGLE_COLUMNS), dtype=np.uint8)
    raster[rows, cols] = HIT
    return raster


def pad_raster(raster: np.ndarray, padding: Padding = "zero") -> np.ndarray:
    """Widen a ``uint8[64, 360]`` raster to 384 columns.

    ``zero`` is the paper's choice. ``wrap`` repeats columns 0–23 after column 359, so an object
    straddling the 0°/360° seam also appears whole once; it is this project's idea and is always
    chosen explicitly, never mixed with ``zero`` in one model.
    """
    if raster.shape != (RANGE_ROWS, ANGLE_COLUMNS):
        raise ScanError(f"raster must have shape {(RANGE_ROWS, ANGLE_COLUMNS)}, got {raster.shape}")
    if padding == "zero":
        pad = np.zeros((RANGE_ROWS, PAD_COLUMNS), dtype=raster.dtype)
    elif padding == "wrap":
        pad = raster[:, :PAD_COLUMNS]
    else:
        raise ScanError(f"padding must be one of {PADDINGS}, got {padding!r}")
    return np.concatenate([raster, pad], axis=1)


def stack_rasters(oldest: np.ndarray, middle: np.ndarray, newest: np.ndarray) -> np.ndarray:
    """``uint8[64, 384, 3]`` with channel 0 = scan t−2, 1 = t−1, 2 = t (the paper's R, G, B)."""
    return np.stack([oldest, middle, newest], axis=-1)


def to_model_input(tensor: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """HWC ``uint8`` tensor → ``float32[1, 3, 64, 384]`` in [0, 1], channel order unchanged.

    Ultralytics trains on the same layout: it reads PNGs as BGR and flips them to RGB, so a PNG whose
    red plane holds scan t−2 reaches the network with t−2 in channel 0, exactly like this tensor.

    The result is C-contiguous: ONNX Runtime copies a transposed, non-contiguous input once more
    inside ``run`` (bench/README.md, "The model input"). ``out``, when given, is where it is written
    and what is returned: a C-contiguous ``float32[1, 3, 64, 384]``, such as a slice of a batch, so
    a batch needs no concatenation. Values are bit-identical to ``tensor.astype(float32) / 255``.
    """
    if tensor.shape != (RANGE_ROWS, IMAGE_WIDTH, STACK_DEPTH) or tensor.dtype != np.uint8:
        raise ScanError(
            f"tensor must be uint8{(RANGE_ROWS, IMAGE_WIDTH, STACK_DEPTH)}, got {tensor.dtype}{tensor.shape}"
        )
    channels_first = tensor.transpose(2, 0, 1)[None]
    if out is None:
        out = np.empty(channels_first.shape, np.float32)
    elif out.shape != channels_first.shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(
            f"out must be a C-contiguous float32{list(channels_first.shape)}, "
            f"got {out.dtype}{list(out.shape)}"
        )
    return np.divide(channels_first, np.float32(255.0), out=out, dtype=np.float32)


def padded_hits(
    rows: np.ndarray, cols: np.ndarray, padding: Padding = "zero"
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`pad_raster` for lit pixels: ``wrap`` repeats the hits in columns 0–23 at 360–383."""
    if padding == "zero":
        return rows, cols
    if padding != "wrap":
        raise ScanError(f"padding must be one of {PADDINGS}, got {padding!r}")
    seam = cols < PAD_COLUMNS
    return np.concatenate([rows, rows[seam]]), np.concatenate([cols, cols[seam] + ANGLE_COLUMNS])


class ReadsScans(Protocol):
    """How a model reads scans, as its metadata declares it (:class:`common.inference.OnnxDetector`,
    :class:`common.model_meta.ModelFacts`): whatever encodes for the model takes all three from here."""

    @property
    def padding(self) -> Padding: ...

    @property
    def invalid(self) -> InvalidRule: ...

    @property
    def raster_yaw_deg(self) -> float: ...


class ScanStacker:
    """The FIFO of Algorithm 1: the last three padded rasters of ONE sensor.

    One stacker per robot; mixing two robots' scans in one FIFO would fuse unrelated geometry. It
    holds each raster as its lit pixels and writes them into a zeroed tensor: the same tensor as
    :func:`stack_rasters` of the padded rasters, without copying three mostly empty planes.
    """

    def __init__(
        self, padding: Padding = "zero", invalid: InvalidRule = "sentinel", raster_yaw_deg: float = 0.0
    ) -> None:
        if padding not in PADDINGS:
            raise ScanError(f"padding must be one of {PADDINGS}, got {padding!r}")
        self.padding: Padding = padding
        self.invalid: InvalidRule = check_invalid_rule(invalid)
        self.raster_yaw_deg: float = check_raster_yaw(raster_yaw_deg)  # the model's (module docstring)
        self._frames: deque[tuple[np.ndarray, np.ndarray]] = deque(maxlen=STACK_DEPTH)

    @classmethod
    def for_model(cls, model: ReadsScans) -> ScanStacker:
        """A stacker that encodes as ``model`` reads scans: its padding, invalid rule and raster yaw."""
        return cls(model.padding, model.invalid, model.raster_yaw_deg)

    def __len__(self) -> int:
        return len(self._frames)

    @property
    def ready(self) -> bool:
        return len(self._frames) == STACK_DEPTH

    def reset(self) -> None:
        self._frames.clear()

    def push_scan(
        self, ranges: np.ndarray, angle_min: float, angle_increment: float, range_min: float, range_max: float
    ) -> np.ndarray | None:
        """Encode a scan and push it; return the stacked ``uint8[64, 384, 3]`` tensor once three are
        held. A scan that cannot be encoded raises and leaves the FIFO as it was."""
        rows, cols = scan_hits(
            ranges, angle_min, angle_increment, range_min, range_max, self.invalid, self.raster_yaw_deg
        )
        self._frames.append(padded_hits(rows, cols, self.padding))
        if not self.ready:
            return None
        tensor = np.zeros((RANGE_ROWS, IMAGE_WIDTH, STACK_DEPTH), dtype=np.uint8)
        for channel, (frame_rows, frame_cols) in enumerate(self._frames):  # channel 0 = oldest
            tensor[frame_rows, frame_cols, channel] = HIT
        return tensor


# --- inverse mapping: raster pixels <-> bearing/range <-> metric position --------------------------------


def bearing_to_pixel_x(bearing_deg: np.ndarray | float) -> np.ndarray:
    """Continuous x of a bearing in degrees (column ``a`` spans ``[a, a+1)`` and is centred on ``a``°)."""
    return np.asarray(bearing_deg, dtype=np.float64) + 0.5


def pixel_x_to_bearing_deg(x_px: np.ndarray | float) -> np.ndarray:
    """Bearing in degrees of a continuous pixel x; columns 360–383 give 359.5°–383.5° (wrap them)."""
    return np.asarray(x_px, dtype=np.float64) - 0.5


def range_to_pixel_y(range_m: np.ndarray | float) -> np.ndarray:
    """Continuous y of a range in metres (row ``r`` spans ranges ``[r, r+1) · 4/63``)."""
    return np.asarray(range_m, dtype=np.float64) * ROW_SCALE


def pixel_y_to_range_m(y_px: np.ndarray | float) -> np.ndarray:
    return np.asarray(y_px, dtype=np.float64) / ROW_SCALE


def wrap_angle(angle: float) -> float:
    """Radians in [-π, π): a heading, or the turn between two."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def wrap_bearing_deg(bearing_deg: np.ndarray | float) -> np.ndarray:
    """Normalise degrees to (−180, 180], the range ROS users expect for a bearing."""
    wrapped = np.mod(np.asarray(bearing_deg, dtype=np.float64) + 180.0, 360.0) - 180.0
    return np.where(wrapped == -180.0, 180.0, wrapped)


def polar_to_xy(bearing_deg: np.ndarray | float, range_m: np.ndarray | float) -> np.ndarray:
    """Sensor-frame position ``float64[..., 2]`` (x forward, y left) of bearings and ranges."""
    theta = np.radians(np.asarray(bearing_deg, dtype=np.float64))
    rho = np.asarray(range_m, dtype=np.float64)
    return np.stack([rho * np.cos(theta), rho * np.sin(theta)], axis=-1)


def scan_points_xy(
    ranges: np.ndarray, angle_min: float, angle_increment: float, range_min: float, range_max: float
) -> np.ndarray:
    """The valid returns of a scan as sensor-frame points ``float64[K, 2]`` (invalid beams left out)."""
    values = _check_scan(ranges, angle_min, angle_increment, range_min, range_max)
    valid = valid_returns(values, range_min, range_max)
    bearings = np.degrees(beam_bearings_rad(angle_min, angle_increment, values.size))
    return polar_to_xy(bearings[valid], values[valid])


def disc_polar(
    centre_xy: np.ndarray | tuple[float, float], radius_m: float
) -> tuple[float, float, float, float, float]:
    """(centre bearing in [0, 360), arc min, arc max, range min, range max) of a disc about a point of
    the sensor's frame (metres): the arc of bearings it covers, unwrapped around the centre, and its
    nearest and farthest range. A sensor inside the disc sees it all around."""
    x, y = float(centre_xy[0]), float(centre_xy[1])
    distance = math.hypot(x, y)
    center = float(np.mod(math.degrees(math.atan2(y, x)), 360.0))
    if distance <= radius_m:
        return center, 0.0, 360.0, 0.0, distance + radius_m
    half = math.degrees(math.asin(radius_m / distance))
    return center, center - half, center + half, distance - radius_m, distance + radius_m


def arc_pixel_boxes(
    center_deg: float, lo_deg: float, hi_deg: float, range_min: float, range_max: float, padding: Padding
) -> tuple[tuple[float, float, float, float], ...]:
    """Raster boxes (x1, y1, x2, y2 pixels) of one arc of bearings (degrees, the raster's frame; the
    ends unwrapped around the centre) and ranges: every pixel a return from it can light, snapped
    outward to whole pixels. With ``zero`` padding one box, the piece holding the centre's column; with
    ``wrap`` every copy in the image (README "Labels": the seam rule)."""
    x1 = math.floor(lo_deg + 0.5)  # column of the arc's first bearing
    x2 = math.floor(hi_deg + 0.5) + 1  # one past the column of its last bearing
    y1 = float(min(math.floor(range_min * ROW_SCALE), RANGE_ROWS - 1))
    y2 = float(min(math.floor(range_max * ROW_SCALE) + 1, RANGE_ROWS))
    x2 = min(x2, x1 + ANGLE_COLUMNS)  # a full circle covers each column once
    if padding == "zero":
        # Keep the one piece (shifted by k·360°) that holds the centre column; clip it to [0, 360).
        shift = -ANGLE_COLUMNS * math.floor(math.floor(center_deg + 0.5) / ANGLE_COLUMNS)
        a, b = max(x1 + shift, 0), min(x2 + shift, ANGLE_COLUMNS)
        return ((float(a), y1, float(b), y2),) if b > a else ()
    # wrap: columns 360–383 repeat 0–23, so every copy of the arc that falls in the image is real.
    boxes = []
    for shift in (-ANGLE_COLUMNS, 0, ANGLE_COLUMNS):
        a, b = max(x1 + shift, 0), min(x2 + shift, IMAGE_WIDTH)
        if b > a:
            boxes.append((float(a), y1, float(b), y2))
    return tuple(boxes)
