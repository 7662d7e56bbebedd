"""ROS 2 LaserScans for bridge and replay tests, serialised by rosbags (not by the code under test)."""

from __future__ import annotations

import math

import numpy as np

from common.messages import Scan
from services.ros2_bridge.ros_types import LASER_SCAN, ros_types


def laser_scan_message(
    ranges: np.ndarray,
    *,
    angle_min: float = -math.pi,
    angle_increment: float | None = None,
    range_min: float = 0.12,
    range_max: float = 3.5,
    frame_id: str = "laser",
    stamp_ns: int = 1_700_000_000_123_456_789,
    intensities: np.ndarray | None = None,
) -> object:
    """A rosbags ``sensor_msgs/msg/LaserScan`` (Jazzy) object."""
    t = ros_types("jazzy").store.types
    values = np.asarray(ranges, dtype=np.float32)
    if angle_increment is None:
        angle_increment = 2.0 * math.pi / max(values.size, 1)
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    return t[LASER_SCAN](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame_id
        ),
        angle_min=angle_min,
        angle_max=angle_min + angle_increment * max(values.size - 1, 0),
        angle_increment=angle_increment,
        time_increment=0.0,
        scan_time=0.1,
        range_min=range_min,
        range_max=range_max,
        ranges=values,
        intensities=np.zeros(0, np.float32) if intensities is None else intensities.astype(np.float32),
    )


def laser_scan_cdr(ranges: np.ndarray, *, little_endian: bool = True, **kwargs: object) -> bytes:
    """CDR bytes (with encapsulation header) of a LaserScan, written by rosbags' serialiser."""
    store = ros_types("jazzy").store
    return bytes(
        store.serialize_cdr(laser_scan_message(ranges, **kwargs), LASER_SCAN, little_endian=little_endian)
    )


def laser_scan_cdr_of(scan: Scan, stamp_ns: int | None = None) -> bytes:
    """The LaserScan a ROS driver would publish for a triscan ``Scan`` (e.g. a simulated one)."""
    return laser_scan_cdr(
        scan.ranges,
        angle_min=scan.angle_min,
        angle_increment=scan.angle_increment,
        range_min=scan.range_min,
        range_max=scan.range_max,
        frame_id=scan.frame_id,
        stamp_ns=scan.stamp_ns if stamp_ns is None else stamp_ns,
    )
