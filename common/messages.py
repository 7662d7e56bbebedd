"""Wire messages of triscan: pydantic v2 models plus a msgpack codec (README, "The loop").

Every payload that crosses Zenoh is a msgpack map carrying ``kind`` and ``schema_version`` next to
the model's fields. Numeric arrays travel as ``{"dtype", "shape", "data"}`` with raw little-endian
bytes, so a C++ or Rust peer can produce them without numpy and a decoder can wrap them without a
parse step.

Payloads come from the network and may be hostile or simply from another build. ``decode_message``
therefore turns *every* way a payload can be wrong into one exception type, ``MessageError``, whose
``reason`` is a short fixed token a service can count, and whose text names the offending field in one
line, so a service can log, count and drop a bad sample and keep serving.

The stacked tensor's raster is binary (0 or ``common.encoding.HIT``) and sparse: one lit pixel per beam
per channel, a few hundred of each channel's 24,576. Schema version 3 lets it travel as its lit pixels
(:class:`LitRasterSpec`), a few kilobytes instead of 73,728 bytes that every hop (msgpack, Zenoh, the
detector's copy and decode) would pay for. The rule that picks the form: ``encode_message`` writes a
version-3 tensor's raster as its lit pixels when the raster is binary and that form is the smaller,
and densely otherwise (a raster with other values can only travel dense); versions 1 and 2 are always
dense, and a version-3 reader accepts both forms. Like every message, a tensor built from an array
without an explicit version gets the lowest version that holds it, and so travels dense; a producer
opts in with ``schema_version=LIT_PIXELS_VERSION``, as the encoder does. A build that speaks only 1
and 2 refuses such a tensor as "schema_version 3 is not supported (this build speaks 1, 2)".

Arrays held by models are always C-contiguous, little-endian and read-only. Read-only is the price
of not copying on decode (``np.frombuffer`` views the unpacked bytes); it also keeps frozen models
honestly immutable. Call ``.copy()`` on an array to get a writable one.
"""

from __future__ import annotations

import bisect
import functools
import itertools
import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar, Final, Literal, TypeVar

import msgpack
import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    GetCoreSchemaHandler,
    GetJsonSchemaHandler,
    SerializationInfo,
    ValidationError,
    ValidationInfo,
    field_serializer,
    field_validator,
    model_validator,
)
from pydantic.json_schema import JsonSchemaValue
from pydantic_core import core_schema

from common.encoding import HIT, wrap_angle
from common.keys import validate_robot_id
from common.model_spec import CLASS_NAMES, MAX_DETECTIONS, TENSOR_SHAPE

SCHEMA_VERSION: Final[int] = 3
"""The newest schema this build writes and reads; it also reads every older one down to version 1.

Version 2 added fields without changing any: ``odom`` (the robot's pose) on scans, tensors and
detections, and the ``tracks`` message. Version 3 adds the lit-pixel form of a tensor's raster
(:data:`LIT_PIXELS_VERSION`) and a tensor's ``raster_yaw_deg``. A message built without an explicit
version gets, and travels as, the *lowest* version that holds it, so a version-1 reader keeps reading
every message without odometry,
and the first one with odometry reaches it as "schema_version 2 is not supported (this build speaks
1)" rather than as an unknown field.
"""
SUPPORTED_SCHEMA_VERSIONS: Final[tuple[int, ...]] = (1, 2, 3)
LIT_PIXELS_VERSION: Final[int] = 3
"""The version whose tensors travel as their lit pixels (module docstring); a producer asks for it."""
MAX_PAYLOAD_BYTES: Final[int] = 4 * 1024 * 1024
MAX_BEAMS: Final[int] = 8192
MAX_TRUTH_OBJECTS: Final[int] = 64
MAX_TRACKS: Final[int] = MAX_DETECTIONS

# Unpacker limits: no legitimate message comes near them, and they stop a small hostile payload from
# declaring a huge container that msgpack would pre-allocate before noticing the data is missing.
_MAX_STR_LEN: Final[int] = 4096
_MAX_ARRAY_LEN: Final[int] = 1024
_MAX_MAP_LEN: Final[int] = 64

_TWO_PI: Final[float] = 2.0 * math.pi

ODOM_JUMP_M: Final[float] = 1.0
ODOM_JUMP_RAD: Final[float] = math.radians(30.0)
"""Farther or more turned than this between two scans, the odometry jumped (a relocalisation, a robot
moved by hand, a simulated robot put into a new world): a robot at 10 Hz would need 10 m/s or 300°/s
to move that much. What a jump breaks: the encoder's three-scan stack, which would show motion that
never happened, and the tracker's tracks, which no longer stand where their objects are."""

OdometryBreak = Literal["odom_reset", "odom_jump"]
# encode_message's serialisation context: fields with a compact wire form (the tensor) write it only then.
_WIRE: Final[dict[str, bool]] = {"wire": True}


