"""triscan ``Detections`` → ``vision_msgs/Detection3DArray`` and ``visualization_msgs/MarkerArray``.

Detection3DArray is what ROS perception consumers (trackers, costmap layers) read; MarkerArray is
what RViz draws with no plugin. Both are stamped with the scan's header stamp and frame, so RViz
places them with the scan they came from.

Geometry, per object, in the laser frame (REP-103: x forward, y left, z up):

* centre: the detection's ``x_m``/``y_m`` (centre bearing, middle range), ``z = 0`` (the scan plane);
* orientation: yaw = the centre bearing, so the box's x axis points away from the sensor;
* size: x = range extent (``range_max_m − range_min_m``), y = arc extent (the box's angular width,
  read counter-clockwise from ``bearing_min_deg`` to ``bearing_max_deg``, times the middle range),
  z = ``SLAB_HEIGHT_M``: a 2D LiDAR measures no height, so boxes are drawn as a thin slab on the scan
  plane rather than claiming a height nobody measured.

Two encoders produce the same bytes: :class:`DetectionMessages`, the one the bridge runs, writes the
CDR directly (rosbags' generic path builds ~30 Python objects per detected object and took ~0.75 ms
for five objects, over the 0.3 ms budget); :class:`ReferenceDetectionMessages` builds rosbags message
objects and lets rosbags serialise them. The tests hold the two equal byte for byte, on Jazzy's and
Humble's definitions, so the fast path cannot drift from the definitions. The fast path's cost must not
grow with Python work per object (a first version, one ``struct`` call per field, took 0.53 ms for a
20-object frame): the geometry of a frame is computed once with numpy (:class:`Boxes`, which both
encoders read) and laid out as rows of doubles in one pass, and only precomputed runs are appended
per object.

Markers: a ``DELETEALL`` first (stale boxes of the previous frame vanish even when fewer objects are
seen), then per object a translucent ``CUBE`` (the box above, in the class colour) and a
``TEXT_VIEW_FACING`` label ``"<class> <score>"`` above it.

Tracks (:class:`~common.messages.Tracks`, the tracker's output) become a Detection3DArray of their own
with ``id`` = the track id, and markers: per track an ``ARROW`` from its position along its velocity
(its length the distance covered in ``ARROW_HORIZON_S``) and a label ``"#<id> <class> <speed>"``, both
in the track's stable colour (:func:`services.tracker.core.track_colour`). They are drawn in the frame
the tracks live in: the odometry frame (``odom_x_m``/``odom_y_m``, where the velocity is too) when the
scans carried odometry, else the laser frame, so no velocity needs rotating. A track has a position,
not an extent: its box is ``MIN_EXTENT_M`` wide (the detection at the same place has the extent), and
Detection3D has no velocity field, so the velocity rides only on the markers (and the tracks message).
"""

from __future__ import annotations

import functools
import math
import struct
from dataclasses import dataclass
from typing import Any, Final, NamedTuple

import numpy as np

from common.messages import Detection, Track, TrackFrame
from common.model_spec import CLASS_COLOURS, UNKNOWN_CLASS_COLOUR
from services.ros2_bridge.ros_types import DETECTION3D_ARRAY, MARKER_ARRAY, RosTypes
from services.tracker.core import track_colour

SLAB_HEIGHT_M: Final[float] = 0.2
MIN_EXTENT_M: Final[float] = 0.01  # a zero-size box is invisible and RViz warns about it
LABEL_HEIGHT_M: Final[float] = 0.12  # text size of the labels
LABEL_LIFT_M: Final[float] = 0.25  # labels float this far above the scan plane
CUBE_ALPHA: Final[float] = 0.5
MARKER_NS: Final[str] = "triscan"
TRACK_MARKER_NS: Final[str] = "triscan_tracks"
ARROW_HORIZON_S: Final[float] = 1.0  # a track's arrow ends where it will be in this long at its velocity
ARROW_WIDTH_M: Final[float] = 0.05
_NS_PER_S: Final[int] = 1_000_000_000
_COVARIANCE: Final[np.ndarray] = np.zeros(36, dtype=np.float64)

# Marker constants (visualization_msgs/msg/Marker), checked against the typestore in the tests.
ARROW: Final[int] = 0
CUBE: Final[int] = 1
TEXT_VIEW_FACING: Final[int] = 9
ADD: Final[int] = 0
DELETEALL: Final[int] = 3

