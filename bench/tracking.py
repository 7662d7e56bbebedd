"""The tracker: CLEAR MOT of the live loop against the simulator's truth, and its cost a frame.

``live``: ``triscan up`` without a viewer (a moving robot in the simulator, the tracker among its
services) for ``--seconds``, and an outside Zenoh subscriber scoring ``triscan/*/tracks`` against
``triscan/*/truth`` with CLEAR MOT (:mod:`services.tracker.mot`, 0.75 m gate). Targets: the objects
the sensor sees in each scan (``visible``), each object one identity per world (class and index);
hypotheses: the confirmed and coasting tracks of the same ``seq``; positions in the laser frame of
that scan (the truth's centre moved by the scan's ``lidar_pose``).

``cost``: :meth:`TrackerCore.update` plus the message's encoding, for ``--objects`` still and moving
objects seen from a driving robot, one frame at a time; p50 against the 0.3 ms goal.

    python -m bench.tracking live --seconds 60
    python -m bench.tracking cost --objects 20
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from bench.machine import machine_info
from bench.report import latency_quantiles_ms, write_report
from common.keys import ALL_TRACKS, ALL_TRUTH, TRACKS, TRUTH, parse_key
from common.messages import (
    Detection,
    Detections,
    GroundTruth,
    MessageError,
    Odometry,
    StageTimings,
    Tracks,
    decode_message,
    encode_message,
)
from common.model_spec import CLASS_NAMES
from common.transport import ZenohSettings, open_session, payload_bytes
from services.launcher import free_tcp_ports
from services.tracker.core import TrackerCore
from services.tracker.mot import DEFAULT_GATE_M, ClearMot

log = logging.getLogger("bench.tracking")

SCORED_STATES = ("confirmed", "coasting")


def targets_of(truth: GroundTruth) -> dict[tuple[int, int, int], tuple[float, float]]:
    """Visible objects in the laser frame of the scan, each named (world, class, index within class)."""
    lx, ly, lyaw = truth.lidar_pose
    c, s = math.cos(lyaw), math.sin(lyaw)
    seen: dict[int, int] = defaultdict(int)
    out = {}
    for obj in truth.objects:
        index = seen[obj.class_id]
        seen[obj.class_id] += 1
        if obj.visible:
            dx, dy = obj.center_xy[0] - lx, obj.center_xy[1] - ly
            out[(truth.scenario_id, obj.class_id, index)] = (c * dx + s * dy, -s * dx + c * dy)
    return out


def hypotheses_of(tracks: Tracks) -> dict[int, tuple[float, float]]:
    return {t.track_id: (t.x_m, t.y_m) for t in tracks.tracks if t.state in SCORED_STATES}


def score_streams(
    truths: dict[str, dict[int, GroundTruth]], tracks: dict[str, list[Tracks]]
) -> dict[str, Any]:
    """CLEAR MOT per robot and in total, on the scans that have both truth and tracks."""
    per_robot = {}
    total = ClearMot(DEFAULT_GATE_M)
    for robot, messages in sorted(tracks.items()):
        accumulator = ClearMot(DEFAULT_GATE_M)
        frames = 0
        for message in sorted(messages, key=lambda m: m.scan_stamp_ns):
            truth = truths.get(robot, {}).get(message.seq)
            if truth is None:
                continue
            targets = {(robot, *k): v for k, v in targets_of(truth).items()}
            hypotheses = {(robot, k): v for k, v in hypotheses_of(message).items()}
            accumulator.update(targets, hypotheses)
            total.update(targets, hypotheses)
            frames += 1
        per_robot[robot] = {"frames": frames, **accumulator.score.to_dict()}
    return {"total": total.score.to_dict(), "robots": per_robot}


def live(seconds: float, robots: int, seed: int) -> dict[str, Any]:
    (port,) = free_tcp_ports(1)
    truths: dict[str, dict[int, GroundTruth]] = defaultdict(dict)
    tracks: dict[str, list[Tracks]] = defaultdict(list)
    lock = threading.Lock()
    bad: list[str] = []

    def on_sample(sample: Any) -> None:
        try:
            robot, topic = parse_key(str(sample.key_expr))
            if topic == TRUTH:
                truth = decode_message(payload_bytes(sample), GroundTruth)
                with lock:
                    truths[robot][truth.seq] = truth
            elif topic == TRACKS:
                message = decode_message(payload_bytes(sample), Tracks)
                with lock:
                    tracks[robot].append(message)
        except (MessageError, ValueError) as exc:
            bad.append(str(exc))

    command = [
        sys.executable, "-m", "services.cli", "up", "--viewer", "none", "--duration", str(seconds),
        "--robots", str(robots), "--seed", str(seed), "--listen", f"tcp/127.0.0.1:{port}", "--no-multicast",
    ]  # fmt: skip
    with open_session(ZenohSettings.loopback(free_tcp_ports(1)[0], [port])) as session:
        up = subprocess.Popen(command)
        connected = False
        deadline = time.monotonic() + seconds + 120
        while up.poll() is None and time.monotonic() < deadline:
            if not connected:
                try:
                    subscribers = [session.declare_subscriber(k, on_sample) for k in (ALL_TRUTH, ALL_TRACKS)]
                    connected = True
                except Exception:  # pragma: no cover - declaring only fails while the session starts
                    time.sleep(0.5)
            time.sleep(0.5)
        if up.poll() is None:
            up.terminate()
        up.wait(30)
        for subscriber in subscribers if connected else []:
            subscriber.undeclare()
    with lock:
        scores = score_streams(dict(truths), dict(tracks))
    minutes = sum(len(v) for v in tracks.values()) / 10.0 / 60.0  # 10 Hz scans
    total = scores["total"]
    return {
        "command": " ".join(command[1:]),
        "seconds": seconds,
        "robots": robots,
        "seed": seed,
        "gate_m": DEFAULT_GATE_M,
        "scored_states": list(SCORED_STATES),
        "tracks_messages": sum(len(v) for v in tracks.values()),
        "undecodable": len(bad),
        "id_switches_per_robot_minute": round(total["id_switches"] / minutes, 2) if minutes else None,
        **scores,
        "launcher_exit": up.returncode,
        "machine": dataclasses.asdict(machine_info()),
    }


def detection_at(x: float, y: float, class_id: int) -> Detection:
    """A detection of a point object at (x, y) in the laser frame."""
    r, b = math.hypot(x, y), math.degrees(math.atan2(y, x))
    return Detection(
        class_id=class_id, class_name=CLASS_NAMES[class_id], score=0.9, box_px=(0.0, 0.0, 1.0, 1.0),
        bearing_deg=b, bearing_min_deg=b, bearing_max_deg=b, range_min_m=r, range_max_m=r, x_m=x, y_m=y,
    )  # fmt: skip


def cost(objects: int, frames: int) -> dict[str, Any]:
    """Per-frame time of the tracker's update and encoding, detections built beforehand."""
    rng = np.random.default_rng(0)
    start = rng.uniform(-3.0, 3.0, (objects, 2))
    velocity = np.where(np.arange(objects)[:, None] % 5 == 4, rng.uniform(-1.0, 1.0, (objects, 2)), 0.0)
    messages = []
    for k in range(frames):
        yaw, x0, y0 = 0.02 * k, 0.03 * k, 0.0
        c, s = math.cos(yaw), math.sin(yaw)
        world = start + velocity * k * 0.1 + rng.normal(0.0, 0.03, (objects, 2))
        dx, dy = world[:, 0] - x0, world[:, 1] - y0
        detections = [
            detection_at(float(c * a + s * b), float(-s * a + c * b), i % len(CLASS_NAMES))
            for i, (a, b) in enumerate(zip(dx, dy, strict=True))
        ]
        messages.append(
            Detections(
                robot_id="bench",
                seq=k,
                stamp_ns=k,
                detections=detections,
                model_id="bench",
                timings=StageTimings(encode_ms=0.0, inference_ms=0.0, nms_ms=0.0),
                scan_stamp_ns=k * 100_000_000,
                odom=Odometry(x_m=x0, y_m=y0, yaw_rad=yaw, stamp_ns=k),
            )
        )
    core = TrackerCore()
    times_ms = []
    for message in messages:
        started = time.perf_counter_ns()
        tracks = core.update(message)
        assert tracks is not None
        encode_message(tracks)
        times_ms.append((time.perf_counter_ns() - started) / 1e6)
    warm = times_ms[10:]  # the first frames open the tracks
    return {
        "objects": objects,
        "frames": frames,
        "frame_ms": latency_quantiles_ms(warm),
        "goal_p50_ms": 0.3,
        "core_share_at_10hz_percent": round(float(np.median(warm)) * 10 / 1000 * 100, 3),
        "tracks_at_end": len(tracks.tracks),
        "machine": dataclasses.asdict(machine_info()),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="mode", required=True)
    live_p = sub.add_parser("live", help="score the live loop against the simulator's truth")
    live_p.add_argument("--seconds", type=float, default=60.0)
    live_p.add_argument("--robots", type=int, default=1)
    live_p.add_argument("--seed", type=int, default=1)
    live_p.add_argument("--out", type=Path, default=Path("bench/results/tracking_live.json"))
    cost_p = sub.add_parser("cost", help="the tracker's time a frame")
    cost_p.add_argument("--objects", type=int, default=20)
    cost_p.add_argument("--frames", type=int, default=2000)
    cost_p.add_argument("--out", type=Path, default=Path("bench/results/tracking_cost.json"))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.mode == "live":
        report = live(args.seconds, args.robots, args.seed)
    else:
        report = cost(args.objects, args.frames)
    write_report(report, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
