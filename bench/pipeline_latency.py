"""Scan published → detections received, across separate processes over Zenoh on loopback.

Three processes, as on a robot: this one simulates the robots (PyBullet, real scans) and publishes
their scans at ``--rate`` Hz; ``python -m services.encoder`` and ``python -m services.detector`` run
as children (or one ``--from-scans`` detector). Each scan is stamped when it is published; the latency
of a scan is the wall time at which its detections arrive back here minus that stamp (same clock, one
machine). The per-stage split comes from the timings the detector puts in every message (encode,
decode and validation of the tensor, queue = accepted → inference start, inference, NMS); the rest
(``transport``) is the two Zenoh hops with their serialisation and the encoder's own receive. Peak RSS
of the children is their ``VmHWM``.

The network's bare cost is measured in the same run, first: the same model and thread setting on the
same recorded tensors, one frame every 1/rate s in this process (``bare_ms``), so ``overhead_ms`` =
pipeline − bare is what the pipeline adds, free of a VM's drift between runs. A VM also drifts
within a run, between the bare phase and the pipeline phase, by as much as the goal; so
``added_per_frame_ms`` takes from each frame's latency that frame's own inference and NMS times: what
the pipeline added to the very frames it measured.

    python -m bench.pipeline_latency --duration 60                # 3 processes: sim, encoder, detector
    python -m bench.pipeline_latency --duration 60 --from-scans   # encoder + detector in one process
    python -m bench.pipeline_latency --duration 30 --trace trace.csv   # per-frame stage rows too
    python -m bench.pipeline_latency --cfg transport/unicast/lowlatency:true \
        --cfg transport/unicast/qos/enabled:false                    # any zenoh setting, every process
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import subprocess
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bench.harness import add_detector_model_argument, proc_status_mb, start_loopback_service, tree_cpu_s
from bench.machine import MachineInfo, machine_info
from bench.report import latency_quantiles_ms, write_report
from common.inference import model_facts
from common.keys import DETECTIONS, scan_key, wildcard_key
from common.messages import Detections, decode_message, encode_message
from common.model_spec import default_model_path
from common.transport import ZenohSettings, open_session, parse_cfg_entry, payload_bytes, wait_for_subscriber
from services.detector.core import default_intra_op_threads, default_workers
from services.launcher import free_tcp_ports, stop_processes
from services.runtime import wait_for_service
from services.simulator.fleet import SimulatedFleet
from services.simulator.sensors import DEFAULT_PROFILE, profile

ROOT = Path(__file__).resolve().parents[1]

log = logging.getLogger("bench.pipeline_latency")

WARM_UP_S = 3.0  # at least this, and until the first detections came back (peers connect on retry)
MAX_WARM_UP_S = 60.0
# The goals for ``overhead_ms["p50"]``: three processes, and --from-scans.
OVERHEAD_GOAL_P50_MS = 1.0
FROM_SCANS_OVERHEAD_GOAL_P50_MS = 0.5


@dataclass
class LatencyReport:
    """What the run measured; ``latency_ms`` quantiles are over scans published after warm-up."""

    mode: str
    model: str
    robots: int
    rate_hz: float
    duration_s: float
    scans_published: int = 0
    scans_answered: int = 0
    answered_share: float = 0.0
    latency_ms: dict[str, float] = field(default_factory=dict)  # p50, p95, p99, max, mean
    # encode, decode, queue, inference, nms, transport (the remainder): mean, p50, p99
    stage_ms_mean: dict[str, float] = field(default_factory=dict)
    stage_ms_p50: dict[str, float] = field(default_factory=dict)
    stage_ms_p99: dict[str, float] = field(default_factory=dict)
    bare_ms: dict[str, float] = field(default_factory=dict)  # the network alone, same model and threads
    overhead_ms: dict[str, float] = field(default_factory=dict)  # pipeline − bare: p50, p99
    # Per frame, its latency minus its own inference and NMS: what the pipeline added to that very
    # frame, free of the drift between the bare phase and the pipeline phase (p50, p99).
    added_per_frame_ms: dict[str, float] = field(default_factory=dict)
    zenoh_cfg: list[str] = field(default_factory=list)  # --cfg entries every process ran with
    bare_threads: int | None = None  # ONNX Runtime threads of the baseline and the detector (None: all)
    peak_rss_mb: dict[str, float] = field(default_factory=dict)  # per child process
    sensor: str = DEFAULT_PROFILE  # the simulated LiDAR profile (services.simulator.sensors)
    # CPU seconds per second of the publishing window, per child (its sibling processes included)
    cpu_cores: dict[str, float] = field(default_factory=dict)
    machine: MachineInfo = field(default_factory=machine_info)


def run(
    robots: int,
    rate_hz: float,
    duration_s: float,
    from_scans: bool,
    threads: int | None,
    model: Path | None = None,
    trace: Path | None = None,
    bare_frames: int = 300,
    zenoh_cfg: tuple[tuple[str, str], ...] = (),
    sensor: str = DEFAULT_PROFILE,
) -> LatencyReport:
    """Start the services, publish the simulated robots' scans through them, and time every answer.

    ``sensor`` is the simulated LiDAR's profile, scanning at ``rate_hz``; the encoder stacks its scans
    at the model's trained period, as the launcher starts it."""
    report = LatencyReport(
        "from-scans (2 processes)" if from_scans else "3 processes",
        (model or default_model_path()).name,
        robots,
        rate_hz,
        duration_s,
        sensor=sensor,
    )
    model = model or default_model_path()
    report.zenoh_cfg = [f"{key}:{value}" for key, value in zenoh_cfg]
    # The detector's own default when --threads is not given, so the baseline times the same setting.
    report.bare_threads = threads or default_intra_op_threads(default_workers(), from_scans)
    report.bare_ms = bare_frame_latency(model, report.bare_threads, rate_hz, bare_frames)
    bench_port, encoder_port, detector_port = free_tcp_ports(3)
    children = _start_services(from_scans, threads, model, bench_port, encoder_port, detector_port, zenoh_cfg)
    received: dict[tuple[str, int], tuple[int, Detections]] = {}
    lock = threading.Lock()

    def on_detections(sample: Any) -> None:
        arrived_ns = time.time_ns()
        message = decode_message(payload_bytes(sample), Detections)
        with lock:
            received[(message.robot_id, message.seq)] = (arrived_ns, message)

    try:
        with (
            open_session(dataclasses.replace(ZenohSettings.loopback(bench_port), cfg=zenoh_cfg)) as session,
            SimulatedFleet(robots, rate_hz=rate_hz, spec=profile(sensor)) as fleet,
        ):
            sub = session.declare_subscriber(wildcard_key(DETECTIONS), on_detections)
            publishers = {rid: session.declare_publisher(scan_key(rid)) for rid in fleet.robot_ids}
            wait_for_subscriber(session, scan_key(fleet.robot_ids[0]))
            if not from_scans:  # it subscribes to a robot's tensors once the encoder announces the robot
                wait_for_service(session, "detector")
            cpu_before = {name: tree_cpu_s(p.pid) for name, p in children.items()}
            started = time.monotonic()
            published = _publish_scans(fleet, publishers, rate_hz, duration_s, received)
            elapsed = time.monotonic() - started
            report.cpu_cores = {
                name: round((tree_cpu_s(p.pid) - cpu_before[name]) / elapsed, 4)
                for name, p in children.items()
            }
            time.sleep(1.0)  # let the last detections arrive
            report.peak_rss_mb = {
                name: round(proc_status_mb(p.pid, "VmHWM"), 1) for name, p in children.items()
            }
            sub.undeclare()
    finally:
        stop_processes(children, grace_s=20)
    latencies, stages = _summarise(report, published, received)
    if trace is not None:
        write_trace(trace, latencies, stages)
    return report


