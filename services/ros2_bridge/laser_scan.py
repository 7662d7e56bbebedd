"""``sensor_msgs/msg/LaserScan`` in, triscan ``Scan`` out: a hand-written CDR reader and the checks between.

Why by hand, when rosbags' generic deserialiser would do (it is fast too, docs/benchmarks.md, ros2_bridge):
the scan is the bridge's hot path and its only input from outside, so this reader checks every count
against ``MAX_BEAMS`` and against the bytes actually present before it touches them, names each fault
precisely (``truncated`` is not ``too_many_beams``), builds no Python object per nested message and
views the ranges in place with ``np.frombuffer`` (zero copy). The tests check it against rosbags'
independent serialiser, in both endiannesses.

CDR layout of a LaserScan body (after the 4-byte encapsulation header; alignment counts from the body):
``int32 sec, uint32 nanosec, uint32 len + frame_id bytes (NUL included)``, pad to 4,
``7 × float32`` (angle_min … range_max), ``uint32 n + n × float32`` ranges, ``uint32 m + m × float32``
intensities.

Every way a payload can be unusable becomes ``ScanRejectedError`` with a fixed ``reason`` (a metrics label),
so the bridge counts and drops it and never raises: ``not_cdr``, ``truncated``, ``bad_cdr``,
``no_beams``, ``too_many_beams``, ``bad_stamp``, ``bad_frame_id``, ``bad_angles``,
``bad_range_limits``, ``invalid``.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Any, Final

import annotated_types
import numpy as np
from pydantic import ValidationError

from common.encoding import MAX_ABS_ANGLE_RAD
from common.messages import MAX_BEAMS, Scan

MAX_FRAME_ID_LEN: Final[int] = next(
    m.max_length for m in Scan.model_fields["frame_id"].metadata if isinstance(m, annotated_types.MaxLen)
)
_NS_PER_S: Final[int] = 1_000_000_000
_TWO_PI: Final[float] = 2.0 * math.pi

_STAMP_LEN = {"<": struct.Struct("<iiI"), ">": struct.Struct(">iiI")}  # sec, nanosec, frame_id length
_FLOATS = {"<": struct.Struct("<7fI"), ">": struct.Struct(">7fI")}  # 7 floats and the ranges count
_COUNT = {"<": struct.Struct("<I"), ">": struct.Struct(">I")}
_F32 = {"<": np.dtype("<f4"), ">": np.dtype(">f4")}


class ScanRejectedError(ValueError):
    """A LaserScan that cannot become a triscan Scan; ``reason`` is a fixed metrics label."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class LaserScanFields:
    """The fields of one LaserScan the bridge uses; ``ranges`` may be a read-only view of the payload."""

    stamp_sec: int
    stamp_nanosec: int
    frame_id: str
    angle_min: float
    angle_max: float
    angle_increment: float
    time_increment: float
    scan_time: float
    range_min: float
    range_max: float
    ranges: np.ndarray
    intensities_count: int = 0


def parse_laser_scan_cdr(payload: bytes | memoryview) -> LaserScanFields:
    """Read a CDR ``sensor_msgs/msg/LaserScan`` (either endianness) or raise ScanRejectedError.

    Counts are checked against ``MAX_BEAMS`` and against the bytes actually present before anything is
    allocated, so a forged count costs nothing.
    """
    view = memoryview(payload)
    if len(view) < 4 or view[0] != 0 or view[1] not in (0, 1):
        raise ScanRejectedError("not_cdr", "LaserScan: no CDR encapsulation header")
    order = "<" if view[1] == 1 else ">"
    body = view[4:]
    size = len(body)
    if size < 12:
        raise ScanRejectedError("truncated", f"LaserScan: {size} body bytes, not even a header")
    sec, nanosec, name_len = _STAMP_LEN[order].unpack_from(body, 0)
    nanosec &= 0xFFFFFFFF
    if name_len == 0 or 12 + name_len > size:
        raise ScanRejectedError("truncated", f"LaserScan: frame_id of {name_len} bytes does not fit")
    if body[12 + name_len - 1] != 0:
        raise ScanRejectedError("bad_cdr", "LaserScan: frame_id is not NUL-terminated")
    try:
        frame_id = bytes(body[12 : 12 + name_len - 1]).decode("utf-8")
    except UnicodeDecodeError:
        raise ScanRejectedError("bad_cdr", "LaserScan: frame_id is not UTF-8") from None
    pos = (12 + name_len + 3) & ~3
    if pos + 32 > size:
        raise ScanRejectedError("truncated", "LaserScan: ends inside its fixed fields")
    angle_min, angle_max, angle_increment, time_increment, scan_time, range_min, range_max, beams = _FLOATS[
        order
    ].unpack_from(body, pos)
    pos += 32
    if beams > MAX_BEAMS:
        raise ScanRejectedError("too_many_beams", f"LaserScan: {beams} beams, the limit is {MAX_BEAMS}")
    end = pos + 4 * beams
    if end + 4 > size:
        raise ScanRejectedError("truncated", f"LaserScan: {beams} ranges declared, fewer present")
    ranges = np.frombuffer(body, dtype=_F32[order], count=beams, offset=pos)
    (intensities,) = _COUNT[order].unpack_from(body, end)
    end += 4
    if intensities > size - end or end + 4 * intensities > size:
        raise ScanRejectedError("truncated", f"LaserScan: {intensities} intensities declared, fewer present")
    end += 4 * intensities
    if size - end > 3:  # CDR allows up to 3 bytes of final padding, nothing more
        raise ScanRejectedError("bad_cdr", f"LaserScan: {size - end} bytes after the message")
    return LaserScanFields(
        sec,
        nanosec,
        frame_id,
        angle_min,
        angle_max,
        angle_increment,
        time_increment,
        scan_time,
        range_min,
        range_max,
        ranges=ranges,
        intensities_count=intensities,
    )


