"""Turn triscan wire messages into Rerun log calls, one robot at a time (no Zenoh here).

The visualizer is the only place where a person sees what the detector sees, so it shows each robot
twice: in the *metric* view (the scan as points in metres, detections at their ``x_m``/``y_m`` with the
arc they cover, and the simulator's true footprints) and in the *raster* view (the very 64×384×3
tensor the network read, with detection and label boxes in raster pixels). Both come from the same
message ``seq``, so scrubbing the ``seq`` timeline shows a frame exactly as the detector got it.

Tracks (the tracker's output) are drawn in the metric view too: each reported track a point labelled
``#<id> <class>`` and a trail of its last ``TRAIL_LENGTH`` positions, both in a colour fixed by the
track id (:func:`services.tracker.core.track_colour`), so one object keeps one colour however its
detections flicker. A trail is kept in the frame the tracks live in: in the odometry frame a still
chair's trail stays a dot while the robot drives, and each frame moves it into that scan's laser frame
with the pose the detections of the same ``seq`` carried (a tracks message follows its detections).
Without that pose a frame draws the tracks but no odometry-frame trails.

Keeping this core free of Zenoh means a test can feed it messages and read the ``.rrd`` back, and any
other transport (a bag replay, a notebook) can reuse it. Payloads come from the network: ``handle``
decodes them itself and turns every bad one into a counted, logged rejection; it never raises.

Frames: data are logged in the sensor frame, ROS REP-103 (x forward, y left), exactly as they travel.
Rerun's 2D views always draw x right and y down, which would show the robot's surroundings mirrored;
so a static display transform (x forward → up, y left → left) is logged on the metric entities. It
changes only how the view draws them, never the logged numbers.
"""

from __future__ import annotations

import logging
import math
import threading
from collections import Counter, OrderedDict, deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Final

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from common.encoding import R_MAX_M, scan_points_xy
from common.keys import parse_key
from common.messages import (
    MESSAGE_TYPES,
    Detection,
    Detections,
    GroundTruth,
    Message,
    MessageError,
    Odometry,
    Scan,
    StackedTensor,
    TrackFrame,
    Tracks,
    decode_message,
)
from common.model_spec import CLASS_COLOURS, CLASS_NAMES, UNKNOWN_CLASS_COLOUR, Rgb
from services.tracker.core import REPORTED_STATES, track_colour

log = logging.getLogger(__name__)

APPLICATION_ID: Final[str] = "triscan_visualizer"
STAMP_TIMELINE: Final[str] = "stamp"
SEQ_TIMELINE: Final[str] = "seq"
TIMING_NAMES: Final[tuple[str, ...]] = ("encode_ms", "inference_ms", "nms_ms")


SCAN_COLOR: Final[Rgb] = (230, 230, 230)
SENSOR_COLOR: Final[Rgb] = (255, 255, 255)
SCAN_RADIUS_M: Final[float] = 0.015
DETECTION_RADIUS_M: Final[float] = 0.05
LINE_RADIUS_M: Final[float] = 0.01
RASTER_LINE_RADIUS_PX: Final[float] = 0.5
ARC_STEP_DEG: Final[float] = 2.0
TRACK_RADIUS_M: Final[float] = 0.07
TRAIL_LENGTH: Final[int] = 20  # positions: two seconds of a 10 Hz LiDAR
POSES_KEPT: Final[int] = 32  # detections' poses by seq, waiting for the tracks of the same seq

DISPLAY_FROM_SENSOR: Final[tuple[tuple[float, ...], ...]] = (
    (0.0, -1.0, 0.0),
    (-1.0, 0.0, 0.0),
    (0.0, 0.0, 1.0),
)
"""Screen (right, down) from REP-103 (forward, left): forward is drawn up and left is drawn left."""

CLASS_ANNOTATIONS: Final[rr.AnnotationContext] = rr.AnnotationContext(
    [rr.AnnotationInfo(id=i, label=name, color=CLASS_COLOURS[i]) for i, name in enumerate(CLASS_NAMES)]
)
"""Class labels and colours, logged once (static, at the root): detections carry only class ids."""


def class_color(class_id: int) -> Rgb:
    return CLASS_COLOURS[class_id] if 0 <= class_id < len(CLASS_COLOURS) else UNKNOWN_CLASS_COLOUR


