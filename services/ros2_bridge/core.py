"""The bridge's pure core: ROS 2 LaserScans in, triscan Scans out; triscan Detections in, ROS messages out.

No Zenoh here: the wiring (``__main__``) hands the core each sample's key, payload and attachment and
publishes what it returns, so every rule below is tested by calling the core directly.

* **Which robot.** A scan's ROS namespace names its robot: ``/robot1/scan`` is robot ``robot1`` (the
  namespace's last segment). A robot in the root namespace (``/scan``) needs ``robot`` in the config.
  ``namespace=None`` serves every one-segment namespace at once (a fleet on one domain).
* **Scans.** seq is the bridge's own counter per robot (ROS 2 headers carry none), stamp_ns the header
  stamp, frame_id kept. rmw_zenoh-style samples must carry rmw_zenoh's attachment and a LaserScan type
  hash of Jazzy (RIHS01) or Humble (``TypeHashNotSupported``); ros2dds-style samples carry neither.
* **Odometry.** ``nav_msgs/Odometry`` on ``<namespace>/odom`` (``odom_topic``; ``None``: no
  odometry) gives the robot's pose; each scan carries the newest one close enough to its stamp
  (:class:`services.ros2_bridge.odometry.OdometryPairing`). Refused poses are counted under
  ``rejected_odometry`` (the scan reasons for keys and types, ``not_cdr``, ``bad_cdr``, and the
  pairing's ``not_finite`` and ``stale``); the scan always goes on.
* **Detections.** Each triscan ``Detections`` of a bridged robot becomes a Detection3DArray on
  ``<namespace>/triscan/detections`` and a MarkerArray on ``<namespace>/triscan/markers``, stamped with
  the scan's header stamp and frame; in rmw_zenoh style each with an attachment of its own publisher
  (own sequence numbers, own GID). Detections of robots this bridge never saw are skipped.
* **Tracks.** Each triscan ``Tracks`` of a bridged robot (its confirmed and coasting tracks,
  :data:`services.tracker.core.REPORTED_STATES`) becomes a Detection3DArray on
  ``<namespace>/triscan/tracks`` whose ``id`` is the track id, and a MarkerArray on
  ``<namespace>/triscan/track_markers`` (an arrow along the velocity and ``#<id>`` per track). They
  are their own topic rather than ids written onto the detections: the tracker has already made the
  assignment (matching again here would be a second, possibly different, answer), a coasting track has
  no detection to carry its id, and tracks arrive on their own sample. They are stamped with the scan's
  stamp, in the odometry frame (the frame of the robot's last pose) when the tracks live there, else in
  the scan's frame.
* **Bad input** never raises: it is counted by reason (``rejected_scans``/``rejected_detections``) and
  dropped. Scan reasons: ``bad_key``, ``wrong_type``, ``type_hash``, ``no_attachment``,
  ``bad_attachment``, ``bad_robot_id``, ``too_many_robots`` and those of
  :mod:`services.ros2_bridge.laser_scan`; detection reasons: ``bad_key``, ``robot_id_mismatch`` and
  those of :class:`common.messages.MessageError`.
"""

from __future__ import annotations

import logging
import os
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final, TypeVar

from common.keys import parse_key, scan_key, validate_robot_id
from common.messages import Detections, Message, MessageError, Tracks, decode_message, encode_message
from services.ros2_bridge.laser_scan import ScanRejectedError, parse_laser_scan_cdr, to_triscan_scan
from services.ros2_bridge.odometry import ODOM_FRAME, ODOMETRY, OdometryPairing, odometry_of_message
from services.ros2_bridge.rmw_zenoh import (
    GID_SIZE,
    PUBLISHER,
    SUBSCRIPTION,
    AttachmentError,
    Style,
    check_style,
    check_topic,
    data_key,
    decode_attachment,
    encode_attachment,
    endpoint_token,
    node_token,
    normalize_namespace,
    parse_data_key,
    qualified_topic,
    subscription_key,
)
from services.ros2_bridge.ros_messages import Boxes, DetectionMessages
from services.ros2_bridge.ros_types import (
    DEFAULT_DISTRO,
    DETECTION3D_ARRAY,
    LASER_SCAN,
    MARKER_ARRAY,
    TYPE_HASH_NOT_SUPPORTED,
    CdrError,
    Distro,
    check_distro,
    dds_type_name,
    ros_types,
)
from services.tracker.core import REPORTED_STATES