def _start_services(
    from_scans: bool,
    threads: int | None,
    model: Path,
    bench_port: int,
    encoder_port: int,
    detector_port: int,
    zenoh_cfg: tuple[tuple[str, str], ...] = (),
) -> dict[str, subprocess.Popen[bytes]]:
    """The encoder and the detector as two processes, or one ``--from-scans`` detector.

    The detector is given ``model`` explicitly, so the pipeline runs the very file the bare baseline
    timed. ``zenoh_cfg`` entries (config path, JSON5 value) go to every process as ``--cfg``.
    """
    cfg = ZenohSettings(cfg=zenoh_cfg).to_cli()  # the --cfg flags, written as every service parses them
    detector_args = [*(["--threads", str(threads)] if threads else []), "--model", str(model), *cfg]
    encoder_args = [*model_facts(model).encoder_flags(), *cfg]  # its tensors as the launcher has them
    if from_scans:
        return {
            "detector": start_loopback_service(
                "services.detector", detector_port, [bench_port], "--from-scans", *detector_args
            )
        }
    return {
        "encoder": start_loopback_service(
            "services.encoder", encoder_port, [bench_port, detector_port], *encoder_args
        ),
        "detector": start_loopback_service(
            "services.detector", detector_port, [bench_port, encoder_port], *detector_args
        ),
    }


