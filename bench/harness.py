"""What benchmarks (and the tests of real processes) need around the services: start one by hand,
read a process's memory, real scans recorded up front so a timed loop simulates nothing, frames timed
one per period as a robot sends them, and spinning processes that keep every CPU awake (``--busy``)."""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from common.encoding import ScanStacker
from common.model_spec import MODEL_ENV
from common.transport import ZenohSettings
from services.launcher import child_environment
from services.sim_bag import recorded_scans

T = TypeVar("T")


def add_detector_model_argument(parser: argparse.ArgumentParser) -> None:
    """``--model`` for a bench that runs the detector; None leaves the detector's own default."""
    parser.add_argument(
        "--model",
        type=Path,
        default=None,
        help=f"detector model (default: ${MODEL_ENV} or the shipped default)",
    )


def start_loopback_service(
    module: str, port: int, connect: Sequence[int], *extra: str, **popen_kwargs: Any
) -> subprocess.Popen[bytes]:
    """``python -m <module>`` as a loopback peer listening on ``port`` and connecting to ``connect``.

    For benchmarks and tests that wire a few services by hand rather than through ``triscan up``.
    """
    settings = ZenohSettings.loopback(port, list(connect))
    command = [sys.executable, "-m", module, *extra, *settings.to_cli()]
    return subprocess.Popen(
        command, cwd=Path(__file__).resolve().parents[1], env=child_environment(), **popen_kwargs
    )


@contextmanager
def cpu_spinners(count: int) -> Iterator[list[subprocess.Popen[bytes]]]:
    """``count`` lowest-priority processes spinning for the duration, one per CPU so none idles.

    On a VM an idle vCPU halts, and a thread woken on it may wait for the hypervisor to run it again.
    With the CPUs kept spinning the same work pays no such wake-up, which tells wake-up costs from work
    per message (``bench.zenoh_rtt --busy``, ``bench.pipeline_latency --busy``; bench/README.md has
    what each showed). At nice 19 a spinner yields to any other runnable task; it is a diagnostic,
    never a setting for a robot (it burns every core it covers).
    """
    spinners = [
        subprocess.Popen([sys.executable, "-c", "import os\nos.nice(19)\nwhile True: pass"])
        for _ in range(count)
    ]
    try:
        yield spinners
    finally:
        for spinner in spinners:
            spinner.kill()
            spinner.wait()


def proc_status_mb(pid: int, field_name: str = "VmRSS") -> float:
    """A memory figure of a live process from /proc (``VmRSS`` now, ``VmHWM`` its peak), in MiB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(f"{field_name}:"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError(f"/proc/{pid}/status has no {field_name}")


def _stat_cpu_s(stat: Path) -> float:
    """User + system CPU seconds from a /proc ``stat`` file (a process's or one of its threads')."""
    fields = stat.read_text().rpartition(")")[2].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime (fields 14, 15)


def proc_cpu_s(pid: int) -> float:
    """CPU seconds (user + system, every thread) a live process has used, from /proc/<pid>/stat."""
    return _stat_cpu_s(Path(f"/proc/{pid}/stat"))


def _per_thread(pid: int, read: Callable[[Path], T]) -> Iterator[tuple[str, T]]:
    """``(comm, read(task dir))`` for each live thread of ``pid``; one that ends meanwhile is skipped."""
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            yield (task / "comm").read_text().strip(), read(task)
        except (FileNotFoundError, ProcessLookupError):
            continue  # the thread ended between the listing and the read


def thread_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds per thread name (``comm``) of a live process, threads of one name summed.

    Python threads are all "python" unless named (the detector names its inference threads);
    Zenoh's runtime threads carry their own names (rx-0, tx-0, net-0, acc-0, app-0).
    """
    totals: dict[str, float] = {}
    for name, seconds in _per_thread(pid, lambda task: _stat_cpu_s(task / "stat")):
        totals[name] = totals.get(name, 0.0) + seconds
    return totals


