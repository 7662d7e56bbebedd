"""Host side of docker/check_compose.sh: subscribe to ``triscan/*/detections`` through the detector
container's published Zenoh port, decode every sample with the repository's own message code, and
fail unless every expected robot delivered detections.

    python docker/check_subscriber.py --connect tcp/127.0.0.1:7447 --duration 30 --robots 2
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import zenoh

from common.keys import ALL_DETECTIONS, parse_key
from common.messages import Detections, decode_message


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--connect", default="tcp/127.0.0.1:7447")
    parser.add_argument("--duration", type=float, default=30.0, help="seconds to listen")
    parser.add_argument("--robots", type=int, default=1, help="robots that must all deliver detections")
    parser.add_argument("--min-per-robot", type=int, default=1)
    args = parser.parse_args()

    config = zenoh.Config()
    config.insert_json5("mode", json.dumps("client"))
    config.insert_json5("connect/endpoints", json.dumps([args.connect]))
    config.insert_json5("scouting/multicast/enabled", "false")

    lock = threading.Lock()
    messages: Counter[str] = Counter()
    objects: Counter[str] = Counter()
    classes: Counter[str] = Counter()
    errors: list[str] = []
    latency_ms: list[float] = []
    first_at: list[float] = []

    def on_sample(sample: zenoh.Sample) -> None:
        try:
            robot_id = parse_key(str(sample.key_expr))[0]
            msg = decode_message(sample.payload.to_bytes(), Detections)
        except Exception as exc:  # any undecodable sample fails the check
            with lock:
                errors.append(f"{sample.key_expr}: {exc}")
            return
        with lock:
            if not first_at:
                first_at.append(time.monotonic())
            messages[robot_id] += 1
            objects[robot_id] += len(msg.detections)
            classes.update(d.class_name for d in msg.detections)
            latency_ms.append((time.time_ns() - msg.scan_stamp_ns) / 1e6)

    start = time.monotonic()
    with zenoh.open(config) as session:
        session.declare_subscriber(ALL_DETECTIONS, on_sample)
        time.sleep(args.duration)
    elapsed = time.monotonic() - start

    with lock:
        print(f"listened {elapsed:.1f} s on {args.connect} to {ALL_DETECTIONS}")
        if first_at:
            print(f"first detections after {first_at[0] - start:.1f} s")
        for robot_id in sorted(messages):
            rate = messages[robot_id] / elapsed
            print(
                f"  {robot_id}: {messages[robot_id]} Detections messages ({rate:.1f}/s), "
                f"{objects[robot_id]} objects"
            )
        if classes:
            print("  classes: " + ", ".join(f"{name} {n}" for name, n in classes.most_common()))
        if latency_ms:
            latency_ms.sort()
            print(f"  scan-to-host latency: median {latency_ms[len(latency_ms) // 2]:.0f} ms")
        print(
            f"TOTAL detections_messages={sum(messages.values())} objects={sum(objects.values())} "
            f"robots={len(messages)} errors={len(errors)}"
        )
        for err in errors[:5]:
            print("  error:", err)
        short = [r for r in messages if messages[r] < args.min_per_robot]
        if errors or len(messages) < args.robots or short:
            print(f"FAIL: wanted >= {args.min_per_robot} Detections from each of {args.robots} robot(s)")
            return 1
    print("OK")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
