"""Tests for common.messages: models, array fields and the msgpack codec's rejection of bad payloads."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from common import messages
from common.encoding import HIT
from common.messages import (
    CLASS_NAMES,
    LIT_PIXELS_VERSION,
    MAX_BEAMS,
    MAX_DETECTIONS,
    MAX_PAYLOAD_BYTES,
    SCHEMA_VERSION,
    SUPPORTED_SCHEMA_VERSIONS,
    TENSOR_SHAPE,
    Detection,
    Detections,
    GroundTruth,
    Message,
    MessageError,
    Odometry,
    Scan,
    StackedTensor,
    StageTimings,
    Track,
    Tracks,
    TruthObject,
    decode_message,
    encode_message,
)
from common.model_spec import FURNITURE_CLASSES

DEG = math.pi / 180.0


def nan_with_payload(payload: int) -> np.float32:
    """A quiet NaN with chosen mantissa bits, to prove the codec does not canonicalise NaNs."""
    return np.array([0x7FC00000 | payload], dtype=np.uint32).view(np.float32)[0]


def make_ranges(n: int = 360) -> np.ndarray:
    ranges = np.linspace(0.2, 3.4, n, dtype=np.float32)
    ranges[5] = np.inf
    ranges[6] = nan_with_payload(0x1234)
    return ranges


def make_scan(**overrides: Any) -> Scan:
    fields: dict[str, Any] = {
        "robot_id": "tb3_0",
        "seq": 42,
        "stamp_ns": 1_700_000_000_000_000_000,
        "angle_min": 0.0,
        "angle_increment": DEG,
        "range_min": 0.12,
        "range_max": 3.5,
        "ranges": make_ranges(),
    }
    fields.update(overrides)
    return Scan(**fields)


def make_tensor(**overrides: Any) -> StackedTensor:
    rng = np.random.default_rng(0)
    fields: dict[str, Any] = {
        "robot_id": "tb3_0",
        "seq": 12,
        "stamp_ns": 5,
        "tensor": rng.integers(0, 256, size=TENSOR_SHAPE, dtype=np.uint8),
        "padding": "wrap",
        "scan_seqs": (10, 11, 12),
        "scan_stamps_ns": (1, 2, 3),
    }
    fields.update(overrides)
    return StackedTensor(**fields)


def detection_fields(**overrides: Any) -> dict[str, Any]:
    fields: dict[str, Any] = {
        "class_id": 2,
        "class_name": "desk",
        "score": 0.87,
        "box_px": (10.0, 3.5, 40.25, 20.0),
        "bearing_deg": 25.0,
        "bearing_min_deg": 10.0,
        "bearing_max_deg": 40.0,
        "range_min_m": 0.8,
        "range_max_m": 1.6,
        "x_m": 1.1,
        "y_m": 0.5,
    }
    fields.update(overrides)
    return fields


def make_detections(**overrides: Any) -> Detections:
    fields: dict[str, Any] = {
        "robot_id": "tb3_0",
        "seq": 12,
        "stamp_ns": 99,
        "detections": [
            Detection(**detection_fields()),
            Detection(**detection_fields(class_id=0, class_name="chair")),
        ],
        "timings": StageTimings(encode_ms=0.4, inference_ms=12.5, nms_ms=0.3),
        "model_id": "yolov8n-triscan-e13",
        "scan_stamp_ns": 90,
    }
    fields.update(overrides)
    return Detections(**fields)


def truth_object(**overrides: Any) -> TruthObject:
    fields: dict[str, Any] = {
        "class_id": 1,
        "class_name": "box",
        "corners_xy": np.array([[0, 0], [0.4, 0], [0.4, 0.6], [0, 0.6]], dtype=np.float32),
        "center_xy": (0.2, 0.3),
        "yaw_rad": 0.5,
        "visible": True,
        "box_px": (100.0, 10.0, 130.0, 14.0),
    }
    fields.update(overrides)
    return TruthObject(**fields)


def make_truth(**overrides: Any) -> GroundTruth:
    fields: dict[str, Any] = {
        "robot_id": "tb3_0",
        "seq": 42,
        "stamp_ns": 7,
        "scenario_id": 3,
        "robot_pose": (0.1, -0.2, 1.0),
        "lidar_pose": (0.07, -0.2, 1.0),
        "objects": [
            truth_object(),
            truth_object(class_id=3, class_name="doorframe", visible=False, box_px=None),
        ],
    }
    fields.update(overrides)
    return GroundTruth(**fields)


def make_odom(**overrides: Any) -> Odometry:
    fields: dict[str, Any] = {"x_m": 1.5, "y_m": -0.25, "yaw_rad": 0.3, "stamp_ns": 88}
    fields.update(overrides)
    return Odometry(**fields)


def track(**overrides: Any) -> Track:
    fields: dict[str, Any] = {
        "track_id": 7,
        "class_id": 4,
        "class_name": "person",
        "score": 0.8,
        "x_m": 1.0,
        "y_m": 0.5,
        "odom_x_m": 2.0,
        "odom_y_m": 1.5,
        "vx_mps": 0.4,
        "vy_mps": -0.1,
        "age_s": 1.2,
        "hits": 12,
        "misses": 0,
        "state": "confirmed",
    }
    fields.update(overrides)
    return Track(**fields)


def make_tracks(**overrides: Any) -> Tracks:
    fields: dict[str, Any] = {
        "robot_id": "tb3_0",
        "seq": 12,
        "stamp_ns": 100,
        "scan_stamp_ns": 90,
        "frame": "odom",
        "tracks": [track(), track(track_id=8, class_id=0, class_name="chair", state="tentative")],
    }
    fields.update(overrides)
    return Tracks(**fields)


def body_of(msg: Message) -> dict[str, Any]:
    """The unpacked wire map, to forge payloads that differ from a valid one in exactly one place."""
    return msgpack.unpackb(encode_message(msg), raw=False)


def pack(body: Any) -> bytes:
    return msgpack.packb(body, use_bin_type=True)


def expect_error(payload: Any, expected: type[Message], reason: str, *fragments: str) -> MessageError:
    with pytest.raises(MessageError) as info:
        decode_message(payload, expected)
    err = info.value
    assert err.reason == reason, str(err)
    text = str(err)
    assert "\n" not in text
    assert text.startswith(f"{expected.KIND}: ")
    for fragment in fragments:
        assert fragment in text, text
    return err


# --------------------------------------------------------------------------------------------------
# Round trips
# --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "factory",
    [
        make_scan,
        make_tensor,
        make_detections,
        make_truth,
        make_tracks,
        lambda: make_scan(odom=make_odom()),
        lambda: make_tensor(odom=make_odom(frame_id="odom_combined")),
        lambda: make_detections(odom=make_odom()),
    ],
)
def test_round_trip_is_exact(factory: Callable[[], Message]) -> None:
    msg = factory()
    decoded = decode_message(encode_message(msg), type(msg))
    assert type(decoded) is type(msg)
    assert decoded == msg
    assert decoded.model_dump(exclude={"ranges", "tensor", "objects"}) == msg.model_dump(
        exclude={"ranges", "tensor", "objects"}
    )


def test_scan_round_trip_keeps_nan_payload_and_inf() -> None:
    scan = make_scan()
    decoded = decode_message(encode_message(scan), Scan)
    assert decoded.ranges.tobytes() == scan.ranges.tobytes()
    assert decoded.ranges.view(np.uint32)[6] == 0x7FC01234
    assert np.isinf(decoded.ranges[5])
    assert decoded.ranges.dtype == np.dtype("<f4")


def test_decoded_arrays_are_read_only_little_endian_contiguous() -> None:
    for msg, name in ((make_scan(), "ranges"), (make_tensor(), "tensor")):
        arr = getattr(decode_message(encode_message(msg), type(msg)), name)
        assert not arr.flags.writeable
        assert arr.flags.c_contiguous
        assert arr.dtype.byteorder in ("<", "|", "=") and arr.dtype.newbyteorder("<") == arr.dtype
        with pytest.raises(ValueError, match="read-only"):
            arr[0] = 0


def test_truth_corners_round_trip() -> None:
    truth = make_truth()
    decoded = decode_message(encode_message(truth), GroundTruth)
    np.testing.assert_array_equal(decoded.objects[0].corners_xy, truth.objects[0].corners_xy)
    assert decoded.objects[1].box_px is None


def test_wire_map_has_kind_version_and_array_maps() -> None:
    body = body_of(make_scan())
    assert body["kind"] == "scan"
    assert body["schema_version"] == 1  # nothing newer in it: a version-1 reader still reads it
    assert body["ranges"]["dtype"] == "<f4"
    assert body["ranges"]["shape"] == [360]
    assert isinstance(body["ranges"]["data"], bytes) and len(body["ranges"]["data"]) == 1440
    assert body_of(make_tensor())["tensor"]["shape"] == list(TENSOR_SHAPE)
    assert [body_of(m)["kind"] for m in (make_tensor(), make_detections(), make_truth())] == [
        "tensor",
        "detections",
        "truth",
    ]


def test_encoding_is_deterministic() -> None:
    assert encode_message(make_truth()) == encode_message(make_truth())


@pytest.mark.parametrize("wrap", [bytearray, memoryview])
def test_decode_accepts_bytes_like(wrap: Callable[[bytes], Any]) -> None:
    scan = make_scan()
    assert decode_message(wrap(encode_message(scan)), Scan) == scan


def test_encode_rejects_non_top_level_model() -> None:
    with pytest.raises(TypeError):
        encode_message(Detection(**detection_fields()))  # type: ignore[arg-type]


def test_equality_sees_array_differences() -> None:
    other = make_ranges()
    other[0] += 1.0
    assert make_scan() != make_scan(ranges=other)
    assert make_scan() != make_scan(seq=43)


# --------------------------------------------------------------------------------------------------
# Array field behaviour at construction
# --------------------------------------------------------------------------------------------------


def test_big_endian_input_comes_back_little_endian_and_equal() -> None:
    native = make_ranges()
    big = native.astype(">f4")
    scan = make_scan(ranges=big)
    assert scan.ranges.dtype == np.dtype("<f4")
    assert scan.ranges.tobytes() == native.tobytes()  # NaN payload survives the byte swap
    decoded = decode_message(encode_message(scan), Scan)
    assert decoded.ranges.tobytes() == native.tobytes()


def test_non_contiguous_input_becomes_c_contiguous() -> None:
    base = np.random.default_rng(1).integers(0, 256, size=(3, 384, 64), dtype=np.uint8)
    fortran_like = base.transpose(2, 1, 0)
    assert not fortran_like.flags.c_contiguous
    msg = make_tensor(tensor=fortran_like)
    assert msg.tensor.flags.c_contiguous
    np.testing.assert_array_equal(msg.tensor, fortran_like)
    np.testing.assert_array_equal(decode_message(encode_message(msg), StackedTensor).tensor, fortran_like)


def test_model_is_decoupled_from_callers_array() -> None:
    ranges = make_ranges()
    scan = make_scan(ranges=ranges)
    ranges[0] = 99.0
    assert scan.ranges[0] != 99.0
    assert not scan.ranges.flags.writeable


@pytest.mark.parametrize(
    ("overrides", "fragment"),
    [
        ({"ranges": np.ones(360, dtype=np.float64)}, "float32"),
        ({"ranges": np.ones((360, 1), dtype=np.float32)}, "1-d"),
        ({"ranges": np.ones(0, dtype=np.float32)}, "at least 1"),
        ({"ranges": [1.0, 2.0]}, "numpy array"),
        ({"angle_increment": 0.0}, "nonzero"),
        ({"angle_increment": float("nan")}, "angle_increment"),
        ({"range_min": 3.5}, "range_min"),
        ({"range_min": -0.1}, "range_min"),
        ({"range_max": float("inf")}, "range_max"),
        ({"angle_increment": 2 * DEG}, "field of view"),
        ({"robot_id": "a/b"}, "robot_id"),
        ({"seq": -1}, "seq"),
        ({"schema_version": 4}, "schema_version"),
        ({"schema_version": 1, "odom": make_odom()}, "odom needs schema_version >= 2"),
        ({"frame_id": ""}, "frame_id"),
    ],
)
def test_scan_construction_rejects(overrides: dict[str, Any], fragment: str) -> None:
    with pytest.raises(ValidationError, match=fragment):
        make_scan(**overrides)


@pytest.mark.parametrize(
    ("n", "increment", "angle_min"),
    [
        (360, DEG, 0.0),
        (1440, 0.25 * DEG, -math.pi),
        (180, DEG, -math.pi / 2),
        (360, -DEG, math.pi),
        (1, 0.01, 0.0),
    ],
)
def test_scan_accepts_real_sensor_layouts(n: int, increment: float, angle_min: float) -> None:
    scan = make_scan(ranges=np.ones(n, dtype=np.float32), angle_increment=increment, angle_min=angle_min)
    assert decode_message(encode_message(scan), Scan) == scan


def test_scan_accepts_float32_rounded_full_circle() -> None:
    increment = float(np.float32(2 * math.pi / 8192)) * (1 + 1e-7)
    make_scan(ranges=np.ones(MAX_BEAMS, dtype=np.float32), angle_increment=increment)


@pytest.mark.parametrize(
    ("factory", "fragment"),
    [
        (lambda: make_tensor(tensor=np.zeros((64, 360, 3), dtype=np.uint8)), "shape"),
        (lambda: make_tensor(tensor=np.zeros(TENSOR_SHAPE, dtype=np.float32)), "uint8"),
        (lambda: make_tensor(padding="reflect"), "padding"),
        (lambda: make_tensor(seq=11), "scan_seqs"),
        (lambda: make_tensor(scan_seqs=(1, 2)), "scan_seqs"),
        (lambda: Detection(**detection_fields(class_id=4, class_name="desk")), "class_id"),
        (lambda: Detection(**detection_fields(class_name="chair")), "class_name"),
        (lambda: Detection(**detection_fields(score=1.01)), "score"),
        (lambda: Detection(**detection_fields(box_px=(5.0, 0.0, 4.0, 1.0))), "x1 <= x2"),
        (lambda: Detection(**detection_fields(box_px=(0.0, 5.0, 4.0, 1.0))), "y1 <= y2"),
        (lambda: Detection(**detection_fields(range_min_m=2.0)), "range_min_m"),
        (lambda: Detection(**detection_fields(x_m=float("inf"))), "x_m"),
        (lambda: StageTimings(encode_ms=-1.0, inference_ms=0.0, nms_ms=0.0), "encode_ms"),
        (lambda: make_detections(detections=[Detection(**detection_fields())] * (MAX_DETECTIONS + 1)), "300"),
        (lambda: make_detections(model_id=""), "model_id"),
        (lambda: truth_object(box_px=None), "visible"),
        (lambda: truth_object(visible=False), "not visible"),
        (lambda: truth_object(corners_xy=np.zeros((3, 2), dtype=np.float32)), "shape"),
        (lambda: truth_object(corners_xy=np.full((4, 2), np.nan, dtype=np.float32)), "finite"),
        (lambda: make_truth(robot_pose=(0.0, float("nan"), 0.0)), "robot_pose"),
    ],
)
def test_model_construction_rejects(factory: Callable[[], Any], fragment: str) -> None:
    with pytest.raises(ValidationError, match=fragment):
        factory()


def test_models_are_frozen_and_forbid_extra() -> None:
    scan = make_scan()
    with pytest.raises(ValidationError):
        scan.seq = 1  # type: ignore[misc]
    with pytest.raises(ValidationError, match="extra"):
        make_scan(intensities=np.ones(360, dtype=np.float32))


def test_messages_travel_as_the_lowest_version_that_holds_them() -> None:
    """Odometry and tracks are version 2; everything else stays readable by a version-1 build."""
    assert SCHEMA_VERSION == max(SUPPORTED_SCHEMA_VERSIONS) == 3
    for plain in (make_scan(), make_tensor(), make_detections(), make_truth()):
        body = body_of(plain)
        assert body["schema_version"] == 1 and "odom" not in body
    for newer in (make_scan(odom=make_odom()), make_detections(odom=make_odom()), make_tracks()):
        assert body_of(newer)["schema_version"] == 2
    assert body_of(make_scan(odom=make_odom()))["odom"] == {
        "x_m": 1.5,
        "y_m": -0.25,
        "yaw_rad": 0.3,
        "frame_id": "odom",
        "stamp_ns": 88,
    }
    # A version-2 payload without odometry (another build chose to write 2) is read as such.
    assert decode_message(with_field(make_scan(), schema_version=2), Scan).schema_version == 2


def test_old_readers_refuse_odometry_by_version_not_by_field() -> None:
    """What a version-1 build does with a version-2 payload: its check names the version."""
    payload = encode_message(make_scan(odom=make_odom()))
    body = msgpack.unpackb(payload)
    assert body["schema_version"] == 2  # a v1 reader stops here: "schema_version 2 is not supported"
    expect_error(with_field(make_scan(odom=make_odom()), schema_version=1), Scan, "invalid", "odom", ">= 2")
    expect_error(with_field(make_tracks(), schema_version=1), Tracks, "invalid", "tracks", ">= 2")


def test_odometry_may_be_non_finite_on_the_wire() -> None:
    """A diverged filter's NaN pose must not cost the scan: consumers refuse the pose, not the message."""
    scan = decode_message(encode_message(make_scan(odom=make_odom(x_m=float("nan")))), Scan)
    assert scan.odom is not None and not scan.odom.finite
    assert make_odom().finite


