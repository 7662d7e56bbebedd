"""How many robots one encoder + detector pair serves: N robots at 10 Hz, N growing until it breaks.

For each N of a ladder, this process publishes N robots' scans at ``--rate`` Hz (real simulated scans,
recorded once and replayed with fresh ids, seqs and stamps, so the publisher costs almost nothing),
into one ``services.encoder`` and one ``services.detector`` process (``--workers`` inference threads,
each running up to ``--batch`` robots per model call), or one ``--from-scans`` detector, over Zenoh
on loopback. A step passes when, over its measured window:

* p99 scan→detection latency < ``--p99-limit-ms`` (100 ms), and
* at least ``--min-answered`` (95 %) of scans got their detections (the detector keeps only the newest
  tensor per robot, so overload shows up as unanswered scans, not as a queue), and
* the children's resident memory did not grow by more than ``--rss-growth-mb`` over the window.

The capacity is the largest passing N. Every step's figures are printed and written as JSON.

``--encode-on-robots`` measures a fleet server instead: the robots encode their own scans on board (a
Pi 5 running ``services.encoder`` next to its LiDAR, the design card's robot) and send stacked tensors,
so this host runs the detector alone. This process then publishes recorded tensors (the encoder's
output for the recorded scans, re-stamped per robot and tick) straight onto the tensor keys.

    python -m bench.fleet_capacity --ladder 10,20,30,40,50 --seconds 20 --workers 2
    python -m bench.fleet_capacity --ladder 10,15,20,25 --workers 1 --threads 2 --batch 8
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from bench.harness import (
    add_detector_model_argument,
    start_loopback_service,
    thread_cpu_s,
    tree_cpu_s,
    tree_rss_mb,
)
from bench.machine import machine_info
from bench.report import latency_quantiles_ms, summed_counters, write_report
from common.inference import model_facts
from common.keys import DETECTIONS, SCAN, TENSOR, scan_key, service_stats_key, tensor_key, wildcard_key
from common.messages import Scan, StackedTensor, encode_message
from common.transport import ZenohSettings, open_session, payload_bytes, wait_for_subscriber
from services.detector.batch_cap import detector_model_and_batch
from services.encoder.core import EncoderCore
from services.launcher import free_tcp_ports, stop_processes
from services.runtime import announce_lead_s, announce_source, wait_for_service
from services.sim_bag import recorded_scans

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

ROOT = Path(__file__).resolve().parents[1]
WARM_UP_S = 3.0  # at least this, and until every robot has been answered (peers connect on retry)
MAX_WARM_UP_S = 60.0
RECORDED_SCANS = 200


@dataclass
class FleetStep:
    robots: int
    scans_published: int = 0
    scans_answered: int = 0
    answered_share: float = 0.0
    latency_ms: dict[str, float] = field(default_factory=dict)
    rss_mb_start: dict[str, float] = field(default_factory=dict)
    rss_mb_end: dict[str, float] = field(default_factory=dict)
    publish_lag_ms_max: float = 0.0  # how late this process itself published (a bench limit, not triscan's)
    rss_mb_timeline: list[dict[str, float]] = field(default_factory=list)  # {"t_s", "encoder", "detector"}
    detector_dropped_stale: int = 0  # from the detector's own stats: tensors replaced before inference
    detector_mean_batch: float = 0.0  # tensors per model call over the whole step (--batch)
    latency_ms_max_per_s: list[float] = field(default_factory=list)  # NaN: nothing answered that second
    # Cores each process kept busy over the window (CPU seconds / wall seconds); "bench" is this process,
    # the load generator, which the machine's two cores also carry.
    cpu_cores: dict[str, float] = field(default_factory=dict)
    # The detector's cores by thread name: its inference threads, Zenoh's threads, "python" (main and
    # Zenoh's callback thread).
    detector_thread_cores: dict[str, float] = field(default_factory=dict)
    passed: bool = False
    why_not: str = ""


def detector_model(args: argparse.Namespace) -> Path:
    """The model file the detector of these flags runs, by the detector's own rule."""
    return detector_model_and_batch(args.model, None if args.detector_defaults else args.batch)[0]


