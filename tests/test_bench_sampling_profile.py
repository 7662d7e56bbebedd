"""bench.sampling_profile: py-spy's raw stacks are read and each sample lands in the right piece."""

from __future__ import annotations

import inspect
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from bench.sampling_profile import (
    DETECTOR_PIECES,
    OTHER,
    Frame,
    Recording,
    detector_profile,
    finish_recording,
    is_inference_thread,
    parse_raw,
    samples_by_piece,
    start_recording,
)
from common.inference import OnnxDetector
from common.messages import encode_message
from common.postprocess import postprocess
from services.detector.core import DetectorCore, InferencePipeline, LatestPerRobot
from services.runtime import RobotPublishers

ROOT = Path(__file__).resolve().parents[1]


def frame(fn: object, line: int = 1) -> str:
    """A frame as py-spy prints it with --full-filenames."""
    return f"{fn.__qualname__} ({inspect.getsourcefile(fn)}:{line})"  # type: ignore[attr-defined]


def raw_line(thread: str, frames: list[str], samples: int) -> str:
    return (
        ";".join([f"thread (0x1f): {thread}", "Thread.run (/usr/lib/python3.11/threading.py:982)", *frames])
        + f" {samples}"
    )


SERVE = frame(InferencePipeline._serve)
RAW = "\n".join(
    [
        raw_line("inference-0", [SERVE, frame(DetectorCore.detect_many), frame(OnnxDetector._run, 751)], 60),
        raw_line("inference-1", [SERVE, frame(DetectorCore.detect_many), frame(OnnxDetector._run, 752)], 40),
        # Innermost first: decode_yolov8 inside postprocess is post-processing, numpy below it too.
        raw_line("inference-0", [SERVE, frame(postprocess), "_amax (/x/numpy/_core/_methods.py:41)"], 20),
        # encode_message called from the publish step is the payload's encoding, Zenoh's put the publishing.
        raw_line("inference-1", [SERVE, frame(encode_message)], 5),
        raw_line("inference-1", [SERVE, frame(RobotPublishers.put)], 10),
        # Were one piece ever to call another, the sample belongs to the callee.
        raw_line("inference-1", [SERVE, frame(RobotPublishers.put), frame(encode_message)], 3),
        raw_line(
            "inference-0",
            [SERVE, frame(LatestPerRobot.take_many), "wait (/usr/lib/python3.11/threading.py:324)"],
            30,
        ),
        raw_line("inference-0", [SERVE, "<unknown frame>"], 5),
        raw_line("Thread-2 (pyo3-closure)", [frame(DetectorCore.decode)], 7),
        raw_line("Thread-2 (pyo3-closure)", [], 50),
    ]
)


def test_raw_stacks_are_read_with_their_thread_and_frames() -> None:
    stacks = parse_raw(RAW + "\n\n")
    assert len(stacks) == 10 and sum(s.samples for s in stacks) == 230
    first = stacks[0]
    assert first.thread == "inference-0" and first.samples == 60
    assert first.frames[-1] == Frame("OnnxDetector._run", inspect.getsourcefile(OnnxDetector._run))
    assert stacks[7].frames[-1] == Frame("<unknown frame>", "")  # kept as it is, counted as other


def test_each_sample_lands_in_the_innermost_piece() -> None:
    stacks = parse_raw(RAW)
    inference = samples_by_piece(stacks, DETECTOR_PIECES, is_inference_thread)
    assert inference == {
        "network (session.run)": 100,
        "post-processing": 20,
        "payload encode": 8,
        "publish (Zenoh put)": 10,
        "waiting for a tensor": 30,
        OTHER: 5,
    }
    others = samples_by_piece(stacks, DETECTOR_PIECES, lambda name: not is_inference_thread(name))
    assert others == {"tensor decode": 7, OTHER: 50}


def test_detector_profile_shares_leave_waiting_out_and_times_are_per_answered_scan() -> None:
    profile = detector_profile(
        Recording(parse_raw(RAW), cpu_s=0.5), scans_answered=500, rate_hz=100, window_s=5.0
    )
    assert profile["profiler_cpu_cores"] == pytest.approx(0.1)
    busy = profile["inference_threads_busy_share"]
    assert "waiting for a tensor" not in busy
    assert busy["network (session.run)"] == pytest.approx(100 / 143, abs=1e-4)
    assert sum(busy.values()) == pytest.approx(1.0, abs=1e-3)
    # 100 samples at 100 Hz = 1 s of thread time over 500 scans = 2 ms a scan.
    assert profile["inference_threads_ms_per_scan"]["network (session.run)"] == pytest.approx(2.0)
    assert profile["inference_threads_ms_per_scan"]["waiting for a tensor"] == pytest.approx(0.6)
    assert profile["samples_per_thread"] == {
        "inference-0": 115,
        "inference-1": 58,
        "Thread-2 (pyo3-closure)": 57,
    }


@pytest.mark.parametrize(
    "line",
    ["Thread.run (threading.py:982) 3", "thread (0x1): inference-0;Thread.run (threading.py:982) many"],
    ids=["no-thread", "no-count"],
)
def test_output_without_threads_is_refused_with_the_line(line: str) -> None:
    with pytest.raises(ValueError, match="line 1 is not py-spy raw output with --threads"):
        parse_raw(line)


def test_a_recorder_that_does_not_end_is_killed_with_a_clear_error(tmp_path: Path) -> None:
    stuck = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"], stderr=subprocess.PIPE)
    with pytest.raises(RuntimeError, match=r"py-spy was still running 0\.2 s after"):
        finish_recording(stuck, tmp_path / "never.txt", timeout_s=0.2)
    assert stuck.returncode is not None  # killed and reaped, not left behind


def test_a_failed_recording_reports_its_own_message(tmp_path: Path) -> None:
    failed = subprocess.Popen(
        [sys.executable, "-c", "import sys; sys.exit('Permission denied: try running again with sudo')"],
        stderr=subprocess.PIPE,
    )
    with pytest.raises(RuntimeError, match="py-spy failed \\(exit 1\\): Permission denied"):
        finish_recording(failed, tmp_path / "none.txt")


@pytest.mark.slow
def test_a_live_process_is_sampled_in_its_busy_piece(tmp_path: Path) -> None:
    """py-spy against a real process whose one named thread runs the post-processing in a loop."""
    busy = textwrap.dedent(
        """
        import threading, numpy as np
        from common.postprocess import postprocess
        out = np.random.default_rng(0).random((1, 8, 504), dtype=np.float32)
        def work():
            while True:
                postprocess(out)
        threading.Thread(target=work, name="inference-0", daemon=True).start()
        print("ready", flush=True)
        threading.Event().wait()
        """
    )
    child = subprocess.Popen([sys.executable, "-c", busy], cwd=ROOT, stdout=subprocess.PIPE)
    try:
        assert child.stdout is not None and child.stdout.readline().strip() == b"ready"
        out = tmp_path / "profile.txt"
        try:
            recording = finish_recording(start_recording(child.pid, 2, out), out)
        except RuntimeError as exc:
            if "ermission" in str(exc) or "ptrace" in str(exc):
                pytest.skip(f"this machine does not let py-spy trace a process: {exc}")
            raise
    finally:
        child.kill()
        child.wait()
    counts = samples_by_piece(recording.stacks, DETECTOR_PIECES, lambda name: name == "inference-0")
    assert counts["post-processing"] >= 0.8 * sum(counts.values()) > 0
    assert recording.cpu_s > 0  # py-spy's own CPU, reaped with it