def _faded(color: Rgb, toward: int = 255, amount: float = 0.5) -> Rgb:
    r, g, b = (round(c + (toward - c) * amount) for c in color)
    return (r, g, b)


@dataclass(frozen=True)
class RobotPaths:
    """Entity paths of one robot; one place so the logger and the blueprint can never disagree."""

    robot_id: str

    @property
    def root(self) -> str:
        return f"robots/{self.robot_id}"

    @property
    def scan(self) -> str:
        return f"{self.root}/scan"

    @property
    def map(self) -> str:
        return f"{self.root}/map"

    @property
    def map_sensor(self) -> str:
        return f"{self.map}/sensor"

    @property
    def map_detections(self) -> str:
        return f"{self.map}/detections"

    @property
    def map_detection_extents(self) -> str:
        return f"{self.map}/detection_extents"

    @property
    def map_tracks(self) -> str:
        return f"{self.map}/tracks"

    @property
    def map_track_trails(self) -> str:
        return f"{self.map}/track_trails"

    @property
    def map_truth(self) -> str:
        return f"{self.map}/truth"

    @property
    def raster(self) -> str:
        return f"{self.root}/raster"

    @property
    def raster_detections(self) -> str:
        return f"{self.raster}/detections"

    @property
    def raster_truth(self) -> str:
        return f"{self.raster}/truth"

    @property
    def timings(self) -> str:
        return f"{self.root}/timings"

    def timing(self, name: str) -> str:
        return f"{self.timings}/{name}"


@dataclass(frozen=True)
class VisualizerStats:
    """A snapshot of what the visualizer has accepted (per topic) and rejected (per reason)."""

    accepted: dict[str, int] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)
    robots: tuple[str, ...] = ()


# --------------------------------------------------------------------------------------------------
# Geometry helpers (pure numpy)
# --------------------------------------------------------------------------------------------------


def world_to_sensor(points_xy: np.ndarray, sensor_pose: Sequence[float]) -> np.ndarray:
    """World-frame points ``[..., 2]`` into the frame of a sensor at world pose ``(x, y, yaw)``."""
    x, y, yaw = (float(v) for v in sensor_pose)
    c, s = math.cos(yaw), math.sin(yaw)
    d = np.asarray(points_xy, dtype=np.float64) - np.array([x, y])
    # p_sensor = R(yaw)^T (p_world - t)
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)


def closed_polygon(corners_xy: np.ndarray) -> np.ndarray:
    """The corners with the first repeated at the end, so a line strip draws a closed outline."""
    corners = np.asarray(corners_xy, dtype=np.float64)
    return np.concatenate([corners, corners[:1]], axis=0)


def sector_outline(detection: Detection, step_deg: float = ARC_STEP_DEG) -> np.ndarray:
    """Outline (sensor frame, metres) of the arc × range interval a detection covers.

    The arc runs counter-clockwise from ``bearing_min_deg`` to ``bearing_max_deg``: after wrapping to
    (−180, 180] a box straddling ±180° has min > max (see ``common.postprocess``).
    """
    start = detection.bearing_min_deg
    span = (detection.bearing_max_deg - start) % 360.0
    steps = max(1, math.ceil(span / step_deg))
    bearings = np.radians(start + np.linspace(0.0, span, steps + 1))
    inner = detection.range_min_m * np.stack([np.cos(bearings), np.sin(bearings)], axis=-1)
    outer = detection.range_max_m * np.stack([np.cos(bearings), np.sin(bearings)], axis=-1)
    return np.concatenate([inner, outer[::-1], inner[:1]], axis=0)


def _detection_label(detection: Detection) -> str:
    return f"{detection.class_name} {detection.score:.2f}"