def runs_encoder(args: argparse.Namespace) -> bool:
    """Whether the fleet has an encoder process: not when the detector encodes (``--from-scans``) or
    the robots do (``--encode-on-robots``)."""
    return not (args.from_scans or args.encode_on_robots)


class RecordedFrame:
    """A recorded frame ready to be re-sent by any robot at any tick.

    The frame is validated and serialised once; each send only swaps its id, seq and stamps in the
    unpacked body and packs it again, so the robots' stand-in costs the host a few microseconds a scan
    and the CPU the bench measures is the services'.
    """

    def __init__(self, frame: Scan | StackedTensor) -> None:
        self.is_tensor = isinstance(frame, StackedTensor)
        self._body: dict[str, Any] = msgpack.unpackb(encode_message(frame), raw=False)

    def seq(self, tick: int) -> int:
        """The seq of this frame sent at ``tick``, which its detections come back with. A tensor's seq is
        its newest scan's, and its three scans' seqs are consecutive: ``tick`` shifted by 2, so none is
        negative."""
        return tick + 2 if self.is_tensor else tick

    def payload(self, robot_id: str, tick: int, stamp_ns: int, period_ns: int) -> bytes:
        """What robot ``robot_id`` sends at ``tick``: this frame with its id, seq and stamps (a tensor's
        three scans ``period_ns`` apart, the newest at ``stamp_ns``)."""
        seq = self.seq(tick)
        body = {**self._body, "robot_id": robot_id, "seq": seq, "stamp_ns": stamp_ns}
        if self.is_tensor:
            body["scan_seqs"] = [seq - 2, seq - 1, seq]
            body["scan_stamps_ns"] = [stamp_ns - 2 * period_ns, stamp_ns - period_ns, stamp_ns]
        return msgpack.packb(body, use_bin_type=True)


def frames_to_send(scans: list[Scan], args: argparse.Namespace) -> list[RecordedFrame]:
    """What the robots publish: the recorded ``scans``, or with ``--encode-on-robots`` the tensors the
    encoder makes of them for the detector's model (as it reads scans: :meth:`EncoderCore.for_model`)."""
    if not args.encode_on_robots:
        return [RecordedFrame(scan) for scan in scans]
    encoder = EncoderCore.for_model(model_facts(detector_model(args)))
    return [RecordedFrame(tensor) for scan in scans if (tensor := encoder.push(scan)) is not None]


def run_step(robots: int, frames: list[RecordedFrame], args: argparse.Namespace) -> FleetStep:
    """One step of the ladder: start the services, drive ``robots`` robots through them, judge it."""
    step = FleetStep(robots)
    bench_port, encoder_port, detector_port = free_tcp_ports(3)
    children = _start_services(args, bench_port, encoder_port, detector_port)
    robot_ids = [f"fleet{i:03d}" for i in range(robots)]
    published: dict[tuple[str, int], int] = {}
    received: dict[tuple[str, int], int] = {}
    lock = threading.Lock()

    def on_detections(sample: Any) -> None:
        arrived = time.time_ns()
        # Only the id and seq: the services' tests check the messages, and a full validation here would
        # put the bench's own CPU into the measured host's.
        body = msgpack.unpackb(payload_bytes(sample), raw=False)
        with lock:
            received[(body["robot_id"], body["seq"])] = arrived

    detector_stats: dict[int, dict[str, Any]] = {}  # pid → its latest counters (--detectors N: several)

    def on_detector_stats(sample: Any) -> None:
        counters = json.loads(payload_bytes(sample))
        detector_stats[int(counters["pid"])] = counters

    try:
        with open_session(ZenohSettings.loopback(bench_port)) as session:
            sub = session.declare_subscriber(wildcard_key(DETECTIONS), on_detections)
            stats_sub = session.declare_subscriber(service_stats_key("detector"), on_detector_stats)
            key = tensor_key if args.encode_on_robots else scan_key
            publishers = [session.declare_publisher(key(rid)) for rid in robot_ids]
            # Each process sharing the fleet subscribes to the announced robots it serves.
            topic = TENSOR if args.encode_on_robots else SCAN
            sources = [announce_source(session, rid, topic) for rid in robot_ids]
            if args.encode_on_robots:
                for rid in robot_ids:
                    wait_for_subscriber(session, tensor_key(rid))
            else:
                wait_for_subscriber(session, scan_key(robot_ids[0]))
            if runs_encoder(args):  # the encoder announces each robot's tensors to the detector
                wait_for_service(session, "detector")
            if not args.encode_on_robots:  # a robot's owner takes its scans once its token has settled
                time.sleep(announce_lead_s(SCAN))
            published = _publish_fleet(step, robot_ids, publishers, frames, args, children, received, lock)
            time.sleep(1.0)
            step.rss_mb_end = _rss_mb(children)

            detector = summed_counters(detector_stats.values())
            step.detector_dropped_stale = int(detector.get("dropped_stale", 0))
            calls = int(detector.get("inference_calls", 0))
            step.detector_mean_batch = round(int(detector.get("processed", 0)) / calls, 2) if calls else 0.0
            sub.undeclare()
            stats_sub.undeclare()
            for source in sources:
                source.undeclare()
    finally:
        stop_processes(children, grace_s=30)
    _judge_step(step, published, received, args)
    return step


