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
(one frame every 1, 3, 10, 30 ms) shows how fast that happens. A last paced pass runs an untimed
throw-away frame of the same path (another input, its result discarded) 0.5, 1, 2 or 5 ms before
each timed one: how much of a frame's cold cost a service could buy back by pre-warming itself just
before a robot's next scan is due, and how much of the network's (``session.run``, reported beside).

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
from common.messages import Scan, encode_message
from common.model_spec import default_model_path
from services.detector.core import DetectorCore
from services.encoder.core import EncoderCore

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

SCANS = 60  # recorded scans: 58 tensors, cycled through
ALLOC_FRAMES = 50  # frames traced by tracemalloc (slower: not timed)
# Shorter frame periods than the scan rate's: how long the host takes to cool a frame's caches.
PERIOD_SWEEP_MS = (1.0, 3.0, 10.0, 30.0)
# How long before each paced frame the pre-warmed passes run their throw-away frame.
PREWARM_LEADS_MS = (0.5, 1.0, 2.0, 5.0)


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
    # Paced, a throw-away frame N ms before each ("none": the plain paced pass), and the p50 of what
    # the frames reported as spent elsewhere (the detector's session.run; 0 for the encoder).
    prewarmed_p50_us_by_lead_ms: dict[str, float]
    excluded_p50_us_by_lead_ms: dict[str, float]


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


def measure(
    name: str, frame: Callable[[int], float], throwaway: Callable[[int], float], frames: int, rate_hz: float
) -> PathCost:
    """``frame(i)`` timed every way of the module docstring; ``throwaway(i)`` is the same path on
    other inputs, for the pre-warmed passes."""
    frame(0)  # first-call costs (imports, caches) are not what a running service pays
    throwaway(0)
    warm_us, _ = timed_us(frame, frames, 0.0)
    excluded: list[float] = []

    def recorded(i: int) -> float:
        excluded.append(frame(i))
        return excluded[-1]

    paced_us, paced_faults = timed_us(recorded, frames, 1.0 / rate_hz)
    prewarmed_us = {"none": paced_us}
    excluded_us = {"none": excluded[:]}
    for lead_ms in PREWARM_LEADS_MS:
        excluded.clear()
        prewarmed_us[f"{lead_ms:g}"], _ = timed_us(
            recorded, frames, 1.0 / rate_hz, prewarm=throwaway, lead_s=lead_ms / 1e3
        )
        excluded_us[f"{lead_ms:g}"] = excluded[:]
    spinning_us, _ = timed_us(frame, frames, 1.0 / rate_hz, spin=True)
    return PathCost(
        name,
        latency_quantiles_ms(warm_us),  # quantiles of µs, in µs
        latency_quantiles_ms(paced_us),
        latency_quantiles_ms(spinning_us),
        peak_alloc_kb(frame, ALLOC_FRAMES),
        round(paced_faults / frames, 2),
        by_period_ms(frame, frames, 1e3 / rate_hz, warm_us, paced_us),
        p50_us_by_key(prewarmed_us),
        p50_us_by_key(excluded_us),
    )


def by_period_ms(
    frame: Callable[[int], float], frames: int, paced_ms: float, warm_us: list[float], paced_us: list[float]
) -> dict[str, float]:
    """p50 µs of a frame at each period of PERIOD_SWEEP_MS, beside back to back (0) and paced."""
    times_by_period = {0.0: warm_us, paced_ms: paced_us}
    for period_ms in PERIOD_SWEEP_MS:
        times_by_period.setdefault(period_ms, timed_us(frame, frames, period_ms / 1e3)[0])
    return p50_us_by_key({f"{ms:g}": times for ms, times in sorted(times_by_period.items())})


def p50_us_by_key(times_by_key: dict[str, list[float]]) -> dict[str, float]:
    """The p50 of each pass's µs, to 0.1 µs, under the pass's key (a period, a lead)."""
    return {key: round(float(np.median(times)), 1) for key, times in times_by_key.items()}


def encoder_path(scans: list[Scan], payloads: int, rate_hz: float) -> Callable[[int], float]:
    """The encoder's frame on a stream of ``payloads`` scan payloads of one robot, primed with two."""
    period_ns = round(1e9 / rate_hz)
    stream = iter(
        [
            encode_message(scans[k % len(scans)].model_copy(update={"seq": k, "stamp_ns": k * period_ns}))
            for k in range(payloads)
        ]
    )
    robot_id = scans[0].robot_id
    encoder = EncoderCore("zero")
    encoder.handle_payload(next(stream), robot_id)
    encoder.handle_payload(next(stream), robot_id)

    def encoder_frame(_: int) -> float:
        tensor = encoder.handle_payload(next(stream), robot_id)
        if tensor is None:
            raise RuntimeError("the recorded stream broke: the encoder made no tensor")
        encode_message(tensor)
        return 0.0

    return encoder_frame


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
    # Two to prime the FIFO, the first call, the warm, paced, spinning, period, pre-warmed and traced
    # passes; the throw-away frames have an encoder and a stream of their own.
    timed_payloads = 2 + 1 + (3 + len(PERIOD_SWEEP_MS) + len(PREWARM_LEADS_MS)) * frames + ALLOC_FRAMES
    encoder_frame = encoder_path(scans, timed_payloads, rate_hz)
    encoder_throwaway = encoder_path(scans, 2 + 1 + len(PREWARM_LEADS_MS) * frames, rate_hz)

    def detector_frame(i: int) -> float:
        tensor = core.decode(tensor_payloads[i % len(tensor_payloads)], robot_id)
        if tensor is None:
            raise RuntimeError("the detector rejected a recorded tensor")
        (message,) = core.detect_many([tensor])
        encode_message(message)
        return message.timings.inference_ms * 1e3

    def detector_throwaway(i: int) -> float:
        return detector_frame(i + len(tensor_payloads) // 2)  # another recorded tensor than the frame's

    for name, frame, throwaway in (
        ("encoder: scan payload → tensor payload", encoder_frame, encoder_throwaway),
        (
            "detector: tensor payload → Detections payload, less session.run",
            detector_frame,
            detector_throwaway,
        ),
    ):
        cost = measure(name, frame, throwaway, frames, rate_hz)
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
        log.info(
            "    paced, p50 µs with a throw-away frame N ms before: %s (session.run: %s)",
            cost.prewarmed_p50_us_by_lead_ms,
            cost.excluded_p50_us_by_lead_ms,
        )
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
