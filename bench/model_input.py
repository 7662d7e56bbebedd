"""What a C-contiguous model input saves: the detector's conversion + ``session.run``, two ways in turns.

``common.encoding.to_model_input`` once returned ``tensor.transpose(2, 0, 1)[None].astype(float32) /
255``: the right values in the tensor's HWC memory order, a non-contiguous array that ONNX Runtime
copies into a contiguous one inside every ``run``. It now writes the same values C-contiguous (into
the batch array itself for a batch). This times conversion + ``session.run`` both ways on recorded
simulated tensors, both ways on the same frames one right after the other, so the median of the
pairs' differences cancels what a noisy VM does between them: back to back
(*warm*, a busy fleet) and one frame every 100 ms (*paced*, one robot at 10 Hz), at batch 1 on the
default model and at the detector's batch cap (``AUTO_BATCH``, 4) on its ``-batch`` variant, 1 ONNX Runtime
thread (the detector's setting).

    python -m bench.model_input --out bench/results/model_input.json
"""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import numpy as np

from bench.harness import recorded_scans
from bench.machine import MachineInfo, machine_info
from bench.report import write_report
from common.encoding import to_model_input
from common.inference import AUTO_BATCH, OnnxDetector
from common.model_spec import INPUT_SHAPE, default_model_path
from services.encoder.core import EncoderCore

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

DEFAULT_OUT: Final[Path] = Path(__file__).resolve().parent / "results" / "model_input.json"
SCANS: Final[int] = 40  # recorded scans: 38 distinct tensors, cycled through
PACED_PERIOD_S: Final[float] = 0.1

Convert = Callable[[Sequence[np.ndarray]], np.ndarray]


def transposed_input(tensors: Sequence[np.ndarray]) -> np.ndarray:
    """The conversion before: per frame a transposed (non-contiguous) float32 view, concatenated."""
    frames = [t.transpose(2, 0, 1)[None].astype(np.float32) / np.float32(255.0) for t in tensors]
    return frames[0] if len(frames) == 1 else np.concatenate(frames)


def contiguous_input(tensors: Sequence[np.ndarray]) -> np.ndarray:
    """The conversion now, as ``OnnxDetector`` does it: every frame written into one batch array."""
    batch = np.empty((len(tensors), *INPUT_SHAPE[1:]), np.float32)
    for index, tensor in enumerate(tensors):
        to_model_input(tensor, batch[index : index + 1])
    return batch


VARIANTS: Final[dict[str, Convert]] = {"transposed": transposed_input, "contiguous": contiguous_input}


@dataclass
class Case:
    """One model and batch size: p50 µs of conversion + ``session.run`` per call, both ways."""

    model: str
    batch: int
    calls: int
    paced_calls: int
    warm_p50_us: dict[str, float]
    paced_p50_us: dict[str, float]
    # Median over calls of (transposed − contiguous) µs, each pair on the same frames moments apart.
    saved_us_median_of_pairs: dict[str, float]
    outputs_equal: bool


@dataclass
class ModelInputReport:
    cases: list[Case] = field(default_factory=list)
    machine: MachineInfo = field(default_factory=machine_info)


def time_case(model: Path, batch: int, tensors: list[np.ndarray], calls: int, paced_calls: int) -> Case:
    detector = OnnxDetector(model, intra_op_threads=1)
    detector.warmup(batch)
    session = detector._session  # the detector's own session and settings, run without its decode
    feed_name, output_names = detector._input_name, detector._output_names

    def call(convert: Convert, i: int) -> tuple[float, np.ndarray]:
        frames = [tensors[(i * batch + k) % len(tensors)] for k in range(batch)]
        started = time.perf_counter_ns()
        output = session.run(output_names, {feed_name: convert(frames)})[0]
        return (time.perf_counter_ns() - started) / 1e3, output

    outputs_equal = all(
        np.array_equal(call(transposed_input, i)[1], call(contiguous_input, i)[1]) for i in range(4)
    )
    p50s, saved = {}, {}
    for regime, period_s, count in (("warm", 0.0, calls), ("paced", PACED_PERIOD_S, paced_calls)):
        times: dict[str, list[float]] = {name: [] for name in VARIANTS}
        for i in range(count):
            # Both ways on the same frames, one right after the other, the order swapped every call:
            # the pair's difference cancels whatever the VM was doing at that moment.
            for name in VARIANTS if i % 2 else reversed(VARIANTS):
                if period_s:
                    time.sleep(period_s)
                times[name].append(call(VARIANTS[name], i)[0])
        p50s[regime] = {name: round(float(np.median(t)), 1) for name, t in times.items()}
        saved[regime] = round(float(np.median(np.subtract(times["transposed"], times["contiguous"]))), 1)
        log.info(
            "%s, batch %d, %s: p50 µs %s, saved per call (median of pairs) %.1f µs",
            *(model.name, batch, regime, p50s[regime], saved[regime]),
        )
    return Case(model.name, batch, calls, paced_calls, p50s["warm"], p50s["paced"], saved, outputs_equal)


def run(calls: int, paced_calls: int) -> ModelInputReport:
    encoder = EncoderCore("zero")
    tensors = [t.tensor for scan in recorded_scans(SCANS) if (t := encoder.push(scan)) is not None]
    report = ModelInputReport()
    for model, batch in ((default_model_path(), 1), (default_model_path(batched=True), AUTO_BATCH)):
        report.cases.append(time_case(model, batch, tensors, calls, paced_calls))
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--calls", type=int, default=1000, help="warm calls of each variant per case")
    parser.add_argument("--paced-calls", type=int, default=150, help="paced calls of each variant per case")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    report = run(args.calls, args.paced_calls)
    write_report(report, args.out)
    return 0 if all(case.outputs_equal for case in report.cases) else 1


if __name__ == "__main__":
    raise SystemExit(main())