def _start_services(
    args: argparse.Namespace, bench_port: int, encoder_port: int, detector_port: int
) -> dict[str, subprocess.Popen[bytes]]:
    """The encoder (unless ``--from-scans`` or ``--encode-on-robots``) and the detector, each connected to
    this bench process."""
    tuning = (
        ()
        if args.detector_defaults
        else (
            *("--workers", str(args.workers), "--batch", str(args.batch)),
            *(("--threads", str(args.threads)) if args.threads else ()),
        )
    )
    detector_args = (
        *tuning,
        *(("--detectors", str(args.detectors)) if args.detectors else ()),
        *(("--no-spin",) if args.no_spin else ()),
        *(("--model", str(args.model)) if args.model else ()),
        *(("--from-scans",) if args.from_scans else ()),
    )
    children = {}
    with_encoder = runs_encoder(args)
    if with_encoder:
        children["encoder"] = start_loopback_service(
            "services.encoder", encoder_port, [bench_port, detector_port]
        )
    children["detector"] = start_loopback_service(
        "services.detector",
        detector_port,
        [bench_port, encoder_port] if with_encoder else [bench_port],
        *detector_args,
    )
    return children


def _rss_mb(children: dict[str, subprocess.Popen[bytes]]) -> dict[str, float]:
    """Resident memory of each child process (with its siblings: ``--detectors``) now, in MB."""
    return {n: round(tree_rss_mb(p.pid), 1) for n, p in children.items()}


