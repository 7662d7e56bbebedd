"""ROS 2 side of docker/check_compose.sh: act as a ROS 2 node on rmw_zenoh and get detections back.

Publishes LaserScans as a node in ``/checkbot`` (``--namespace``) would with
``RMW_IMPLEMENTATION=rmw_zenoh_cpp`` (its data key with the Jazzy type hash, CDR written by rosbags,
rmw_zenoh's 33-byte attachment) to the bridge's Zenoh endpoint, and subscribes to
``<namespace>/triscan/detections`` (``vision_msgs/Detection3DArray``).
Passes when the bridge, the encoder and the detector turned the scans into Detection3DArrays stamped
with the scans' own stamps. Needs the base install plus rosbags (the robot image has both):

    podman exec -i triscan_ros2_bridge_1 python - --connect tcp/127.0.0.1:7447 < docker/check_ros2_bridge.py
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import threading
import time
from pathlib import Path

if "__file__" in globals():  # from a checkout; piped into the robot image, PYTHONPATH has /opt/triscan
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import zenoh

from common.transport import ZenohSettings, open_session
from services.ros2_bridge.core import DEFAULT_SCAN_TOPIC, DETECTIONS_TOPIC
from services.ros2_bridge.rmw_zenoh import GID_SIZE, data_key, encode_attachment, qualified_topic
from services.ros2_bridge.ros_types import DETECTION3D_ARRAY, LASER_SCAN, RosTypes, dds_type_name, ros_types

DEFAULT_NAMESPACE = "/checkbot"
BEAMS = 360


def laser_scan(types: RosTypes, stamp_ns: int, frame: int) -> object:
    """A room-like scan: walls 1.5–2.5 m away, a little different each frame (the robot turns)."""
    t = types.store.types
    angles = np.arange(BEAMS) * 2 * math.pi / BEAMS + 0.02 * frame
    ranges = (2.0 + 0.5 * np.cos(2 * angles)).astype(np.float32)
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    return t[LASER_SCAN](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id="laser"
        ),
        angle_min=-math.pi, angle_max=-math.pi + 2 * math.pi * (BEAMS - 1) / BEAMS,
        angle_increment=2 * math.pi / BEAMS, time_increment=0.0, scan_time=0.1, range_min=0.12,
        range_max=3.5, ranges=ranges, intensities=np.zeros(0, np.float32),
    )  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--connect", default="tcp/127.0.0.1:7447", help="the bridge's Zenoh endpoint")
    parser.add_argument("--domain", type=int, default=0, help="ROS_DOMAIN_ID the bridge serves")
    parser.add_argument("--namespace", default=DEFAULT_NAMESPACE, help="the node's ROS namespace")
    parser.add_argument("--scans", type=int, default=50, help="LaserScans to publish at 10 Hz")
    parser.add_argument("--min-arrays", type=int, default=5, help="Detection3DArrays needed to pass")
    args = parser.parse_args()

    types = ros_types("jazzy")
    scan_key = data_key(
        "rmw_zenoh", args.domain, qualified_topic(args.namespace, DEFAULT_SCAN_TOPIC),
        dds_type_name(LASER_SCAN), types.type_hash(LASER_SCAN),
    )  # fmt: skip
    detections_key = data_key(
        "rmw_zenoh", args.domain, qualified_topic(args.namespace, DETECTIONS_TOPIC),
        dds_type_name(DETECTION3D_ARRAY), types.type_hash(DETECTION3D_ARRAY),
    )  # fmt: skip
    sent_stamps: set[int] = set()
    arrays: list[tuple[int, int]] = []  # (stamp of the scan, detections in it)
    errors: list[str] = []
    lock = threading.Lock()

    def on_array(sample: zenoh.Sample) -> None:
        try:
            message = types.deserialize(sample.payload.to_bytes(), DETECTION3D_ARRAY)
            stamp = message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec
        except Exception as exc:  # any undecodable sample fails the check
            with lock:
                errors.append(str(exc))
            return
        with lock:
            arrays.append((stamp, len(message.detections)))

    settings = ZenohSettings(mode="client", connect=(args.connect,), multicast_scouting=False)
    gid = os.urandom(GID_SIZE)
    started = time.monotonic()
    with open_session(settings) as session:
        subscriber = session.declare_subscriber(detections_key, on_array)
        publisher = session.declare_publisher(scan_key)
        deadline = time.monotonic() + 30
        while not publisher.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.05)  # until the bridge's subscription is seen, or nothing published counts
        for frame in range(args.scans):
            stamp_ns = time.time_ns()
            payload = bytes(types.store.serialize_cdr(laser_scan(types, stamp_ns, frame), LASER_SCAN))
            publisher.put(payload, attachment=encode_attachment(frame, stamp_ns, gid))
            sent_stamps.add(stamp_ns)
            time.sleep(0.1)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            with lock:
                if len(arrays) >= args.scans - 2:  # every scan from the third on
                    break
            time.sleep(0.1)
        publisher.undeclare()
        subscriber.undeclare()
    with lock:
        matched = sum(1 for stamp, _ in arrays if stamp in sent_stamps)
        print(
            f"published {args.scans} LaserScans on {scan_key} in {time.monotonic() - started:.1f} s; "
            f"received {len(arrays)} Detection3DArrays ({matched} stamped with a sent scan's stamp, "
            f"{sum(n for _, n in arrays)} detections), {len(errors)} decode errors"
        )
        if errors or matched < args.min_arrays:
            print(f"FAIL: wanted >= {args.min_arrays} Detection3DArrays matching sent scans, no errors")
            return 1
    print("OK")
    return 0


if __name__ == "__main__":
    sys.exit(main())
