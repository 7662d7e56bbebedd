"""The ROS 2 bridge's pure parts: types and hashes, CDR, rmw_zenoh keys/attachments/tokens, and the core.

Expected values come from outside this code wherever one exists: RIHS01 hashes from rosidl's generated
type descriptions, CDR bytes from rosbags' serialiser, attachment bytes from zenoh's own serialiser.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from zenoh.ext import Int64, z_serialize

from common.encoding import ANGLE_COLUMNS, ScanStacker, angle_columns, beam_bearings_rad, encode_scan
from common.keys import detections_key, scan_key, tracks_key
from common.messages import (
    Detections,
    Scan,
    StageTimings,
    Track,
    TrackFrame,
    Tracks,
    TrackState,
    decode_message,
    encode_message,
)
from common.model_spec import CLASS_NAMES
from services.ros2_bridge.core import BridgeConfig, BridgeCore
from services.ros2_bridge.laser_scan import parse_laser_scan_cdr
from services.ros2_bridge.odometry import ODOMETRY
from services.ros2_bridge.rmw_zenoh import (
    ATTACHMENT_SIZE,
    AttachmentError,
    data_key,
    decode_attachment,
    encode_attachment,
    endpoint_token,
    node_token,
    normalize_namespace,
    parse_data_key,
    subscription_key,
)
from services.ros2_bridge.ros_messages import (
    ADD,
    ARROW,
    ARROW_HORIZON_S,
    CUBE,
    DELETEALL,
    TEXT_VIEW_FACING,
    DetectionMessages,
    ReferenceDetectionMessages,
)
from services.ros2_bridge.ros_types import (
    DETECTION3D_ARRAY,
    LASER_SCAN,
    MARKER_ARRAY,
    TYPE_HASH_NOT_SUPPORTED,
    dds_type_name,
    ros_types,
)
from services.tracker.core import track_colour
from tests.support.detection_builders import one_detection
from tests.support.ros2_scans import laser_scan_cdr

JAZZY_LASER_SCAN_HASH = "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828"
# From rosidl_generator_c's vision_msgs description.c (EXPECTED_HASH of each type), Jazzy build.
ROSIDL_VISION_HASHES = {
    "vision_msgs/msg/Detection3DArray": "793f5eab9595ac1c0da07873cc859db42eae51f0ee76056db8562515d830e018",
    "vision_msgs/msg/Detection3D": "ddd703be132ab0b69d33121f1bb034132bfbb3b0ac5f9fb1516005ba1c8a265b",
    "vision_msgs/msg/BoundingBox3D": "bbb73a65c163d7f9bb29009c7bde9f7faa576bd2d23299c4511d19230dab4698",
    "vision_msgs/msg/ObjectHypothesis": "51da43cec11c01957a64d1e05a24acd18aae7745ec30b74348ad5f6d634f7f90",
    "vision_msgs/msg/ObjectHypothesisWithPose": (
        "41c12344c0396c48b81df12467c192d99b2a0eb1463c5c37194e4223251c80bc"
    ),
}
GID = bytes(range(16))
STAMP_NS = 1_700_000_000_123_456_789


# -- types, hashes, CDR --------------------------------------------------------------------------


def test_type_hashes_are_rosidls() -> None:
    jazzy = ros_types("jazzy")
    assert jazzy.type_hash(LASER_SCAN) == JAZZY_LASER_SCAN_HASH
    for typename, digest in ROSIDL_VISION_HASHES.items():
        assert jazzy.type_hash(typename) == f"RIHS01_{digest}", typename
    assert ros_types("humble").type_hash(DETECTION3D_ARRAY) == TYPE_HASH_NOT_SUPPORTED
    assert dds_type_name(LASER_SCAN) == "sensor_msgs::msg::dds_::LaserScan_"


@pytest.mark.parametrize("little_endian", [True, False], ids=["le", "be"])
@pytest.mark.parametrize("frame_id", ["l", "laser", "base_laser_link", "ü-frame"])
def test_cdr_reader_reads_what_rosbags_writes(little_endian: bool, frame_id: str) -> None:
    rng = np.random.default_rng(len(frame_id))
    ranges = rng.uniform(0.1, 9.0, 517).astype(np.float32)
    ranges[::7] = np.inf
    payload = laser_scan_cdr(
        ranges, little_endian=little_endian, frame_id=frame_id, intensities=np.ones(5), stamp_ns=STAMP_NS
    )
    reference = ros_types().deserialize(payload, LASER_SCAN)
    fields = parse_laser_scan_cdr(payload)
    assert fields.frame_id == reference.header.frame_id == frame_id
    assert (fields.stamp_sec, fields.stamp_nanosec) == (
        reference.header.stamp.sec,
        reference.header.stamp.nanosec,
    )
    assert fields.angle_min == reference.angle_min and fields.angle_increment == reference.angle_increment
    assert fields.range_min == reference.range_min and fields.range_max == reference.range_max
    assert fields.ranges.astype("<f4").tobytes() == reference.ranges.astype("<f4").tobytes()
    assert fields.intensities_count == 5


def test_detection_encoders_write_rosbags_bytes_on_both_distros() -> None:
    detections = [one_detection((10 + 40 * i, 5, 30 + 40 * i, 30), 0.5 + 0.1 * i, i % 4) for i in range(4)]
    detections.append(one_detection((370, 3, 380, 9), 0.9, 2))  # straddles 0°: min > max after wrapping
    # a crowded frame: every class at many offsets, so every alignment case of the fast path occurs
    detections += [
        one_detection((9 * i, 2 + i, 9 * i + 7, 20 + i), 0.31 + 0.023 * i, i % 4) for i in range(24)
    ]
    for distro in ("jazzy", "humble"):
        fast, reference = DetectionMessages(ros_types(distro)), ReferenceDetectionMessages(ros_types(distro))
        for count in (0, 1, 2, 5, 7, 29):
            for frame_id in ("l", "laser", "base_scan", "a_b"):
                args = (detections[:count], STAMP_NS, frame_id)
                assert fast.detection_array(*args) == reference.detection_array(*args), (
                    distro,
                    count,
                    frame_id,
                )
                assert fast.marker_array(*args) == reference.marker_array(*args), (distro, count, frame_id)
    marker = ros_types().store.types["visualization_msgs/msg/Marker"]
    assert (marker.ARROW, marker.CUBE, marker.TEXT_VIEW_FACING, marker.ADD, marker.DELETEALL) == (
        ARROW,
        CUBE,
        TEXT_VIEW_FACING,
        ADD,
        DELETEALL,
    )


def _track(
    track_id: int, x: float, y: float, vx: float, vy: float, frame: TrackFrame, state: TrackState
) -> Track:
    odom = {"odom_x_m": x + 10.0, "odom_y_m": y - 5.0} if frame == "odom" else {}
    return Track(
        track_id=track_id, class_id=track_id % 5, class_name=CLASS_NAMES[track_id % 5],
        score=0.3 + 0.05 * (track_id % 11), x_m=x, y_m=y, vx_mps=vx, vy_mps=vy, age_s=1.0, hits=4,
        misses=0, state=state, **odom,
    )  # fmt: skip


def test_track_encoders_write_rosbags_bytes_on_both_distros() -> None:
    for distro in ("jazzy", "humble"):
        fast, reference = DetectionMessages(ros_types(distro)), ReferenceDetectionMessages(ros_types(distro))
        for frame in ("odom", "laser"):
            # ids of every length (the id string's padding), still and moving tracks
            tracks = [
                _track(7**i, 0.3 * i, -0.2 * i, 0.1 * (i % 3), -0.4 * (i % 2), frame, "confirmed")
                for i in range(12)
            ]
            for count in (0, 1, 2, 5, 12):
                for frame_id in ("l", "odom", "base_scan"):
                    args = (tracks[:count], frame, STAMP_NS, frame_id)
                    assert fast.track_array(*args) == reference.track_array(*args), (distro, frame, count)
                    assert fast.track_marker_array(*args) == reference.track_marker_array(*args), (
                        distro,
                        frame,
                        count,
                    )


# -- rmw_zenoh: attachment, keys, tokens ---------------------------------------------------------


def test_attachment_is_zenohs_serialisation_and_round_trips() -> None:
    raw = encode_attachment(42, STAMP_NS, GID)
    assert len(raw) == ATTACHMENT_SIZE == 33
    assert raw == z_serialize((Int64(42), Int64(STAMP_NS), GID)).to_bytes()  # zenoh-ext, as rmw_zenoh_cpp
    decoded = decode_attachment(raw)
    assert (decoded.sequence_number, decoded.source_timestamp_ns, decoded.gid) == (42, STAMP_NS, GID)
    for bad in (None, raw[:-1], raw + b"\0", raw[:16] + b"\x0f" + raw[17:]):
        with pytest.raises(AttachmentError):
            decode_attachment(bad)


def test_keys_of_both_styles_distros_and_namespaces() -> None:
    scan_type = dds_type_name(LASER_SCAN)
    assert data_key("rmw_zenoh", 0, "/scan", scan_type, JAZZY_LASER_SCAN_HASH) == (
        f"0/scan/sensor_msgs::msg::dds_::LaserScan_/{JAZZY_LASER_SCAN_HASH}"
    )
    assert data_key("rmw_zenoh", 7, "/r1/scan", scan_type, TYPE_HASH_NOT_SUPPORTED) == (
        "7/r1/scan/sensor_msgs::msg::dds_::LaserScan_/TypeHashNotSupported"
    )
    assert data_key("ros2dds", 7, "/r1/scan", scan_type, "ignored") == "r1/scan"
    assert subscription_key("rmw_zenoh", 3, "/a/b", "scan", scan_type) == f"3/a/b/scan/{scan_type}/*"
    assert subscription_key("rmw_zenoh", 0, None, "scan", scan_type) == f"0/*/scan/{scan_type}/*"
    assert subscription_key("ros2dds", 0, "/", "sensors/scan", scan_type) == "sensors/scan"
    assert subscription_key("ros2dds", 0, None, "scan", scan_type) == "*/scan"
    parsed = parse_data_key("rmw_zenoh", 0, f"0/a/b/scan/{scan_type}/{TYPE_HASH_NOT_SUPPORTED}", "scan")
    assert (parsed.namespace, parsed.dds_type, parsed.type_hash) == (
        "/a/b",
        scan_type,
        TYPE_HASH_NOT_SUPPORTED,
    )
    assert parse_data_key("ros2dds", 0, "r1/sensors/scan", "sensors/scan").namespace == "/r1"
    assert parse_data_key("ros2dds", 0, "scan", "scan").namespace == "/"
    for key, style in (
        (f"1/scan/{scan_type}/x", "rmw_zenoh"),
        ("r1/odom", "ros2dds"),
        ("0/scan", "rmw_zenoh"),
    ):
        with pytest.raises(ValueError):
            parse_data_key(style, 0, key, "scan")
    assert normalize_namespace("") == normalize_namespace("/") == "/"
    assert normalize_namespace("robot1/") == "/robot1"
    with pytest.raises(ValueError):
        normalize_namespace("/a//b")


def test_liveliness_tokens_follow_rmw_zenoh_and_read_back_with_zenoh_ros2_sdk() -> None:
    from zenoh_ros2_sdk.discovery import _parse_liveliness_keyexpr

    token = endpoint_token(
        "MP", 0, "abc123", 1, 4, "/r1", "triscan_bridge", "/r1/triscan/markers",
        dds_type_name(MARKER_ARRAY), ros_types().type_hash(MARKER_ARRAY),
    )  # fmt: skip
    assert token.startswith("@ros2_lv/0/abc123/1/4/MP/%/%r1/triscan_bridge/%r1%triscan%markers/")
    assert token.endswith(
        f"/visualization_msgs::msg::dds_::MarkerArray_/{ros_types().type_hash(MARKER_ARRAY)}/::,10:,:,:,,"
    )
    parsed = _parse_liveliness_keyexpr(token)  # an independent parser of the same format
    assert parsed is not None
    assert (parsed["qualified_name"], parsed["namespace"], parsed["node_name"]) == (
        "/r1/triscan/markers", "/r1", "triscan_bridge",
    )  # fmt: skip
    assert node_token(0, "abc123", 1, "/", "n") == "@ros2_lv/0/abc123/1/1/NN/%/%/n"


# -- the core: scans -----------------------------------------------------------------------------


def _rmw_key(
    namespace: str = "", hash_: str = JAZZY_LASER_SCAN_HASH, domain: int = 0, topic: str = "scan"
) -> str:
    name = f"{namespace.strip('/')}/{topic}".strip("/")
    return f"{domain}/{name}/{dds_type_name(LASER_SCAN)}/{hash_}"


def _good_ranges(beams: int = 360) -> np.ndarray:
    return np.linspace(0.5, 3.0, beams, dtype=np.float32)


def test_core_turns_laser_scans_into_triscan_scans_with_its_own_seq() -> None:
    core = BridgeCore(BridgeConfig(namespace="/robot1"))
    attachment = encode_attachment(0, 1, GID)
    out = [
        core.handle_scan(
            _rmw_key("robot1", hash_), laser_scan_cdr(_good_ranges(), stamp_ns=STAMP_NS + i), attachment
        )
        for i, hash_ in enumerate((JAZZY_LASER_SCAN_HASH, TYPE_HASH_NOT_SUPPORTED, JAZZY_LASER_SCAN_HASH))
    ]
    assert all(o is not None and o.key == scan_key("robot1") and o.attachment is None for o in out)
    scans = [decode_message(o.payload, Scan) for o in out if o is not None]
    assert [s.seq for s in scans] == [0, 1, 2]
    assert [s.stamp_ns for s in scans] == [STAMP_NS, STAMP_NS + 1, STAMP_NS + 2]
    assert scans[0].robot_id == "robot1" and scans[0].frame_id == "laser"
    assert scans[0].ranges.tobytes() == _good_ranges().tobytes()
    assert core.counters.scans_published == 3 and not core.counters.rejected_scans


def test_core_root_namespace_needs_robot_and_fleet_mode_names_robots_by_namespace() -> None:
    with pytest.raises(ValueError):
        BridgeConfig(namespace="/")
    root = BridgeCore(BridgeConfig(style="ros2dds", robot="tb3"))
    out = root.handle_scan("scan", laser_scan_cdr(_good_ranges()))
    assert out is not None and out.key == scan_key("tb3")
    fleet = BridgeCore(BridgeConfig(namespace=None, domain=5))
    attachment = encode_attachment(0, 1, GID)
    for robot in ("alpha", "bravo", "alpha"):
        fleet.handle_scan(_rmw_key(robot, domain=5), laser_scan_cdr(_good_ranges()), attachment)
    assert fleet.robot_ids == ["alpha", "bravo"]
    assert fleet.scan_subscription_key == f"5/*/scan/{dds_type_name(LASER_SCAN)}/*"
    assert fleet.counters.scans_published == 3


def _bad_scans() -> list[tuple[str, str, bytes, bytes | None]]:
    """(expected reason, key, payload, attachment) for every way a ROS scan can be refused."""
    good = laser_scan_cdr(_good_ranges())
    att = encode_attachment(0, 1, GID)
    key = _rmw_key("robot1")
    huge_count = bytearray(laser_scan_cdr(_good_ranges(4)))
    huge_count[4 + 12 + 8 + 28 : 4 + 12 + 8 + 32] = (100_000).to_bytes(4, "little")  # "laser\0" pads to 8
    lying_count = bytearray(huge_count)
    lying_count[4 + 12 + 8 + 28 : 4 + 12 + 8 + 32] = (4000).to_bytes(4, "little")
    return [
        ("bad_key", "0/robot1/odom/x/y", good, att),
        ("bad_key", _rmw_key("robot1", domain=1), good, att),
        ("wrong_type", f"0/robot1/scan/sensor_msgs::msg::dds_::Imu_/{JAZZY_LASER_SCAN_HASH}", good, att),
        ("type_hash", _rmw_key("robot1", "RIHS01_" + "0" * 64), good, att),
        ("no_attachment", key, good, None),
        ("bad_attachment", key, good, att[:-2]),
        ("bad_robot_id", _rmw_key("r" * 70), good, att),  # a ROS name, too long for a robot id (fleet mode)
        ("not_cdr", key, b"\x01\x02", att),
        (
            "not_cdr",
            key,
            encode_message(
                Scan(
                    robot_id="x",
                    seq=0,
                    stamp_ns=0,
                    angle_min=0.0,
                    angle_increment=0.1,
                    range_min=0.0,
                    range_max=1.0,
                    ranges=np.ones(3, np.float32),
                )
            ),
            att,
        ),
        ("truncated", key, good[:40], att),
        ("truncated", key, good[:-8], att),
        ("truncated", key, bytes(lying_count), att),
        ("bad_cdr", key, good + bytes(8), att),
        ("too_many_beams", key, bytes(huge_count), att),
        ("no_beams", key, laser_scan_cdr(np.zeros(0)), att),
        ("bad_stamp", key, laser_scan_cdr(_good_ranges(), stamp_ns=-5), att),
        ("bad_frame_id", key, laser_scan_cdr(_good_ranges(), frame_id=""), att),
        ("bad_angles", key, laser_scan_cdr(_good_ranges(), angle_min=math.nan), att),
        ("bad_angles", key, laser_scan_cdr(_good_ranges(), angle_increment=0.0), att),
        ("bad_angles", key, laser_scan_cdr(_good_ranges(), angle_increment=math.inf), att),
        ("bad_angles", key, laser_scan_cdr(_good_ranges(), angle_increment=0.1), att),  # 36 rad of fov
        ("bad_range_limits", key, laser_scan_cdr(_good_ranges(), range_min=2.0, range_max=1.0), att),
        ("bad_range_limits", key, laser_scan_cdr(_good_ranges(), range_max=math.nan), att),
    ]


def test_core_counts_every_bad_scan_by_reason_and_never_raises() -> None:
    expected: dict[str, int] = {}
    for reason, key, payload, attachment in _bad_scans():
        core = BridgeCore(BridgeConfig(namespace=None if reason == "bad_robot_id" else "/robot1"))
        assert core.handle_scan(key, payload, attachment) is None, reason
        assert dict(core.counters.rejected_scans) == {reason: 1}, (reason, dict(core.counters.rejected_scans))
        expected[reason] = expected.get(reason, 0) + 1
    # ros2dds style carries no attachment and no type in the key: the same payload checks still apply.
    dds = BridgeCore(BridgeConfig(style="ros2dds", namespace="/robot1"))
    assert dds.handle_scan("robot1/scan", b"garbage!") is None and dds.counters.rejected_scans == {
        "not_cdr": 1
    }
    rng = np.random.default_rng(0)
    good = laser_scan_cdr(_good_ranges())
    for _ in range(300):  # random corruption of a real scan: dropped or accepted, never raised
        mutated = bytearray(good)
        for i in rng.integers(0, len(mutated), 4):
            mutated[i] = int(rng.integers(0, 256))
        dds.handle_scan("robot1/scan", bytes(mutated[: int(rng.integers(0, len(mutated) + 1))]))
    assert dds.counters.scans_received == 301


# -- the core: detections ------------------------------------------------------------------------


def _detections(robot_id: str, stamp_ns: int, count: int = 3) -> Detections:
    items = [one_detection((20 + 60 * i, 10, 40 + 60 * i, 30), 0.6 + 0.1 * i, i % 4) for i in range(count)]
    return Detections(
        robot_id=robot_id, seq=2, stamp_ns=stamp_ns, detections=items,
        timings=StageTimings(encode_ms=0.1, inference_ms=1.0, nms_ms=0.1), model_id="m",
        scan_stamp_ns=stamp_ns,
    )  # fmt: skip


def test_core_publishes_detection3darray_and_markers_with_attachments() -> None:
    core = BridgeCore(BridgeConfig(namespace="/robot1"), clock_ns=lambda: 99)
    att = encode_attachment(0, 1, GID)
    core.handle_scan(_rmw_key("robot1"), laser_scan_cdr(_good_ranges(), frame_id="base_scan"), att)
    message = _detections("robot1", STAMP_NS)
    first = core.handle_detections(detections_key("robot1"), encode_message(message))
    second = core.handle_detections(detections_key("robot1"), encode_message(message))
    types = ros_types()
    assert [o.key for o in first] == [
        f"0/robot1/triscan/detections/vision_msgs::msg::dds_::Detection3DArray_/{types.type_hash(DETECTION3D_ARRAY)}",
        f"0/robot1/triscan/markers/visualization_msgs::msg::dds_::MarkerArray_/{types.type_hash(MARKER_ARRAY)}",
    ]
    (a1, m1), (a2, m2) = ([decode_attachment(o.attachment) for o in out] for out in (first, second))
    assert (a1.sequence_number, a2.sequence_number, m1.sequence_number, m2.sequence_number) == (0, 1, 0, 1)
    assert a1.gid == a2.gid != m1.gid == m2.gid and a1.source_timestamp_ns == 99
    array = types.deserialize(first[0].payload, DETECTION3D_ARRAY)
    assert array.header.frame_id == "base_scan"
    assert array.header.stamp.sec * 1_000_000_000 + array.header.stamp.nanosec == STAMP_NS
    assert len(array.detections) == 3
    for got, want in zip(array.detections, message.detections, strict=True):
        assert got.results[0].hypothesis.class_id == want.class_name
        assert got.results[0].hypothesis.score == pytest.approx(want.score)
        assert (got.bbox.center.position.x, got.bbox.center.position.y) == pytest.approx((want.x_m, want.y_m))
        assert got.bbox.size.x == pytest.approx(want.range_max_m - want.range_min_m)
        arc = (
            math.radians((want.bearing_max_deg - want.bearing_min_deg) % 360)
            * (want.range_min_m + want.range_max_m)
            / 2
        )
        assert got.bbox.size.y == pytest.approx(arc)
    markers = types.deserialize(first[1].payload, MARKER_ARRAY).markers
    assert markers[0].action == DELETEALL
    assert [m.type for m in markers[1:]] == [CUBE, TEXT_VIEW_FACING] * 3
    assert markers[2].text.startswith(message.detections[0].class_name)
    assert {m.header.frame_id for m in markers} == {"base_scan"}


def _tracks(robot_id: str, frame: TrackFrame) -> Tracks:
    tracks = [
        _track(1_700_000_000_001, 1.0, 0.5, 0.0, 0.0, frame, "confirmed"),  # still furniture
        _track(1_700_000_000_002, 2.0, -1.0, 0.6, 0.8, frame, "coasting"),  # a walker, just missed
        _track(1_700_000_000_003, 0.5, 0.5, 0.0, 0.0, frame, "tentative"),  # maybe noise: not published
    ]
    return Tracks(robot_id=robot_id, seq=3, stamp_ns=1, scan_stamp_ns=STAMP_NS, frame=frame, tracks=tracks)


@pytest.mark.parametrize("frame", ["odom", "laser"])
def test_core_publishes_tracks_with_track_ids_and_velocity_arrows(frame: TrackFrame) -> None:
    core = BridgeCore(BridgeConfig(namespace="/robot1"), clock_ns=lambda: 99)
    att = encode_attachment(0, 1, GID)
    core.handle_scan(_rmw_key("robot1"), laser_scan_cdr(_good_ranges(), frame_id="base_scan"), att)
    core.handle_odometry(
        f"0/robot1/odom/{dds_type_name(ODOMETRY)}/{ros_types().type_hash(ODOMETRY)}",
        _odometry_cdr(1.0, 0.2, STAMP_NS),
        att,
    )
    message = _tracks("robot1", frame)
    out = core.handle_tracks(tracks_key("robot1"), encode_message(message))
    types = ros_types()
    assert [o.key for o in out] == [
        f"0/robot1/triscan/tracks/vision_msgs::msg::dds_::Detection3DArray_/{types.type_hash(DETECTION3D_ARRAY)}",
        f"0/robot1/triscan/track_markers/visualization_msgs::msg::dds_::MarkerArray_/{types.type_hash(MARKER_ARRAY)}",
    ]
    assert all(decode_attachment(o.attachment).source_timestamp_ns == 99 for o in out)
    # the tracks' frame: the odometry's frame (named by the robot's odometry), else the scan's
    frame_id = "odom" if frame == "odom" else "base_scan"
    published = message.tracks[:2]
    array = types.deserialize(out[0].payload, DETECTION3D_ARRAY)
    assert array.header.frame_id == frame_id
    assert array.header.stamp.sec * 1_000_000_000 + array.header.stamp.nanosec == STAMP_NS
    assert [d.id for d in array.detections] == [str(t.track_id) for t in published]
    for got, want in zip(array.detections, published, strict=True):
        where = (want.odom_x_m, want.odom_y_m) if frame == "odom" else (want.x_m, want.y_m)
        assert (got.bbox.center.position.x, got.bbox.center.position.y) == pytest.approx(where)
        assert got.results[0].hypothesis.class_id == want.class_name
    markers = types.deserialize(out[1].payload, MARKER_ARRAY).markers
    assert markers[0].action == DELETEALL and {m.header.frame_id for m in markers} == {frame_id}
    assert [m.type for m in markers[1:]] == [ARROW, TEXT_VIEW_FACING] * 2
    walker_arrow, walker_label = markers[3], markers[4]
    assert walker_label.text.startswith(f"#{published[1].track_id} ") and "1.0 m/s" in walker_label.text
    assert walker_arrow.scale.x == pytest.approx(1.0 * ARROW_HORIZON_S)  # |(0.6, 0.8)| m/s
    q = walker_arrow.pose.orientation
    assert 2 * math.atan2(q.z, q.w) == pytest.approx(math.atan2(0.8, 0.6))
    colour = walker_arrow.color
    assert (colour.r, colour.g, colour.b) == pytest.approx(
        [c / 255 for c in track_colour(published[1].track_id)]
    )
    assert markers[1].scale.x > 0  # still furniture still gets a (tiny) arrow RViz can draw
    # a second sample: own sequence numbers per publisher
    again = core.handle_tracks(tracks_key("robot1"), encode_message(message))
    assert [decode_attachment(o.attachment).sequence_number for o in again] == [1, 1]
    tokens = core.liveliness_tokens("z")
    assert any("%triscan%tracks/" in t for t in tokens) and any(
        "%triscan%track_markers/" in t for t in tokens
    )


def test_core_skips_tracks_of_unknown_robots_and_counts_bad_ones() -> None:
    core = BridgeCore(BridgeConfig(namespace="/robot1"))
    assert core.handle_tracks(tracks_key("robot1"), encode_message(_tracks("robot1", "laser"))) == []
    assert core.counters.tracks_skipped == 1  # no scan yet: no frame to draw in
    cases = [
        ("bad_key", "triscan/bad.id/tracks", encode_message(_tracks("robot1", "laser"))),
        ("robot_id_mismatch", tracks_key("robot1"), encode_message(_tracks("other", "laser"))),
        ("not_msgpack", tracks_key("robot1"), b"\xc1"),
        ("wrong_kind", tracks_key("robot1"), encode_message(_detections("robot1", 5))),
    ]
    for _, key, payload in cases:
        assert core.handle_tracks(key, payload) == []
    assert dict(core.counters.rejected_tracks) == {reason: 1 for reason, _, _ in cases}
    assert core.counters.tracks_received == 5 and not core.counters.rejected_detections


def test_core_skips_unknown_robots_and_counts_bad_detections() -> None:
    core = BridgeCore(BridgeConfig(namespace="/robot1"))
    assert core.handle_detections(detections_key("robot1"), encode_message(_detections("robot1", 5))) == []
    assert core.counters.detections_skipped == 1  # no scan yet: no frame to draw in
    assert core.handle_detections(detections_key("other"), encode_message(_detections("other", 5))) == []
    cases = [
        ("bad_key", "triscan/bad.id/detections", encode_message(_detections("robot1", 5))),
        ("robot_id_mismatch", detections_key("robot1"), encode_message(_detections("other", 5))),
        ("not_msgpack", detections_key("robot1"), b"\xc1"),
        ("wrong_kind", detections_key("robot1"), encode_message(Scan(robot_id="robot1", seq=0, stamp_ns=0,
         angle_min=0.0, angle_increment=0.1, range_min=0.0, range_max=1.0, ranges=np.ones(3, np.float32)))),
    ]  # fmt: skip
    for _, key, payload in cases:
        assert core.handle_detections(key, payload) == []
    assert dict(core.counters.rejected_detections) == {reason: 1 for reason, _, _ in cases}


def test_ros2dds_style_publishes_without_attachments_and_humble_without_hashes() -> None:
    dds = BridgeCore(BridgeConfig(style="ros2dds", namespace="/r2"))
    dds.handle_scan("r2/scan", laser_scan_cdr(_good_ranges()))
    out = dds.handle_detections(detections_key("r2"), encode_message(_detections("r2", 5)))
    assert [(o.key, o.attachment) for o in out] == [
        ("r2/triscan/detections", None),
        ("r2/triscan/markers", None),
    ]
    humble = BridgeCore(BridgeConfig(distro="humble", namespace="/r2"))
    humble.handle_scan(
        _rmw_key("r2", TYPE_HASH_NOT_SUPPORTED), laser_scan_cdr(_good_ranges()), encode_attachment(0, 0, GID)
    )
    out = humble.handle_detections(detections_key("r2"), encode_message(_detections("r2", 5)))
    assert all(o.key.endswith("/TypeHashNotSupported") for o in out)
    assert any("/TypeHashNotSupported/" in t for t in humble.liveliness_tokens("z"))


# -- any real sensor -----------------------------------------------------------------------------

SENSORS = {
    "hokuyo_512_180": (512, math.pi, 5.6),
    "sick_768_270": (768, math.radians(270.0), 8.0),
    "rplidar_1440_360": (1440, 2 * math.pi, 12.0),
}


@pytest.mark.parametrize("sensor", list(SENSORS))
def test_real_sensor_geometries_pass_the_bridge_and_light_the_right_columns(sensor: str) -> None:
    beams, fov, range_max = SENSORS[sensor]
    increment = fov / beams if fov >= 2 * math.pi else fov / (beams - 1)
    angle_min = -fov / 2
    rng = np.random.default_rng(beams)
    core = BridgeCore(BridgeConfig(style="ros2dds", robot="sensor"))
    stacker = ScanStacker("zero")
    tensor = None
    for i in range(3):
        ranges = rng.uniform(4.2, range_max - 0.1, beams).astype(np.float32)  # all beyond R_MAX = 4 m
        ranges[rng.integers(0, beams, 10)] = np.inf
        payload = laser_scan_cdr(ranges, angle_min=angle_min, angle_increment=increment, range_min=0.05,
                                 range_max=range_max, stamp_ns=STAMP_NS + i)  # fmt: skip
        out = core.handle_scan("scan", payload)
        assert out is not None, dict(core.counters.rejected_scans)
        scan = decode_message(out.payload, Scan)
        assert scan.ranges.shape == (beams,)
        tensor = stacker.push_scan(
            scan.ranges, scan.angle_min, scan.angle_increment, scan.range_min, scan.range_max
        )
    assert tensor is not None
    lit = np.flatnonzero(tensor[:, :ANGLE_COLUMNS, 2].any(axis=0))
    expected = np.unique(
        angle_columns(beam_bearings_rad(np.float32(angle_min), np.float32(increment), beams))
    )
    assert lit.tolist() == expected.tolist()
    # Beyond 4 m every return is on the last range row; nothing is dropped or wrapped.
    raster = encode_scan(scan.ranges, scan.angle_min, scan.angle_increment, scan.range_min, scan.range_max)
    assert raster[-1, expected].all() and not raster[:-1].any()
    if fov < 2 * math.pi:  # a partial field of view leaves the columns behind the sensor dark
        assert len(lit) < ANGLE_COLUMNS


# -- the core: odometry --------------------------------------------------------------------------


def _odometry_cdr(x: float, yaw: float, stamp_ns: int) -> bytes:
    """A Jazzy nav_msgs/Odometry serialised by rosbags (not by the code under test)."""
    types = ros_types("jazzy")
    t = types.store.types
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=x, y=-1.0, z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)),
    )
    zero = t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    message = t[ODOMETRY](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id="odom"
        ),
        child_frame_id="base_footprint",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=np.zeros(36)
        ),
    )
    return types.serialize(message, ODOMETRY)


@pytest.mark.parametrize("style", ["rmw_zenoh", "ros2dds"])
def test_core_pairs_each_scan_with_the_robots_odometry_in_both_key_styles(style: str) -> None:
    core = BridgeCore(BridgeConfig(style=style, namespace=None))  # type: ignore[arg-type]
    attachment = encode_attachment(0, 1, GID) if style == "rmw_zenoh" else None

    def odom_key(robot: str) -> str:
        if style == "ros2dds":
            return f"{robot}/odom"
        return f"0/{robot}/odom/{dds_type_name(ODOMETRY)}/{ros_types('jazzy').type_hash(ODOMETRY)}"

    def scan_key_of(robot: str) -> str:
        return _rmw_key(robot) if style == "rmw_zenoh" else f"{robot}/scan"

    assert core.odom_subscription_key == (
        "*/odom" if style == "ros2dds" else f"0/*/odom/{dds_type_name(ODOMETRY)}/*"
    )
    first = core.handle_scan(
        scan_key_of("alpha"), laser_scan_cdr(_good_ranges(), stamp_ns=STAMP_NS), attachment
    )
    assert first is not None and decode_message(first.payload, Scan).odom is None  # no pose yet: still a scan
    core.handle_odometry(odom_key("alpha"), _odometry_cdr(2.5, 0.4, STAMP_NS + 90_000_000), attachment)
    core.handle_odometry(odom_key("bravo"), _odometry_cdr(float("nan"), 0.0, STAMP_NS), attachment)
    out = core.handle_scan(
        scan_key_of("alpha"), laser_scan_cdr(_good_ranges(), stamp_ns=STAMP_NS + 100_000_000), attachment
    )
    assert out is not None
    scan = decode_message(out.payload, Scan)
    assert scan.odom is not None and scan.schema_version == 2
    assert (scan.odom.x_m, scan.odom.y_m, scan.odom.frame_id) == (2.5, -1.0, "odom")
    assert scan.odom.yaw_rad == pytest.approx(0.4) and scan.odom.stamp_ns == STAMP_NS + 90_000_000
    # Alpha's pose is 2 s old by now: the scan goes on without it.
    late = core.handle_scan(
        scan_key_of("alpha"), laser_scan_cdr(_good_ranges(), stamp_ns=STAMP_NS + 2_100_000_000), attachment
    )
    assert late is not None and decode_message(late.payload, Scan).odom is None
    core.handle_odometry(odom_key("alpha"), b"garbage!", attachment)
    assert core.counters.odometry_received == 3 and core.counters.odometry_attached == 1
    assert dict(core.counters.rejected_odometry) == {"not_finite": 1, "stale": 1, "not_cdr": 1}
    assert core.counters.scans_published == 3 and not core.counters.rejected_scans


def test_core_without_odometry_subscribes_to_none() -> None:
    core = BridgeCore(BridgeConfig(namespace="/robot1", odom_topic=None))
    assert core.odom_subscription_key is None
    core.handle_odometry("0/robot1/odom/x/y", b"", None)
    assert dict(core.counters.rejected_odometry) == {"bad_key": 1}