log = logging.getLogger(__name__)

M = TypeVar("M", bound=Message)

DETECTIONS_TOPIC: Final[str] = "triscan/detections"
MARKERS_TOPIC: Final[str] = "triscan/markers"
TRACKS_TOPIC: Final[str] = "triscan/tracks"
TRACK_MARKERS_TOPIC: Final[str] = "triscan/track_markers"
DEFAULT_SCAN_TOPIC: Final[str] = "scan"
DEFAULT_ODOM_TOPIC: Final[str] = "odom"
DEFAULT_NODE_NAME: Final[str] = "triscan_bridge"
DEFAULT_MAX_ROBOTS: Final[int] = 1024
LASER_SCAN_HASHES: Final[frozenset[str]] = frozenset(
    {ros_types("jazzy").type_hash(LASER_SCAN), TYPE_HASH_NOT_SUPPORTED}
)
"""LaserScan's layout is the same on Humble and Jazzy, so a scan from either distro is accepted."""
ODOMETRY_HASHES: Final[frozenset[str]] = frozenset(
    {ros_types("jazzy").type_hash(ODOMETRY), TYPE_HASH_NOT_SUPPORTED}
)


@dataclass(frozen=True)
class BridgeConfig:
    """What the bridge serves; ``namespace=None`` means every one-segment namespace (a fleet)."""

    style: Style = "rmw_zenoh"
    domain: int = 0
    scan_topic: str = DEFAULT_SCAN_TOPIC
    odom_topic: str | None = DEFAULT_ODOM_TOPIC
    namespace: str | None = "/"
    robot: str | None = None
    distro: Distro = DEFAULT_DISTRO
    node_name: str = DEFAULT_NODE_NAME

    def __post_init__(self) -> None:
        check_style(self.style)
        check_distro(self.distro)
        check_topic(self.scan_topic)
        if self.odom_topic is not None:
            check_topic(self.odom_topic)
        if not 0 <= self.domain <= 232:  # ROS_DOMAIN_ID's documented range
            raise ValueError(f"domain must be in [0, 232], got {self.domain}")
        if self.namespace is None:
            if self.robot is not None:
                raise ValueError("robot names one robot; it cannot be combined with serving every namespace")
            return
        namespace = normalize_namespace(self.namespace)
        if self.robot is None and namespace == "/":
            raise ValueError("a robot in the root namespace needs a robot id (--robot)")
        validate_robot_id(self.robot_of(namespace))

    def robot_of(self, namespace: str) -> str:
        """The triscan robot id of the robot in ``namespace`` (ValueError if it is not a usable id)."""
        if self.robot is not None:
            return self.robot
        return validate_robot_id(namespace.rstrip("/").rsplit("/", 1)[-1])


@dataclass
class BridgeCounters:
    """What the bridge did with every sample; published as its stats."""

    scans_received: int = 0
    scans_published: int = 0
    detections_received: int = 0
    detections_skipped: int = 0  # of robots this bridge does not serve
    tracks_received: int = 0
    tracks_skipped: int = 0  # of robots this bridge does not serve
    ros_published: int = 0
    robots: int = 0
    odometry_received: int = 0
    odometry_attached: int = 0
    rejected_scans: Counter[str] = field(default_factory=Counter)
    rejected_detections: Counter[str] = field(default_factory=Counter)
    rejected_odometry: Counter[str] = field(default_factory=Counter)
    rejected_tracks: Counter[str] = field(default_factory=Counter)

    def to_dict(self) -> dict[str, object]:
        return {
            "scans_received": self.scans_received,
            "scans_published": self.scans_published,
            "detections_received": self.detections_received,
            "detections_skipped": self.detections_skipped,
            "tracks_received": self.tracks_received,
            "tracks_skipped": self.tracks_skipped,
            "ros_published": self.ros_published,
            "robots": self.robots,
            "odometry_received": self.odometry_received,
            "odometry_attached": self.odometry_attached,
            "rejected_scans": dict(self.rejected_scans),
            "rejected_detections": dict(self.rejected_detections),
            "rejected_odometry": dict(self.rejected_odometry),
            "rejected_tracks": dict(self.rejected_tracks),
        }


