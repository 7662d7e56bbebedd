"""Publish LiDAR scans as triscan ``Scan`` messages, with only zenoh, msgpack and numpy: a driver without ROS.

    pip install eclipse-zenoh msgpack numpy
    python -m services.detector --from-scans --listen tcp/127.0.0.1:7447      # on the robot (base install)
    python examples/publish_scans.py --connect tcp/127.0.0.1:7447 --robot myrobot

Replace ``read_scan`` with your driver's call: it returns one sweep as (angle_min, angle_increment,
range_min, range_max, ranges in metres). Any beam count and field of view work; each beam is binned by
its own angle (README, "The encoding"). The payload is a msgpack map whose fields mirror ROS
``sensor_msgs/LaserScan`` (README, "Detection message": the Scans paragraph under it); ``seq`` counts
up by one per sweep (a gap restarts the detector's three-scan stack), ``stamp_ns`` is the sweep's
time, and ``robot_id`` must equal the key's ``<robot>`` chunk.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import time

import msgpack
import numpy as np
import zenoh

log = logging.getLogger("publish_scans")

SCHEMA_VERSION = 1
ODOM_SCHEMA_VERSION = 2  # a scan that carries odometry (the tracker keeps still objects still with it)


def read_scan(t: float) -> tuple[float, float, float, float, np.ndarray]:
    """A stand-in sensor: an LDS-01-like sweep (360 beams) of a 3 x 4 m room turning slowly around it."""
    beams = 360
    angles = -math.pi + np.arange(beams) * (2 * math.pi / beams) + 0.2 * t
    # distance to the walls of an axis-aligned 3 x 4 m box centred on the sensor
    with np.errstate(divide="ignore"):
        ranges = np.minimum(np.abs(1.5 / np.cos(angles)), np.abs(2.0 / np.sin(angles)))
    return -math.pi, 2 * math.pi / beams, 0.12, 3.5, ranges.astype("<f4")


def read_odometry(t: float) -> tuple[float, float, float] | None:
    """Your robot's pose (x, y, yaw) in its odometry frame, or None without: this one turns in place."""
    return 0.0, 0.0, 0.2 * t


def scan_payload(robot_id: str, seq: int, stamp_ns: int, frame_id: str, t: float) -> bytes:
    angle_min, angle_increment, range_min, range_max, ranges = read_scan(t)
    body = {
        "kind": "scan",
        "schema_version": SCHEMA_VERSION,
        "robot_id": robot_id,
        "seq": seq,
        "stamp_ns": stamp_ns,
        "angle_min": angle_min,
        "angle_increment": angle_increment,
        "range_min": range_min,
        "range_max": range_max,
        "ranges": {"dtype": "<f4", "shape": [len(ranges)], "data": ranges.tobytes()},
        "frame_id": frame_id,
    }
    pose = read_odometry(t)
    if pose is not None:
        odom = {"x_m": pose[0], "y_m": pose[1], "yaw_rad": pose[2], "frame_id": "odom", "stamp_ns": stamp_ns}
        body.update(schema_version=ODOM_SCHEMA_VERSION, odom=odom)
    return msgpack.packb(body, use_bin_type=True)


def main(config: zenoh.Config, robot_id: str, rate_hz: float, count: int, wait_s: float) -> None:
    with zenoh.open(config) as session:  # closing the session lets the interpreter exit
        publisher = session.declare_publisher(f"triscan/{robot_id}/scan")
        deadline = time.monotonic() + wait_s
        while not publisher.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.05)  # Zenoh drops a put nobody subscribes to: wait for the detector first
        started = time.monotonic()
        seq = 0
        while not count or seq < count:
            due = started + seq / rate_hz  # a fixed schedule: the rate does not drift
            time.sleep(max(0.0, due - time.monotonic()))
            publisher.put(scan_payload(robot_id, seq, time.time_ns(), "laser", time.monotonic() - started))
            seq += 1
            if seq % int(10 * rate_hz) == 0:
                log.info("published %d scans on triscan/%s/scan", seq, robot_id)
        publisher.undeclare()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connect", "-e", action="append", default=[], help="zenoh endpoint(s)")
    parser.add_argument("--robot", default="myrobot", help="robot id: letters, digits, '_' and '-'")
    parser.add_argument("--rate", type=float, default=10.0, help="scans per second")
    parser.add_argument("--count", type=int, default=0, help="stop after this many scans (0: never)")
    parser.add_argument("--wait", type=float, default=10.0, help="seconds to wait for a subscriber first")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    config = zenoh.Config()
    if args.connect:
        config.insert_json5("connect/endpoints", json.dumps(args.connect))
        config.insert_json5("scouting/multicast/enabled", "false")
    with contextlib.suppress(KeyboardInterrupt):
        main(config, args.robot, args.rate, args.count, args.wait)