@dataclass
class _RobotTracks:
    """One robot's track trails (in the tracks' frame) and the poses its detections carried."""

    frame: TrackFrame = "laser"
    trails: dict[int, deque[tuple[float, float]]] = field(default_factory=dict)
    poses: OrderedDict[int, Odometry] = field(default_factory=OrderedDict)  # by seq, the newest last

    def remember_pose(self, seq: int, pose: Odometry) -> None:
        self.poses[seq] = pose
        while len(self.poses) > POSES_KEPT:
            self.poses.popitem(last=False)

    def trails_in_laser_frame(self, message: Tracks) -> list[tuple[int, np.ndarray]]:
        """Record ``message``'s reported tracks; (track id, trail in its scan's laser frame) of each.

        Tracks that are gone lose their trail; a change of frame (odometry appearing or lost) starts
        every trail afresh, since old positions are in the other frame.
        """
        if message.frame != self.frame:
            self.frame, self.trails = message.frame, {}
        reported = [t for t in message.tracks if t.state in REPORTED_STATES]
        alive = {t.track_id for t in message.tracks}
        self.trails = {k: v for k, v in self.trails.items() if k in alive}
        for t in reported:
            point = (t.x_m, t.y_m) if t.odom_x_m is None or t.odom_y_m is None else (t.odom_x_m, t.odom_y_m)
            self.trails.setdefault(t.track_id, deque(maxlen=TRAIL_LENGTH)).append(point)
        pose = self.poses.get(message.seq)
        if message.frame == "odom" and pose is None:
            return []
        out = []
        for t in reported:
            trail = np.array(self.trails[t.track_id], dtype=np.float64)
            if pose is not None and message.frame == "odom":
                trail = world_to_sensor(trail, (pose.x_m, pose.y_m, pose.yaw_rad))
            out.append((t.track_id, trail))
        return out


# --------------------------------------------------------------------------------------------------
# Blueprint
# --------------------------------------------------------------------------------------------------


def robot_container(robot_id: str) -> rrb.Container:
    """One robot's layout: metric view on the left, raster above timings on the right."""
    paths = RobotPaths(robot_id)
    metric = rrb.Spatial2DView(
        name=f"{robot_id}: scan + detections (m, forward up)",
        origin=paths.root,
        contents=[paths.scan, f"{paths.map}/**"],
        visual_bounds=rrb.VisualBounds2D(x_range=[-R_MAX_M, R_MAX_M], y_range=[-R_MAX_M, R_MAX_M]),
    )
    raster = rrb.Spatial2DView(name=f"{robot_id}: network input (raster px)", origin=paths.raster)
    timings = rrb.TimeSeriesView(name=f"{robot_id}: stage timings (ms)", origin=paths.timings)
    return rrb.Horizontal(metric, rrb.Vertical(raster, timings, row_shares=[1, 1]), name=robot_id)


def blueprint(robot_ids: Iterable[str]) -> rrb.Blueprint:
    """The viewer layout for these robots: one tab per robot (a single robot fills the window)."""
    ids = sorted(set(robot_ids))
    if not ids:
        return rrb.Blueprint(rrb.Spatial2DView(name="waiting for robots", origin="robots"))
    containers = [robot_container(robot_id) for robot_id in ids]
    root = containers[0] if len(containers) == 1 else rrb.Tabs(*containers)
    return rrb.Blueprint(root, collapse_panels=False)


# --------------------------------------------------------------------------------------------------
# The visualizer
# --------------------------------------------------------------------------------------------------