@pytest.mark.parametrize(
    ("factory", "fragment"),
    [
        (lambda: track(class_name="chair"), "class_name"),
        (lambda: track(state="lost"), "state"),
        (lambda: track(odom_y_m=None), "together"),
        (lambda: track(x_m=float("nan")), "x_m"),
        (lambda: make_tracks(frame="laser"), "laser-frame"),
        (lambda: make_tracks(tracks=[track(odom_x_m=None, odom_y_m=None)]), "odom-frame"),
        (lambda: make_tracks(frame="map"), "frame"),
        (lambda: make_odom(frame_id=""), "frame_id"),
    ],
)
def test_track_models_reject(factory: Callable[[], Any], fragment: str) -> None:
    with pytest.raises(ValidationError, match=fragment):
        factory()


def test_class_names() -> None:
    assert CLASS_NAMES == ("chair", "box", "desk", "doorframe", "person")
    assert CLASS_NAMES[: len(FURNITURE_CLASSES)] == FURNITURE_CLASSES == ("chair", "box", "desk", "doorframe")


# --------------------------------------------------------------------------------------------------
# Decoding bad payloads
# --------------------------------------------------------------------------------------------------


def with_field(msg: Message, **changes: Any) -> bytes:
    body = body_of(msg)
    body.update(changes)
    return pack(body)


