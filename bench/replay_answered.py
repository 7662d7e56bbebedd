"""How many scans of a recorded drive get detections, and how fast: a bag replayed into real services.

A replayed bag is what a user's first session with triscan looks like (``triscan up --replay``): a
recorded robot, at recorded pace, into the encoder and detector processes over loopback Zenoh. This
measures it without the launcher and the viewer, so the figure is the pipeline's own:

* the bag: a 10 Hz ROS 2 bag of real simulated scans (`triscan sim-bag`, rosbags' MCAP writer), or
  any bag given with ``--bag``;
* the services: ``python -m services.encoder`` and ``python -m services.detector`` as children
  (:func:`bench.harness.start_loopback_service`), primed first with the bag replayed under another
  robot id until detections come back, so the measured pass starts with every link up and the model
  loaded;
* the replay: :func:`services.bag_replay.replay` at recorded pace (``--speed``), puts blocking under
  congestion; each scan's publish time is taken just before its put.

A scan is *answerable* from its robot's third scan on (the encoder's FIFO stacks three); it is
*answered* when detections with its seq come back. Reported: the share answered (goal ≥ 99 %),
scan-put → detections-received latency p50/p95/p99/max, the detector's own stage timings (p50), its
counters (``dropped_stale`` says whether it kept up), and the machine.

With ``--connect ENDPOINT`` nothing is started here: the bag goes to a detector already running there
(``services.detector --from-scans``, e.g. in an emulated arm64 container: ``docker/check_arm64.sh``).

    python -m bench.replay_answered --scans 300
    python -m bench.replay_answered --bag BAG --connect tcp/127.0.0.1:7460 --wait 600
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import numpy as np
import zenoh

from bench.harness import add_detector_model_argument, start_loopback_service
from bench.machine import MachineInfo, machine_info
from bench.report import latency_quantiles_ms, summed_counters, write_report
from common.keys import ALL_STATS, DETECTIONS, scan_key, wildcard_key
from common.messages import Detections, Scan, decode_message
from common.model_spec import default_model_path
from common.transport import ZenohSettings, open_session, payload_bytes, wait_for_subscriber
from services.bag_replay import ReplayConfig, replay
from services.launcher import free_tcp_ports, stop_processes
from services.runtime import STATS_PERIOD_S, wait_for_service
from services.simulator.defaults import SCAN_RATE_HZ

log = logging.getLogger("bench.replay_answered")

ROBOT: Final[str] = "bagbot"
PRIMING_ROBOT: Final[str] = "warmup"
GOAL_SHARE: Final[float] = 0.99
FIRST_ANSWERABLE_SEQ: Final[int] = 2  # scans 0 and 1 only fill the encoder's FIFO
DEFAULT_WAIT_S: Final[float] = 120.0  # for the services' subscriptions, then for the first detections
DRAIN_TIMEOUT_S: Final[float] = 10.0


@dataclass
class ReplayAnsweredReport:
    bag: str
    model: str
    speed: float
    scans_published: int = 0
    scans_answerable: int = 0
    scans_answered: int = 0
    answered_share: float = 0.0
    goal_share: float = GOAL_SHARE
    passed: bool = False
    latency_ms: dict[str, float] = field(default_factory=dict)  # p50, p95, p99, max
    detector_stage_ms_p50: dict[str, float] = field(default_factory=dict)  # encode, inference, nms
    objects_per_frame: float = 0.0
    detector_counters: dict[str, Any] = field(default_factory=dict)
    encoder_counters: dict[str, Any] = field(default_factory=dict)
    machine: MachineInfo = field(default_factory=machine_info)


class Answers:
    """Detections by (robot, seq) with their arrival time, and the services' latest counters."""

    def __init__(self) -> None:
        self.arrived_ns: dict[tuple[str, int], int] = {}
        self.objects: dict[tuple[str, int], int] = {}
        self.stage_ms: dict[tuple[str, int], tuple[float, float, float]] = {}
        self.stats: dict[str, dict[int, dict[str, Any]]] = {}  # service → pid → latest counters
        self.first_priming_answer = threading.Event()
        self._lock = threading.Lock()

    def on_detections(self, sample: Any) -> None:
        arrived_ns = time.time_ns()
        message = decode_message(payload_bytes(sample), Detections)
        with self._lock:
            self.arrived_ns[(message.robot_id, message.seq)] = arrived_ns
            self.objects[(message.robot_id, message.seq)] = len(message.detections)
            timings = message.timings
            self.stage_ms[(message.robot_id, message.seq)] = (
                timings.encode_ms,
                timings.inference_ms,
                timings.nms_ms,
            )
        if message.robot_id == PRIMING_ROBOT:
            self.first_priming_answer.set()

    def on_stats(self, sample: Any) -> None:
        body = json.loads(payload_bytes(sample))
        with self._lock:  # per process: a --detectors N launch publishes one body each
            self.stats.setdefault(body["service"], {})[int(body["pid"])] = body

    def answered(self, keys: list[tuple[str, int]]) -> list[tuple[str, int]]:
        with self._lock:
            return [key for key in keys if key in self.arrived_ns]


