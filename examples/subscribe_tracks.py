"""Print every triscan track: stable ids and velocities for your app, with only zenoh and msgpack.

    pip install eclipse-zenoh msgpack
    python examples/subscribe_tracks.py --connect tcp/127.0.0.1:7447   # `triscan up` listens there

Each payload on ``triscan/<robot_id>/tracks`` is a msgpack map; the README's tracks table lists every
field. ``track_id`` names one object for as long as the tracker follows it and is never reused;
``vx_mps``/``vy_mps`` are in the message's ``frame`` ("odom" with the robot's odometry, else "laser").
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import threading

import msgpack
import zenoh

log = logging.getLogger("subscribe_tracks")

KNOWN_SCHEMAS = (2,)  # tracks first appeared in schema 2


def describe(message: dict, states: tuple[str, ...] = ("confirmed", "coasting")) -> str:
    tracks = ", ".join(
        f"#{t['track_id']} {t['class_name']} {t['state']} at ({t['x_m']:+.2f}, {t['y_m']:+.2f}) m "
        f"moving ({t['vx_mps']:+.2f}, {t['vy_mps']:+.2f}) m/s"
        for t in message["tracks"]
        if t["state"] in states
    )
    return f"{message['robot_id']} #{message['seq']} [{message['frame']}]: {tracks or '-'}"


def main(config: zenoh.Config, key: str, count: int, stop: threading.Event) -> None:
    received = 0

    def on_tracks(sample: zenoh.Sample) -> None:
        nonlocal received
        if stop.is_set():
            return
        message = msgpack.unpackb(sample.payload.to_bytes())
        if not isinstance(message, dict) or message.get("kind") != "tracks":
            log.warning("skipping %s: not a tracks message", sample.key_expr)
            return
        if message.get("schema_version") not in KNOWN_SCHEMAS:
            log.warning("skipping %s: schema %s, this reader knows %s", sample.key_expr,
                        message.get("schema_version"), KNOWN_SCHEMAS)  # fmt: skip
            return
        log.info("%s", describe(message))
        received += 1
        if count and received >= count:
            stop.set()

    with zenoh.open(config) as session:  # closing the session lets the interpreter exit
        session.declare_subscriber(key, on_tracks)
        log.info("listening on %s (Ctrl-C to stop)", key)
        stop.wait()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--connect", "-e", action="append", default=[], help="zenoh endpoint(s) to connect to"
    )
    parser.add_argument(
        "--zenoh-config", "-c", default=None, help="zenoh JSON5 config file (e.g. the secure mode's)"
    )
    parser.add_argument("--key", default="triscan/*/tracks", help="one robot: triscan/<id>/tracks")
    parser.add_argument("--count", type=int, default=0, help="exit after this many messages (0: never)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    config = zenoh.Config.from_file(args.zenoh_config) if args.zenoh_config else zenoh.Config()
    if args.connect:
        config.insert_json5("connect/endpoints", json.dumps(args.connect))
        config.insert_json5("scouting/multicast/enabled", "false")
    with contextlib.suppress(KeyboardInterrupt):
        main(config, args.key, args.count, threading.Event())