NO_SHM = (("transport/shared_memory/enabled", "false"),)  # zenoh copies every payload through the socket


def _publish_scans(
    fleet: SimulatedFleet,
    publishers: dict[str, Any],
    rate_hz: float,
    duration_s: float,
    received: dict[tuple[str, int], tuple[int, Detections]],
) -> dict[tuple[str, int], int]:
    """Publish the fleet's scans at ``rate_hz`` until ``duration_s`` after warm-up; their stamps.

    Only scans published once the pipeline has answered and ``WARM_UP_S`` has passed are returned,
    keyed by (robot, seq): they are the ones the report measures.
    """
    published: dict[tuple[str, int], int] = {}
    period = 1.0 / rate_hz
    start = time.monotonic()
    measure_from: float | None = None  # set once the pipeline has answered and warmed up
    tick = 0
    while measure_from is None or time.monotonic() - measure_from < duration_s:
        due = start + tick * period
        if (now := time.monotonic()) < due:
            time.sleep(due - now)
        if measure_from is None and received and time.monotonic() - start >= WARM_UP_S:
            measure_from = time.monotonic()
        if measure_from is None and time.monotonic() - start > MAX_WARM_UP_S:
            raise TimeoutError(f"no detections within {MAX_WARM_UP_S:.0f} s: is the pipeline up?")
        for scan, _truth in fleet.step(time.time_ns()):
            scan = scan.model_copy(update={"stamp_ns": time.time_ns()})
            publishers[scan.robot_id].put(encode_message(scan))
            if measure_from is not None:
                published[(scan.robot_id, scan.seq)] = scan.stamp_ns
        tick += 1
    return published


def _summarise(
    report: LatencyReport,
    published: dict[tuple[str, int], int],
    received: dict[tuple[str, int], tuple[int, Detections]],
) -> tuple[list[float], dict[str, list[float]]]:
    """Latency quantiles and the per-stage split of every answered scan, into ``report``; returns the
    per-frame values (total, and each stage) for ``--trace``."""
    latencies: list[float] = []
    stages: dict[str, list[float]] = {name: [] for name in STAGES}
    for key, stamp in published.items():
        if key not in received:
            continue
        arrived, message = received[key]
        total = (arrived - stamp) / 1e6
        latencies.append(total)
        t = message.timings
        measured = {
            "encode": t.encode_ms,
            "decode": t.decode_ms,
            "queue": t.queue_ms,
            "inference": t.inference_ms,
            "nms": t.nms_ms,
        }
        measured["transport"] = total - sum(measured.values())
        for name, value in measured.items():
            stages[name].append(value)
    report.scans_published, report.scans_answered = len(published), len(latencies)
    report.answered_share = round(len(latencies) / max(1, len(published)), 4)
    if latencies:
        report.latency_ms = {**latency_quantiles_ms(latencies), "mean": round(float(np.mean(latencies)), 2)}
        report.stage_ms_mean = {k: round(float(np.mean(v)), 3) for k, v in stages.items()}
        report.stage_ms_p50 = {k: round(float(np.percentile(v, 50)), 3) for k, v in stages.items()}
        report.stage_ms_p99 = {k: round(float(np.percentile(v, 99)), 3) for k, v in stages.items()}
        report.overhead_ms = {
            q: round(report.latency_ms[q] - report.bare_ms[q], 3)
            for q in ("p50", "p99")
            if q in report.bare_ms
        }
        added = np.array(latencies) - np.array(stages["inference"]) - np.array(stages["nms"])
        report.added_per_frame_ms = {
            q: round(float(np.percentile(added, p)), 3) for q, p in (("p50", 50), ("p99", 99))
        }
    return latencies, stages