def pin_named_threads(pid: int, prefix: str) -> dict[str, int]:
    """Pin each thread of ``pid`` named ``<prefix><N>`` to the N-th CPU this process may use (modulo
    their count), from outside the process; returns the CPU each got.

    A diagnostic for ``bench.fleet_capacity --pin-inference-threads``: does the scheduler putting both
    of the detector's inference threads on one vCPU now and then (while the other runs the encoder or
    the robots) cost the fleet its tail latency? Linux only (``sched_setaffinity`` on a thread id).
    """
    cpus = sorted(os.sched_getaffinity(0))
    pinned: dict[str, int] = {}
    for name, thread_id in _per_thread(pid, lambda task: int(task.name)):
        number = name[len(prefix) :]
        if not name.startswith(prefix) or not number.isdigit():
            continue
        cpu = cpus[int(number) % len(cpus)]
        try:
            os.sched_setaffinity(thread_id, {cpu})
        except ProcessLookupError:
            continue  # the thread ended between the listing and the pinning
        pinned[name] = cpu
    return pinned


def _voluntary_switches(task: Path) -> int:
    for line in (task / "status").read_text().splitlines():
        if line.startswith("voluntary_ctxt_switches:"):
            return int(line.split()[1])
    raise RuntimeError(f"{task}/status has no voluntary_ctxt_switches")


def thread_wakeups(pid: int) -> dict[str, int]:
    """Voluntary context switches per thread name of a live process (threads of one name summed).

    A thread switches voluntarily when it blocks (a socket read, a condition, a channel) and counts
    one when it is woken again: the difference over a timed loop, per message, is how many times each
    kind of thread was put to sleep and woken to move one message (``bench.zenoh_rtt``).
    """
    totals: dict[str, int] = {}
    for name, switches in _per_thread(pid, _voluntary_switches):
        totals[name] = totals.get(name, 0) + switches
    return totals


def _minor_faults() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def _wait_for_deadline(deadline: float, spin: bool) -> None:
    if not spin:
        time.sleep(max(0.0, deadline - time.monotonic()))
        return
    while time.monotonic() < deadline:
        pass


def timed_us(
    frame: Callable[[int], float],
    frames: int,
    period_s: float,
    spin: bool = False,
    *,
    prewarm: Callable[[int], object] | None = None,
    lead_s: float = 0.0,
) -> tuple[list[float], int]:
    """µs of ``frame(i)`` for ``i`` in range(frames), less the µs each call returns as spent elsewhere
    (e.g. the network, for a bench of what surrounds it), and the minor page faults the frames took;
    ``period_s`` apart when above 0, the thread sleeping between frames or, with ``spin``, busy (its
    vCPU never idles). With ``prewarm``, paced frames are each preceded by an untimed ``prewarm(i)``
    that ends ``lead_s`` before the frame starts: does a throw-away frame just before a real one
    leave the real one warm?"""
    if prewarm is not None and not 0.0 < lead_s < period_s:
        raise ValueError(f"a pre-warmed pass needs 0 < lead_s < period_s, got {lead_s} and {period_s}")
    times = []
    faults = 0
    next_due = time.monotonic()
    for i in range(frames):
        faults_before = _minor_faults()
        frame_started = time.monotonic()
        started = time.perf_counter_ns()
        excluded_us = frame(i)
        times.append((time.perf_counter_ns() - started) / 1e3 - excluded_us)
        faults += _minor_faults() - faults_before
        if period_s > 0:
            if prewarm is None:
                next_due += period_s
            else:
                # The period stretches by the throw-away frame's own time, the lead stays exact. Counted
                # from this frame's own start, not its due time: a frame that started late (the thread
                # was preempted) must not bring the next one closer than a period.
                _wait_for_deadline(frame_started + period_s - lead_s, spin)
                prewarm(i)
                next_due = time.monotonic() + lead_s
            _wait_for_deadline(next_due, spin)
    return times, faults


def simulated_tensor(seed: int = 1) -> np.ndarray:
    """The stacked tensor of three consecutive simulated scans (one robot, world ``seed``)."""
    stacker = ScanStacker()
    tensor = None
    for scan in recorded_scans(3, seed=seed):
        tensor = stacker.push_scan(
            scan.ranges, scan.angle_min, scan.angle_increment, scan.range_min, scan.range_max
        )
    assert tensor is not None
    return tensor
