"""The ROS 2 bridge's per-message cost, both directions, on real simulated scans and real detections.

* **scan**: one CDR ``sensor_msgs/LaserScan`` sample (key, payload, rmw_zenoh attachment) through
  ``BridgeCore.handle_scan`` to the triscan ``Scan`` payload it publishes: key and attachment checks,
  CDR read, validation, msgpack. Scans are the simulator's (LDS-01, 360 beams), serialised by rosbags
  as a ROS driver would publish them; the 1,440-beam row resamples them to an RPLIDAR-like density.
* **detections**: one triscan ``Detections`` payload through ``BridgeCore.handle_detections`` to its
  ``Detection3DArray`` and ``MarkerArray`` payloads with attachments. The detections are the shipped
  model's on the same scans (the frame with the most objects is used, and also a 20-object frame made
  by repeating them, for a crowded room).
* **rosbags_reference**: the same work done by rosbags' generic (de)serialiser, for comparison; the
  bridge runs the hand-written paths (byte-equal to rosbags, see ``tests/test_ros2_bridge.py``).

Timing is wall clock per message (``perf_counter_ns``), after a warm-up, one message at a time. Goal of
the issue: p50 ≤ 0.3 ms for each direction. Nothing here asserts a time.

    python -m bench.ros2_bridge                      # → bench/results/ros2_bridge.json
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any, Final

import numpy as np

from bench.harness import recorded_scans
from bench.machine import machine_info
from bench.report import latency_quantiles_ms, write_report
from common.encoding import ScanStacker
from common.inference import OnnxDetector
from common.keys import detections_key
from common.messages import Detections, Scan, StageTimings, encode_message
from common.model_spec import default_model_path
from services.ros2_bridge.core import BridgeConfig, BridgeCore
from services.ros2_bridge.laser_scan import fields_of_message, to_triscan_scan
from services.ros2_bridge.rmw_zenoh import encode_attachment
from services.ros2_bridge.ros_messages import ReferenceDetectionMessages
from services.ros2_bridge.ros_types import LASER_SCAN, dds_type_name, ros_types

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

ROBOT: Final[str] = "robot1"
GOAL_MS: Final[float] = 0.3
DEFAULT_OUT: Final[Path] = Path(__file__).resolve().parent / "results" / "ros2_bridge.json"


def time_per_call(fn: Callable[[int], Any], count: int, warmup: int = 200) -> dict[str, float]:
    for i in range(warmup):
        fn(i)
    samples = np.empty(count, dtype=np.float64)
    for i in range(count):
        started = time.perf_counter_ns()
        fn(i)
        samples[i] = (time.perf_counter_ns() - started) / 1e6
    return {**latency_quantiles_ms(samples), "mean_us": round(float(samples.mean()) * 1000, 1)}


def laser_scan_payloads(scans: list[Scan], beams: int) -> list[bytes]:
    """The scans as a ROS driver publishes them (rosbags' serialiser), resampled to ``beams`` beams."""
    t = ros_types("jazzy").store.types
    payloads = []
    for scan in scans:
        ranges = (
            np.repeat(scan.ranges, beams // scan.ranges.size) if beams != scan.ranges.size else scan.ranges
        )
        increment = scan.angle_increment * scan.ranges.size / beams
        sec, nanosec = divmod(scan.stamp_ns, 1_000_000_000)
        message = t[LASER_SCAN](
            header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
                                            frame_id=scan.frame_id),
            angle_min=scan.angle_min, angle_max=scan.angle_min + increment * (beams - 1),
            angle_increment=increment,
            time_increment=0.0, scan_time=0.1, range_min=scan.range_min, range_max=scan.range_max,
            ranges=ranges.astype(np.float32), intensities=np.zeros(0, np.float32),
        )  # fmt: skip
        payloads.append(bytes(ros_types("jazzy").store.serialize_cdr(message, LASER_SCAN)))
    return payloads


def model_detections(scans: list[Scan]) -> list[Any]:
    """The shipped model's detections on consecutive scans; the frame with the most objects."""
    detector = OnnxDetector(default_model_path(), intra_op_threads=1)
    stacker = ScanStacker("zero")
    best: list[Any] = []
    for scan in scans:
        tensor = stacker.push_scan(
            scan.ranges, scan.angle_min, scan.angle_increment, scan.range_min, scan.range_max
        )
        if tensor is not None:
            detections, _ = detector.detect(tensor)
            best = detections if len(detections) > len(best) else best
    return best


def run(count: int, scans_n: int) -> dict[str, Any]:
    machine = machine_info()
    scans = recorded_scans(scans_n, seed=3)
    key = f"0/{ROBOT}/scan/{dds_type_name(LASER_SCAN)}/{ros_types('jazzy').type_hash(LASER_SCAN)}"
    attachment = encode_attachment(0, time.time_ns(), bytes(16))
    results: dict[str, Any] = {"scan": {}, "detections": {}, "rosbags_reference": {}}
    for beams in (360, 1440):
        payloads = laser_scan_payloads(scans, beams)
        core = BridgeCore(BridgeConfig(namespace=f"/{ROBOT}"))
        results["scan"][f"{beams}_beams"] = time_per_call(
            lambda i, p=payloads, c=core: c.handle_scan(key, p[i % len(p)], attachment), count
        )
        assert core.counters.rejected_scans == {}, core.counters.rejected_scans
        store = ros_types("jazzy")
        results["rosbags_reference"][f"scan_{beams}_beams"] = time_per_call(
            lambda i, p=payloads, s=store: encode_message(
                to_triscan_scan(fields_of_message(s.deserialize(p[i % len(p)], LASER_SCAN)), ROBOT, i)
            ),
            count,
        )
    found = model_detections(scans)
    log.info("the model's busiest frame has %d objects", len(found))
    core = BridgeCore(BridgeConfig(namespace=f"/{ROBOT}"))
    core.handle_scan(key, laser_scan_payloads(scans[:1], 360)[0], attachment)
    reference = ReferenceDetectionMessages(ros_types("jazzy"))
    crowd = (found * (20 // max(len(found), 1) + 1))[:20] if found else []
    for label, detections in ((f"{len(found)}_objects_model", found), ("20_objects", crowd)):
        message = Detections(
            robot_id=ROBOT, seq=2, stamp_ns=scans[2].stamp_ns, detections=detections,
            timings=StageTimings(encode_ms=0.0, inference_ms=0.0, nms_ms=0.0), model_id="bench",
            scan_stamp_ns=scans[2].stamp_ns,
        )  # fmt: skip
        payload = encode_message(message)
        results["detections"][label] = time_per_call(
            lambda i, p=payload: core.handle_detections(detections_key(ROBOT), p), count
        )
        results["rosbags_reference"][f"detections_{label}"] = time_per_call(
            lambda i, d=detections, s=message.scan_stamp_ns: (
                reference.detection_array(d, s, "laser"),
                reference.marker_array(d, s, "laser"),
            ),
            count,
        )
    machine.loadavg_end = [round(x, 2) for x in os.getloadavg()]
    p50 = {
        "scan_360_beams": results["scan"]["360_beams"]["p50"],
        f"detections_{len(found)}_objects": results["detections"][f"{len(found)}_objects_model"]["p50"],
        "detections_20_objects": results["detections"]["20_objects"]["p50"],
    }
    return {
        "goal_p50_ms": GOAL_MS,
        "goal_met": all(v <= GOAL_MS for v in p50.values()),
        "p50_ms": p50,
        "messages_timed": count,
        "results_ms": results,
        "machine": asdict(machine),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=3000, help="messages timed per case")
    parser.add_argument("--scans", type=int, default=60, help="simulated scans to cycle through")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    write_report(run(args.count, args.scans), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