MARKER_FIELDS: Final[tuple[str, ...]] = (
    "header", "ns", "id", "type", "action", "pose", "scale", "color", "lifetime", "frame_locked",
    "points", "colors", "texture_resource", "texture", "uv_coordinates", "text", "mesh_resource",
    "mesh_file", "mesh_use_embedded_materials",
)  # fmt: skip
"""The Marker layout the hand-written encoder writes (Humble and Jazzy alike)."""


@dataclass(frozen=True)
class Boxes:
    """The detections' boxes in the laser frame, one entry per object (see the module docstring).

    Computed once per frame for all objects with numpy; both encoders read them, so the two agree on
    every bit of the geometry and the tests compare only how it is laid out.
    """

    x: np.ndarray
    y: np.ndarray
    qz: np.ndarray  # the yaw quaternion (0, 0, qz, qw)
    qw: np.ndarray
    length: np.ndarray  # along the bearing (range extent)
    width: np.ndarray  # across it (arc extent)

    @classmethod
    def of(cls, detections: list[Detection]) -> Boxes:
        f = np.array(
            [
                (
                    d.x_m,
                    d.y_m,
                    d.bearing_deg,
                    d.bearing_min_deg,
                    d.bearing_max_deg,
                    d.range_min_m,
                    d.range_max_m,
                )
                for d in detections
            ],
            dtype=np.float64,
        ).reshape(-1, 7)
        half_yaw = np.radians(f[:, 2]) / 2.0
        arc_rad = np.radians(np.mod(f[:, 4] - f[:, 3], 360.0))
        middle_range = (f[:, 5] + f[:, 6]) / 2.0
        return cls(
            x=f[:, 0],
            y=f[:, 1],
            qz=np.sin(half_yaw),
            qw=np.cos(half_yaw),
            length=np.maximum(f[:, 6] - f[:, 5], MIN_EXTENT_M),
            width=np.maximum(arc_rad * middle_range, MIN_EXTENT_M),
        )

    @classmethod
    def of_tracks(cls, tracks: list[Track], frame: TrackFrame) -> Boxes:
        """Tracks as extent-less boxes (see the module docstring) in the frame they live in."""
        xy = np.array([track_position(t, frame) for t in tracks], dtype=np.float64).reshape(-1, 2)
        count = len(tracks)
        extent = np.full(count, MIN_EXTENT_M)
        return cls(x=xy[:, 0], y=xy[:, 1], qz=np.zeros(count), qw=np.ones(count), length=extent, width=extent)

    def pose_columns(self, z: float) -> list[np.ndarray | float]:
        """geometry_msgs/Pose as 7 columns: position x, y, z, orientation x, y, z, w."""
        return [self.x, self.y, z, 0.0, 0.0, self.qz, self.qw]


def _rgba(class_id: int, alpha: float) -> tuple[float, float, float, float]:
    colour = CLASS_COLOURS[class_id] if class_id < len(CLASS_COLOURS) else UNKNOWN_CLASS_COLOUR
    r, g, b = (c / 255.0 for c in colour)
    return (r, g, b, alpha)


def label_text(detection: Detection) -> str:
    return f"{detection.class_name} {detection.score:.2f}"


def track_position(track: Track, frame: TrackFrame) -> tuple[float, float]:
    """Where a track is in the frame its tracks message lives in (its velocity's frame too)."""
    if frame == "odom" and track.odom_x_m is not None and track.odom_y_m is not None:
        return track.odom_x_m, track.odom_y_m
    return track.x_m, track.y_m


def track_label(track: Track) -> str:
    return f"#{track.track_id} {track.class_name} {math.hypot(track.vx_mps, track.vy_mps):.1f} m/s"


class MarkerSpec(NamedTuple):
    """What one marker shows, independent of how it is encoded."""

    marker_id: int
    kind: int
    action: int
    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]
    scale: tuple[float, float, float]
    rgba: tuple[float, float, float, float]
    text: str = ""


DELETE_ALL_MARKER: Final[MarkerSpec] = MarkerSpec(
    0, CUBE, DELETEALL, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0, 0.0)
)
"""The first marker of every frame: clears the previous frame's boxes."""


