"""Where a running service's Python threads spend their time: py-spy's samples, grouped into pieces.

The fleet benches read each process's and each thread's CPU from ``/proc``; that says the detector's
inference threads are busy, not with what. ``bench.detector_path`` times the pieces of the detector's
path in one process without Zenoh. This module samples the real service while a fleet drives it:
`py-spy <https://github.com/benfred/py-spy>`_ (in the ``dev`` extra) records every thread's Python
stack ``rate_hz`` times a second, and each sample is counted for the innermost frame that belongs to a
named piece of the detector (the network's ``session.run``, the model input, the post-processing, …),
so a rename fails loudly at import instead of silently moving time into "other".

py-spy reads the stacks without pausing the process (``--nonblocking``): paused 100 times a second,
the detector lost a quarter of its CPU time in a fleet on two cores. py-spy still takes CPU of its own,
which the report gives (``profiler_cpu_cores``), so a profiled fleet step is a picture of where the time
goes, not a capacity figure. A sample counts a thread that is running or ready to run (py-spy leaves
out the ones it finds idle, with a heuristic in this mode): the shares of one run, pieces measured side
by side, are the figure to read.
"""

from __future__ import annotations

import functools
import inspect
import os
import re
import shutil
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

from common.encoding import to_model_input
from common.inference import OnnxDetector
from common.messages import encode_message
from common.postprocess import detections_from_boxes, postprocess
from services.detector.core import INFERENCE_THREAD_PREFIX, DetectorCore, LatestPerRobot
from services.encoder.core import EncoderCore
from services.runtime import RobotPublishers

PROFILE_RATE_HZ = 50
OTHER = "other"
# A frame of py-spy's raw format: ``function (file:line)``; the thread comes first with --threads.
_FRAME = re.compile(r"^(?P<function>.*) \((?P<file>.*):(?P<line>\d+)\)$")
_THREAD = re.compile(r"^thread \((?P<tid>\w+)\): (?P<name>.*)$")


class Frame(NamedTuple):
    function: str  # the qualified name, as py-spy prints it (``OnnxDetector._run``)
    file: str


class StackSamples(NamedTuple):
    """How many samples found one thread in one stack (outermost frame first)."""

    thread: str
    frames: tuple[Frame, ...]
    samples: int


@dataclass(frozen=True)
class Piece:
    """A named piece of a service's work: every sample inside one of ``functions`` belongs to it.

    ``waiting``: the piece is a thread waiting for work. py-spy cannot always tell a thread blocked in
    ``Condition.wait`` from a running one, so such samples are reported apart from the busy ones.
    """

    name: str
    functions: tuple[Callable[..., Any], ...]
    waiting: bool = False

    def frames(self) -> set[Frame]:
        """The frames py-spy prints for these functions (``--full-filenames``)."""
        return {Frame(fn.__qualname__, _resolved(inspect.getsourcefile(fn) or "")) for fn in self.functions}


@functools.cache
def _resolved(file: str) -> str:
    """One spelling per source file, so a frame and a function compare equal."""
    return str(Path(file).resolve()) if file else file


# The detector's pieces, innermost first wins: a sample in ``encode_message`` called by the publish
# step is "payload encode", one in Zenoh's ``put`` is "publish".
DETECTOR_PIECES: tuple[Piece, ...] = (
    Piece("network (session.run)", (OnnxDetector._run,)),
    Piece("model input", (to_model_input,)),
    Piece("post-processing", (postprocess,)),
    Piece("wire detections", (detections_from_boxes,)),
    Piece("detections message", (DetectorCore._message,)),
    Piece("payload encode", (encode_message,)),
    Piece("publish (Zenoh put)", (RobotPublishers.put,)),
    Piece("waiting for a tensor", (LatestPerRobot.take_many,), waiting=True),
    Piece("tensor decode", (DetectorCore.decode,)),
    Piece("scan encode (--from-scans)", (EncoderCore.handle_payload,)),
    Piece("mailbox put", (LatestPerRobot.put,)),
)


def py_spy_path() -> str:
    """The py-spy executable: next to this interpreter (a venv's ``bin``) or on ``PATH``."""
    found = shutil.which("py-spy", path=str(Path(sys.executable).parent)) or shutil.which("py-spy")
    if found is None:
        raise FileNotFoundError("py-spy is not installed: pip install py-spy (it is in triscan's dev extra)")
    return found


def start_recording(
    pid: int, seconds: float, out: Path, rate_hz: int = PROFILE_RATE_HZ
) -> subprocess.Popen[bytes]:
    """Start sampling process ``pid`` for ``seconds`` into ``out`` (py-spy's raw format, per thread)."""
    command = [
        py_spy_path(),
        "record",
        *("--pid", str(pid), "--duration", str(max(1, round(seconds))), "--rate", str(rate_hz)),
        *("--format", "raw", "--threads", "--full-filenames", "--nonblocking", "--output", str(out)),
    ]
    return subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


