"""How many robots one encoder + detector pair serves: N robots at 10 Hz, N growing until it breaks.

For each N of a ladder, N robots publish scans at ``--rate`` Hz from processes of this bench's own
(``--robot-processes``; real simulated scans, recorded once and replayed with fresh ids, seqs and
stamps, so the publishers cost little),
into one ``services.encoder`` and one ``services.detector`` process (``--workers`` inference threads,
each running up to ``--batch`` robots per model call), or one ``--from-scans`` detector, over Zenoh
on loopback. A step passes when, over its measured window:

* p99 scan→detection latency < ``--p99-limit-ms`` (100 ms), and
* at least ``--min-answered`` (95 %) of scans got their detections (the detector keeps only the newest
  tensor per robot, so overload shows up as unanswered scans, not as a queue), and
* no child process's resident memory (a ``--detectors N`` launch's processes each on its own) grew by
  more than ``--rss-growth-mb`` over the window.

The capacity is the largest passing N. Every step's figures are printed and written as JSON.

``--encode-on-robots`` measures a fleet server instead: the robots encode their own scans on board (a
Pi 5 running ``services.encoder`` next to its LiDAR, the design card's robot) and send stacked tensors,
so this host runs the detector alone. The robots then publish recorded tensors (the encoder's
output for the recorded scans, re-stamped per robot and tick) straight onto the tensor keys.

    python -m bench.fleet_capacity --ladder 10,20,30,40,50 --seconds 20 --workers 2
    python -m bench.fleet_capacity --ladder 10,15,20,25 --workers 1 --threads 2 --batch 8
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import multiprocessing
import os
import subprocess
import threading
import time
from dataclasses import asdict, dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from bench.harness import (
    add_detector_model_argument,
    proc_cpu_s,
    proc_status_mb,
    start_loopback_service,
    thread_cpu_s,
    tree_cpu_s,
    tree_rss_mb,
    tree_values,
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
ROBOTS_PER_PROCESS = 150  # robots one bench process sends for at 10 Hz with time to spare (0.2 ms a scan)


@dataclass
class FleetStep:
    robots: int
    scans_published: int = 0
    scans_answered: int = 0
    answered_share: float = 0.0
    latency_ms: dict[str, float] = field(default_factory=dict)
    rss_mb_start: dict[str, float] = field(default_factory=dict)
    rss_mb_end: dict[str, float] = field(default_factory=dict)
    # Memory by process (pid → MiB) at the window's start and end, which the growth limit applies to:
    # 16 processes that each warm up by 2 MB are not a leak, one that grows by 20 MB is.
    rss_mb_by_pid_start: dict[int, float] = field(default_factory=dict)
    rss_mb_by_pid_end: dict[int, float] = field(default_factory=dict)
    # How late a robot was sent after its slot in the tick, at worst (a bench limit, not triscan's).
    publish_lag_ms_max: float = 0.0
    window_s: float = 0.0  # the measured window's length, which the per-second figures divide by
    rss_mb_timeline: list[dict[str, float]] = field(default_factory=list)  # {"t_s", "encoder", "detector"}
    detector_dropped_stale: int = 0  # from the detector's own stats: tensors replaced before inference
    detector_mean_batch: float = 0.0  # tensors per model call over the whole step (--batch)
    # Robots each detector process answered for, fewest first: how evenly the processes share them.
    detector_robots_per_process: list[int] = field(default_factory=list)
    latency_ms_max_per_s: list[float] = field(default_factory=list)  # NaN: nothing answered that second
    # Cores each process kept busy over the window (CPU seconds / wall seconds); "bench" is this process
    # and its robot processes, the load generator, which the measured host's cores also carry.
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

    services = (detector_port, encoder_port) if runs_encoder(args) else (detector_port,)
    fleet: RobotProcesses | None = None
    try:
        fleet = RobotProcesses(robot_ids, frames, args, connect=(bench_port, *services))
        with open_session(ZenohSettings.loopback(bench_port)) as session:
            sub = session.declare_subscriber(wildcard_key(DETECTIONS), on_detections)
            stats_sub = session.declare_subscriber(service_stats_key("detector"), on_detector_stats)
            if runs_encoder(args):  # the encoder announces each robot's tensors to the detector
                wait_for_service(session, "detector")
            try:
                fleet.start()
            except RuntimeError as exc:  # a step the robots could not even start fails, the ladder goes on
                step.why_not = str(exc)
            else:
                published = _drive_fleet(step, fleet, args, children, received, lock)
            time.sleep(1.0)
            step.rss_mb_end = _rss_mb(children)
            step.rss_mb_by_pid_end = _rss_mb_by_pid(children)

            detector = summed_counters(detector_stats.values())
            step.detector_dropped_stale = int(detector.get("dropped_stale", 0))
            calls = int(detector.get("inference_calls", 0))
            step.detector_mean_batch = round(int(detector.get("processed", 0)) / calls, 2) if calls else 0.0
            served = (int(counters.get("robots", 0)) for counters in detector_stats.values())
            step.detector_robots_per_process = sorted(served)
            sub.undeclare()
            stats_sub.undeclare()
    finally:
        if fleet is not None:
            fleet.stop()
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
        *(("--gather-ms", str(args.gather_ms)) if args.gather_ms is not None else ()),
        *(("--model", str(args.model)) if args.model else ()),
        *(("--from-scans",) if args.from_scans else ()),
    )
    children = {}
    with_encoder = runs_encoder(args)
    if with_encoder:
        encoder_flags = model_facts(detector_model(args)).encoder_flags()  # the model's tensors
        children["encoder"] = start_loopback_service(
            "services.encoder", encoder_port, [bench_port, detector_port], *encoder_flags
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


def _rss_mb_by_pid(children: dict[str, subprocess.Popen[bytes]]) -> dict[int, float]:
    """Resident memory of each child process and of each of its descendants now, in MB."""
    memory: dict[int, float] = {}
    for child in children.values():
        memory.update(tree_values(child.pid, proc_status_mb))
    return {pid: round(mb, 1) for pid, mb in memory.items()}


def robot_processes(robots: int, requested: int | None) -> int:
    """How many processes publish the bench's robots: ``requested``, else one per
    :data:`ROBOTS_PER_PROCESS` robots, so that a many-core host's fleet is not held back by one Python
    process sending every scan."""
    return max(1, min(robots, requested or -(-robots // ROBOTS_PER_PROCESS)))


def _robot_process(
    connect: tuple[int, ...],
    robot_ids: list[str],
    first_index: int,
    fleet_size: int,
    frames: list[RecordedFrame],
    args: argparse.Namespace,
    pipe: Connection,
    stop: Any,
) -> None:
    """One process of the bench's robots: announce them, wait for their subscribers, report ready, then
    publish each robot's frames at ``--rate`` from the start time it is sent until ``stop`` is set.

    Robot ``first_index + i`` of the whole fleet publishes at its own slot of the tick, so the fleet's
    scans arrive spread over the period as independent robots' do, not in bursts per process. Sends back
    every (robot, seq, publish stamp) and each tick's (end stamp, how late its latest robot was sent).
    """
    encode_on_robots = args.encode_on_robots
    key = tensor_key if encode_on_robots else scan_key
    with open_session(ZenohSettings.loopback(None, connect)) as session:
        publishers = [session.declare_publisher(key(rid)) for rid in robot_ids]
        topic = TENSOR if encode_on_robots else SCAN
        tokens = [announce_source(session, rid, topic) for rid in robot_ids]
        for rid in robot_ids if encode_on_robots else robot_ids[:1]:
            wait_for_subscriber(session, key(rid))
        if not encode_on_robots:  # a robot's owner takes its scans once its token has settled
            time.sleep(announce_lead_s(SCAN))
        pipe.send("ready")
        start = pipe.recv()  # time.monotonic() is one clock for every process of the host
        if start is None:  # the step ends before it began (another robot process failed)
            return
        period = 1.0 / args.rate
        period_ns = round(1e9 * period)
        published: list[tuple[str, int, int]] = []
        lags: list[tuple[int, float]] = []
        tick = 0
        while not stop.is_set():
            due = start + tick * period
            late = 0.0
            base = frames[tick % len(frames)]
            seq = base.seq(tick)
            for offset, (rid, publisher) in enumerate(zip(robot_ids, publishers, strict=True)):
                slot = due + (first_index + offset) * period / fleet_size
                if (wait := slot - time.monotonic()) > 0:
                    time.sleep(wait)
                late = max(late, time.monotonic() - slot)
                stamp = time.time_ns()
                publisher.put(base.payload(rid, tick, stamp, period_ns))
                published.append((rid, seq, stamp))
            lags.append((time.time_ns(), late * 1e3))
            tick += 1
        for token in tokens:
            token.undeclare()
    pipe.send((published, lags))
    pipe.close()


class RobotProcesses:
    """The bench's robots, split over :func:`robot_processes` spawned processes of their own."""

    def __init__(
        self,
        robot_ids: list[str],
        frames: list[RecordedFrame],
        args: argparse.Namespace,
        connect: tuple[int, ...],
    ) -> None:
        context = multiprocessing.get_context("spawn")  # Zenoh's runtime threads do not survive a fork
        self.size = len(robot_ids)
        count = robot_processes(self.size, args.robot_processes)
        self.stop_event = context.Event()
        self.pipes: list[Connection] = []
        self.processes: list[Any] = []
        bounds = [round(i * self.size / count) for i in range(count + 1)]
        self._child_ends: list[Connection] = []
        for first, end in itertools.pairwise(bounds):
            here, there = context.Pipe()
            process = context.Process(
                target=_robot_process,
                args=(connect, robot_ids[first:end], first, self.size, frames, args, there, self.stop_event),
                daemon=True,
            )
            self.pipes.append(here)
            self._child_ends.append(there)
            self.processes.append(process)
        self.started = False
        self.start_s = 0.0

    def start(self, timeout_s: float = 60.0) -> None:
        """Start every process, wait until each has its subscribers, and give them one start time.

        Raises ``RuntimeError`` naming the first process that exited or was not ready by ``timeout_s``.
        """
        for process in self.processes:
            process.start()
        for end in self._child_ends:  # only the child holds it now: its exit reads as end-of-file here
            end.close()
        deadline = time.monotonic() + timeout_s
        for index, (pipe, process) in enumerate(zip(self.pipes, self.processes, strict=True)):
            try:
                ready = pipe.poll(max(0.0, deadline - time.monotonic())) and pipe.recv() == "ready"
            except EOFError:
                ready = False
            if not ready:
                process.join(timeout=1.0)
                why = f"exited with {process.exitcode}" if process.exitcode is not None else "was not ready"
                raise RuntimeError(
                    f"robot process {index} of {len(self.processes)} {why} within {timeout_s:.0f} s"
                )
        self.start_s = time.monotonic() + 0.05
        for pipe in self.pipes:
            pipe.send(self.start_s)
        self.started = True

    def pids(self) -> list[int]:
        return [p.pid for p in self.processes if p.pid is not None]

    def finish(self) -> tuple[list[tuple[str, int, int]], list[tuple[int, float]], int]:
        """Stop publishing; every process's (robot, seq, stamp) sends and per-tick lags, and how many
        processes sent no report (their robots' scans would be missing from the figures)."""
        self.stop_event.set()
        published: list[tuple[str, int, int]] = []
        lags: list[tuple[int, float]] = []
        missing = 0
        for pipe in self.pipes:
            try:
                sent, late = pipe.recv() if pipe.poll(30.0) else ([], [])
            except EOFError:
                sent, late = [], []
            if not sent:
                missing += 1
            published += sent
            lags += late
        return published, lags, missing

    def stop(self) -> None:
        """End every robot process, one waiting for its start time included."""
        self.stop_event.set()
        if not self.started:
            for pipe in self.pipes:
                try:
                    pipe.send(None)
                except (BrokenPipeError, OSError):
                    continue  # it has exited already
        for process in self.processes:
            if process.pid is not None:
                process.join(timeout=10.0)
                if process.is_alive():
                    process.kill()