def marker_specs(detections: list[Detection]) -> list[MarkerSpec]:
    """``DELETEALL``, then a cube and a label per object (see the module docstring)."""
    boxes = Boxes.of(detections)
    specs = [DELETE_ALL_MARKER]
    for i, detection in enumerate(detections):
        x, y = float(boxes.x[i]), float(boxes.y[i])
        size = (float(boxes.length[i]), float(boxes.width[i]), SLAB_HEIGHT_M)
        orientation = (0.0, 0.0, float(boxes.qz[i]), float(boxes.qw[i]))
        specs.append(
            MarkerSpec(
                2 * i, CUBE, ADD, (x, y, 0.0), orientation,
                size, _rgba(detection.class_id, CUBE_ALPHA),
            )
        )  # fmt: skip
        specs.append(
            MarkerSpec(
                2 * i + 1, TEXT_VIEW_FACING, ADD, (x, y, LABEL_LIFT_M), orientation,
                (0.0, 0.0, LABEL_HEIGHT_M), _rgba(detection.class_id, 1.0), label_text(detection),
            )
        )  # fmt: skip
    return specs


def track_marker_specs(tracks: list[Track], frame: TrackFrame) -> list[MarkerSpec]:
    """``DELETEALL``, then a velocity arrow and a label per track (see the module docstring)."""
    specs = [DELETE_ALL_MARKER]
    for i, track in enumerate(tracks):
        x, y = track_position(track, frame)
        speed, heading = math.hypot(track.vx_mps, track.vy_mps), math.atan2(track.vy_mps, track.vx_mps)
        r, g, b = track_colour(track.track_id)
        rgba = (r / 255.0, g / 255.0, b / 255.0, 1.0)
        specs.append(
            MarkerSpec(
                2 * i, ARROW, ADD, (x, y, 0.0), (0.0, 0.0, math.sin(heading / 2), math.cos(heading / 2)),
                (max(speed * ARROW_HORIZON_S, MIN_EXTENT_M), ARROW_WIDTH_M, ARROW_WIDTH_M), rgba,
            )
        )  # fmt: skip
        specs.append(
            MarkerSpec(
                2 * i + 1, TEXT_VIEW_FACING, ADD, (x, y, LABEL_LIFT_M), (0.0, 0.0, 0.0, 1.0),
                (0.0, 0.0, LABEL_HEIGHT_M), rgba, track_label(track),
            )
        )  # fmt: skip
    return specs


def _stamp(stamp_ns: int) -> tuple[int, int]:
    return stamp_ns // _NS_PER_S, stamp_ns % _NS_PER_S


_U32 = struct.Struct("<I")
_STAMP = struct.Struct("<iI")
_MARKER_IDS = struct.Struct("<iii")
_POSE_SCALE = struct.Struct("<10d")
_COLOR = struct.Struct("<4f")
_LIFETIME_LOCKED = struct.Struct("<iI?")
_PAD: Final[tuple[bytes, ...]] = tuple(bytes(n) for n in range(8))


def _cdr_string(text: str) -> bytes:
    raw = text.encode("utf-8")
    return _U32.pack(len(raw) + 1) + raw + b"\x00"


_EMPTY_STRING: Final[bytes] = _cdr_string("")


class _CdrWriter:
    """Little-endian CDR into one bytearray; alignment counts from the end of the encapsulation header."""

    __slots__ = ("buf",)

    def __init__(self) -> None:
        self.buf = bytearray(b"\x00\x01\x00\x00")

    def align(self, size: int) -> None:
        self.buf += _PAD[-(len(self.buf) - 4) % size]

    def pack(self, fmt: struct.Struct, align: int, *values: object) -> None:
        self.align(align)
        self.buf += fmt.pack(*values)

    def string(self, text: str) -> None:
        self.align(4)
        self.buf += _cdr_string(text)

    def header(self, stamp: tuple[int, int], frame_id: str) -> None:
        self.pack(_STAMP, 4, *stamp)
        self.string(frame_id)

    def body_from_4_aligned(self) -> bytes:
        """The bytes after the encapsulation header, padded to 4: a run that keeps its layout wherever
        it is placed 4-aligned (nothing in it aligns to 8)."""
        self.align(4)
        return bytes(self.buf[4:])


def _rows(columns: list[np.ndarray | float], count: int) -> list[bytes]:
    """Per object, its doubles as little-endian bytes: one numpy pass for the whole frame."""
    table = np.zeros((count, len(columns)), dtype="<f8")
    for j, column in enumerate(columns):
        if not (isinstance(column, float) and column == 0.0):  # most of a covariance or a pose
            table[:, j] = column
    raw = table.tobytes()
    size = 8 * len(columns)
    return [raw[i * size : (i + 1) * size] for i in range(count)]


