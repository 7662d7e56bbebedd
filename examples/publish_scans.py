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
# Seconds between announcing the robot and its first scan (services.runtime.announce_lead_s("scan")): on
# a fleet server each detector process subscribes to the announced robots it serves, and the one that
# serves this robot takes its scans once every process has seen the announcement.
ANNOUNCE_LEAD_S = 0.6


# A stand-in room, ray-cast in closed form: solids as axis-aligned rectangles (x_min, y_min, x_max, y_max),
# metres, with the sizes of the simulator's furniture (docs/encoding-and-simulator.md): chairs and desks
# are four legs under a top the scan plane passes beneath, the box is solid.
def _legs(cx: float, cy: float, width: float, depth: float, leg: float) -> list[tuple[float, ...]]:
    hx, hy = (width - leg) / 2, (depth - leg) / 2
    return [
        (cx + dx - leg / 2, cy + dy - leg / 2, cx + dx + leg / 2, cy + dy + leg / 2)
        for dx in (-hx, hx)
        for dy in (-hy, hy)
    ]


WALLS = [(-2.1, -2.1, 2.1, -2.0), (-2.1, 2.0, 2.1, 2.1), (-2.1, -2.0, -2.0, 2.0), (2.0, -2.0, 2.1, 2.0)]
DESK = _legs(1.2, 0.6, 0.8, 1.6, 0.05)
BOX = [(-1.4, -1.3, -1.0, -0.7)]
CHAIR = _legs(0.2, -1.2, 0.4, 0.4, 0.03)
SOLIDS = np.array(WALLS + DESK + BOX + CHAIR)
BEAMS, RANGE_MIN, RANGE_MAX = 360, 0.12, 3.5  # an LDS-01-like sensor
_noise = np.random.default_rng(0)


def read_scan(t: float) -> tuple[float, float, float, float, np.ndarray]:
    """A stand-in sensor: a 360-beam sweep of a 4 x 4 m room with a desk, a box and a chair, from a robot
    driving back and forth along the room's x axis at 0.1 m/s (the detector reads motion across three
    scans, as on a real robot)."""
    x = -0.6 + abs((0.1 * t) % 2.0 - 1.0)  # between -0.6 and 0.4 m, facing +x
    angles = -math.pi + np.arange(BEAMS) * (2 * math.pi / BEAMS)
    directions = np.stack([np.cos(angles), np.sin(angles)], axis=1)[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):  # slab test of every beam against every solid
        near = (SOLIDS[None, :, :2] - (x, 0.0)) / directions
        far = (SOLIDS[None, :, 2:] - (x, 0.0)) / directions
    enter = np.nanmax(np.minimum(near, far), axis=2)
    leave = np.nanmin(np.maximum(near, far), axis=2)
    ranges = np.where((leave >= enter) & (leave > 0), enter, np.inf).min(axis=1)
    ranges = ranges + _noise.normal(0.0, 0.005, BEAMS)
    ranges[ranges > RANGE_MAX] = np.inf  # no return, as drivers report it
    return -math.pi, 2 * math.pi / BEAMS, RANGE_MIN, RANGE_MAX, ranges.astype("<f4")


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
        # Announce the robot's scans (a liveliness token held while it publishes). A driver that does
        # not is still served, by whichever detector process serves the robots that announce nothing.
        source = session.liveliness().declare_token(f"triscan/@sources/scan/{robot_id}/{session.zid()}")
        deadline = time.monotonic() + wait_s
        while not publisher.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.05)  # Zenoh drops a put nobody subscribes to: wait for the detector first
        time.sleep(ANNOUNCE_LEAD_S)
        started = time.monotonic()
        seq = 0
        while not count or seq < count:
            due = started + seq / rate_hz  # a fixed schedule: the rate does not drift
            time.sleep(max(0.0, due - time.monotonic()))
            publisher.put(scan_payload(robot_id, seq, time.time_ns(), "laser", time.monotonic() - started))
            seq += 1
            if seq % int(10 * rate_hz) == 0:
                log.info("published %d scans on triscan/%s/scan", seq, robot_id)
        source.undeclare()
        publisher.undeclare()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    parser.add_argument("--connect", "-e", action="append", default=[], help="zenoh endpoint(s)")
    parser.add_argument("--discover", action="store_true", help="also find zenoh peers by multicast scouting")
    parser.add_argument("--robot", default="myrobot", help="robot id: letters, digits, '_' and '-'")
    parser.add_argument("--rate", type=float, default=10.0, help="scans per second")
    parser.add_argument("--count", type=int, default=0, help="stop after this many scans (0: never)")
    parser.add_argument("--wait", type=float, default=10.0, help="seconds to wait for a subscriber first")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    config = zenoh.Config()
    # Only the peers it is pointed at, as every triscan process (common/transport.py): multicast
    # scouting would join any Zenoh network on the LAN.
    config.insert_json5("scouting/multicast/enabled", json.dumps(args.discover))
    if args.connect:
        config.insert_json5("connect/endpoints", json.dumps(args.connect))
    with contextlib.suppress(KeyboardInterrupt):
        main(config, args.robot, args.rate, args.count, args.wait)