def with_ranges(**changes: Any) -> bytes:
    body = body_of(make_scan())
    body["ranges"].update(changes)
    return pack(body)


def without(msg: Message, key: str) -> bytes:
    body = body_of(msg)
    del body[key]
    return pack(body)


def test_shape_byte_length_mismatch_message_is_exact() -> None:
    err = expect_error(with_ranges(data=b"\x00" * 1000), Scan, "invalid")
    assert str(err) == "scan: ranges: 360 float32 expected 1440 bytes, got 1000"


@pytest.mark.parametrize(
    ("payload", "reason", "fragments"),
    [
        (b"\xc1\x00\x17garbage", "not_msgpack", ("not valid msgpack",)),
        (encode_message(make_scan())[:-100], "not_msgpack", ("not valid msgpack",)),
        (encode_message(make_scan()) + b"\x00", "not_msgpack", ("not valid msgpack",)),
        (b"", "not_msgpack", ()),
        (b"\xdd\xff\xff\xff\xff", "not_msgpack", ()),  # declares a 4-billion-element array
        (b"\xdf\xff\xff\xff\xff", "not_msgpack", ()),  # declares a 4-billion-entry map
        (b"\xc6\x7f\xff\xff\xff", "not_msgpack", ()),  # declares a 2 GiB bin
        (pack({1: 2}), "not_msgpack", ()),  # non-string map keys
        (msgpack.packb(msgpack.ExtType(5, b"xx")), "not_msgpack", ()),
        (pack([1, 2, 3]), "not_a_map", ("list",)),
        (pack(7), "not_a_map", ("int",)),
        (encode_message(make_tensor()), "wrong_kind", ("'tensor'", "'scan'")),
        (without(make_scan(), "kind"), "wrong_kind", ("None",)),
        (with_field(make_scan(), schema_version=4), "schema_version", ("4", "speaks 1, 2, 3")),
        (with_field(make_scan(), schema_version="1"), "schema_version", ("'1'",)),
        (with_field(make_scan(), schema_version=True), "schema_version", ("True",)),
        (without(make_scan(), "schema_version"), "schema_version", ("missing",)),
        (with_ranges(dtype="<f8"), "invalid", ("ranges", "float32", "'<f8'")),
        (with_ranges(dtype=">f4"), "invalid", ("ranges", "little-endian")),
        (with_ranges(dtype="O"), "invalid", ("ranges",)),
        (with_ranges(shape=[361]), "invalid", ("ranges", "1444 bytes, got 1440")),
        (with_ranges(shape=[360, 1]), "invalid", ("ranges", "1-d")),
        (with_ranges(shape=[-360]), "invalid", ("ranges", "non-negative")),
        (with_ranges(shape=[2**62]), "invalid", ("ranges", "8192")),
        (with_ranges(shape=["360"]), "invalid", ("ranges",)),
        (with_ranges(data="x" * 1440), "invalid", ("ranges", "bytes")),
        (with_ranges(extra=1), "invalid", ("ranges", "keys")),
        (with_field(make_scan(), ranges=[1.0, 2.0]), "invalid", ("ranges",)),
        (with_field(make_scan(), angle_min=float("nan")), "invalid", ("angle_min",)),
        (with_field(make_scan(), range_max=float("inf")), "invalid", ("range_max",)),
        (with_field(make_scan(), robot_id="a/b"), "invalid", ("robot_id",)),
        (with_field(make_scan(), robot_id=""), "invalid", ("robot_id",)),
        (with_field(make_scan(), robot_id="*"), "invalid", ("robot_id",)),
        (with_field(make_scan(), robot_id="r" * 65), "invalid", ("robot_id",)),
        (with_field(make_scan(), seq=-1), "invalid", ("seq",)),
        (with_field(make_scan(), stamp_ns=-5), "invalid", ("stamp_ns",)),
        (with_field(make_scan(), hostname="x"), "invalid", ("hostname", "xtra")),
        (without(make_scan(), "ranges"), "invalid", ("ranges", "required")),
        (with_field(make_scan(), angle_increment=0.0), "invalid", ("nonzero",)),
    ],
)
def test_decode_rejects_scan_payloads(payload: bytes, reason: str, fragments: tuple[str, ...]) -> None:
    expect_error(payload, Scan, reason, *fragments)