def _detection3d_array(
    stamp_ns: int,
    frame_id: str,
    boxes: Boxes,
    class_names: list[str],
    scores: list[float],
    ids: list[str] | None,
) -> bytes:
    """A Detection3DArray of one hypothesis per object; ``ids`` None: every ``id`` empty."""
    stamp = _stamp(stamp_ns)
    w = _CdrWriter()
    w.header(stamp, frame_id)
    w.pack(_U32, 4, len(class_names))
    if not class_names:
        return bytes(w.buf)
    head = _CdrWriter()  # each Detection3D: the array's header, then one hypothesis
    head.header(stamp, frame_id)
    head.pack(_U32, 4, 1)
    object_head = head.body_from_4_aligned()
    # hypothesis score, PoseWithCovariance (pose, 36 zeros), BoundingBox3D (pose, size): 54 doubles
    rows = _rows(
        [np.array(scores, dtype=np.float64), *boxes.pose_columns(0.0), *([0.0] * 36),
         *boxes.pose_columns(0.0), boxes.length, boxes.width, SLAB_HEIGHT_M],
        len(class_names),
    )  # fmt: skip
    buf = w.buf
    for i, (class_name, row) in enumerate(zip(class_names, rows, strict=True)):
        buf += _PAD[-(len(buf) - 4) % 4]
        buf += object_head
        buf += _class_string(class_name)
        buf += _PAD[-(len(buf) - 4) % 8]
        buf += row
        buf += _EMPTY_STRING if ids is None else _cdr_string(ids[i])
    return bytes(buf)


class DetectionMessages:
    """The bridge's encoder: hand-written CDR for Detection3DArray and MarkerArray (see module docstring).

    The numbers of a frame are laid out by numpy in one pass (:class:`Boxes`, :func:`_rows`); per object,
    Python only appends precomputed runs and pads to the alignment CDR asks for. ``types`` is only
    checked, not used: the layout written here must be the distro's.
    """

    def __init__(self, types: RosTypes) -> None:
        fields = tuple(name for name, _ in types.store.fielddefs["visualization_msgs/msg/Marker"][1])
        if fields != MARKER_FIELDS:
            raise ValueError(
                f"{types.distro}: Marker has fields {fields}, this encoder writes {MARKER_FIELDS}"
            )
        self.types = types

    def detection_array(
        self, detections: list[Detection], stamp_ns: int, frame_id: str, boxes: Boxes | None = None
    ) -> bytes:
        """``boxes``: ``Boxes.of(detections)``, when the caller has them already."""
        return _detection3d_array(
            stamp_ns, frame_id, Boxes.of(detections) if boxes is None else boxes,
            [d.class_name for d in detections], [d.score for d in detections], None,
        )  # fmt: skip

    def track_array(self, tracks: list[Track], frame: TrackFrame, stamp_ns: int, frame_id: str) -> bytes:
        """The tracks as Detection3Ds with ``id`` = the track id, in ``frame_id`` (``frame``'s name)."""
        return _detection3d_array(
            stamp_ns, frame_id, Boxes.of_tracks(tracks, frame), [t.class_name for t in tracks],
            [t.score for t in tracks], [str(t.track_id) for t in tracks],
        )  # fmt: skip

    def track_marker_array(
        self, tracks: list[Track], frame: TrackFrame, stamp_ns: int, frame_id: str
    ) -> bytes:
        """Arrows and labels (:func:`track_marker_specs`); per-marker packing: a frame has few tracks."""
        head = _CdrWriter()
        head.header(_stamp(stamp_ns), frame_id)
        head.string(TRACK_MARKER_NS)
        marker_head = head.body_from_4_aligned()
        specs = track_marker_specs(tracks, frame)
        buf = bytearray(b"\x00\x01\x00\x00")
        buf += _U32.pack(len(specs))
        for spec in specs:
            numbers = _POSE_SCALE.pack(*spec.position, *spec.orientation, *spec.scale) + _COLOR.pack(
                *spec.rgba
            )
            _marker(buf, marker_head, spec.marker_id, spec.kind, spec.action, numbers, spec.text)
        return bytes(buf)

    def marker_array(
        self, detections: list[Detection], stamp_ns: int, frame_id: str, boxes: Boxes | None = None
    ) -> bytes:
        # Every marker starts with the same header and namespace, and after its colour come the same
        # empty fields; each of those runs starts 4-aligned, so their bytes are built once per frame.
        head = _CdrWriter()
        head.header(_stamp(stamp_ns), frame_id)
        head.string(MARKER_NS)
        marker_head = head.body_from_4_aligned()
        count = len(detections)
        buf = bytearray(b"\x00\x01\x00\x00")
        buf += _U32.pack(2 * count + 1)
        d = DELETE_ALL_MARKER
        _marker(buf, marker_head, d.marker_id, d.kind, d.action, _DELETE_ALL_NUMBERS, d.text)
        if not count:
            return bytes(buf)
        boxes = Boxes.of(detections) if boxes is None else boxes
        # pose, scale: 10 doubles
        cube_rows = _rows([*boxes.pose_columns(0.0), boxes.length, boxes.width, SLAB_HEIGHT_M], count)
        label_rows = _rows([*boxes.pose_columns(LABEL_LIFT_M), 0.0, 0.0, LABEL_HEIGHT_M], count)
        for i, detection in enumerate(detections):
            cube_colour, label_colour = _colours(detection.class_id)
            _marker(buf, marker_head, 2 * i, CUBE, ADD, cube_rows[i] + cube_colour, "")
            _marker(
                buf, marker_head, 2 * i + 1, TEXT_VIEW_FACING, ADD, label_rows[i] + label_colour,
                label_text(detection),
            )  # fmt: skip
        return bytes(buf)