def _publish_fleet(
    step: FleetStep,
    robot_ids: list[str],
    publishers: list[Any],
    frames: list[RecordedFrame],
    args: argparse.Namespace,
    children: dict[str, subprocess.Popen[bytes]],
    received: dict[tuple[str, int], int],
    lock: threading.Lock,
) -> dict[tuple[str, int], int]:
    """Publish every robot's frames at ``--rate`` through warm-up and the measured window.

    Returns the publish stamp of each (robot, seq) sent in the measured window, which starts once
    warm-up is over and every robot has been answered; records RSS, CPU and publish lag into ``step``.
    """
    robots = len(robot_ids)
    published: dict[tuple[str, int], int] = {}
    next_rss_sample = 0.0
    period = 1.0 / args.rate
    period_ns = round(1e9 * period)
    start = time.monotonic()
    tick = 0
    measure_from: float | None = None  # once every robot has been answered and warm-up is over
    while measure_from is None or time.monotonic() - measure_from < args.seconds:
        due = start + tick * period
        if (now := time.monotonic()) < due:
            time.sleep(due - now)
        if measure_from is None and time.monotonic() - start >= WARM_UP_S:
            with lock:
                answered = {rid for rid, _ in received}
            if len(answered) == robots:
                measure_from = time.monotonic()
                step.rss_mb_start = _rss_mb(children)
                cpu_start = _cpu_s(children)
                threads_start = thread_cpu_s(children["detector"].pid)
            elif time.monotonic() - start > MAX_WARM_UP_S:
                step.why_not = f"only {len(answered)}/{robots} robots answered within {MAX_WARM_UP_S:.0f} s"
                break
        if measure_from is not None:
            step.publish_lag_ms_max = max(step.publish_lag_ms_max, (time.monotonic() - due) * 1e3)
            if (elapsed := time.monotonic() - measure_from) >= next_rss_sample:
                step.rss_mb_timeline.append({"t_s": round(elapsed, 1), **_rss_mb(children)})
                next_rss_sample += args.rss_every
        measuring = measure_from is not None
        base = frames[tick % len(frames)]
        seq = base.seq(tick)
        # Robots publish spread over the tick, as independent robots would, not in one burst.
        for index, (rid, publisher) in enumerate(zip(robot_ids, publishers, strict=True)):
            stamp = time.time_ns()
            publisher.put(base.payload(rid, tick, stamp, period_ns))
            if measuring:
                published[(rid, seq)] = stamp
            slot = due + (index + 1) * period / robots
            if (wait := slot - time.monotonic()) > 0:
                time.sleep(wait)
        tick += 1
    if measure_from is not None:
        window = time.monotonic() - measure_from
        step.cpu_cores = {
            name: round((seconds - cpu_start[name]) / window, 3) for name, seconds in _cpu_s(children).items()
        }
        threads_end = thread_cpu_s(children["detector"].pid)
        used = {
            name: (seconds - threads_start.get(name, 0.0)) / window for name, seconds in threads_end.items()
        }
        step.detector_thread_cores = {
            name: round(cores, 3) for name, cores in sorted(used.items(), key=lambda item: -item[1])
        }
    return published


def _cpu_s(children: dict[str, subprocess.Popen[bytes]]) -> dict[str, float]:
    """CPU seconds used so far by each child (with its siblings: ``--detectors``) and by this process."""
    return {**{n: tree_cpu_s(p.pid) for n, p in children.items()}, "bench": time.process_time()}


def _worst_latency_per_second(
    published: dict[tuple[str, int], int], received: dict[tuple[str, int], int]
) -> list[float]:
    """Worst latency per second of the window (NaN: nothing answered that second).

    A few stalls and a saturated detector look alike in a p99 but not here.
    """
    first = min(published.values())
    worst: dict[int, float] = {}
    for key, stamp in published.items():
        if key in received:
            second = (stamp - first) // 1_000_000_000
            worst[second] = max(worst.get(second, 0.0), (received[key] - stamp) / 1e6)
    return [round(worst.get(s, float("nan")), 1) for s in range(max(worst) + 1)] if worst else []


def _judge_step(
    step: FleetStep,
    published: dict[tuple[str, int], int],
    received: dict[tuple[str, int], int],
    args: argparse.Namespace,
) -> None:
    """Fill in the step's latency and answer figures, and whether it passed (and if not, why)."""
    latencies = np.array([(received[k] - t) / 1e6 for k, t in published.items() if k in received])
    if published:
        step.latency_ms_max_per_s = _worst_latency_per_second(published, received)
    step.scans_published, step.scans_answered = len(published), len(latencies)
    step.answered_share = round(len(latencies) / max(1, len(published)), 4)
    if len(latencies):
        step.latency_ms = latency_quantiles_ms(latencies)
    growth = max(step.rss_mb_end[n] - step.rss_mb_start.get(n, step.rss_mb_end[n]) for n in step.rss_mb_end)
    reasons = [step.why_not] if step.why_not else []
    if not len(latencies) or step.latency_ms["p99"] >= args.p99_limit_ms:
        reasons.append(f"p99 {step.latency_ms.get('p99', float('inf'))} ms >= {args.p99_limit_ms}")
    if step.answered_share < args.min_answered:
        reasons.append(f"answered {step.answered_share:.3f} < {args.min_answered}")
    if growth > args.rss_growth_mb:
        reasons.append(f"RSS grew {growth:.1f} MB")
    step.passed, step.why_not = not reasons, "; ".join(reasons)


