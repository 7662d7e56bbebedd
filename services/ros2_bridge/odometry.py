"""ROS odometry in, triscan :class:`~common.messages.Odometry` out: ``nav_msgs/Odometry`` or ``/tf``.

The bridge and bag replay both pair each LaserScan with the robot's pose in the odometry frame, so the
tracker can keep furniture still while the robot drives. The pose comes from either:

* ``nav_msgs/msg/Odometry`` (``/odom``, ``<ns>/odom``): ``pose.pose`` of ``child_frame_id`` in
  ``header.frame_id``;
* ``tf2_msgs/msg/TFMessage`` (``/tf``): the transform from the odometry frame (``odom`` unless told
  otherwise) to the robot's base (``base_link`` or ``base_footprint``).

Odometry is not the hot path (tens of messages a second at most), so rosbags' generic deserialiser
reads it. A scan gets the newest pose no older than ``MAX_ODOM_AGE_NS`` from its own stamp (odometry
runs faster than a LiDAR, so the newest one is within one odometry period); a pose that is stale or
not finite is refused by reason and the scan goes on without one.
"""

from __future__ import annotations

import math
from collections import Counter
from typing import Any, Final

from common.messages import Odometry, Scan

ODOMETRY: Final[str] = "nav_msgs/msg/Odometry"
TF_MESSAGE: Final[str] = "tf2_msgs/msg/TFMessage"
ODOM_FRAME: Final[str] = "odom"
BASE_FRAMES: Final[tuple[str, ...]] = ("base_link", "base_footprint")
MAX_ODOM_AGE_NS: Final[int] = 500_000_000
_NS_PER_S: Final[int] = 1_000_000_000


def yaw_of(x: float, y: float, z: float, w: float) -> float:
    """Rotation about z of a quaternion, radians in (−π, π]."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def _stamp_ns(stamp: Any) -> int:
    return max(0, int(stamp.sec) * _NS_PER_S + int(stamp.nanosec))


def _pose(position: Any, orientation: Any, frame_id: str, stamp: Any) -> Odometry:
    return Odometry(
        x_m=float(position.x),
        y_m=float(position.y),
        yaw_rad=yaw_of(
            float(orientation.x), float(orientation.y), float(orientation.z), float(orientation.w)
        ),
        frame_id=frame_id or ODOM_FRAME,
        stamp_ns=_stamp_ns(stamp),
    )


def odometry_of_message(message: Any) -> Odometry:
    """The pose of a deserialised ``nav_msgs/Odometry`` (ROS 1 or ROS 2)."""
    pose = message.pose.pose
    return _pose(pose.position, pose.orientation, str(message.header.frame_id), message.header.stamp)


def odometry_of_tf(message: Any, odom_frame: str = ODOM_FRAME) -> Odometry | None:
    """The odometry frame → robot base transform of a ``tf2_msgs/TFMessage``, or None if it has none."""
    for transform in message.transforms:
        parent = str(transform.header.frame_id).lstrip("/")
        child = str(transform.child_frame_id).lstrip("/")
        if parent == odom_frame and child.rsplit("/", 1)[-1] in BASE_FRAMES:
            t = transform.transform
            return _pose(t.translation, t.rotation, parent, transform.header.stamp)
    return None


class OdometryPairing:
    """The newest pose of one robot, handed to each scan that comes close enough after it.

    ``refused`` counts the poses not attached, by reason: ``not_finite`` (a diverged filter's NaN),
    ``stale`` (no pose within ``MAX_ODOM_AGE_NS`` of the scan). A scan never waits for a pose.
    """

    def __init__(self, max_age_ns: int = MAX_ODOM_AGE_NS, refused: Counter[str] | None = None) -> None:
        self.max_age_ns = max_age_ns
        self.latest: Odometry | None = None
        self.attached = 0
        self.refused: Counter[str] = Counter() if refused is None else refused  # shareable by robots

    def update(self, odom: Odometry) -> None:
        if not odom.finite:
            self.refused["not_finite"] += 1
            return
        self.latest = odom

    def attach(self, scan: Scan) -> Scan:
        """``scan`` with the newest pose, or unchanged when there is none close enough."""
        odom = self.latest
        if odom is None:
            return scan
        if abs(scan.stamp_ns - odom.stamp_ns) > self.max_age_ns:
            self.refused["stale"] += 1
            return scan
        self.attached += 1
        return with_odometry(scan, odom)

    def counters(self) -> dict[str, object]:
        return {"attached": self.attached, "refused": dict(self.refused)}


def with_odometry(scan: Scan, odom: Odometry) -> Scan:
    """A copy of ``scan`` carrying ``odom``, validated (and versioned) like any new message."""
    return Scan(**{**scan.model_dump(exclude={"schema_version", "odom"}), "odom": odom})