STAGES = ("encode", "decode", "queue", "inference", "nms", "transport")


def bare_frame_latency(model: Path, threads: int | None, rate_hz: float, frames: int) -> dict[str, float]:
    """The network alone: ``OnnxDetector.detect`` on recorded tensors, one frame every 1/rate s.

    Paced like the pipeline (not back to back), so the ONNX Runtime thread pool idles between frames
    exactly as it does in the detector; the difference to the pipeline is what the pipeline adds.
    """
    from bench.harness import timed_us
    from common.inference import OnnxDetector
    from services.encoder.core import EncoderCore
    from services.sim_bag import recorded_scans

    encoder = EncoderCore.for_model(model_facts(model))  # the tensors the pipeline's encoder makes
    tensors = [t.tensor for scan in recorded_scans(60) if (t := encoder.push(scan)) is not None]
    detector = OnnxDetector(model, intra_op_threads=threads)
    detector.warmup()

    times_us = timed_us(lambda i: detector.detect(tensors[i % len(tensors)]), frames, 1.0 / rate_hz)
    return {**latency_quantiles_ms([t / 1e3 for t in times_us]), "frames": frames}


def write_trace(path: Path, latencies: list[float], stages: dict[str, list[float]]) -> None:
    """One row per answered scan: total and each stage in ms, for anyone to slice further."""
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = ["total_ms," + ",".join(f"{name}_ms" for name in STAGES)]
    for i, total in enumerate(latencies):
        rows.append(f"{total:.3f}," + ",".join(f"{stages[name][i]:.3f}" for name in STAGES))
    path.write_text("\n".join(rows) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=60.0, help="measured seconds (after warm-up)")
    parser.add_argument("--robots", type=int, default=1)
    parser.add_argument("--rate", type=float, default=10.0, help="scans per second per robot")
    parser.add_argument("--from-scans", action="store_true", help="encoder + detector in one process")
    parser.add_argument("--threads", type=int, default=None, help="detector ONNX Runtime threads")
    add_detector_model_argument(parser)
    parser.add_argument("--out", type=Path, default=None, help="write the report as JSON here")
    parser.add_argument("--trace", type=Path, default=None, help="also write per-frame stage times (CSV)")
    parser.add_argument("--bare-frames", type=int, default=300, help="frames of the bare-network baseline")
    parser.add_argument(
        "--no-shm", action="store_true", help="zenoh shared memory off in every process (the comparison)"
    )
    parser.add_argument(
        "--cfg",
        action="append",
        default=[],
        type=parse_cfg_entry,
        metavar="KEY:VALUE",
        help="a zenoh config entry for every process, this one included (as the services' --cfg)",
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    report = run(
        args.robots,
        args.rate,
        args.duration,
        args.from_scans,
        args.threads,
        args.model,
        trace=args.trace,
        bare_frames=args.bare_frames,
        zenoh_cfg=(*(NO_SHM if args.no_shm else ()), *args.cfg),
    )
    write_report(report, args.out)
    if "p50" in report.overhead_ms:
        goal = FROM_SCANS_OVERHEAD_GOAL_P50_MS if args.from_scans else OVERHEAD_GOAL_P50_MS
        log.info("%s: overhead p50 %+.2f ms against the bare network (goal <= %+.1f ms); added per frame "
                 "p50 %.2f ms", report.mode, report.overhead_ms["p50"], goal,
                 report.added_per_frame_ms["p50"])  # fmt: skip
    return 0 if report.scans_answered else 1


if __name__ == "__main__":
    raise SystemExit(main())