def build_parser() -> argparse.ArgumentParser:
    """The bench's flags; :func:`parse_step_args` parses and checks them."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ladder", default="5,10,20,30,40,50,60", help="robot counts to try, ascending")
    parser.add_argument("--seconds", type=float, default=20.0, help="measured seconds per step")
    parser.add_argument("--rate", type=float, default=10.0, help="scans per second per robot")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="detector inference threads")
    add_detector_model_argument(parser)
    parser.add_argument(
        "--batch", type=int, default=1, help="detector --batch (above 1: the default model's -batch file)"
    )
    parser.add_argument("--threads", type=int, default=None, help="detector --threads per worker")
    parser.add_argument(
        "--detector-defaults",
        action="store_true",
        help="pass no --workers/--batch/--threads: measure the detector as it configures itself",
    )
    parser.add_argument(
        "--detectors",
        type=int,
        default=None,
        help="detector processes sharing the fleet (default: the detector's own, one per core)",
    )
    parser.add_argument(
        "--no-spin", action="store_true", help="the detector's ONNX Runtime threads sleep instead of spinning"
    )
    parser.add_argument(
        "--from-scans",
        action="store_true",
        help="detector --from-scans processes (each encodes its robots' scans) instead of encoder + detector",
    )
    parser.add_argument(
        "--encode-on-robots",
        action="store_true",
        help="the robots send tensors (their own encoder on board): this host runs the detector alone",
    )
    parser.add_argument("--p99-limit-ms", type=float, default=100.0)
    parser.add_argument("--min-answered", type=float, default=0.95)
    parser.add_argument("--rss-growth-mb", type=float, default=20.0)
    parser.add_argument("--rss-every", type=float, default=5.0, help="seconds between RSS samples")
    parser.add_argument("--keep-going", action="store_true", help="try every step even after one fails")
    parser.add_argument("--out", type=Path, default=Path("bench/results/fleet_capacity.json"))
    return parser


def parse_step_args(argv: list[str] | None = None) -> argparse.Namespace:
    """This bench's flags, parsed and checked together, before any process starts."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.from_scans and args.encode_on_robots:
        parser.error("--from-scans and --encode-on-robots are two different fleets: choose one")
    try:
        detector_model(args)
    except ValueError as exc:  # a --batch the model cannot take: the detector would refuse it too
        parser.error(str(exc))
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_step_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    ladder = [int(n) for n in args.ladder.split(",")]
    frames = frames_to_send(recorded_scans(RECORDED_SCANS, seed=7), args)
    steps: list[FleetStep] = []
    for robots in ladder:
        step = run_step(robots, frames, args)
        steps.append(step)
        log.info(
            "%3d robots: p99 %s ms, answered %.1f %%, RSS %s → %s MB: %s",
            robots,
            step.latency_ms.get("p99"),
            100 * step.answered_share,
            step.rss_mb_start,
            step.rss_mb_end,
            "pass" if step.passed else f"FAIL ({step.why_not})",
        )
        if not step.passed and not args.keep_going:
            break
    # Capacity counts only up to the first failing step: near saturation a later, larger step can pass
    # by luck (--keep-going shows those too, as largest_passing_robots).
    first_failure = next((i for i, s in enumerate(steps) if not s.passed), len(steps))
    capacity = max((s.robots for s in steps[:first_failure]), default=0)
    report = {
        "capacity_robots": capacity,
        "largest_passing_robots": max((s.robots for s in steps if s.passed), default=0),
        "criteria": {
            "p99_limit_ms": args.p99_limit_ms,
            "min_answered": args.min_answered,
            "rss_growth_mb": args.rss_growth_mb,
        },
        "rate_hz": args.rate,
        "workers": "detector default" if args.detector_defaults else args.workers,
        "batch": "detector default" if args.detector_defaults else args.batch,
        "threads": "detector default" if args.detector_defaults else args.threads,
        "detectors": args.detectors or "detector default",
        "from_scans": args.from_scans,
        "encode_on_robots": args.encode_on_robots,
        "model": detector_model(args).name,
        "seconds_per_step": args.seconds,
        "machine": asdict(machine_info()),
        "steps": [asdict(s) for s in steps],
    }
    write_report(report, args.out)
    log.info("capacity: %d robots at %.0f Hz", capacity, args.rate)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
