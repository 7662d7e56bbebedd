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
Humble's definitions, so the fast path cannot drift from the definitions.

Markers: a ``DELETEALL`` first (stale boxes of the previous frame vanish even when fewer objects are
seen), then per object a translucent ``CUBE`` (the box above, in the class colour) and a
``TEXT_VIEW_FACING`` label ``"<class> <score>"`` above it.
"""

from __future__ import annotations

import math
import struct
from typing import Any, Final, NamedTuple

import numpy as np

from common.messages import Detection
from common.model_spec import CLASS_COLOURS, UNKNOWN_CLASS_COLOUR
from services.ros2_bridge.ros_types import DETECTION3D_ARRAY, MARKER_ARRAY, RosTypes

SLAB_HEIGHT_M: Final[float] = 0.2
MIN_EXTENT_M: Final[float] = 0.01  # a zero-size box is invisible and RViz warns about it
LABEL_HEIGHT_M: Final[float] = 0.12  # text size of the labels
LABEL_LIFT_M: Final[float] = 0.25  # labels float this far above the scan plane
CUBE_ALPHA: Final[float] = 0.5
MARKER_NS: Final[str] = "triscan"
_NS_PER_S: Final[int] = 1_000_000_000
_COVARIANCE: Final[np.ndarray] = np.zeros(36, dtype=np.float64)

# Marker constants (visualization_msgs/msg/Marker), checked against the typestore in the tests.
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


class BoxGeometry(NamedTuple):  # a NamedTuple: built per object per frame, ~4× cheaper than a dataclass
    """A detection's box in the laser frame: centre, yaw and size (see the module docstring)."""

    x: float
    y: float
    yaw: float
    length: float  # along the bearing (range extent)
    width: float  # across it (arc extent)


def box_geometry(detection: Detection) -> BoxGeometry:
    arc_deg = (detection.bearing_max_deg - detection.bearing_min_deg) % 360.0
    middle_range = (detection.range_min_m + detection.range_max_m) / 2.0
    return BoxGeometry(
        x=detection.x_m,
        y=detection.y_m,
        yaw=math.radians(detection.bearing_deg),
        length=max(detection.range_max_m - detection.range_min_m, MIN_EXTENT_M),
        width=max(math.radians(arc_deg) * middle_range, MIN_EXTENT_M),
    )


class MarkerSpec(NamedTuple):
    """What one marker shows, independent of how it is encoded."""

    marker_id: int
    kind: int
    action: int
    position: tuple[float, float, float]
    yaw: float
    scale: tuple[float, float, float]
    rgba: tuple[float, float, float, float]
    text: str = ""


def boxes_of(detections: list[Detection], boxes: list[BoxGeometry] | None) -> list[BoxGeometry]:
    return [box_geometry(d) for d in detections] if boxes is None else boxes


def marker_specs(detections: list[Detection], boxes: list[BoxGeometry] | None = None) -> list[MarkerSpec]:
    """``DELETEALL``, then a cube and a label per object (see the module docstring)."""
    specs = [MarkerSpec(0, CUBE, DELETEALL, (0.0, 0.0, 0.0), 0.0, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0, 0.0))]
    for index, (detection, box) in enumerate(zip(detections, boxes_of(detections, boxes), strict=True)):
        colour = (
            CLASS_COLOURS[detection.class_id]
            if detection.class_id < len(CLASS_COLOURS)
            else UNKNOWN_CLASS_COLOUR
        )
        r, g, b = (c / 255.0 for c in colour)
        specs.append(
            MarkerSpec(
                2 * index, CUBE, ADD, (box.x, box.y, 0.0), box.yaw,
                (box.length, box.width, SLAB_HEIGHT_M), (r, g, b, CUBE_ALPHA),
            )
        )  # fmt: skip
        specs.append(
            MarkerSpec(
                2 * index + 1, TEXT_VIEW_FACING, ADD, (box.x, box.y, LABEL_LIFT_M), box.yaw,
                (0.0, 0.0, LABEL_HEIGHT_M), (r, g, b, 1.0), f"{detection.class_name} {detection.score:.2f}",
            )
        )  # fmt: skip
    return specs


def _yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))


def _stamp(stamp_ns: int) -> tuple[int, int]:
    return stamp_ns // _NS_PER_S, stamp_ns % _NS_PER_S


_U32 = struct.Struct("<I")
_I32 = struct.Struct("<i")
_STAMP = struct.Struct("<iI")
_MARKER_IDS = struct.Struct("<iii")
_POSE_SCALE = struct.Struct("<10d")  # position, orientation, scale
_COLOR = struct.Struct("<4f")
_LIFETIME_LOCKED = struct.Struct("<iI?")
_SCORE_POSE_COVARIANCE = struct.Struct("<44d")  # hypothesis score, then PoseWithCovariance: 7 + 36 doubles
_BBOX = struct.Struct("<10d")
_COVARIANCE_ZEROS: Final[tuple[float, ...]] = (0.0,) * 36