class Publishers:
    """Blocking publishers declared on first use, one a key: the replay decides which keys it puts on."""

    def __init__(self, session: Any) -> None:
        self._session = session
        self._publishers: dict[str, Any] = {}

    def put(self, key: str, payload: bytes) -> None:
        """Put under congestion control that blocks: nothing replayed is dropped on the way."""
        publisher = self._publishers.get(key)
        if publisher is None:
            publisher = self._publishers[key] = self._session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK
            )
        publisher.put(payload)

    def undeclare(self) -> None:
        """Close the publishers before the session, as the subscribers are."""
        for publisher in self._publishers.values():
            publisher.undeclare()


def _start_pipeline(
    model: Path | None, connect: str | None
) -> tuple[ZenohSettings, dict[str, subprocess.Popen[bytes]]]:
    """This process's Zenoh settings, and the encoder and detector as children unless ``connect`` is given."""
    bench_port, encoder_port, detector_port = free_tcp_ports(3)
    detector_args = ["--model", str(model)] if model is not None else []
    children = {} if connect else {
        "encoder": start_loopback_service("services.encoder", encoder_port, [bench_port, detector_port]),
        "detector": start_loopback_service(
            "services.detector", detector_port, [bench_port, encoder_port], *detector_args
        ),
    }  # fmt: skip
    settings = ZenohSettings.loopback(bench_port)
    if connect:
        settings = ZenohSettings(mode="peer", connect=(connect,), multicast_scouting=False)
    return settings, children


def _measure(
    bag: Path, speed: float, put: Callable[[str, bytes], None], answers: Answers
) -> tuple[dict[tuple[str, int], int], list[tuple[str, int]]]:
    """Replay ``bag`` once, timing each scan's put, then wait for the answers: (publish times, answerable)."""
    published_ns: dict[tuple[str, int], int] = {}

    def timed_put(key: str, payload: bytes) -> None:
        scan = decode_message(payload, Scan)
        published_ns[(scan.robot_id, scan.seq)] = time.time_ns()
        put(key, payload)

    replay(ReplayConfig(bags=(bag,), robot=ROBOT, speed=speed, progress=False), timed_put)
    answerable = [key for key in published_ns if key[1] >= FIRST_ANSWERABLE_SEQ]
    deadline = time.monotonic() + DRAIN_TIMEOUT_S
    while len(answers.answered(answerable)) < len(answerable) and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(1.5 * STATS_PERIOD_S)  # one more stats period, so the counters below include the last frames
    return published_ns, answerable


def run(
    bag: Path,
    speed: float = 1.0,
    model: Path | None = None,
    *,
    connect: str | None = None,
    wait_s: float = DEFAULT_WAIT_S,
) -> ReplayAnsweredReport:
    """Replay ``bag`` once (after priming) into fresh encoder and detector processes, or into the
    pipeline already running at ``connect``; see the module docstring."""
    model_name = "(the external detector's)" if connect else (model or default_model_path()).name
    report = ReplayAnsweredReport(bag=str(bag), model=model_name, speed=speed)
    settings, children = _start_pipeline(model, connect)
    answers = Answers()
    try:
        with open_session(settings) as session:
            subscribers = [
                session.declare_subscriber(wildcard_key(DETECTIONS), answers.on_detections),
                session.declare_subscriber(ALL_STATS, answers.on_stats),
            ]
            wait_for_subscriber(session, scan_key(ROBOT), wait_s)
            if not connect:  # it subscribes to the robot's tensors once the encoder announces them
                wait_for_service(session, "detector", wait_s)
            publishers = Publishers(session)
            _prime(bag, publishers.put, answers, wait_s)
            log.info("pipeline answered the priming replay: measuring %s at speed %g", bag, speed)
            published_ns, answerable = _measure(bag, speed, publishers.put, answers)
            for subscriber in subscribers:
                subscriber.undeclare()
            publishers.undeclare()
    finally:
        stop_processes(children, grace_s=20)
    _fill_report(report, answers, published_ns, answerable)
    return report