class MessageError(ValueError):
    """A payload that cannot be accepted; ``reason`` is a fixed token suitable as a metrics label.

    Reasons: ``not_bytes``, ``too_large``, ``not_msgpack``, ``not_a_map``, ``wrong_kind``,
    ``schema_version``, ``invalid``.
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


# --------------------------------------------------------------------------------------------------
# Array fields
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class NDArraySpec:
    """Pydantic annotation turning ``np.ndarray`` into a checked wire array.

    Use as ``Annotated[np.ndarray, NDArraySpec(...)]``. ``shape`` gives one entry per axis: an int
    fixes that axis, ``None`` leaves it free (bounded by ``min_elements``/``max_elements``). The
    element cap is checked on the *declared* shape before any buffer is touched, so a forged shape
    cannot trigger a large allocation. ``finite`` rejects NaN/inf where they can only be a bug
    (geometry), while sensor data such as ranges legitimately carries them.
    """

    dtypes: tuple[str, ...]
    shape: tuple[int | None, ...]
    min_elements: int = 0
    max_elements: int | None = None
    finite: bool = False

    # Cached: every message carrying an array validates it, several hundred times a second in a fleet.
    @functools.cached_property
    def _allowed(self) -> tuple[np.dtype[Any], ...]:
        return tuple(np.dtype(d).newbyteorder("<") for d in self.dtypes)

    @functools.cached_property
    def _wire_names(self) -> dict[str, np.dtype[Any]]:
        # Accept the canonical numpy spelling ("<f4", "|u1") and, for one-byte types, "<u1"/"u1",
        # which non-numpy producers naturally write. A fixed table means we never hand an arbitrary
        # network string to np.dtype().
        names: dict[str, np.dtype[Any]] = {}
        for dt in self._allowed:
            names[dt.str] = dt
            if dt.itemsize == 1:
                names["<" + dt.str[1:]] = dt
                names[dt.str[1:]] = dt
        return names

    def _describe_allowed(self) -> str:
        return "/".join(dt.name for dt in self._allowed)

    def _check_shape(self, shape: tuple[int, ...]) -> int:
        if len(shape) != len(self.shape):
            raise ValueError(f"expected a {len(self.shape)}-d array, got shape {list(shape)}")
        for axis, (got, want) in enumerate(zip(shape, self.shape, strict=True)):
            if want is not None and got != want:
                raise ValueError(f"expected shape {self._shape_text()}, got {list(shape)} (axis {axis})")
        count = math.prod(shape)
        if count < self.min_elements:
            raise ValueError(f"expected at least {self.min_elements} elements, got {count}")
        if self.max_elements is not None and count > self.max_elements:
            raise ValueError(f"at most {self.max_elements} elements allowed, got {count}")
        return count

    def _shape_text(self) -> str:
        return "[" + ", ".join("N" if d is None else str(d) for d in self.shape) + "]"

    def _finish(self, arr: np.ndarray) -> np.ndarray:
        if self.finite and arr.dtype.kind == "f" and not bool(np.isfinite(arr).all()):
            raise ValueError("array must contain only finite values")
        arr.flags.writeable = False
        return arr

    def validate(self, value: Any) -> np.ndarray:
        """Accept an ndarray (from a producer) or the wire map (from the decoder)."""
        if isinstance(value, np.ndarray):
            return self._from_ndarray(value)
        if isinstance(value, dict):
            return self._from_map(value)
        raise ValueError(
            f"expected a numpy array or a {{dtype, shape, data}} map, got {type(value).__name__}"
        )

    def _from_ndarray(self, arr: np.ndarray) -> np.ndarray:
        target = arr.dtype.newbyteorder("<")
        if target not in self._allowed:
            raise ValueError(f"dtype must be {self._describe_allowed()}, got {arr.dtype.name}")
        self._check_shape(arr.shape)
        out = np.ascontiguousarray(arr, dtype=target)
        if arr.flags.writeable and np.may_share_memory(out, arr):
            # Decouple from the caller's buffer: a frozen message must not change under our feet.
            out = arr.copy(order="C")
        return self._finish(out)

    def _declared(self, dtype_name: Any, shape_raw: Any) -> tuple[np.dtype[Any], tuple[int, ...], int]:
        """A wire map's dtype and shape, checked: what the map declares, before any buffer is touched."""
        dt = self._wire_names.get(dtype_name) if isinstance(dtype_name, str) else None
        if dt is None:
            raise ValueError(f"dtype must be {self._describe_allowed()} (little-endian), got {dtype_name!r}")
        if not isinstance(shape_raw, list | tuple) or not all(type(d) is int and d >= 0 for d in shape_raw):
            raise ValueError(f"shape must be a list of non-negative ints, got {shape_raw!r}")
        shape = tuple(shape_raw)
        return dt, shape, self._check_shape(shape)

    def _from_map(self, value: dict[Any, Any]) -> np.ndarray:
        if set(value) != {"dtype", "shape", "data"}:
            raise ValueError(
                f"array map must have exactly the keys dtype, shape, data; got {sorted(map(str, value))}"
            )
        data = value["data"]
        dt, shape, count = self._declared(value["dtype"], value["shape"])
        if not isinstance(data, bytes | bytearray):
            # ValueError, not TypeError: pydantic only turns ValueError into a ValidationError.
            raise ValueError(f"data must be bytes, got {type(data).__name__}")
        expected = count * dt.itemsize
        if len(data) != expected:
            raise ValueError(f"{count} {dt.name} expected {expected} bytes, got {len(data)}")
        # Zero-copy view of the unpacked bytes; _finish makes it read-only (bytearray input is writable).
        return self._finish(np.frombuffer(data, dtype=dt).reshape(shape))

    @staticmethod
    def serialize(arr: np.ndarray) -> dict[str, Any]:
        """Validated arrays are already little-endian and contiguous, so tobytes() is the wire format."""
        return {"dtype": arr.dtype.str, "shape": list(arr.shape), "data": arr.tobytes()}

    def __get_pydantic_core_schema__(
        self, source: Any, handler: GetCoreSchemaHandler
    ) -> core_schema.CoreSchema:
        return core_schema.no_info_plain_validator_function(
            self.validate,
            serialization=core_schema.plain_serializer_function_ser_schema(self.serialize),
        )

    def __get_pydantic_json_schema__(
        self, schema: core_schema.CoreSchema, handler: GetJsonSchemaHandler
    ) -> JsonSchemaValue:
        return {
            "type": "object",
            "description": f"{self._describe_allowed()} {self._shape_text()}, raw little-endian bytes",
            "properties": {
                "dtype": {"type": "string"},
                "shape": {"type": "array", "items": {"type": "integer"}},
                "data": {"type": "string", "format": "binary"},
            },
            "required": ["dtype", "shape", "data"],
        }


