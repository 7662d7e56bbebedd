"""The per-thread /proc readings the benchmarks split CPU time and hand-offs by."""

from __future__ import annotations

import os
import threading
import time

from bench.harness import pin_named_threads, thread_cpu_s, thread_wakeups
from services.detector.core import name_os_thread

SLEEPS = 5


class _Probe(threading.Thread):
    """A thread named ``os_name`` in the OS that blocks ``SLEEPS`` times when told to."""

    def __init__(self, os_name: str = "wake-probe") -> None:
        super().__init__(daemon=True)
        self.os_name = os_name
        self.named, self.go, self.slept, self.release = (threading.Event() for _ in range(4))

    def run(self) -> None:
        name_os_thread(self.os_name)
        self.named.set()
        self.go.wait()
        for _ in range(SLEEPS):
            time.sleep(0.005)  # each sleep blocks the thread once: one voluntary switch
        self.slept.set()
        self.release.wait()  # alive until the test has read /proc

    def __enter__(self) -> _Probe:
        self.start()
        assert self.named.wait(10.0)
        return self

    def __exit__(self, *exc: object) -> None:
        self.go.set()
        self.release.set()
        self.join(10.0)


def test_thread_wakeups_count_each_time_a_named_thread_blocks() -> None:
    with _Probe() as probe:
        before = thread_wakeups(os.getpid())
        probe.go.set()
        assert probe.slept.wait(10.0)
        after = thread_wakeups(os.getpid())
    assert "wake-probe" in before
    assert after["wake-probe"] - before["wake-probe"] >= SLEEPS


def test_thread_cpu_s_names_the_threads_that_used_it() -> None:
    with _Probe():
        seconds = thread_cpu_s(os.getpid())
    assert "wake-probe" in seconds and all(value >= 0.0 for value in seconds.values())


def test_pin_named_threads_pins_only_the_numbered_threads_of_that_name() -> None:
    cpus = sorted(os.sched_getaffinity(0))
    with _Probe("pin-probe-1") as probe, _Probe("pin-probe-x") as unnumbered:
        pinned = pin_named_threads(os.getpid(), "pin-probe-")
        assert probe.native_id is not None and unnumbered.native_id is not None
        probe_cpus = os.sched_getaffinity(probe.native_id)
        unnumbered_cpus = os.sched_getaffinity(unnumbered.native_id)
    expected = cpus[1 % len(cpus)]
    assert pinned == {"pin-probe-1": expected}
    assert probe_cpus == {expected}
    assert unnumbered_cpus == set(cpus) and os.sched_getaffinity(0) == set(cpus)
