"""The per-thread /proc readings the benchmarks split CPU time by, and their paced timing."""

from __future__ import annotations

import os
import threading
import time

import pytest

from bench import harness
from bench.harness import thread_cpu_s
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


def test_thread_cpu_s_names_the_threads_that_used_it() -> None:
    with _Probe():
        seconds = thread_cpu_s(os.getpid())
    assert "wake-probe" in seconds and all(value >= 0.0 for value in seconds.values())


def test_paced_timing_sleeps_out_each_period_and_times_only_the_frames(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    sleeps: list[float] = []
    real_sleep = time.sleep
    monkeypatch.setattr(harness.time, "sleep", lambda s: (sleeps.append(s), real_sleep(s)))
    started = time.monotonic()
    times = harness.timed_us(lambda _: real_sleep(0.005), 3, 0.02)
    assert time.monotonic() - started >= 0.06  # three frames, each 20 ms apart
    assert len(sleeps) == 3  # the thread sleeps between frames, as a service's does
    assert len(times) == 3 and all(us >= 5_000 for us in times)  # each frame's own 5 ms at least