_LIT_KEYS: Final[frozenset[str]] = frozenset({"dtype", "shape", "counts", "lit"})
_LIT_INDEX: Final[np.dtype[Any]] = np.dtype("<u2")


def _channel_at(counts: list[int] | tuple[int, ...], position: int) -> int:
    """The channel whose indices hold ``position`` of the lit bytes (an error message's detail)."""
    return bisect.bisect_right(list(itertools.accumulate(counts)), position)


@dataclass(frozen=True)
class LitRasterSpec(NDArraySpec):
    """A fixed-shape uint8 raster of planes (last axis: channels) that may also travel as its lit pixels.

    The lit form is ``{"dtype", "shape", "counts", "lit"}``: ``counts`` holds one count per channel,
    and ``lit`` the channels' pixel indices one channel after the other, each channel's strictly
    increasing, as little-endian uint16 (``row * width + column`` within the plane). A listed pixel is
    ``HIT``, every other 0. Two bytes per lit pixel against a dense byte per pixel and channel: an
    encoder raster, with one lit pixel per beam per channel, shrinks some thirty-fold; a bitmap would
    cost a fixed eighth of the dense form whatever the scan, and varint deltas would need a byte loop
    to decode, where uint16 indices are a numpy view that scatters straight into the dense array.

    Decoding checks everything a dense map's decoding does, and first, on the declared numbers alone
    (before anything is allocated), that the counts are in range and add up to the bytes; then that
    every index lies in the plane and each channel's are sorted and unique. The result is the same
    read-only dense array either form gives, so nothing downstream knows which form came.
    """

    def __post_init__(self) -> None:
        plane = [d for d in self.shape[:-1] if d is not None]
        if None in self.shape or math.prod(plane) > 1 << (8 * _LIT_INDEX.itemsize):
            raise ValueError(
                f"lit pixels need a fixed shape whose planes fit uint16 indices, got {self.shape}"
            )

    def _from_map(self, value: dict[Any, Any]) -> np.ndarray:
        return self._from_lit(value) if "lit" in value else super()._from_map(value)

    def _from_lit(self, value: dict[Any, Any]) -> np.ndarray:
        if set(value) != _LIT_KEYS:
            raise ValueError(
                f"lit-pixel map must have exactly the keys {', '.join(sorted(_LIT_KEYS))}; "
                f"got {sorted(map(str, value))}"
            )
        dt, shape, count = self._declared(value["dtype"], value["shape"])
        channels, plane = shape[-1], count // shape[-1]
        counts_raw, lit = value["counts"], value["lit"]
        if not isinstance(counts_raw, list | tuple) or len(counts_raw) != channels:
            got = (
                f"{len(counts_raw)} items"
                if isinstance(counts_raw, list | tuple)
                else type(counts_raw).__name__
            )
            raise ValueError(f"counts must be a list of {channels} ints, one per channel, got {got}")
        for channel, n in enumerate(counts_raw):
            if type(n) is not int or not 0 <= n <= plane:
                raise ValueError(f"counts[{channel}] must be an int in 0..{plane}, got {n!r}")
        if not isinstance(lit, bytes | bytearray):
            raise ValueError(f"lit must be bytes, got {type(lit).__name__}")
        total = sum(counts_raw)
        if len(lit) != total * _LIT_INDEX.itemsize:
            raise ValueError(
                f"counts add up to {total} pixels, expected {total * _LIT_INDEX.itemsize} bytes of lit, "
                f"got {len(lit)}"
            )
        indices = np.frombuffer(lit, dtype=_LIT_INDEX)
        if total and int(indices.max()) >= plane:
            at = int(np.argmax(indices >= plane))
            raise ValueError(
                f"lit index {indices[at]} of channel {_channel_at(counts_raw, at)} is outside the "
                f"{plane}-pixel plane"
            )
        channel_of = np.repeat(np.arange(channels, dtype=np.intp), counts_raw)
        # Every index is below the plane, so channel * plane + index rises strictly over the whole
        # array exactly when each channel's indices do: one comparison checks every channel.
        key = channel_of * plane + indices
        rises = key[1:] > key[:-1]
        if not rises.all():
            at = int(np.argmin(rises)) + 1
            raise ValueError(
                f"lit indices of channel {_channel_at(counts_raw, at)} must be sorted and unique, "
                f"got {indices[at]} after {indices[at - 1]}"
            )
        dense = np.zeros(count, dtype=dt)
        dense[indices.astype(np.intp) * channels + channel_of] = HIT
        return self._finish(dense.reshape(shape))

    @staticmethod
    def lit_map(arr: np.ndarray) -> dict[str, Any] | None:
        """The lit-pixel form of a validated raster, or None where dense is the only or the smaller form."""
        channels = arr.shape[-1]
        flat = arr.reshape(-1)
        total = int(np.count_nonzero(flat))
        if total * _LIT_INDEX.itemsize >= flat.size:
            return None
        # nonzero() on a bool array is several times faster than on uint8; a raster whose nonzero
        # pixels are not all HIT has fewer HIT pixels than nonzero ones, and travels dense.
        lit = np.flatnonzero(flat == HIT)
        if lit.size != total:
            return None
        pixel, channel = np.divmod(lit, channels)
        # lit is ascending, so a stable sort by channel leaves each channel's pixels ascending; on the
        # smallest integer type that holds the channels, numpy's stable sort is a radix sort.
        pixels = pixel[np.argsort(channel.astype(np.min_scalar_type(channels - 1)), kind="stable")]
        return {
            "dtype": arr.dtype.str,
            "shape": list(arr.shape),
            "counts": np.bincount(channel, minlength=channels).tolist(),
            "lit": pixels.astype(_LIT_INDEX).tobytes(),
        }

    def __get_pydantic_json_schema__(
        self, schema: core_schema.CoreSchema, handler: GetJsonSchemaHandler
    ) -> JsonSchemaValue:
        lit = {
            "type": "object",
            "description": f"{self._describe_allowed()} {self._shape_text()} as its lit pixels: per channel, "
            "sorted little-endian uint16 indices row * width + column, their counts in counts",
            "properties": {
                "dtype": {"type": "string"},
                "shape": {"type": "array", "items": {"type": "integer"}},
                "counts": {"type": "array", "items": {"type": "integer"}},
                "lit": {"type": "string", "format": "binary"},
            },
            "required": sorted(_LIT_KEYS),
        }
        return {"oneOf": [super().__get_pydantic_json_schema__(schema, handler), lit]}