@dataclass(frozen=True)
class Outgoing:
    """One sample to publish: Zenoh key, payload and (rmw_zenoh style) attachment."""

    key: str
    payload: bytes
    attachment: bytes | None = None


@dataclass
class _RosPublisher:
    """One ROS publisher of the bridge: its key, its graph identity and its own sequence numbers."""

    fq_topic: str
    typename: str
    key: str
    entity_id: int
    gid: bytes
    sequence_number: int = 0


@dataclass
class _Robot:
    robot_id: str
    namespace: str
    node_id: int
    subscription_entity_id: int
    detections: _RosPublisher
    markers: _RosPublisher
    tracks: _RosPublisher
    track_markers: _RosPublisher
    odometry: OdometryPairing  # refusals counted in the bridge's rejected_odometry
    frame_id: str | None = None  # of the latest scan: the frame the detections are drawn in
    next_seq: int = 0


class BridgeCore:
    """See the module docstring. Not thread-safe: the wiring serialises calls."""

    def __init__(
        self,
        config: BridgeConfig,
        *,
        max_robots: int = DEFAULT_MAX_ROBOTS,
        clock_ns: Callable[[], int] = time.time_ns,
        new_gid: Callable[[], bytes] = lambda: os.urandom(GID_SIZE),
    ) -> None:
        self.config = config
        self.max_robots = max_robots
        self.clock_ns = clock_ns
        self.new_gid = new_gid
        self.types = ros_types(config.distro)
        self.messages = DetectionMessages(self.types)
        self.counters = BridgeCounters()
        self._robots: dict[str, _Robot] = {}  # by robot id
        self._by_namespace: dict[str, _Robot] = {}
        self._entities = 0
        self._scan_dds_type = dds_type_name(LASER_SCAN)
        if config.namespace is not None:  # one robot, known from the start: its topics exist at once
            self._robot_for(normalize_namespace(config.namespace))

    @property
    def scan_subscription_key(self) -> str:
        c = self.config
        namespace = None if c.namespace is None else normalize_namespace(c.namespace)
        return subscription_key(c.style, c.domain, namespace, c.scan_topic, self._scan_dds_type)

    @property
    def odom_subscription_key(self) -> str | None:
        """Where the robots' odometry arrives (None: the bridge pairs no odometry)."""
        c = self.config
        if c.odom_topic is None:
            return None
        namespace = None if c.namespace is None else normalize_namespace(c.namespace)
        return subscription_key(c.style, c.domain, namespace, c.odom_topic, dds_type_name(ODOMETRY))

    @property
    def robot_ids(self) -> list[str]:
        return list(self._robots)

    def _next_entity(self) -> int:
        self._entities += 1
        return self._entities

    def _publisher(self, namespace: str, topic: str, typename: str) -> _RosPublisher:
        c = self.config
        fq_topic = qualified_topic(namespace, topic)
        key = data_key(c.style, c.domain, fq_topic, dds_type_name(typename), self.types.type_hash(typename))
        return _RosPublisher(fq_topic, typename, key, self._next_entity(), self.new_gid())

    def _robot_for(self, namespace: str) -> _Robot:
        robot = self._by_namespace.get(namespace)
        if robot is not None:
            return robot
        robot_id = self.config.robot_of(namespace)
        if robot_id in self._robots:
            raise ValueError(f"namespace {namespace} names robot {robot_id!r}, already bridged elsewhere")
        if len(self._robots) >= self.max_robots:
            raise OverflowError(f"already bridging {self.max_robots} robots")
        robot = _Robot(
            robot_id=robot_id,
            namespace=namespace,
            node_id=self._next_entity(),
            subscription_entity_id=self._next_entity(),
            detections=self._publisher(namespace, DETECTIONS_TOPIC, DETECTION3D_ARRAY),
            markers=self._publisher(namespace, MARKERS_TOPIC, MARKER_ARRAY),
            tracks=self._publisher(namespace, TRACKS_TOPIC, DETECTION3D_ARRAY),
            track_markers=self._publisher(namespace, TRACK_MARKERS_TOPIC, MARKER_ARRAY),
            odometry=OdometryPairing(refused=self.counters.rejected_odometry),
        )
        self._robots[robot_id] = self._by_namespace[namespace] = robot
        self.counters.robots = len(self._robots)
        log.info("bridging ROS namespace %s as robot %s", namespace, robot_id)
        return robot

    # -- ROS → triscan ---------------------------------------------------------------------------

    def _reject_scan(self, reason: str, detail: str) -> None:
        self.counters.rejected_scans[reason] += 1
        log.debug("ROS scan rejected (%s): %s", reason, detail)

    def handle_scan(self, key: str, payload: bytes, attachment: bytes | None = None) -> Outgoing | None:
        """One ROS sample on the scan subscription → the triscan Scan to publish, or None (counted)."""
        self.counters.scans_received += 1
        c = self.config
        try:
            parsed = parse_data_key(c.style, c.domain, key, c.scan_topic)
        except ValueError as exc:
            self._reject_scan("bad_key", str(exc))
            return None
        if c.style == "rmw_zenoh":
            if parsed.dds_type != self._scan_dds_type:
                self._reject_scan("wrong_type", f"{key}: type {parsed.dds_type}, not {self._scan_dds_type}")
                return None
            if parsed.type_hash not in LASER_SCAN_HASHES:
                self._reject_scan("type_hash", f"{key}: hash {parsed.type_hash} is not LaserScan's")
                return None
            try:
                decode_attachment(attachment)
            except AttachmentError as exc:
                self._reject_scan("no_attachment" if attachment is None else "bad_attachment", str(exc))
                return None
        try:
            robot = self._robot_for(parsed.namespace)
        except ValueError as exc:
            self._reject_scan("bad_robot_id", str(exc))
            return None
        except OverflowError as exc:
            self._reject_scan("too_many_robots", str(exc))
            return None
        try:
            scan = to_triscan_scan(parse_laser_scan_cdr(payload), robot.robot_id, robot.next_seq)
        except ScanRejectedError as exc:
            self._reject_scan(exc.reason, f"{key}: {exc}")
            return None
        robot.next_seq += 1
        robot.frame_id = scan.frame_id
        attached = robot.odometry.attached
        scan = robot.odometry.attach(scan)
        self.counters.odometry_attached += robot.odometry.attached - attached
        self.counters.scans_published += 1
        return Outgoing(scan_key(robot.robot_id), encode_message(scan))

    def _reject_odometry(self, reason: str, detail: str) -> None:
        self.counters.rejected_odometry[reason] += 1
        log.debug("ROS odometry rejected (%s): %s", reason, detail)

    def handle_odometry(self, key: str, payload: bytes, attachment: bytes | None = None) -> None:
        """One ``nav_msgs/Odometry`` sample: the robot's newest pose, for its next scans (counted)."""
        self.counters.odometry_received += 1
        c = self.config
        if c.odom_topic is None:
            self._reject_odometry("bad_key", f"{key}: this bridge pairs no odometry")
            return
        try:
            parsed = parse_data_key(c.style, c.domain, key, c.odom_topic)
        except ValueError as exc:
            self._reject_odometry("bad_key", str(exc))
            return
        if c.style == "rmw_zenoh":
            if parsed.dds_type != dds_type_name(ODOMETRY):
                self._reject_odometry("wrong_type", f"{key}: type {parsed.dds_type}")
                return
            if parsed.type_hash not in ODOMETRY_HASHES:
                self._reject_odometry("type_hash", f"{key}: hash {parsed.type_hash} is not Odometry's")
                return
            try:
                decode_attachment(attachment)
            except AttachmentError as exc:
                self._reject_odometry("no_attachment" if attachment is None else "bad_attachment", str(exc))
                return
        try:
            robot = self._robot_for(parsed.namespace)
        except ValueError as exc:
            self._reject_odometry("bad_robot_id", str(exc))
            return
        except OverflowError as exc:
            self._reject_odometry("too_many_robots", str(exc))
            return
        try:
            pose = odometry_of_message(self.types.deserialize(payload, ODOMETRY))
        except CdrError as exc:
            self._reject_odometry(exc.reason, f"{key}: {exc}")
            return
        robot.odometry.update(pose)

    # -- triscan → ROS ---------------------------------------------------------------------------

    def _stamped(self, publisher: _RosPublisher, payload: bytes) -> Outgoing:
        attachment = None
        if self.config.style == "rmw_zenoh":
            attachment = encode_attachment(publisher.sequence_number, self.clock_ns(), publisher.gid)
        publisher.sequence_number += 1
        return Outgoing(publisher.key, payload, attachment)

    def _decoded(self, key: str, payload: bytes, kind: type[M], rejected: Counter[str]) -> M | None:
        """The triscan message of ``kind`` in a sample, or None (counted in ``rejected`` by reason)."""
        try:
            key_robot, _ = parse_key(key)
        except ValueError as exc:
            reason, detail = "bad_key", str(exc)
        else:
            try:
                message = decode_message(payload, kind)
            except MessageError as exc:
                reason, detail = exc.reason, str(exc)
            else:
                if message.robot_id == key_robot:
                    return message
                reason, detail = "robot_id_mismatch", f"key says {key_robot!r}, payload {message.robot_id!r}"
        rejected[reason] += 1
        log.debug("triscan %s rejected (%s): %s", kind.KIND, reason, detail)
        return None

    def handle_detections(self, key: str, payload: bytes) -> list[Outgoing]:
        """One triscan Detections sample → its Detection3DArray and MarkerArray samples ([] if none)."""
        self.counters.detections_received += 1
        message = self._decoded(key, payload, Detections, self.counters.rejected_detections)
        if message is None:
            return []
        robot = self._robots.get(message.robot_id)
        if robot is None or robot.frame_id is None:
            self.counters.detections_skipped += 1
            return []
        stamp, detections = message.scan_stamp_ns, message.detections
        boxes = Boxes.of(detections)  # once for both messages
        out = [
            self._stamped(
                robot.detections, self.messages.detection_array(detections, stamp, robot.frame_id, boxes)
            ),
            self._stamped(
                robot.markers, self.messages.marker_array(detections, stamp, robot.frame_id, boxes)
            ),
        ]
        self.counters.ros_published += len(out)
        return out

    def handle_tracks(self, key: str, payload: bytes) -> list[Outgoing]:
        """One triscan Tracks sample → its Detection3DArray (id = track id) and MarkerArray ([] if none)."""
        self.counters.tracks_received += 1
        message = self._decoded(key, payload, Tracks, self.counters.rejected_tracks)
        if message is None:
            return []
        robot = self._robots.get(message.robot_id)
        if robot is None or robot.frame_id is None:
            self.counters.tracks_skipped += 1
            return []
        if message.frame == "odom":
            latest = robot.odometry.latest
            frame_id = ODOM_FRAME if latest is None else latest.frame_id
        else:
            frame_id = robot.frame_id
        tracks = [t for t in message.tracks if t.state in REPORTED_STATES]
        stamp, frame = message.scan_stamp_ns, message.frame
        out = [
            self._stamped(robot.tracks, self.messages.track_array(tracks, frame, stamp, frame_id)),
            self._stamped(
                robot.track_markers, self.messages.track_marker_array(tracks, frame, stamp, frame_id)
            ),
        ]
        self.counters.ros_published += len(out)
        return out

    # -- the ROS graph ---------------------------------------------------------------------------

    def liveliness_tokens(self, zid: str) -> list[str]:
        """rmw_zenoh graph tokens of every bridged robot: its node, scan subscription and four publishers.

        Declared by the wiring (rmw_zenoh style only), they make ``ros2 topic list`` and
        ``ros2 node list`` show the bridge like any ROS 2 node.
        """
        c = self.config
        tokens = []
        for robot in self._robots.values():
            ns = robot.namespace
            tokens.append(node_token(c.domain, zid, robot.node_id, ns, c.node_name))
            tokens.append(
                endpoint_token(
                    SUBSCRIPTION, c.domain, zid, robot.node_id, robot.subscription_entity_id, ns, c.node_name,
                    qualified_topic(ns, c.scan_topic), self._scan_dds_type, self.types.type_hash(LASER_SCAN),
                )
            )  # fmt: skip
            for publisher in (robot.detections, robot.markers, robot.tracks, robot.track_markers):
                tokens.append(
                    endpoint_token(
                        PUBLISHER, c.domain, zid, robot.node_id, publisher.entity_id, ns, c.node_name,
                        publisher.fq_topic, dds_type_name(publisher.typename),
                        self.types.type_hash(publisher.typename),
                    )
                )  # fmt: skip
        return tokens