class Recording(NamedTuple):
    stacks: list[StackSamples]
    cpu_s: float  # py-spy's own CPU time: what sampling took from the machine


def finish_recording(recorder: subprocess.Popen[bytes], out: Path, timeout_s: float = 60.0) -> Recording:
    """Wait for a recording (it ends after its ``--duration``) and read its samples; py-spy's own
    message if it failed (no permission to trace the process, say). One still running ``timeout_s``
    after this call is killed: a bench must not hang on its profiler."""
    deadline = time.monotonic() + timeout_s
    while True:
        pid, status, usage = os.wait4(recorder.pid, os.WNOHANG)  # reaped here, with its CPU time
        if pid:
            break
        if time.monotonic() > deadline:
            recorder.kill()
            recorder.wait()
            raise RuntimeError(
                f"py-spy was still running {timeout_s:g} s after its recording should have ended"
            )
        time.sleep(0.05)
    recorder.returncode = os.waitstatus_to_exitcode(status)
    stderr = recorder.stderr.read() if recorder.stderr is not None else b""
    if recorder.returncode != 0 or not out.exists():
        detail = " ".join(stderr.decode(errors="replace").split())
        raise RuntimeError(f"py-spy failed (exit {recorder.returncode}): {detail}")
    return Recording(parse_raw(out.read_text()), usage.ru_utime + usage.ru_stime)


def parse_raw(text: str) -> list[StackSamples]:
    """py-spy's raw (collapsed) output with ``--threads``: one ``thread;frame;…;frame count`` per line."""
    stacks = []
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        stack, _, count = line.rpartition(" ")
        first, *rest = stack.split(";")
        thread = _THREAD.match(first)
        if thread is None or not count.isdigit():
            raise ValueError(f"line {number} is not py-spy raw output with --threads: {line[:120]!r}")
        frames = []
        for text_frame in rest:
            match = _FRAME.match(text_frame)
            # A frame py-spy could not name (native, or a torn read without a file) is kept as it is.
            frames.append(Frame(match["function"], match["file"]) if match else Frame(text_frame, ""))
        stacks.append(StackSamples(thread["name"], tuple(frames), int(count)))
    return stacks


def piece_of(frames: Sequence[Frame], index: dict[Frame, str]) -> str:
    """The piece of the innermost frame that belongs to one, else ``other``."""
    for frame in reversed(frames):
        piece = index.get(Frame(frame.function, _resolved(frame.file)))
        if piece is not None:
            return piece
    return OTHER


def samples_by_piece(
    stacks: Iterable[StackSamples], pieces: Sequence[Piece], threads: Callable[[str], bool]
) -> Counter[str]:
    """Samples per piece over the threads whose name ``threads`` accepts."""
    index = {frame: piece.name for piece in pieces for frame in piece.frames()}
    counts: Counter[str] = Counter()
    for stack in stacks:
        if threads(stack.thread):
            counts[piece_of(stack.frames, index)] += stack.samples
    return counts


def is_inference_thread(name: str) -> bool:
    return name.startswith(INFERENCE_THREAD_PREFIX)


def detector_profile(
    recording: Recording, scans_answered: int, rate_hz: int, window_s: float
) -> dict[str, Any]:
    """The detector's samples as a report: per thread, and for its inference threads each piece's share
    of their busy samples (waiting left out) and its milliseconds of thread time per answered scan."""
    stacks = recording.stacks
    per_thread: Counter[str] = Counter()
    for stack in stacks:
        per_thread[stack.thread] += stack.samples
    inference = samples_by_piece(stacks, DETECTOR_PIECES, is_inference_thread)
    others = samples_by_piece(stacks, DETECTOR_PIECES, lambda name: not is_inference_thread(name))
    waiting = {piece.name for piece in DETECTOR_PIECES if piece.waiting}
    busy = sum(n for piece, n in inference.items() if piece not in waiting)
    return {
        "rate_hz": rate_hz,
        "profiler_cpu_cores": round(recording.cpu_s / window_s, 3),
        "samples_per_thread": dict(per_thread.most_common()),
        "inference_threads_busy_share": {
            piece: round(n / busy, 4) for piece, n in inference.most_common() if piece not in waiting
        }
        if busy
        else {},
        "inference_threads_ms_per_scan": {
            piece: round(1e3 * n / rate_hz / scans_answered, 4) for piece, n in inference.most_common()
        }
        if scans_answered
        else {},
        "other_threads_samples": dict(others.most_common()),
    }