RangesArray = Annotated[
    np.ndarray, NDArraySpec(dtypes=("float32",), shape=(None,), min_elements=1, max_elements=MAX_BEAMS)
]
TensorArray = Annotated[np.ndarray, LitRasterSpec(dtypes=("uint8",), shape=TENSOR_SHAPE)]
CornersArray = Annotated[np.ndarray, NDArraySpec(dtypes=("float32",), shape=(4, 2), finite=True)]

# --------------------------------------------------------------------------------------------------
# Models
# --------------------------------------------------------------------------------------------------

RobotId = Annotated[str, AfterValidator(validate_robot_id)]
NonNegInt = Annotated[int, Field(ge=0)]
NonNegFloat = Annotated[float, Field(ge=0.0)]
ClassId = Annotated[int, Field(ge=0, le=len(CLASS_NAMES) - 1)]
BoxPx = tuple[float, float, float, float]
Pose2D = tuple[float, float, float]


def _values_equal(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        # Bit-exact: NaN ranges with equal payloads compare equal, unlike ndarray ==.
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and a.tobytes() == b.tobytes()
        )
    return bool(a == b)


def _check_class(class_id: int, class_name: str) -> None:
    if CLASS_NAMES[class_id] != class_name:
        raise ValueError(
            f"class_name {class_name!r} does not match class_id {class_id} ({CLASS_NAMES[class_id]!r})"
        )


