"""The per-thread /proc readings the benchmarks split CPU time and hand-offs by."""

from __future__ import annotations

import os
import threading
import time

from bench.harness import thread_cpu_s, thread_wakeups
from services.detector.core import name_os_thread

SLEEPS = 5


class _Probe(threading.Thread):
    """A thread named ``wake-probe`` in the OS that blocks ``SLEEPS`` times when told to."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.named, self.go, self.slept, self.release = (threading.Event() for _ in range(4))

    def run(self) -> None:
        name_os_thread("wake-probe")
        self.named.set()
        self.go.wait()
        for _ in range(SLEEPS):
            time.sleep(0.005)  # each sleep blocks the thread once: one voluntary switch
        self.slept.set()
        self.release.wait()  # alive until the test has read /proc


def test_thread_wakeups_count_each_time_a_named_thread_blocks() -> None:
    probe = _Probe()
    probe.start()
    try:
        assert probe.named.wait(10.0)
        before = thread_wakeups(os.getpid())
        probe.go.set()
        assert probe.slept.wait(10.0)
        after = thread_wakeups(os.getpid())
    finally:
        probe.go.set()
        probe.release.set()
        probe.join(10.0)
    assert "wake-probe" in before
    assert after["wake-probe"] - before["wake-probe"] >= SLEEPS


def test_thread_cpu_s_names_the_threads_that_used_it() -> None:
    probe = _Probe()
    probe.start()
    try:
        assert probe.named.wait(10.0)
        seconds = thread_cpu_s(os.getpid())
    finally:
        probe.go.set()
        probe.release.set()
        probe.join(10.0)
    assert "wake-probe" in seconds and all(value >= 0.0 for value in seconds.values())
