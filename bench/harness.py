"""What benchmarks (and the tests of real processes) need around the services: start one by hand,
read a process's memory and CPU, real scans recorded up front so a timed loop simulates nothing, and
frames timed one per period as a robot sends them."""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar

from common.model_spec import MODEL_ENV
from common.transport import ZenohSettings
from services.launcher import child_environment
from services.sim_bag import recorded_scans as recorded_scans  # the benches' recorded scans, re-exported

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


def process_tree(pid: int) -> list[int]:
    """``pid`` and its live descendants (a service's ``--detectors N`` siblings are its children)."""
    pids, index = [pid], 0
    while index < len(pids):
        for task in Path(f"/proc/{pids[index]}/task").glob("*/children"):
            try:
                pids += [int(child) for child in task.read_text().split()]
            except (FileNotFoundError, ProcessLookupError):
                continue
        index += 1
    return pids


def tree_values(pid: int, read: Callable[[int], float]) -> dict[int, float]:
    """``read`` of ``pid`` and of each of its live descendants, by pid; one that ends meanwhile (or is a
    zombie, with no memory left to read) is left out."""
    values = {}
    for member in process_tree(pid):
        try:
            values[member] = read(member)
        except (FileNotFoundError, ProcessLookupError, RuntimeError):
            continue
    return values


def _tree_sum(pid: int, read: Callable[[int], float]) -> float:
    """``read`` of ``pid`` and of each of its descendants, summed; one that ends meanwhile counts 0."""
    return sum(tree_values(pid, read).values())


def tree_cpu_s(pid: int) -> float:
    """:func:`proc_cpu_s` of ``pid`` and its descendants together."""
    return _tree_sum(pid, proc_cpu_s)


def tree_rss_mb(pid: int) -> float:
    """Resident memory of ``pid`` and its descendants together, in MiB."""
    return _tree_sum(pid, proc_status_mb)


def _per_thread(pid: int, read: Callable[[Path], T]) -> Iterator[tuple[str, T]]:
    """``(comm, read(task dir))`` for each live thread of ``pid``; one that ends meanwhile is skipped."""
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:
            yield (task / "comm").read_text().strip(), read(task)
        except (FileNotFoundError, ProcessLookupError):
            continue  # the thread ended between the listing and the read


def thread_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds per thread name (``comm``) of a live process and its descendants, threads of one name
    summed.

    Python threads are all "python" unless named (the detector names its inference threads);
    Zenoh's runtime threads carry their own names (rx-0, tx-0, net-0, acc-0, app-0).
    """
    totals: dict[str, float] = {}
    for member in process_tree(pid):  # the siblings of a --detectors N launch, whose threads are alike
        for name, seconds in _per_thread(member, lambda task: _stat_cpu_s(task / "stat")):
            totals[name] = totals.get(name, 0.0) + seconds
    return totals


def timed_us(frame: Callable[[int], object], frames: int, period_s: float) -> list[float]:
    """µs of each ``frame(i)`` for ``i`` in range(frames), ``period_s`` apart when above 0, the thread
    sleeping between frames as a service's does between a robot's scans."""
    times = []
    next_due = time.monotonic()
    for i in range(frames):
        started = time.perf_counter_ns()
        frame(i)
        times.append((time.perf_counter_ns() - started) / 1e3)
        if period_s > 0:
            next_due += period_s
            time.sleep(max(0.0, next_due - time.monotonic()))
    return times