def _check_box(box: BoxPx | None) -> None:
    if box is not None and (box[0] > box[2] or box[1] > box[3]):
        raise ValueError(f"box_px must be (x1, y1, x2, y2) with x1 <= x2 and y1 <= y2, got {box}")


class WireModel(BaseModel):
    """Base of every wire model: immutable, no unknown fields, no NaN/inf in scalar floats.

    ``__eq__`` is replaced because pydantic's compares field dicts, which raises on ndarray fields.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    def __eq__(self, other: object) -> bool:
        if type(self) is not type(other):
            return NotImplemented
        return all(_values_equal(getattr(self, n), getattr(other, n)) for n in type(self).model_fields)


def _speaks() -> str:
    return ", ".join(map(str, SUPPORTED_SCHEMA_VERSIONS))


class Odometry(WireModel):
    """The robot's pose in an odometry frame when its scan was taken: ``nav_msgs/Odometry``'s pose in 2D.

    The pose is of the robot (``base_link``), as odometry reports it; consumers treat the laser as
    sitting at the robot's origin, which a mount offset of a few centimetres keeps well inside any
    tracking gate. Non-finite values are accepted on the wire, as in ``ranges``: a diverged filter
    reports NaN and the scan it came with is still good, so the encoder and the tracker refuse the pose
    (and count it), never the scan.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=True)

    x_m: float
    y_m: float
    yaw_rad: float
    frame_id: str = Field(default="odom", min_length=1, max_length=256)
    stamp_ns: NonNegInt

    @property
    def finite(self) -> bool:
        return math.isfinite(self.x_m) and math.isfinite(self.y_m) and math.isfinite(self.yaw_rad)

    def break_from(
        self, last: Odometry, jump_m: float = ODOM_JUMP_M, jump_rad: float = ODOM_JUMP_RAD
    ) -> OdometryBreak | None:
        """How this pose breaks with ``last``, the pose of the scan before: ``"odom_reset"`` (another
        odometry frame), ``"odom_jump"`` (moved more than ``jump_m`` or turned more than ``jump_rad``)
        or None (one motion)."""
        if last.frame_id != self.frame_id:
            return "odom_reset"
        turned = abs(wrap_angle(self.yaw_rad - last.yaw_rad))
        if math.hypot(self.x_m - last.x_m, self.y_m - last.y_m) > jump_m or turned > jump_rad:
            return "odom_jump"
        return None


class Message(WireModel):
    """A top-level message: one Zenoh sample. ``KIND`` names it on the wire.

    ``MIN_VERSION`` is the schema version that introduced the kind, ``FIELD_VERSIONS`` the version
    that introduced each optional field: a field left ``None`` is not written at all, so a message
    that uses nothing newer is built, and travels, as the older version (:data:`SCHEMA_VERSION`).
    """

    KIND: ClassVar[str] = ""
    MIN_VERSION: ClassVar[int] = 1
    FIELD_VERSIONS: ClassVar[dict[str, int]] = {}

    schema_version: int = SCHEMA_VERSION
    robot_id: RobotId
    seq: NonNegInt
    stamp_ns: NonNegInt

    @field_validator("schema_version")
    @classmethod
    def _known_version(cls, v: int) -> int:
        if v not in SUPPORTED_SCHEMA_VERSIONS:
            raise ValueError(f"schema_version {v} is not supported (this build speaks {_speaks()})")
        return v

    @model_validator(mode="before")
    @classmethod
    def _lowest_version(cls, data: Any) -> Any:
        # A message built without an explicit version gets the lowest that holds it (see SCHEMA_VERSION).
        if isinstance(data, dict) and "schema_version" not in data:
            data = {**data, "schema_version": max([cls.MIN_VERSION, *cls._versions_used(data)])}
        return data

    @classmethod
    def _versions_used(cls, data: dict[str, Any]) -> list[int]:
        """The versions that what ``data`` holds needs: each optional field's that is set."""
        return [v for name, v in cls.FIELD_VERSIONS.items() if data.get(name) is not None]

    @model_validator(mode="after")
    def _fields_exist_in_version(self) -> Message:
        if self.schema_version < self.MIN_VERSION:
            raise ValueError(f"{self.KIND} messages need schema_version >= {self.MIN_VERSION}")
        for name, version in self.FIELD_VERSIONS.items():
            if getattr(self, name) is not None and self.schema_version < version:
                raise ValueError(f"{name} needs schema_version >= {version}, got {self.schema_version}")
        return self