def test_decode_rejects_too_many_beams() -> None:
    n = MAX_BEAMS + 1
    body = body_of(make_scan())
    body["angle_increment"] = 1e-4  # keeps the field of view legal, so only the beam count is wrong
    body["ranges"] = {"dtype": "<f4", "shape": [n], "data": b"\x00" * (4 * n)}
    expect_error(pack(body), Scan, "invalid", "ranges", f"at most {MAX_BEAMS} elements", str(n))


def test_oversized_payload_rejected_before_unpacking() -> None:
    body = body_of(make_scan())
    body["frame_id"] = "x" * 10  # keep it a perfectly valid message apart from the size
    payload = pack(body) + b"\x00" * (MAX_PAYLOAD_BYTES + 1)
    expect_error(payload, Scan, "too_large", str(MAX_PAYLOAD_BYTES))
    expect_error(memoryview(payload), Scan, "too_large")


@pytest.mark.parametrize("payload", ["a string", 42, None, [b"x"]])
def test_decode_rejects_non_bytes(payload: Any) -> None:
    expect_error(payload, Scan, "not_bytes")


@pytest.mark.parametrize(
    ("payload", "expected", "fragments"),
    [
        (
            with_field(make_tensor(), tensor={"dtype": "<f4", "shape": [64, 384, 3], "data": b""}),
            StackedTensor,
            ("tensor", "uint8"),
        ),
        (
            with_field(
                make_tensor(), tensor={"dtype": "|u1", "shape": [64, 360, 3], "data": b"\x00" * 69120}
            ),
            StackedTensor,
            ("tensor", "shape"),
        ),
        (
            with_field(make_tensor(), tensor={"dtype": "|u1", "shape": [64, 384, 3], "data": b"\x00" * 10}),
            StackedTensor,
            ("tensor", "73728 bytes, got 10"),
        ),
        (with_field(make_tensor(), padding="mirror"), StackedTensor, ("padding",)),
        (with_field(make_tensor(), scan_seqs=[10, 11]), StackedTensor, ("scan_seqs",)),
        (with_field(make_detections(), model_id=7), Detections, ("model_id",)),
        (
            with_field(
                make_detections(), timings={"encode_ms": float("nan"), "inference_ms": 1.0, "nms_ms": 1.0}
            ),
            Detections,
            ("timings.encode_ms",),
        ),
        (with_field(make_truth(), robot_pose=[0.0, 0.0]), GroundTruth, ("robot_pose",)),
    ],
)
def test_decode_rejects_other_payloads(
    payload: bytes, expected: type[Message], fragments: tuple[str, ...]
) -> None:
    expect_error(payload, expected, "invalid", *fragments)


