"""The tracker: CLEAR MOT of the live loop against the simulator's truth, and its cost a frame.

``live``: ``triscan up`` without a viewer (a moving robot in the simulator, the tracker among its
services) for ``--seconds``, and an outside Zenoh subscriber scoring ``triscan/*/tracks`` against
``triscan/*/truth`` with CLEAR MOT (:mod:`services.tracker.mot`, 0.75 m gate), furniture and people
apart. Targets: the objects the sensor sees in each scan (``visible``), each object one identity per
world (class and index); ignored: those there but unseen (a track on one is no false positive);
hypotheses: the reported tracks (``REPORTED_STATES``) of the same ``seq``; positions in the laser
frame of that scan (the truth's centre moved by the scan's ``lidar_pose``).

``live --record FILE`` also keeps the run's detections and truth (msgpack), and ``offline FILE`` runs
a fresh :class:`TrackerCore` over those detections in scan order and scores it the same way: one live
run, then every change to the tracker measured on the very same detections, in seconds.

``cost``: :meth:`TrackerCore.update` plus the message's encoding, for ``--objects`` still and moving
objects seen from a driving robot, one frame at a time; p50 against the 0.3 ms goal.

    python -m bench.tracking live --seconds 60 [--record runs/tracking_live.msgpack]
    python -m bench.tracking offline runs/tracking_live.msgpack
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

import msgpack
import numpy as np

from bench.machine import machine_info
from bench.report import latency_quantiles_ms, write_report
from common.keys import ALL_DETECTIONS, ALL_TRACKS, ALL_TRUTH, DETECTIONS, TRACKS, TRUTH, parse_key
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
from common.moving_people import add_motion_argument
from common.transport import ZenohSettings, open_session, payload_bytes
from services.launcher import free_tcp_ports
from services.tracker import add_tracker_arguments, rule_flags, rules_of, tracker_config
from services.tracker.core import REPORTED_STATES, TrackerConfig, TrackerCore
from services.tracker.mot import DEFAULT_GATE_M, GROUPS, ClearMot, group_of, hypotheses_of

log = logging.getLogger("bench.tracking")


Points = dict[Any, tuple[float, float]]


def truth_points(truth: GroundTruth) -> tuple[dict[str, Points], dict[str, Points]]:
    """(targets, ignored) by group: the objects the scan sees, and those there but unseen (occluded or
    hit by too few beams), in the laser frame of the scan, each named (world, class, index in class)."""
    lx, ly, lyaw = truth.lidar_pose
    c, s = math.cos(lyaw), math.sin(lyaw)
    seen: dict[int, int] = defaultdict(int)
    targets: dict[str, Points] = {group: {} for group in GROUPS}
    ignored: dict[str, Points] = {group: {} for group in GROUPS}
    for obj in truth.objects:
        index = seen[obj.class_id]
        seen[obj.class_id] += 1
        dx, dy = obj.center_xy[0] - lx, obj.center_xy[1] - ly
        where = targets if obj.visible else ignored
        where[group_of(obj.class_name)][(truth.scenario_id, obj.class_id, index)] = (
            c * dx + s * dy,
            -s * dx + c * dy,
        )
    return targets, ignored


def score_streams(
    truths: dict[str, dict[int, GroundTruth]], tracks: dict[str, list[Tracks]]
) -> dict[str, Any]:
    """CLEAR MOT by group, per robot and in total, on the scans that have both truth and tracks."""
    out: dict[str, Any] = {}
    for group in GROUPS:
        per_robot = {}
        total = ClearMot(DEFAULT_GATE_M)
        for robot, messages in sorted(tracks.items()):
            accumulator = ClearMot(DEFAULT_GATE_M)
            frames = 0
            for message in sorted(messages, key=lambda m: m.scan_stamp_ns):
                truth = truths.get(robot, {}).get(message.seq)
                if truth is None:
                    continue
                targets, ignored = (
                    {(robot, *k): v for k, v in points[group].items()} for points in truth_points(truth)
                )
                hypotheses = {(robot, k): v for k, v in hypotheses_of(message)[group].items()}
                accumulator.update(targets, hypotheses, ignored)
                total.update(targets, hypotheses, ignored)
                frames += 1
            per_robot[robot] = {"frames": frames, **accumulator.score.to_dict()}
        out[group] = {"total": total.score.to_dict(), "robots": per_robot}
    return out


def _switches_per_robot_minute(scores: dict[str, Any], tracks: dict[str, list[Tracks]]) -> float | None:
    minutes = sum(len(v) for v in tracks.values()) / 10.0 / 60.0  # 10 Hz scans
    switches = sum(scores[group]["total"]["id_switches"] for group in GROUPS)
    return round(switches / minutes, 2) if minutes else None


def live(
    seconds: float,
    robots: int,
    seed: int,
    record: Path | None = None,
    model: Path | None = None,
    rules: dict[str, float] | None = None,
    motion_confirm: bool = True,
) -> dict[str, Any]:
    """``rules``: tracker rules by :class:`TrackerConfig` field (:func:`services.tracker.given_rules`),
    passed to the loop's tracker; checked here first, so a bad value fails before anything starts.
    ``motion_confirm`` False runs the detector with ``--no-motion-confirm``."""
    rules = rules or {}
    config = TrackerConfig(**rules)  # type: ignore[arg-type]  # each rule is a number field
    (port,) = free_tcp_ports(1)
    truths: dict[str, dict[int, GroundTruth]] = defaultdict(dict)
    tracks: dict[str, list[Tracks]] = defaultdict(list)
    recorded: dict[str, list[bytes]] = {TRUTH: [], DETECTIONS: []}
    lock = threading.Lock()
    bad: list[str] = []

    def on_sample(sample: Any) -> None:
        try:
            robot, topic = parse_key(str(sample.key_expr))
            if topic == TRUTH:
                truth = decode_message(payload_bytes(sample), GroundTruth)
                with lock:
                    truths[robot][truth.seq] = truth
                    recorded[TRUTH].append(payload_bytes(sample))
            elif topic == DETECTIONS:
                with lock:
                    recorded[DETECTIONS].append(payload_bytes(sample))
            elif topic == TRACKS:
                message = decode_message(payload_bytes(sample), Tracks)
                with lock:
                    tracks[robot].append(message)
        except (MessageError, ValueError) as exc:
            bad.append(str(exc))

    command = [
        sys.executable, "-m", "services.cli", "up", "--viewer", "none", "--duration", str(seconds),
        "--robots", str(robots), "--seed", str(seed), "--listen", f"tcp/127.0.0.1:{port}", "--no-multicast",
        *(("--model", str(model)) if model is not None else ()),
        *(() if motion_confirm else ("--no-motion-confirm",)),
        *rule_flags(rules),
    ]  # fmt: skip
    with open_session(ZenohSettings.loopback(free_tcp_ports(1)[0], [port])) as session:
        up = subprocess.Popen(command)
        connected = False
        deadline = time.monotonic() + seconds + 120
        while up.poll() is None and time.monotonic() < deadline:
            if not connected:
                try:
                    keys = (ALL_TRUTH, ALL_TRACKS, *((ALL_DETECTIONS,) if record else ()))
                    subscribers = [session.declare_subscriber(k, on_sample) for k in keys]
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
        if record is not None:
            record.parent.mkdir(parents=True, exist_ok=True)
            record.write_bytes(msgpack.packb(recorded))
            log.info("recorded %d detections, %d truth messages: %s", len(recorded[DETECTIONS]),
                     len(recorded[TRUTH]), record)  # fmt: skip
    return {
        "command": " ".join(command[1:]),
        "seconds": seconds,
        "robots": robots,
        "seed": seed,
        "gate_m": DEFAULT_GATE_M,
        "tracker_config": dataclasses.asdict(config),
        "scored_states": list(REPORTED_STATES),
        "tracks_messages": sum(len(v) for v in tracks.values()),
        "undecodable": len(bad),
        "id_switches_per_robot_minute": _switches_per_robot_minute(scores, tracks),
        **scores,
        "launcher_exit": up.returncode,
        "machine": dataclasses.asdict(machine_info()),
    }


def offline(recording: Path, config: TrackerConfig | None = None) -> dict[str, Any]:
    """A fresh tracker over a recorded live run's detections (scan order), scored like the live run."""
    recorded = msgpack.unpackb(recording.read_bytes())
    truths: dict[str, dict[int, GroundTruth]] = defaultdict(dict)
    for payload in recorded[TRUTH]:
        truth = decode_message(payload, GroundTruth)
        truths[truth.robot_id][truth.seq] = truth
    detections = sorted(
        (decode_message(p, Detections) for p in recorded[DETECTIONS]), key=lambda d: d.scan_stamp_ns
    )
    core = TrackerCore(config)
    tracks: dict[str, list[Tracks]] = defaultdict(list)
    for message in detections:
        out = core.update(message)
        if out is not None:
            tracks[out.robot_id].append(out)
    scores = score_streams(dict(truths), dict(tracks))
    return {
        "recording": str(recording),
        "config": dataclasses.asdict(core.config),
        "id_switches_per_robot_minute": _switches_per_robot_minute(scores, tracks),
        **scores,
        "counters": core.counters.to_dict(),
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
    live_p.add_argument("--record", type=Path, default=None, help="keep the detections and truth here")
    live_p.add_argument("--model", type=Path, default=None, help="detector model (default: shipped)")
    add_motion_argument(live_p)
    add_tracker_arguments(live_p)
    offline_p = sub.add_parser("offline", help="a fresh tracker over a --record'ed run, scored the same way")
    offline_p.add_argument("recording", type=Path)
    add_tracker_arguments(offline_p)
    offline_p.add_argument("--out", type=Path, default=Path("bench/results/tracking_offline.json"))
    cost_p = sub.add_parser("cost", help="the tracker's time a frame")
    cost_p.add_argument("--objects", type=int, default=20)
    cost_p.add_argument("--frames", type=int, default=2000)
    cost_p.add_argument("--out", type=Path, default=Path("bench/results/tracking_cost.json"))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.mode == "live":
        report = live(
            args.seconds, args.robots, args.seed, args.record, args.model, rules_of(args), args.motion_confirm
        )
    elif args.mode == "offline":
        report = offline(args.recording, tracker_config(args))
    else:
        report = cost(args.objects, args.frames)
    write_report(report, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