class Scan(Message):
    """One 2D LiDAR sweep, mirroring ROS ``sensor_msgs/LaserScan``.

    ``ranges`` may hold NaN/inf (real sensors report them); the encoder maps them to its sentinel.
    """

    KIND: ClassVar[str] = "scan"
    FIELD_VERSIONS: ClassVar[dict[str, int]] = {"odom": 2}

    angle_min: float
    angle_increment: float
    range_min: NonNegFloat
    range_max: float
    ranges: RangesArray
    frame_id: str = Field(default="laser", min_length=1, max_length=256)
    odom: Odometry | None = None  # the robot's pose when the scan was taken, if the source knows it

    @field_validator("angle_increment")
    @classmethod
    def _nonzero_increment(cls, v: float) -> float:
        if v == 0.0:
            raise ValueError("angle_increment must be nonzero")
        return v

    @model_validator(mode="after")
    def _consistent(self) -> Scan:
        if not self.range_min < self.range_max:
            raise ValueError(f"range_min ({self.range_min}) must be < range_max ({self.range_max})")
        inc = abs(self.angle_increment)
        fov = self.ranges.shape[0] * inc
        # One increment of slack: an N-beam full circle spans (N-1)*inc between its first and last
        # beam, and float32-derived increments round either way.
        if fov > _TWO_PI + inc + 1e-9:
            raise ValueError(
                f"field of view {self.ranges.shape[0]} beams x {inc:.6g} rad = {fov:.6g} rad exceeds 2*pi"
            )
        return self


class StackedTensor(Message):
    """Three consecutive rasters stacked as the network input (channel 0 = t-2, 1 = t-1, 2 = t).

    The raster's wire form, dense or its lit pixels, follows the message's version (module docstring).
    """

    KIND: ClassVar[str] = "tensor"
    FIELD_VERSIONS: ClassVar[dict[str, int]] = {"odom": 2, "raster_yaw_deg": 3}

    tensor: TensorArray
    padding: Literal["zero", "wrap"]
    invalid: Literal["sentinel", "empty"] = "sentinel"  # where invalid returns went (common.encoding)
    scan_seqs: tuple[NonNegInt, NonNegInt, NonNegInt]
    scan_stamps_ns: tuple[NonNegInt, NonNegInt, NonNegInt]
    encode_ms: NonNegFloat = 0.0  # the encoder's time for the newest scan (raster + stack), for Detections
    odom: Odometry | None = None  # of the newest scan (scan t), copied from it
    # Degrees the scans were turned by before binning (common.encoding, "raster yaw"); None is 0, the
    # paper's raster, which is how every encoder without a yaw writes it.
    raster_yaw_deg: Annotated[float, Field(ge=0.0, lt=360.0)] | None = None

    @property
    def yaw_deg(self) -> float:
        """The raster yaw the tensor was encoded with, 0 when the field is absent."""
        return self.raster_yaw_deg or 0.0

    @classmethod
    def _versions_used(cls, data: dict[str, Any]) -> list[int]:
        lit = isinstance(data.get("tensor"), dict) and "lit" in data["tensor"]
        return [*super()._versions_used(data), *([LIT_PIXELS_VERSION] if lit else [])]

    @field_validator("tensor", mode="before")
    @classmethod
    def _lit_pixels_need_their_version(cls, value: Any, info: ValidationInfo) -> Any:
        version = info.data.get("schema_version")  # absent when it failed its own check
        if (
            isinstance(value, dict)
            and "lit" in value
            and version is not None
            and version < LIT_PIXELS_VERSION
        ):
            raise ValueError(f"lit pixels need schema_version >= {LIT_PIXELS_VERSION}, got {version}")
        return value

    @field_serializer("tensor")
    def _tensor_form(self, tensor: np.ndarray, info: SerializationInfo) -> dict[str, Any]:
        # The rule of the module docstring. Only encode_message asks for the wire form: model_dump keeps
        # the dense map, which rebuilds the message under any version.
        if info.context is _WIRE and self.schema_version >= LIT_PIXELS_VERSION:
            lit = LitRasterSpec.lit_map(tensor)
            if lit is not None:
                return lit
        return NDArraySpec.serialize(tensor)

    @model_validator(mode="after")
    def _seq_is_newest(self) -> StackedTensor:
        if self.seq != self.scan_seqs[2]:
            raise ValueError(
                f"seq ({self.seq}) must equal the newest scan's seq scan_seqs[2] ({self.scan_seqs[2]})"
            )
        return self