def test_decode_names_nested_field() -> None:
    body = body_of(make_detections())
    body["detections"][1]["score"] = 2.0
    expect_error(pack(body), Detections, "invalid", "detections.1.score")


def test_decode_accepts_one_byte_dtype_spellings() -> None:
    for spelling in ("|u1", "<u1", "u1"):
        body = body_of(make_tensor())
        body["tensor"]["dtype"] = spelling
        assert decode_message(pack(body), StackedTensor) == make_tensor()


def test_message_error_is_value_error_with_reason() -> None:
    err = expect_error(b"\xc1", Scan, "not_msgpack")
    assert isinstance(err, ValueError)


# --------------------------------------------------------------------------------------------------
# Tensors as their lit pixels (schema version 3)
# --------------------------------------------------------------------------------------------------

PLANE = TENSOR_SHAPE[0] * TENSOR_SHAPE[1]


def binary_raster(seed: int = 3, empty_channels: tuple[int, ...] = ()) -> np.ndarray:
    """What the encoder makes: per channel one lit pixel per one-degree beam, at a random range row."""
    rng = np.random.default_rng(seed)
    raster = np.zeros(TENSOR_SHAPE, dtype=np.uint8)
    for channel in set(range(TENSOR_SHAPE[2])) - set(empty_channels):
        raster[rng.integers(0, TENSOR_SHAPE[0], size=360), np.arange(360), channel] = HIT
    return raster