def _drive_fleet(
    step: FleetStep,
    fleet: RobotProcesses,
    args: argparse.Namespace,
    children: dict[str, subprocess.Popen[bytes]],
    received: dict[tuple[str, int], int],
    lock: threading.Lock,
) -> dict[tuple[str, int], int]:
    """Let the robots publish through warm-up and the measured window, which starts once warm-up is
    over and every robot has been answered.

    Returns the publish stamp of each (robot, seq) sent in the measured window; records RSS, CPU and
    publish lag into ``step``.
    """
    robots = fleet.size
    next_rss_sample = 0.0
    measure_from: float | None = None  # once every robot has been answered and warm-up is over
    while measure_from is None or time.monotonic() - measure_from < args.seconds:
        time.sleep(0.05)
        if measure_from is None and time.monotonic() - fleet.start_s >= WARM_UP_S:
            with lock:
                answered = {rid for rid, _ in received}
            if len(answered) == robots:
                measure_from = time.monotonic()
                first_ns = time.time_ns()
                cpu_start = _cpu_s(children, fleet)  # CPU first: the window is timed from here
                threads_start = thread_cpu_s(children["detector"].pid)
                step.rss_mb_start = _rss_mb(children)
                step.rss_mb_by_pid_start = _rss_mb_by_pid(children)
            elif time.monotonic() - fleet.start_s > MAX_WARM_UP_S:
                step.why_not = f"only {len(answered)}/{robots} robots answered within {MAX_WARM_UP_S:.0f} s"
                break
        if measure_from is not None and (elapsed := time.monotonic() - measure_from) >= next_rss_sample:
            step.rss_mb_timeline.append({"t_s": round(elapsed, 1), **_rss_mb(children)})
            next_rss_sample += args.rss_every
    if measure_from is not None:
        window = time.monotonic() - measure_from
        end_ns = time.time_ns()
        step.window_s = round(window, 3)
        step.cpu_cores = {
            name: round((seconds - cpu_start[name]) / window, 3)
            for name, seconds in _cpu_s(children, fleet).items()
        }
        threads_end = thread_cpu_s(children["detector"].pid)
        used = {
            name: (seconds - threads_start.get(name, 0.0)) / window for name, seconds in threads_end.items()
        }
        step.detector_thread_cores = {
            name: round(cores, 3) for name, cores in sorted(used.items(), key=lambda item: -item[1])
        }
    sent, lags, missing = fleet.finish()
    if missing:
        step.why_not = f"{missing} robot process(es) sent no report: their robots are not counted"
    if measure_from is None:
        return {}
    step.publish_lag_ms_max = round(max((lag for at, lag in lags if first_ns <= at < end_ns), default=0.0), 2)
    return {(rid, seq): stamp for rid, seq, stamp in sent if first_ns <= stamp < end_ns}


def _cpu_s(children: dict[str, subprocess.Popen[bytes]], fleet: RobotProcesses) -> dict[str, float]:
    """CPU seconds used so far by each child (with its siblings: ``--detectors``) and by the bench: this
    process and its robot processes."""
    robots = sum(proc_cpu_s(pid) for pid in fleet.pids())
    return {**{n: tree_cpu_s(p.pid) for n, p in children.items()}, "bench": time.process_time() + robots}


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
    start, end = step.rss_mb_by_pid_start, step.rss_mb_by_pid_end
    growth = max((end[pid] - start[pid] for pid in end.keys() & start.keys()), default=0.0)
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
        "--gather-ms", type=float, default=None, help="detector --gather-ms (default: the detector's own)"
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
    parser.add_argument(
        "--robot-processes",
        type=int,
        default=None,
        help=f"processes publishing the robots (default: one per {ROBOTS_PER_PROCESS} robots)",
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
    if args.robot_processes is not None and args.robot_processes < 1:
        parser.error(f"--robot-processes must be >= 1, got {args.robot_processes}")
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
        "gather_ms": "detector default" if args.gather_ms is None else args.gather_ms,
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
