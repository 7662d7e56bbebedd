"""Kill -9 a service mid-stream under ``triscan up``; how long until fresh detections flow again?

Starts ``triscan up --headless`` (four processes), waits until detections flow, then for each of the
encoder, the detector and the simulator in turn: finds its pid from its own stats messages, sends
SIGKILL, and measures the time until the first detections of a scan *published after the kill*
arrive (the launcher restarts the service; the restarted one must start a fresh stream). Meanwhile
every tensor on the wire is checked: its three scans must be consecutive and in time order, so a
restarted stream never mixes old and new frames. The goal is recovery within 2 s.

    python -m bench.fault_recovery
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bench.machine import MachineInfo, machine_info
from bench.report import write_report
from common.keys import ALL_STATS, DETECTIONS, TENSOR, wildcard_key
from common.messages import Detections, StackedTensor, decode_message
from common.transport import ZenohSettings, open_session, payload_bytes
from services.launcher import free_tcp_ports

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

ROOT = Path(__file__).resolve().parents[1]
VICTIMS = ("encoder", "detector", "simulator")
GOAL_S = 2.0


@dataclass
class Recovery:
    service: str
    killed_pid: int
    new_pid: int | None = None
    recovery_s: float | None = None  # kill → first detections of a scan published after the kill


@dataclass
class FaultReport:
    recoveries: list[Recovery] = field(default_factory=list)
    tensors_checked: int = 0
    mixed_tensors: int = 0  # tensors whose scans are not consecutive or not in time order
    launcher_exit_code: int | None = None
    goal_s: float = GOAL_S
    met: bool = False
    machine: MachineInfo = field(default_factory=machine_info)


class Watcher:
    """Latest pid per service (from stats), detections' scan stamps, and tensor sanity, from Zenoh."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.pids: dict[str, int] = {}
        self.latest_scan_stamp_ns = 0
        self.tensors = 0
        self.mixed = 0

    def on_stats(self, sample: Any) -> None:
        body = json.loads(payload_bytes(sample))
        with self.lock:
            self.pids[body["service"]] = int(body["pid"])

    def on_detections(self, sample: Any) -> None:
        message = decode_message(payload_bytes(sample), Detections)
        with self.lock:
            self.latest_scan_stamp_ns = max(self.latest_scan_stamp_ns, message.scan_stamp_ns)

    def on_tensor(self, sample: Any) -> None:
        tensor = decode_message(payload_bytes(sample), StackedTensor)
        seqs, stamps = tensor.scan_seqs, tensor.scan_stamps_ns
        consecutive = seqs[1] == seqs[0] + 1 and seqs[2] == seqs[1] + 1
        ordered = stamps[0] < stamps[1] < stamps[2]
        with self.lock:
            self.tensors += 1
            self.mixed += int(not (consecutive and ordered))


def wait_until(condition: Any, timeout_s: float) -> float | None:
    """Seconds until ``condition()`` held, or None after ``timeout_s``."""
    start = time.monotonic()
    while time.monotonic() - start < timeout_s:
        if condition():
            return time.monotonic() - start
        time.sleep(0.01)
    return None


def run(timeout_s: float = 30.0) -> FaultReport:
    # The recording is only a sink for the visualizer; it must not outlive the run, or repeated
    # runs (the suite runs this) slowly fill /tmp.
    with tempfile.TemporaryDirectory(prefix="triscan-faults-") as workdir:
        return _run_in(Path(workdir) / "faults.rrd", timeout_s)


def _run_in(rrd: Path, timeout_s: float) -> FaultReport:
    report = FaultReport()
    (port,) = free_tcp_ports(1)
    command = [sys.executable, "-m", "services.cli", "up", "--headless", "--rrd", str(rrd)]
    command += ["--listen", f"tcp/127.0.0.1:{port}", "--max-restarts", "10"]
    launcher = subprocess.Popen(command, cwd=ROOT, stderr=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
    watcher = Watcher()
    try:
        with open_session(ZenohSettings.loopback(None, [port])) as session:
            subs = [
                session.declare_subscriber(ALL_STATS, watcher.on_stats),
                session.declare_subscriber(wildcard_key(DETECTIONS), watcher.on_detections),
                session.declare_subscriber(wildcard_key(TENSOR), watcher.on_tensor),
            ]
            if (
                wait_until(lambda: watcher.latest_scan_stamp_ns and set(VICTIMS) <= set(watcher.pids), 90)
                is None
            ):
                raise TimeoutError("the loop never came up")
            for service in VICTIMS:
                time.sleep(3.0)  # steady state between faults
                with watcher.lock:
                    pid = watcher.pids[service]
                recovery = Recovery(service, pid)
                killed_ns = time.time_ns()
                os.kill(pid, signal.SIGKILL)
                recovery.recovery_s = wait_until(
                    lambda k=killed_ns: watcher.latest_scan_stamp_ns > k, timeout_s
                )
                wait_until(lambda s=service, p=pid: watcher.pids.get(s) not in (None, p), 10)
                recovery.new_pid = watcher.pids.get(service)
                report.recoveries.append(recovery)
                log.info("%s: recovered in %s s", service, recovery.recovery_s)
            for sub in subs:
                sub.undeclare()
    finally:
        launcher.send_signal(signal.SIGINT)
        try:
            report.launcher_exit_code = launcher.wait(30)
        except subprocess.TimeoutExpired:
            launcher.kill()
    report.tensors_checked, report.mixed_tensors = watcher.tensors, watcher.mixed
    report.met = (
        all(r.recovery_s is not None and r.recovery_s <= GOAL_S for r in report.recoveries)
        and report.mixed_tensors == 0
    )
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--timeout", type=float, default=30.0, help="give up on one recovery after this")
    parser.add_argument("--out", type=Path, default=Path("bench/results/fault_recovery.json"))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    report = run(args.timeout)
    write_report(report, args.out)
    recovered = all(r.recovery_s is not None for r in report.recoveries) and report.mixed_tensors == 0
    return 0 if recovered else 1


if __name__ == "__main__":
    raise SystemExit(main())