def fields_of_message(message: Any) -> LaserScanFields:
    """The same fields from a deserialised rosbags LaserScan (ROS 1 or ROS 2): bag replay uses this."""
    return LaserScanFields(
        stamp_sec=int(message.header.stamp.sec),
        stamp_nanosec=int(message.header.stamp.nanosec),
        frame_id=str(message.header.frame_id),
        angle_min=float(message.angle_min),
        angle_max=float(message.angle_max),
        angle_increment=float(message.angle_increment),
        time_increment=float(message.time_increment),
        scan_time=float(message.scan_time),
        range_min=float(message.range_min),
        range_max=float(message.range_max),
        ranges=np.asarray(message.ranges),
        intensities_count=len(message.intensities),
    )


def stamp_ns(fields: LaserScanFields) -> int:
    """The header stamp in nanoseconds; ScanRejectedError(``bad_stamp``) before 1970 or with nanosec ≥ 1 s."""
    if fields.stamp_sec < 0 or not 0 <= fields.stamp_nanosec < _NS_PER_S:
        raise ScanRejectedError(
            "bad_stamp", f"LaserScan: stamp {fields.stamp_sec} s {fields.stamp_nanosec} ns"
        )
    return fields.stamp_sec * _NS_PER_S + fields.stamp_nanosec


def to_triscan_scan(fields: LaserScanFields, robot_id: str, seq: int) -> Scan:
    """A validated triscan ``Scan`` (stamp = header stamp, frame_id kept), or ScanRejectedError.

    The cheap, specific checks run first so each bad scan is counted under the reason that names its
    fault; whatever the model itself still refuses is counted as ``invalid``.
    """
    stamp = stamp_ns(fields)
    if not fields.frame_id or len(fields.frame_id) > MAX_FRAME_ID_LEN:
        raise ScanRejectedError("bad_frame_id", f"LaserScan: frame_id of {len(fields.frame_id)} characters")
    beams = fields.ranges.shape[0]
    if beams == 0:
        raise ScanRejectedError("no_beams", "LaserScan: no ranges")
    if beams > MAX_BEAMS:
        raise ScanRejectedError("too_many_beams", f"LaserScan: {beams} beams, the limit is {MAX_BEAMS}")
    amin, inc = fields.angle_min, fields.angle_increment
    if not (math.isfinite(amin) and math.isfinite(inc)) or inc == 0.0 or abs(amin) > MAX_ABS_ANGLE_RAD:
        raise ScanRejectedError("bad_angles", f"LaserScan: angle_min {amin}, angle_increment {inc}")
    if beams * abs(inc) > _TWO_PI + abs(inc) + 1e-6:
        raise ScanRejectedError("bad_angles", f"LaserScan: {beams} beams × {inc:.6g} rad exceed a full turn")
    rmin, rmax = fields.range_min, fields.range_max
    if not (math.isfinite(rmin) and math.isfinite(rmax)) or not 0.0 <= rmin < rmax:
        raise ScanRejectedError("bad_range_limits", f"LaserScan: range_min {rmin}, range_max {rmax}")
    try:
        return Scan(
            robot_id=robot_id,
            seq=seq,
            stamp_ns=stamp,
            angle_min=amin,
            angle_increment=inc,
            range_min=rmin,
            range_max=rmax,
            ranges=fields.ranges,
            frame_id=fields.frame_id,
        )
    except ValidationError as exc:
        raise ScanRejectedError("invalid", f"LaserScan: {exc.errors(include_url=False)[0]['msg']}") from None