class Detection(WireModel):
    """One detected object; pixel box plus its polar and Cartesian reading in the laser frame.

    ``box_px`` is in the pixels of the model's raster, which a model with a raster yaw sees turned by
    it (:mod:`common.encoding`); the bearings and ``x_m``/``y_m`` are always in the laser frame, ROS
    REP-103 (x forward, y left).
    """

    class_id: ClassId
    class_name: str
    score: Annotated[float, Field(ge=0.0, le=1.0)]
    box_px: BoxPx
    bearing_deg: float
    bearing_min_deg: float
    bearing_max_deg: float
    range_min_m: NonNegFloat
    range_max_m: NonNegFloat
    x_m: float
    y_m: float

    @model_validator(mode="after")
    def _consistent(self) -> Detection:
        _check_class(self.class_id, self.class_name)
        _check_box(self.box_px)
        if self.range_min_m > self.range_max_m:
            raise ValueError(f"range_min_m ({self.range_min_m}) must be <= range_max_m ({self.range_max_m})")
        return self


class StageTimings(WireModel):
    """Per-frame stage durations, so latency regressions are visible from the wire alone."""

    encode_ms: NonNegFloat
    inference_ms: NonNegFloat
    nms_ms: NonNegFloat
    # Where a frame waits outside the network (bench.pipeline_latency --trace): the detector's decode
    # and validation of the tensor payload, and accepted → inference start (mailbox and thread hand-off).
    decode_ms: NonNegFloat = 0.0
    queue_ms: NonNegFloat = 0.0


class Detections(Message):
    """The detector's output for one tensor.

    ``seq`` and ``scan_stamp_ns`` are the newest scan's (t), so ``stamp_ns - scan_stamp_ns`` is the
    end-to-end latency. The boxes, though, are the middle scan's (t-1): the network is trained on its
    labels, so ``x_m``/``y_m`` are in the laser frame where it stood at ``pose_stamp_ns``, which is
    where a turning robot must look up its transform. It is optional on the wire (None when a producer
    does not fill it), so messages without it still decode.
    """

    KIND: ClassVar[str] = "detections"
    FIELD_VERSIONS: ClassVar[dict[str, int]] = {"odom": 2, "pose_stamp_ns": 2}

    detections: list[Detection] = Field(max_length=MAX_DETECTIONS)
    timings: StageTimings
    model_id: str = Field(min_length=1, max_length=256)
    scan_stamp_ns: NonNegInt
    odom: Odometry | None = None  # of scan t, copied from the tensor
    pose_stamp_ns: NonNegInt | None = None

    @model_validator(mode="after")
    def _pose_is_not_newer(self) -> Detections:
        if self.pose_stamp_ns is not None and self.pose_stamp_ns > self.scan_stamp_ns:
            raise ValueError(
                f"pose_stamp_ns ({self.pose_stamp_ns}) is the middle scan's and cannot be newer than "
                f"scan_stamp_ns ({self.scan_stamp_ns})"
            )
        return self


TrackState = Literal["tentative", "confirmed", "coasting"]
TrackFrame = Literal["odom", "laser"]


class Track(WireModel):
    """One tracked object (services.tracker): a stable id, a smoothed class and a velocity.

    ``x_m``/``y_m`` are in the laser frame of the scan the tracks were updated from; ``odom_x_m`` /
    ``odom_y_m`` in the odometry frame when the scan carried odometry, else ``None``; the velocity is
    in the tracks' ``frame``.
    """

    track_id: NonNegInt
    class_id: ClassId
    class_name: str
    score: Annotated[float, Field(ge=0.0, le=1.0)]
    x_m: float
    y_m: float
    odom_x_m: float | None = None
    odom_y_m: float | None = None
    vx_mps: float
    vy_mps: float
    age_s: NonNegFloat
    hits: NonNegInt
    misses: NonNegInt
    state: TrackState

    @model_validator(mode="after")
    def _consistent(self) -> Track:
        _check_class(self.class_id, self.class_name)
        if (self.odom_x_m is None) != (self.odom_y_m is None):
            raise ValueError("odom_x_m and odom_y_m come together")
        return self


class Tracks(Message):
    """The tracker's state for one robot after one detections message (``seq`` is that message's)."""

    KIND: ClassVar[str] = "tracks"
    MIN_VERSION: ClassVar[int] = 2

    scan_stamp_ns: NonNegInt
    frame: TrackFrame
    tracks: list[Track] = Field(max_length=MAX_TRACKS)

    @model_validator(mode="after")
    def _odom_matches_frame(self) -> Tracks:
        with_odom = [t.odom_x_m is not None for t in self.tracks]
        if self.frame == "laser" and any(with_odom):
            raise ValueError("laser-frame tracks carry no odom_x_m/odom_y_m")
        if self.frame == "odom" and not all(with_odom):
            raise ValueError("odom-frame tracks carry odom_x_m/odom_y_m")
        return self


