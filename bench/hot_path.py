"""The Python each message costs the services, outside the network: time and memory per frame.

The pipeline's stage split (``bench.pipeline_latency``) times the stages inside running services;
this bench times the same code paths alone, on recorded scans, so a change to them can be measured
in seconds: the encoder's (scan payload → decoded scan → raster → stacked tensor → tensor payload)
and the detector's (tensor payload → decoded tensor → ``DetectorCore.detect_many``: model input,
``session.run``, decode, NMS, wire detections → ``Detections`` payload) minus the ``session.run``
time the frame itself reports. Each path runs back to back (*warm*: caches hot) and paced at the
scan rate (*paced*: one frame every 1/rate s, as a robot sends them, caches cooled by the sleep),
and ``tracemalloc`` records the peak memory each frame allocates in Python and numpy (ONNX Runtime's
own arena is not traced). Minor page faults per frame (``getrusage``, around each frame but outside
its timing) tell whether a paced frame's extra time is memory the allocator returned to the kernel
between frames and faults back in; a second paced pass whose thread spins between frames instead of
sleeping tells whether it is the idle vCPU (halted, rescheduled, clocked down) or time itself (caches
and predictors overwritten by everything else the host runs in 100 ms); a sweep of shorter periods
(one frame every 1, 3, 10, 30 ms) shows how fast that happens.

    python -m bench.hot_path --out bench/results/hot_path_pico_default.json
"""

from __future__ import annotations

import argparse
import logging
import tracemalloc
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from bench.harness import add_detector_model_argument, recorded_scans, timed_us
from bench.machine import MachineInfo, machine_info
from bench.report import latency_quantiles_ms, write_report
from common.inference import OnnxDetector
from common.messages import encode_message
from common.model_spec import default_model_path
from services.detector.core import DetectorCore
from services.encoder.core import EncoderCore

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

SCANS = 60  # recorded scans: 58 tensors, cycled through
ALLOC_FRAMES = 50  # frames traced by tracemalloc (slower: not timed)
# Shorter frame periods than the scan rate's: how long the host takes to cool a frame's caches.
PERIOD_SWEEP_MS = (1.0, 3.0, 10.0, 30.0)


@dataclass
class PathCost:
    """One code path's cost per frame: p50 µs back to back and paced, and peak bytes allocated."""

    path: str
    warm_us: dict[str, float]
    paced_us: dict[str, float]
    paced_spinning_us: dict[str, float]  # paced, the thread spinning between frames instead of sleeping
    peak_alloc_kb: float
    paced_minor_faults_per_frame: float  # mean over the paced frames
    p50_us_by_period_ms: dict[str, float]  # one frame every N ms, sleeping between; 0 = back to back


@dataclass
class HotPathReport:
    model: str
    frames: int
    rate_hz: float
    paths: list[PathCost] = field(default_factory=list)
    machine: MachineInfo = field(default_factory=machine_info)


def peak_alloc_kb(frame: Callable[[int], float], frames: int) -> float:
    """Median over frames of the peak memory one frame allocates (``tracemalloc``), in kB."""
    peaks = []
    tracemalloc.start()
    try:
        for i in range(frames):
            baseline, _ = tracemalloc.get_traced_memory()
            tracemalloc.reset_peak()
            frame(i)
            peaks.append(tracemalloc.get_traced_memory()[1] - baseline)
    finally:
        tracemalloc.stop()
    return round(float(np.median(peaks)) / 1e3, 1)


def measure(name: str, frame: Callable[[int], float], frames: int, rate_hz: float) -> PathCost:
    frame(0)  # first-call costs (imports, caches) are not what a running service pays
    warm_us, _ = timed_us(frame, frames, 0.0)
    paced_us, paced_faults = timed_us(frame, frames, 1.0 / rate_hz)
    spinning_us, _ = timed_us(frame, frames, 1.0 / rate_hz, spin=True)
    return PathCost(
        name,
        latency_quantiles_ms(warm_us),  # quantiles of µs, in µs
        latency_quantiles_ms(paced_us),
        latency_quantiles_ms(spinning_us),
        peak_alloc_kb(frame, ALLOC_FRAMES),
        round(paced_faults / frames, 2),
        by_period_ms(frame, frames, 1e3 / rate_hz, warm_us, paced_us),
    )