def _fill_report(
    report: ReplayAnsweredReport,
    answers: Answers,
    published_ns: dict[tuple[str, int], int],
    answerable: list[tuple[str, int]],
) -> None:
    """The share answered, latencies, stage timings and counters, from what came back."""
    answered = answers.answered(answerable)
    latencies_ms = [(answers.arrived_ns[key] - published_ns[key]) / 1e6 for key in answered]
    report.scans_published = len(published_ns)
    report.scans_answerable = len(answerable)
    report.scans_answered = len(answered)
    report.answered_share = round(len(answered) / max(1, len(answerable)), 4)
    report.passed = bool(answerable) and report.answered_share >= GOAL_SHARE
    if latencies_ms:
        report.latency_ms = latency_quantiles_ms(latencies_ms)
        report.objects_per_frame = round(sum(answers.objects[k] for k in answered) / len(answered), 2)
        stages = np.array([answers.stage_ms[k] for k in answered])
        report.detector_stage_ms_p50 = {
            name: round(float(np.median(stages[:, i])), 2)
            for i, name in enumerate(("encode", "inference", "nms"))
        }
    for service in ("detector", "encoder"):
        summed = summed_counters(answers.stats.get(service, {}).values())
        counters = {k: v for k, v in summed.items() if k not in ("pid", "stamp_ns")}
        setattr(report, f"{service}_counters", counters)
    report.machine.loadavg_end = [round(x, 2) for x in os.getloadavg()]


def _prime(bag: Path, put: Callable[[str, bytes], None], answers: Answers, timeout_s: float) -> None:
    """Replay ``bag`` as another robot, looping, until its first detections come back."""
    stop = threading.Event()
    deadline = time.monotonic() + timeout_s

    def priming_put(key: str, payload: bytes) -> None:
        put(key, payload)
        if answers.first_priming_answer.is_set() or time.monotonic() > deadline:
            stop.set()

    config = ReplayConfig(bags=(bag,), robot=PRIMING_ROBOT, speed=1.0, loop=True, progress=False)
    replay(config, priming_put, stop=stop)
    if not answers.first_priming_answer.is_set():
        raise TimeoutError(f"no detections within {timeout_s:.0f} s: is the pipeline up?")


def main(argv: list[str] | None = None) -> int:
    from services.sim_bag import write_sim_bag

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bag", type=Path, default=None, help="a bag to replay (default: simulate one)")
    parser.add_argument("--scans", type=int, default=300, help="scans of the simulated 10 Hz bag")
    parser.add_argument("--speed", type=float, default=1.0, help="replay speed (1: recorded pace)")
    add_detector_model_argument(parser)
    parser.add_argument(
        "--connect", default=None, metavar="ENDPOINT", help="an already running detector's Zenoh endpoint"
    )
    parser.add_argument(
        "--wait", type=float, default=DEFAULT_WAIT_S, help="seconds to wait for the pipeline, then its answer"
    )
    parser.add_argument("--out", type=Path, default=Path("bench/results/replay_answered.json"))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    with tempfile.TemporaryDirectory(prefix="triscan-replay-") as tmp:
        bag = args.bag or write_sim_bag(Path(tmp) / "sim_drive", args.scans)
        report = run(bag, args.speed, args.model, connect=args.connect, wait_s=args.wait)
        if args.bag is None:
            report.bag = f"simulated: {args.scans} scans at {SCAN_RATE_HZ:g} Hz (triscan sim-bag)"
    write_report(report, args.out)
    return 0 if report.passed else 1


if __name__ == "__main__":
    raise SystemExit(main())