class RerunVisualizer:
    """Logs triscan messages of any number of robots into one ``rr.RecordingStream``.

    Thread-safe: Zenoh calls ``handle`` from its own threads. Rerun's ``set_time`` is per thread, so
    each message sets both timelines right before its log calls on the calling thread; the small lock
    guards only this object's bookkeeping (robot set, counters).

    ``send_blueprints``: send a new blueprint whenever a robot appears, so the layout grows with the
    fleet; the initial ``robot_ids`` get theirs at construction.
    """

    def __init__(
        self,
        recording: rr.RecordingStream,
        robot_ids: Iterable[str] = (),
        *,
        send_blueprints: bool = True,
    ) -> None:
        self._rec = recording
        self._send_blueprints = send_blueprints
        self._lock = threading.Lock()
        self._robots: set[str] = set()
        self._accepted: Counter[str] = Counter()
        self._rejected: Counter[str] = Counter()
        self._tracks: dict[str, _RobotTracks] = {}
        initial = sorted(set(robot_ids))
        self._rec.log("/", CLASS_ANNOTATIONS, static=True)
        for robot_id in initial:
            self._add_robot(robot_id)
        if self._send_blueprints:
            self._rec.send_blueprint(blueprint(initial))

    # ---------------------------------------------------------------------------------- bookkeeping

    @property
    def robots(self) -> tuple[str, ...]:
        with self._lock:
            return tuple(sorted(self._robots))

    def stats(self) -> VisualizerStats:
        with self._lock:
            return VisualizerStats(
                accepted=dict(self._accepted),
                rejected=dict(self._rejected),
                robots=tuple(sorted(self._robots)),
            )

    def _reject(self, reason: str, detail: str) -> None:
        with self._lock:
            self._rejected[reason] += 1
            count = self._rejected[reason]
        # Log the first rejection of each reason and then every power of ten, so a flood of bad
        # samples cannot flood the log too.
        if math.log10(count).is_integer():
            log.warning("rejected payload (%s, %d so far): %s", reason, count, detail)
        else:
            log.debug("rejected payload (%s): %s", reason, detail)

    def _add_robot(self, robot_id: str) -> None:
        """Static per-robot entities: display transforms of the metric view and the sensor marker."""
        paths = RobotPaths(robot_id)
        display = rr.Transform3D(mat3x3=DISPLAY_FROM_SENSOR)
        self._rec.log(paths.scan, display, static=True)
        self._rec.log(paths.map, display, static=True)
        self._rec.log(
            paths.map_sensor,
            rr.Arrows2D(origins=[[0.0, 0.0]], vectors=[[0.3, 0.0]], colors=[SENSOR_COLOR], labels=["lidar"]),
            static=True,
        )
        self._robots.add(robot_id)

    def _ensure_robot(self, robot_id: str) -> None:
        with self._lock:
            if robot_id in self._robots:
                return
            self._add_robot(robot_id)
            robots = sorted(self._robots)
            # Sent under the lock so that two robots appearing at once cannot send their layouts in
            # the wrong order (the last one sent is the one shown).
            if self._send_blueprints:
                self._rec.send_blueprint(blueprint(robots))
        log.info("new robot %r: now showing %s", robot_id, ", ".join(robots))

    # ------------------------------------------------------------------------------------- entry

    def handle(self, key: str, payload: bytes | bytearray | memoryview) -> bool:
        """Decode and log one Zenoh sample; False (counted and logged) if it was rejected."""
        try:
            robot_id, topic = parse_key(key)
        except (ValueError, TypeError) as exc:
            self._reject("bad_key", str(exc))
            return False
        try:
            message = decode_message(payload, MESSAGE_TYPES[topic])
        except MessageError as exc:
            self._reject(exc.reason, f"{key}: {exc}")
            return False
        if message.robot_id != robot_id:
            self._reject("robot_id_mismatch", f"{key}: payload robot_id is {message.robot_id!r}")
            return False
        try:
            self.log_message(message)
        except Exception as exc:  # a message that validated but cannot be drawn must not kill the service
            self._reject("log_error", f"{key}: {type(exc).__name__}: {exc}")
            return False
        with self._lock:
            self._accepted[topic] += 1
        return True

    def log_message(self, message: Message) -> None:
        """Log an already-validated message (the typed entry point for non-Zenoh callers)."""
        self._ensure_robot(message.robot_id)
        self._set_time(message)
        if isinstance(message, Scan):
            self._log_scan(message)
        elif isinstance(message, StackedTensor):
            self._log_tensor(message)
        elif isinstance(message, Detections):
            self._log_detections(message)
        elif isinstance(message, GroundTruth):
            self._log_truth(message)
        elif isinstance(message, Tracks):
            self._log_tracks(message)
        else:
            raise TypeError(f"no visualisation for {type(message).__name__}")

    # ----------------------------------------------------------------------------------- loggers

    def _set_time(self, message: Message) -> None:
        self._rec.set_time(STAMP_TIMELINE, timestamp=np.datetime64(message.stamp_ns, "ns"))
        self._rec.set_time(SEQ_TIMELINE, sequence=message.seq)

    def _log_scan(self, scan: Scan) -> None:
        points = scan_points_xy(
            scan.ranges, scan.angle_min, scan.angle_increment, scan.range_min, scan.range_max
        )
        self._rec.log(
            RobotPaths(scan.robot_id).scan,
            rr.Points2D(points, radii=SCAN_RADIUS_M, colors=[SCAN_COLOR]),
        )

    def _log_tensor(self, tensor: StackedTensor) -> None:
        # Channel 0 = scan t−2, 1 = t−1, 2 = t: shown as R, G, B, as the paper draws it.
        self._rec.log(RobotPaths(tensor.robot_id).raster, rr.Image(tensor.tensor, color_model="RGB"))

    def _log_detections(self, message: Detections) -> None:
        paths = RobotPaths(message.robot_id)
        dets = message.detections
        class_ids = [d.class_id for d in dets]  # colours come from CLASS_ANNOTATIONS
        labels = [_detection_label(d) for d in dets]
        self._rec.log(
            paths.raster_detections,
            rr.Boxes2D(
                array=np.array([d.box_px for d in dets], dtype=np.float32).reshape(-1, 4),
                array_format=rr.Box2DFormat.XYXY,
                labels=labels,
                class_ids=class_ids,
                radii=RASTER_LINE_RADIUS_PX,
            ),
        )
        self._rec.log(
            paths.map_detections,
            rr.Points2D(
                np.array([(d.x_m, d.y_m) for d in dets], dtype=np.float64).reshape(-1, 2),
                labels=labels,
                class_ids=class_ids,
                radii=DETECTION_RADIUS_M,
            ),
        )
        self._rec.log(
            paths.map_detection_extents,
            rr.LineStrips2D([sector_outline(d) for d in dets], class_ids=class_ids, radii=LINE_RADIUS_M),
        )
        timings = message.timings
        for name in TIMING_NAMES:
            self._rec.log(paths.timing(name), rr.Scalars(float(getattr(timings, name))))
        if message.odom is not None and message.odom.finite:
            with self._lock:
                self._tracks.setdefault(message.robot_id, _RobotTracks()).remember_pose(
                    message.seq, message.odom
                )

    def _log_tracks(self, message: Tracks) -> None:
        paths = RobotPaths(message.robot_id)
        reported = [t for t in message.tracks if t.state in REPORTED_STATES]
        with self._lock:
            trails = self._tracks.setdefault(message.robot_id, _RobotTracks()).trails_in_laser_frame(message)
        self._rec.log(
            paths.map_tracks,
            rr.Points2D(
                np.array([(t.x_m, t.y_m) for t in reported], dtype=np.float64).reshape(-1, 2),
                colors=[track_colour(t.track_id) for t in reported],
                labels=[f"#{t.track_id} {t.class_name}" for t in reported],
                radii=TRACK_RADIUS_M,
            ),
        )
        self._rec.log(
            paths.map_track_trails,
            rr.LineStrips2D(
                [trail for _, trail in trails],
                colors=[track_colour(track_id) for track_id, _ in trails],
                radii=LINE_RADIUS_M,
            ),
        )

    def _log_truth(self, truth: GroundTruth) -> None:
        paths = RobotPaths(truth.robot_id)
        objects = truth.objects
        # Footprints are in the world frame; the scan is in the sensor frame at lidar_pose.
        outlines = [closed_polygon(world_to_sensor(obj.corners_xy, truth.lidar_pose)) for obj in objects]
        colors = [_faded(class_color(obj.class_id), amount=0.35 if obj.visible else 0.75) for obj in objects]
        labels = [f"{obj.class_name} (truth{'' if obj.visible else ', unseen'})" for obj in objects]
        self._rec.log(
            paths.map_truth,
            rr.LineStrips2D(outlines, colors=colors, labels=labels, radii=LINE_RADIUS_M),
        )
        visible = [obj for obj in objects if obj.box_px is not None]
        self._rec.log(
            paths.raster_truth,
            rr.Boxes2D(
                array=np.array([obj.box_px for obj in visible], dtype=np.float32).reshape(-1, 4),
                array_format=rr.Box2DFormat.XYXY,
                labels=[f"{obj.class_name} (truth)" for obj in visible],
                colors=[_faded(class_color(obj.class_id)) for obj in visible],
                class_ids=[obj.class_id for obj in visible],
                radii=RASTER_LINE_RADIUS_PX,
            ),
        )