def by_period_ms(
    frame: Callable[[int], float], frames: int, paced_ms: float, warm_us: list[float], paced_us: list[float]
) -> dict[str, float]:
    """p50 µs of a frame at each period of PERIOD_SWEEP_MS, beside back to back (0) and paced."""
    times_by_period = {0.0: warm_us, paced_ms: paced_us}
    for period_ms in PERIOD_SWEEP_MS:
        times_by_period.setdefault(period_ms, timed_us(frame, frames, period_ms / 1e3)[0])
    return {f"{ms:g}": round(float(np.median(times)), 1) for ms, times in sorted(times_by_period.items())}


def run(frames: int, rate_hz: float, model: Path | None = None) -> HotPathReport:
    """Both services' per-frame Python on recorded scans; see the module docstring."""
    model = model or default_model_path()
    scans = recorded_scans(SCANS)
    robot_id = scans[0].robot_id
    reference = EncoderCore("zero")
    tensor_payloads = [encode_message(t) for scan in scans if (t := reference.push(scan)) is not None]
    core = DetectorCore(OnnxDetector(model, intra_op_threads=1))
    core.detector.warmup()
    report = HotPathReport(model.name, frames, rate_hz)
    # One unbroken stream for the encoder, the recorded scans cycled with ever larger seqs and stamps,
    # so every frame after the first two yields a tensor (a restarted stream would warm up again).
    period_ns = round(1e9 / rate_hz)
    # Two to prime the FIFO, the first call, the warm, paced, spinning and period passes, the traced ones.
    payloads = 2 + 1 + (3 + len(PERIOD_SWEEP_MS)) * frames + ALLOC_FRAMES
    stream = iter(
        [
            encode_message(scans[k % len(scans)].model_copy(update={"seq": k, "stamp_ns": k * period_ns}))
            for k in range(payloads)
        ]
    )
    encoder = EncoderCore("zero")
    encoder.handle_payload(next(stream), robot_id)
    encoder.handle_payload(next(stream), robot_id)

    def encoder_frame(_: int) -> float:
        tensor = encoder.handle_payload(next(stream), robot_id)
        if tensor is None:
            raise RuntimeError("the recorded stream broke: the encoder made no tensor")
        encode_message(tensor)
        return 0.0

    def detector_frame(i: int) -> float:
        tensor = core.decode(tensor_payloads[i % len(tensor_payloads)], robot_id)
        if tensor is None:
            raise RuntimeError("the detector rejected a recorded tensor")
        (message,) = core.detect_many([tensor])
        encode_message(message)
        return message.timings.inference_ms * 1e3

    for name, frame in (
        ("encoder: scan payload → tensor payload", encoder_frame),
        ("detector: tensor payload → Detections payload, less session.run", detector_frame),
    ):
        cost = measure(name, frame, frames, rate_hz)
        log.info(
            "%-62s p50 warm %6.1f µs, paced %6.1f µs (spinning between frames %6.1f), peak %6.1f kB,"
            " %.2f minor faults a paced frame",
            name,
            cost.warm_us["p50"],
            cost.paced_us["p50"],
            cost.paced_spinning_us["p50"],
            cost.peak_alloc_kb,
            cost.paced_minor_faults_per_frame,
        )
        log.info("    p50 µs at one frame every N ms: %s", cost.p50_us_by_period_ms)
        report.paths.append(cost)
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200, help="frames per path and pacing")
    parser.add_argument("--rate", type=float, default=10.0, help="paced frames per second")
    add_detector_model_argument(parser)
    parser.add_argument("--out", type=Path, default=None, help="write the report as JSON here")
    args = parser.parse_args(argv)
    if args.frames < 1 or args.rate <= 0:
        parser.error("--frames must be >= 1 and --rate > 0")
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    write_report(asdict(run(args.frames, args.rate, args.model)), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