def make_lit_tensor(**overrides: Any) -> StackedTensor:
    return make_tensor(**{"tensor": binary_raster(), "schema_version": LIT_PIXELS_VERSION, **overrides})


def with_lit(**changes: Any) -> bytes:
    body = body_of(make_lit_tensor())
    body["tensor"].update(changes)
    return pack(body)


def lit_indices(tensor: StackedTensor) -> np.ndarray:
    return np.frombuffer(body_of(tensor)["tensor"]["lit"], dtype="<u2").copy()


def with_indices(indices: np.ndarray) -> bytes:
    return with_lit(lit=indices.astype("<u2").tobytes())


@pytest.mark.parametrize(
    "raster",
    [
        binary_raster(),
        binary_raster(empty_channels=(0,)),
        binary_raster(empty_channels=(1, 2)),
        np.zeros(TENSOR_SHAPE, np.uint8),
    ],
    ids=["full", "first_empty", "last_two_empty", "dark"],
)
def test_lit_pixels_round_trip_bit_identical(raster: np.ndarray) -> None:
    msg = make_lit_tensor(tensor=raster, odom=make_odom())
    payload = encode_message(msg)
    wire = msgpack.unpackb(payload)["tensor"]
    assert set(wire) == {"dtype", "shape", "counts", "lit"} and wire["shape"] == list(TENSOR_SHAPE)
    assert wire["counts"] == [int(np.count_nonzero(raster[:, :, c])) for c in range(3)]
    decoded = decode_message(payload, StackedTensor)
    assert decoded == msg and decoded.schema_version == LIT_PIXELS_VERSION
    assert decoded.tensor.tobytes() == raster.tobytes() and decoded.tensor.dtype == np.uint8
    assert not decoded.tensor.flags.writeable and decoded.tensor.flags.c_contiguous


def test_lit_indices_are_each_channels_sorted_pixels() -> None:
    raster = binary_raster()
    wire = body_of(make_lit_tensor(tensor=raster))["tensor"]
    indices, ends = np.frombuffer(wire["lit"], dtype="<u2"), np.cumsum([0, *wire["counts"]])
    for c in range(3):
        rows, cols = np.nonzero(raster[:, :, c])
        np.testing.assert_array_equal(indices[ends[c] : ends[c + 1]], np.sort(rows * TENSOR_SHAPE[1] + cols))


def test_a_lit_tensor_payload_is_a_few_kilobytes() -> None:
    assert len(encode_message(make_lit_tensor())) < 4096 < 70_000 < len(encode_message(make_tensor()))


@pytest.mark.parametrize(
    ("raster", "why"),
    [
        (
            np.random.default_rng(0).integers(0, 256, size=TENSOR_SHAPE, dtype=np.uint8),
            "values other than 0/255",
        ),
        (np.where(binary_raster() > 0, np.uint8(1), np.uint8(0)), "lit with 1, not HIT"),
        (np.full(TENSOR_SHAPE, HIT, np.uint8), "dense is smaller"),
    ],
)
def test_a_version_3_raster_travels_dense_where_lit_pixels_cannot_hold_it(
    raster: np.ndarray, why: str
) -> None:
    msg = make_lit_tensor(tensor=raster)
    wire = body_of(msg)["tensor"]
    assert set(wire) == {"dtype", "shape", "data"}, why
    assert decode_message(encode_message(msg), StackedTensor) == msg


def test_which_version_a_tensor_travels_as() -> None:
    """Built without a version a tensor is the lowest that holds it, dense; a producer opts in to 3."""
    plain = make_tensor(tensor=binary_raster())
    assert plain.schema_version == 1 and set(body_of(plain)["tensor"]) == {"dtype", "shape", "data"}
    assert body_of(make_tensor(tensor=binary_raster(), odom=make_odom()))["schema_version"] == 2
    # Built from a lit-pixel map, only version 3 holds it.
    from_map = StackedTensor(
        **{
            **make_tensor().model_dump(exclude={"schema_version"}),
            "tensor": body_of(make_lit_tensor())["tensor"],
        }
    )
    assert (
        from_map.schema_version == LIT_PIXELS_VERSION
        and from_map.tensor.tobytes() == binary_raster().tobytes()
    )


def test_model_dump_stays_dense_so_a_message_rebuilds_under_any_version() -> None:
    lit = make_lit_tensor()
    dumped = lit.model_dump()
    assert set(dumped["tensor"]) == {"dtype", "shape", "data"}
    assert StackedTensor(**{**dumped, "schema_version": 2}).tensor.tobytes() == lit.tensor.tobytes()