class TruthObject(WireModel):
    """A simulated object's true footprint (world frame, metres) and, if the sensor sees it, its label box."""

    class_id: ClassId
    class_name: str
    corners_xy: CornersArray
    center_xy: tuple[float, float]
    yaw_rad: float
    visible: bool
    box_px: BoxPx | None = None

    @model_validator(mode="after")
    def _consistent(self) -> TruthObject:
        _check_class(self.class_id, self.class_name)
        _check_box(self.box_px)
        # Labels exist exactly for visible objects (README, "Labels"); anything else is a simulator bug.
        if self.visible and self.box_px is None:
            raise ValueError("a visible object must carry box_px")
        if not self.visible and self.box_px is not None:
            raise ValueError("an object that is not visible must not carry box_px")
        return self


class GroundTruth(Message):
    """Simulator ground truth for the scan with the same ``seq``; poses are (x, y, yaw) in the world frame."""

    KIND: ClassVar[str] = "truth"

    scenario_id: NonNegInt
    robot_pose: Pose2D
    lidar_pose: Pose2D
    objects: list[TruthObject] = Field(max_length=MAX_TRUTH_OBJECTS)


MESSAGE_TYPES: Final[dict[str, type[Message]]] = {
    cls.KIND: cls for cls in (Scan, StackedTensor, Detections, GroundTruth, Tracks)
}

M = TypeVar("M", bound=Message)

# --------------------------------------------------------------------------------------------------
# Codec
# --------------------------------------------------------------------------------------------------


def encode_message(msg: Message) -> bytes:
    """Serialise a top-level message; ``kind`` goes first so a reader can route before validating."""
    if not isinstance(msg, Message) or type(msg).KIND not in MESSAGE_TYPES:
        raise TypeError(f"only top-level messages can be encoded, got {type(msg).__name__}")
    body: dict[str, Any] = {"kind": type(msg).KIND}
    unset = {name for name in type(msg).FIELD_VERSIONS if getattr(msg, name) is None}
    body.update(msg.model_dump(exclude=unset, context=_WIRE))
    return msgpack.packb(body, use_bin_type=True)


def _loc_prefix(loc: Iterable[int | str]) -> str:
    # Model-level validators have an empty location; their messages already name the fields.
    text = ".".join(str(p) for p in loc)
    return f"{text}: " if text else ""


def _validation_text(kind: str, exc: ValidationError) -> str:
    errors = exc.errors(include_url=False, include_input=False)
    first = errors[0]
    text = str(first["msg"]).removeprefix("Value error, ").removeprefix("Assertion failed, ")
    more = f" (+{len(errors) - 1} more)" if len(errors) > 1 else ""
    return " ".join(f"{kind}: {_loc_prefix(first['loc'])}{text}{more}".split())


def decode_message(payload: bytes | bytearray | memoryview, expected: type[M]) -> M:
    """Validate a payload as an ``expected`` message, or raise MessageError and nothing else.

    Checks run cheapest-first and size before parsing, so a hostile sample costs little. The
    schema version is checked before the kind because a different version may rename kinds.
    """
    kind = expected.KIND
    if not isinstance(payload, bytes | bytearray | memoryview):
        raise MessageError("not_bytes", f"{kind}: payload must be bytes, got {type(payload).__name__}")
    size = payload.nbytes if isinstance(payload, memoryview) else len(payload)
    if size > MAX_PAYLOAD_BYTES:
        raise MessageError("too_large", f"{kind}: payload is {size} bytes, the limit is {MAX_PAYLOAD_BYTES}")
    try:
        body = msgpack.unpackb(
            payload,
            raw=False,
            strict_map_key=True,
            max_bin_len=MAX_PAYLOAD_BYTES,
            max_str_len=_MAX_STR_LEN,
            max_array_len=_MAX_ARRAY_LEN,
            max_map_len=_MAX_MAP_LEN,
            max_ext_len=0,
        )
    except Exception as exc:  # msgpack raises a zoo of exception types for malformed input
        detail = " ".join(str(exc).split()) or type(exc).__name__
        raise MessageError("not_msgpack", f"{kind}: payload is not valid msgpack ({detail})") from None
    if not isinstance(body, dict):
        raise MessageError("not_a_map", f"{kind}: payload must be a msgpack map, got {type(body).__name__}")

    version = body.pop("schema_version", None)
    if version is None:
        raise MessageError(
            "schema_version", f"{kind}: schema_version is missing (this build speaks {_speaks()})"
        )
    if type(version) is not int or version not in SUPPORTED_SCHEMA_VERSIONS:
        raise MessageError(
            "schema_version",
            f"{kind}: schema_version {version!r} is not supported (this build speaks {_speaks()})",
        )
    got_kind = body.pop("kind", None)
    if got_kind != kind:
        raise MessageError("wrong_kind", f"{kind}: payload kind is {got_kind!r}, expected {kind!r}")
    try:
        body["schema_version"] = version
        return expected.model_validate(body)
    except ValidationError as exc:
        raise MessageError("invalid", _validation_text(kind, exc)) from None