class _CdrWriter:
    """Little-endian CDR into one bytearray; alignment counts from the end of the encapsulation header."""

    __slots__ = ("buf",)

    def __init__(self) -> None:
        self.buf = bytearray(b"\x00\x01\x00\x00")

    def align(self, size: int) -> None:
        pad = -(len(self.buf) - 4) % size
        if pad:
            self.buf += bytes(pad)

    def pack(self, fmt: struct.Struct, align: int, *values: object) -> None:
        self.align(align)
        self.buf += fmt.pack(*values)

    def string(self, text: str) -> None:
        raw = text.encode("utf-8")
        self.align(4)
        self.buf += _U32.pack(len(raw) + 1)
        self.buf += raw
        self.buf.append(0)

    def header(self, stamp: tuple[int, int], frame_id: str) -> None:
        self.pack(_STAMP, 4, *stamp)
        self.string(frame_id)


class DetectionMessages:
    """The bridge's encoder: hand-written CDR for Detection3DArray and MarkerArray (see module docstring).

    ``types`` is only checked, not used: the layout written here must be the distro's.
    """

    def __init__(self, types: RosTypes) -> None:
        fields = tuple(name for name, _ in types.store.fielddefs["visualization_msgs/msg/Marker"][1])
        if fields != MARKER_FIELDS:
            raise ValueError(
                f"{types.distro}: Marker has fields {fields}, this encoder writes {MARKER_FIELDS}"
            )
        self.types = types

    def detection_array(
        self,
        detections: list[Detection],
        stamp_ns: int,
        frame_id: str,
        boxes: list[BoxGeometry] | None = None,
    ) -> bytes:
        """``boxes``: the detections' :func:`box_geometry`, when the caller has them already."""
        stamp = _stamp(stamp_ns)
        w = _CdrWriter()
        w.header(stamp, frame_id)
        w.pack(_U32, 4, len(detections))
        for detection, box in zip(detections, boxes_of(detections, boxes), strict=True):
            pose = (box.x, box.y, 0.0, *_yaw_quaternion(box.yaw))
            w.header(stamp, frame_id)
            w.pack(_U32, 4, 1)  # one hypothesis
            w.string(detection.class_name)
            w.pack(_SCORE_POSE_COVARIANCE, 8, detection.score, *pose, *_COVARIANCE_ZEROS)
            w.pack(_BBOX, 8, *pose, box.length, box.width, SLAB_HEIGHT_M)
            w.string("")  # id
        return bytes(w.buf)

    def marker_array(
        self,
        detections: list[Detection],
        stamp_ns: int,
        frame_id: str,
        boxes: list[BoxGeometry] | None = None,
    ) -> bytes:
        # Every marker starts with the same header and namespace, and after its colour come the same
        # empty fields; each of those runs starts 4-aligned, so their bytes are built once per frame.
        head = _CdrWriter()
        head.header(_stamp(stamp_ns), frame_id)
        head.string(MARKER_NS)
        head.align(4)
        head_bytes = bytes(head.buf[4:])
        w = _CdrWriter()
        specs = marker_specs(detections, boxes)
        w.pack(_U32, 4, len(specs))
        for spec in specs:
            w.align(4)
            w.buf += head_bytes
            w.buf += _MARKER_IDS.pack(spec.marker_id, spec.kind, spec.action)
            w.pack(_POSE_SCALE, 8, *spec.position, *_yaw_quaternion(spec.yaw), *spec.scale)
            w.buf += _COLOR.pack(*spec.rgba)  # 8-aligned here, so the constant run below is 4-aligned
            w.buf += _AFTER_COLOR
            w.string(spec.text)
            w.buf += _AFTER_TEXT[(len(w.buf) - 4) % 4]
        return bytes(w.buf)


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

    def _pose(self, position: tuple[float, float, float], yaw: float) -> Any:
        qx, qy, qz, qw = _yaw_quaternion(yaw)
        return self.t["geometry_msgs/msg/Pose"](
            position=self.t["geometry_msgs/msg/Point"](x=position[0], y=position[1], z=position[2]),
            orientation=self.t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        )

    def _vector3(self, xyz: tuple[float, float, float]) -> Any:
        return self.t["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2])

    def detection_array(self, detections: list[Detection], stamp_ns: int, frame_id: str) -> bytes:
        t = self.t
        header = self._header(stamp_ns, frame_id)
        items = []
        for detection in detections:
            box = box_geometry(detection)
            pose = self._pose((box.x, box.y, 0.0), box.yaw)
            hypothesis = t["vision_msgs/msg/ObjectHypothesisWithPose"](
                hypothesis=t["vision_msgs/msg/ObjectHypothesis"](
                    class_id=detection.class_name, score=detection.score
                ),
                pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=_COVARIANCE),
            )
            bbox = t["vision_msgs/msg/BoundingBox3D"](
                center=pose, size=self._vector3((box.length, box.width, SLAB_HEIGHT_M))
            )
            items.append(
                t["vision_msgs/msg/Detection3D"](header=header, results=[hypothesis], bbox=bbox, id="")
            )
        return self.types.serialize(t[DETECTION3D_ARRAY](header=header, detections=items), DETECTION3D_ARRAY)

    def marker_array(self, detections: list[Detection], stamp_ns: int, frame_id: str) -> bytes:
        t = self.t
        header = self._header(stamp_ns, frame_id)
        empty_bytes = np.zeros(0, dtype=np.uint8)
        markers = [
            t["visualization_msgs/msg/Marker"](
                header=header,
                ns=MARKER_NS,
                id=spec.marker_id,
                type=spec.kind,
                action=spec.action,
                pose=self._pose(spec.position, spec.yaw),
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
            for spec in marker_specs(detections)
        ]
        return self.types.serialize(t[MARKER_ARRAY](markers=markers), MARKER_ARRAY)