def test_version_3_readers_accept_the_dense_form_and_older_versions() -> None:
    dense = body_of(make_tensor(tensor=binary_raster(), odom=make_odom()))
    assert dense["schema_version"] == 2
    assert decode_message(pack(dense), StackedTensor) == make_tensor(tensor=binary_raster(), odom=make_odom())
    as_v3 = decode_message(pack({**dense, "schema_version": 3}), StackedTensor)
    assert as_v3.schema_version == 3 and as_v3.tensor.tobytes() == binary_raster().tobytes()


def test_lit_pixels_under_an_older_version_are_refused() -> None:
    for version in (1, 2):
        expect_error(
            with_field(make_lit_tensor(), schema_version=version),
            StackedTensor,
            "invalid",
            f"tensor: lit pixels need schema_version >= 3, got {version}",
        )


def test_a_build_that_speaks_1_and_2_refuses_version_3_by_its_version(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """What docs/services.md promises an older detector says when a newer encoder's tensor reaches it."""
    lit, older = encode_message(make_lit_tensor()), encode_message(make_tensor(odom=make_odom()))
    monkeypatch.setattr(messages, "SUPPORTED_SCHEMA_VERSIONS", (1, 2))
    err = expect_error(lit, StackedTensor, "schema_version")
    assert str(err) == "tensor: schema_version 3 is not supported (this build speaks 1, 2)"
    assert decode_message(older, StackedTensor).schema_version == 2


def _moved(at: int, to: int) -> np.ndarray:
    indices = lit_indices(make_lit_tensor())
    indices[at] = to
    return indices


_N = int(np.count_nonzero(binary_raster()[:, :, 0]))  # pixels of channel 0, so channel 1 starts at _N


@pytest.mark.parametrize(
    ("payload", "fragments"),
    [
        (
            with_lit(extra=1),
            ("lit-pixel map must have exactly the keys counts, dtype, lit, shape", "'extra'"),
        ),
        (with_lit(data=b""), ("exactly the keys",)),
        (with_lit(dtype="<f4"), ("uint8", "'<f4'")),
        (with_lit(shape=[64, 360, 3]), ("shape [64, 384, 3]",)),
        (with_lit(shape=[64, 384]), ("3-d",)),
        (with_lit(shape=[2**62, 384, 3]), ("shape",)),
        (with_lit(counts="360,360,360"), ("counts must be a list of 3 ints, one per channel, got str",)),
        (with_lit(counts=[360, 360]), ("got 2 items",)),
        (with_lit(counts=[-1, 360, 360]), ("counts[0] must be an int in 0..24576, got -1",)),
        (with_lit(counts=[360, PLANE + 1, 360]), ("counts[1] must be an int in 0..24576, got 24577",)),
        (with_lit(counts=[360, 360, 2**40]), ("counts[2]", str(2**40))),
        (with_lit(counts=[360, 360.0, 360]), ("counts[1]", "360.0")),
        (with_lit(counts=[True, 360, 360]), ("counts[0]", "True")),
        (with_lit(lit="x" * 2160), ("lit must be bytes, got str",)),
        (
            with_lit(counts=[360, 360, 359]),
            ("counts add up to 1079 pixels, expected 2158 bytes of lit, got 2160",),
        ),
        (with_lit(lit=bytes(2161)), ("expected 2160 bytes of lit, got 2161",)),
        (with_indices(_moved(5, PLANE)), ("lit index 24576 of channel 0 is outside the 24576-pixel plane",)),
        (with_indices(_moved(3 * 360 - 1, 65535)), ("lit index 65535 of channel 2 is outside",)),
        (
            with_indices(_moved(_N + 7, 0)),
            ("lit indices of channel 1 must be sorted and unique", "got 0 after"),
        ),
        (with_indices(_moved(_N - 1, 0)), ("channel 0 must be sorted and unique",)),
    ],
)
def test_decode_rejects_bad_lit_pixel_maps(payload: bytes, fragments: tuple[str, ...]) -> None:
    expect_error(payload, StackedTensor, "invalid", "tensor: ", *fragments)


def test_decode_rejects_a_repeated_lit_pixel() -> None:
    indices = lit_indices(make_lit_tensor())
    indices[_N + 4] = indices[_N + 3]
    err = expect_error(with_indices(indices), StackedTensor, "invalid")
    twice = indices[_N + 3]
    assert (
        str(err)
        == f"tensor: tensor: lit indices of channel 1 must be sorted and unique, got {twice} after {twice}"
    )


# --------------------------------------------------------------------------------------------------
# Properties
# --------------------------------------------------------------------------------------------------


@st.composite
def scans(draw: st.DrawFn) -> Scan:
    n = draw(st.integers(min_value=1, max_value=MAX_BEAMS))
    # Any uint32 bit pattern: covers every NaN payload, both infinities, subnormals and -0.0.
    bits = np.random.default_rng(draw(st.integers(0, 2**32 - 1))).integers(0, 2**32, size=n, dtype=np.uint32)
    magnitude = draw(st.floats(min_value=1e-6, max_value=2 * math.pi / n))
    sign = draw(st.sampled_from([1.0, -1.0]))
    range_min = draw(st.floats(min_value=0.0, max_value=10.0))
    return Scan(
        robot_id=draw(st.from_regex(r"[A-Za-z0-9_-]{1,64}", fullmatch=True)),
        seq=draw(st.integers(min_value=0, max_value=2**63 - 1)),
        stamp_ns=draw(st.integers(min_value=0, max_value=2**63 - 1)),
        angle_min=draw(st.floats(min_value=-4.0, max_value=4.0)),
        angle_increment=sign * magnitude,
        range_min=range_min,
        range_max=range_min + draw(st.floats(min_value=1e-3, max_value=100.0)),
        ranges=bits.view(np.float32),
        frame_id=draw(st.text(min_size=1, max_size=32)),
    )


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scans())
def test_random_valid_scans_round_trip(scan: Scan) -> None:
    decoded = decode_message(encode_message(scan), Scan)
    assert decoded == scan
    assert decoded.ranges.tobytes() == scan.ranges.tobytes()


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0.0, 1e-4, 0.01, 0.3, 0.6]), st.booleans())
def test_random_rasters_round_trip_at_version_3(seed: int, density: float, binary: bool) -> None:
    """Whichever form the serialiser picks (lit pixels, or dense past half lit or for other values)."""
    rng = np.random.default_rng(seed)
    raster = np.where(rng.random(TENSOR_SHAPE) < density, HIT, np.uint8(0)).astype(np.uint8)
    if not binary:
        raster[rng.integers(0, 64), rng.integers(0, 384), rng.integers(0, 3)] = 7
    msg = make_lit_tensor(tensor=raster)
    payload = encode_message(msg)
    assert ("lit" in msgpack.unpackb(payload)["tensor"]) == (binary and density < 0.5)
    assert decode_message(payload, StackedTensor).tensor.tobytes() == raster.tobytes()


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=512), st.sampled_from([Scan, StackedTensor, Detections, GroundTruth]))
def test_random_bytes_only_raise_message_error(payload: bytes, expected: type[Message]) -> None:
    with pytest.raises(MessageError):
        decode_message(payload, expected)