def _marker(
    buf: bytearray, head: bytes, marker_id: int, kind: int, action: int, numbers: bytes, text: str
) -> None:
    """One Marker: ``numbers`` = pose and scale (10 doubles, 8-aligned) and the colour (4 floats)."""
    buf += _PAD[-(len(buf) - 4) % 4]
    buf += head
    buf += _MARKER_IDS.pack(marker_id, kind, action)
    buf += _PAD[-(len(buf) - 4) % 8]
    buf += numbers  # ends 8-aligned: the constant run below starts 4-aligned
    buf += _AFTER_COLOR
    buf += _cdr_string(text)
    buf += _AFTER_TEXT[(len(buf) - 4) % 4]


@functools.cache
def _class_string(class_name: str) -> bytes:
    return _cdr_string(class_name)


@functools.cache
def _colours(class_id: int) -> tuple[bytes, bytes]:
    """A class's cube and label colours as CDR ColorRGBA."""
    return _COLOR.pack(*_rgba(class_id, CUBE_ALPHA)), _COLOR.pack(*_rgba(class_id, 1.0))


_DELETE_ALL_NUMBERS: Final[bytes] = struct.pack(
    "<10d", *DELETE_ALL_MARKER.position, *DELETE_ALL_MARKER.orientation, *DELETE_ALL_MARKER.scale
) + _COLOR.pack(*DELETE_ALL_MARKER.rgba)


def _after_color() -> bytes:
    """Marker fields from ``lifetime`` to ``uv_coordinates``, all zero or empty, starting 4-aligned."""
    w = _CdrWriter()
    w.pack(_LIFETIME_LOCKED, 4, 0, 0, False)
    w.pack(_U32, 4, 0)  # points
    w.pack(_U32, 4, 0)  # colors
    w.string("")  # texture_resource
    w.header((0, 0), "")  # texture: CompressedImage header
    w.string("")  # texture.format
    w.pack(_U32, 4, 0)  # texture.data
    w.pack(_U32, 4, 0)  # uv_coordinates
    return bytes(w.buf[4:])


def _after_text(offset: int) -> bytes:
    """Marker fields after ``text`` (empty mesh resource and file, no embedded materials), from ``offset``."""
    w = _CdrWriter()
    w.buf += bytes(offset)
    w.string("")  # mesh_resource
    w.string("")  # mesh_file.filename
    w.pack(_U32, 4, 0)  # mesh_file.data
    w.buf.append(0)  # mesh_use_embedded_materials
    return bytes(w.buf[4 + offset :])


_AFTER_COLOR: Final[bytes] = _after_color()
_AFTER_TEXT: Final[tuple[bytes, ...]] = tuple(_after_text(offset) for offset in range(4))
"""By the body offset modulo 4 after ``text``: the padding before the next string differs."""


