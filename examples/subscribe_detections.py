"""Print every triscan detection: what another app (yours) needs, with only zenoh and msgpack.

    pip install eclipse-zenoh msgpack
    python examples/subscribe_detections.py --connect tcp/127.0.0.1:7447   # `triscan up` listens there

Each payload on ``triscan/<robot_id>/detections`` is a msgpack map; the README's "Detection message"
table lists every field. Positions are metres in the robot's laser frame (REP-103: x forward, y left).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import threading

import msgpack
import zenoh

log = logging.getLogger("subscribe_detections")


def describe(message: dict) -> str:
    objects = ", ".join(
        f"{d['class_name']} {d['score']:.2f} at ({d['x_m']:+.2f}, {d['y_m']:+.2f}) m {d['bearing_deg']:+.0f}°"
        for d in message["detections"]
    )
    latency_ms = (message["stamp_ns"] - message["scan_stamp_ns"]) / 1e6
    return f"{message['robot_id']} #{message['seq']} ({latency_ms:.1f} ms after the scan): {objects or '-'}"


def main(config: zenoh.Config, key: str, count: int, stop: threading.Event) -> None:
    received = 0

    def on_detections(sample: zenoh.Sample) -> None:
        nonlocal received
        if stop.is_set():
            return
        message = msgpack.unpackb(sample.payload.to_bytes())
        if not isinstance(message, dict) or message.get("kind") != "detections":
            log.warning("skipping %s: not a detections message", sample.key_expr)
            return
        if message.get("schema_version") not in (1, 2):  # 2 adds the robot's pose (`odom`), nothing else
            log.warning(
                "skipping %s: schema %s, this reader knows 1 and 2",
                sample.key_expr,
                message.get("schema_version"),
            )
            return
        log.info("%s", describe(message))
        received += 1
        if count and received >= count:
            stop.set()

    with zenoh.open(config) as session:  # closing the session lets the interpreter exit
        session.declare_subscriber(key, on_detections)
        log.info("listening on %s (Ctrl-C to stop)", key)
        stop.wait()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    parser.add_argument(
        "--connect", "-e", action="append", default=[], help="zenoh endpoint(s) to connect to"
    )
    parser.add_argument("--discover", action="store_true", help="also find zenoh peers by multicast scouting")
    parser.add_argument(
        "--zenoh-config", "-c", default=None, help="zenoh JSON5 config file (e.g. the secure mode's)"
    )
    parser.add_argument("--key", default="triscan/*/detections", help="one robot: triscan/<id>/detections")
    parser.add_argument("--count", type=int, default=0, help="exit after this many messages (0: never)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    config = zenoh.Config.from_file(args.zenoh_config) if args.zenoh_config else zenoh.Config()
    # Only the peers it is pointed at, as every triscan process (common/transport.py): multicast
    # scouting would join any Zenoh network on the LAN.
    config.insert_json5("scouting/multicast/enabled", json.dumps(args.discover))
    if args.connect:
        config.insert_json5("connect/endpoints", json.dumps(args.connect))
    with contextlib.suppress(KeyboardInterrupt):
        main(config, args.key, args.count, threading.Event())