msgpack_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**63), max_value=2**64 - 1)
    | st.floats()
    | st.text(max_size=20)
    | st.binary(max_size=64),
    lambda children: (
        st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=8), children, max_size=5)
    ),
    max_leaves=20,
)


@settings(max_examples=300, deadline=None)
@given(
    st.sampled_from([make_scan(), make_tensor(), make_lit_tensor(), make_detections(), make_truth()]),
    st.data(),
    msgpack_values,
)
def test_structured_garbage_only_raises_message_error(msg: Message, data: st.DataObject, value: Any) -> None:
    """Replace one field, or one part of an array map, with an arbitrary msgpack value."""
    body = body_of(msg)
    key = data.draw(st.sampled_from(sorted(body)))
    target = body
    if isinstance(body[key], dict) and data.draw(st.booleans()):
        target = body[key]
        key = data.draw(st.sampled_from(sorted(target)))
    target[key] = value
    try:
        decoded = decode_message(pack(body), type(msg))
    except MessageError as err:
        assert err.reason in {"wrong_kind", "schema_version", "invalid"}
    else:
        assert isinstance(decoded, type(msg))


@pytest.mark.parametrize(
    "body",
    [
        {"kind": "scan", "schema_version": 1, "junk": list(range(2000))},
        {"kind": "scan", "schema_version": 1, "junk": {f"k{i}": i for i in range(100)}},
        {"kind": "scan", "schema_version": 1, "frame_id": "x" * 5000},
    ],
)
def test_unpacker_limits_reject_oversized_containers(body: dict[str, Any]) -> None:
    """No legal message has containers this big, so they are refused while unpacking, not validated."""
    expect_error(pack(body), Scan, "not_msgpack")


def test_detections_carry_the_stamp_of_the_scan_their_boxes_belong_to() -> None:
    """The boxes are the middle scan's: its stamp travels beside the newest scan's, never after it."""
    message = make_detections(scan_stamp_ns=90, pose_stamp_ns=80)
    assert decode_message(encode_message(message), Detections).pose_stamp_ns == 80
    body = msgpack.unpackb(encode_message(make_detections()))  # a producer that does not fill it
    assert "pose_stamp_ns" not in body and body["schema_version"] == 1, "a version-1 reader still reads it"
    assert decode_message(msgpack.packb(body), Detections).pose_stamp_ns is None
    assert msgpack.unpackb(encode_message(message))["schema_version"] == 2
    with pytest.raises(ValidationError, match="cannot be newer than scan_stamp_ns"):
        make_detections(scan_stamp_ns=90, pose_stamp_ns=91)


def test_a_tensors_raster_yaw_is_optional_and_needs_version_3() -> None:
    plain = make_tensor()
    assert plain.raster_yaw_deg is None and plain.yaw_deg == 0.0
    assert plain.schema_version == 1  # the lowest version that holds it, as before the field existed
    assert "raster_yaw_deg" not in msgpack.unpackb(encode_message(plain))
    turned = make_tensor(raster_yaw_deg=180.0)
    assert turned.schema_version == 3 and turned.yaw_deg == 180.0
    assert decode_message(encode_message(turned), StackedTensor) == turned
    with pytest.raises(ValidationError, match="raster_yaw_deg needs schema_version >= 3"):
        make_tensor(raster_yaw_deg=180.0, schema_version=2)
    for bad in (360.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValidationError):
            make_tensor(raster_yaw_deg=bad)