class ReferenceDetectionMessages:
    """The same two messages built as rosbags objects and serialised by rosbags (tests and bench)."""

    def __init__(self, types: RosTypes) -> None:
        self.types = types
        self.t = types.store.types

    def _header(self, stamp_ns: int, frame_id: str) -> Any:
        sec, nanosec = _stamp(stamp_ns)
        return self.t["std_msgs/msg/Header"](
            stamp=self.t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
        )

    def _pose(
        self, position: tuple[float, float, float], orientation: tuple[float, float, float, float]
    ) -> Any:
        qx, qy, qz, qw = orientation
        return self.t["geometry_msgs/msg/Pose"](
            position=self.t["geometry_msgs/msg/Point"](x=position[0], y=position[1], z=position[2]),
            orientation=self.t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        )

    def _vector3(self, xyz: tuple[float, float, float]) -> Any:
        return self.t["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2])

    def detection_array(self, detections: list[Detection], stamp_ns: int, frame_id: str) -> bytes:
        return self._array(
            stamp_ns, frame_id, Boxes.of(detections), [(d.class_name, d.score, "") for d in detections]
        )

    def track_array(self, tracks: list[Track], frame: TrackFrame, stamp_ns: int, frame_id: str) -> bytes:
        return self._array(
            stamp_ns, frame_id, Boxes.of_tracks(tracks, frame),
            [(t.class_name, t.score, str(t.track_id)) for t in tracks],
        )  # fmt: skip

    def _array(
        self, stamp_ns: int, frame_id: str, boxes: Boxes, objects: list[tuple[str, float, str]]
    ) -> bytes:
        t = self.t
        header = self._header(stamp_ns, frame_id)
        items = []
        for i, (class_name, score, object_id) in enumerate(objects):
            pose = self._pose(
                (float(boxes.x[i]), float(boxes.y[i]), 0.0),
                (0.0, 0.0, float(boxes.qz[i]), float(boxes.qw[i])),
            )
            hypothesis = t["vision_msgs/msg/ObjectHypothesisWithPose"](
                hypothesis=t["vision_msgs/msg/ObjectHypothesis"](class_id=class_name, score=score),
                pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=_COVARIANCE),
            )
            bbox = t["vision_msgs/msg/BoundingBox3D"](
                center=pose,
                size=self._vector3((float(boxes.length[i]), float(boxes.width[i]), SLAB_HEIGHT_M)),
            )
            items.append(
                t["vision_msgs/msg/Detection3D"](header=header, results=[hypothesis], bbox=bbox, id=object_id)
            )
        return self.types.serialize(t[DETECTION3D_ARRAY](header=header, detections=items), DETECTION3D_ARRAY)

    def marker_array(self, detections: list[Detection], stamp_ns: int, frame_id: str) -> bytes:
        return self._markers(marker_specs(detections), MARKER_NS, stamp_ns, frame_id)

    def track_marker_array(
        self, tracks: list[Track], frame: TrackFrame, stamp_ns: int, frame_id: str
    ) -> bytes:
        return self._markers(track_marker_specs(tracks, frame), TRACK_MARKER_NS, stamp_ns, frame_id)

    def _markers(self, specs: list[MarkerSpec], namespace: str, stamp_ns: int, frame_id: str) -> bytes:
        t = self.t
        header = self._header(stamp_ns, frame_id)
        empty_bytes = np.zeros(0, dtype=np.uint8)
        markers = [
            t["visualization_msgs/msg/Marker"](
                header=header,
                ns=namespace,
                id=spec.marker_id,
                type=spec.kind,
                action=spec.action,
                pose=self._pose(spec.position, spec.orientation),
                scale=self._vector3(spec.scale),
                color=t["std_msgs/msg/ColorRGBA"](*spec.rgba),
                lifetime=t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
                frame_locked=False,
                points=[],
                colors=[],
                texture_resource="",
                texture=t["sensor_msgs/msg/CompressedImage"](
                    header=self._header(0, ""), format="", data=empty_bytes
                ),
                uv_coordinates=[],
                text=spec.text,
                mesh_resource="",
                mesh_file=t["visualization_msgs/msg/MeshFile"](filename="", data=empty_bytes),
                mesh_use_embedded_materials=False,
            )
            for spec in specs
        ]
        return self.types.serialize(t[MARKER_ARRAY](markers=markers), MARKER_ARRAY)
