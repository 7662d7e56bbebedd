"""What the model input costs: the detector's conversion + ``session.run``, three ways in turns.

``common.encoding.to_model_input`` once returned ``tensor.transpose(2, 0, 1)[None].astype(float32) /
255`` (*transposed*): the right values in the tensor's HWC memory order, a non-contiguous array that
ONNX Runtime copies into a contiguous one inside every ``run``. It now writes the same values
C-contiguous, into the batch array itself for a batch (*contiguous*). A third way is a lever
measured, not taken: the same model with the conversion inside its graph, fed the uint8 tensors as
they arrive (*uint8_graph*, :func:`with_uint8_input`). All three run on the same recorded simulated
frames one right after the other, the order rotated every call, so the median of two ways'
differences cancels what a noisy VM does between calls: back to back (*warm*, a busy fleet) and one
call every 100 ms (*paced*, one robot at 10 Hz), at batch 1 on the default model and at batch 4
(``FLEET_BATCH``, the detector's cap when these figures were taken; it now times its own, up to
``common.inference.AUTO_BATCH``) on its ``-batch`` variant, 1 ONNX Runtime thread (the detector's
setting). The outputs of the three ways must be equal, bit for bit.

    python -m bench.model_input --out bench/results/model_input.json
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import numpy as np
import onnxruntime as ort

from bench.harness import recorded_scans
from bench.machine import MachineInfo, machine_info
from bench.report import write_report
from common.encoding import to_model_input
from common.inference import session_options
from common.model_spec import INPUT_SHAPE, TENSOR_SHAPE, default_model_path
from services.encoder.core import EncoderCore

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

DEFAULT_OUT: Final[Path] = Path(__file__).resolve().parent / "results" / "model_input.json"
SCANS: Final[int] = 40  # recorded scans: 38 distinct tensors, cycled through
FLEET_BATCH: Final[int] = 4  # the batch case: the committed figures (bench/README.md) were taken at 4
PACED_PERIOD_S: Final[float] = 0.1

Way = Callable[[Sequence[np.ndarray]], np.ndarray]  # HWC uint8 frames → the model's raw output


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


def with_uint8_input(model: Path, out: Path) -> Path:
    """``model`` with the conversion inside the graph: a ``uint8[N, 64, 384, 3]`` input, then
    Transpose, Cast and Div by 255 in front of the network. Written to ``out``; the lever measured
    here, not a shipped format (bench/README.md, "The model input")."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    graph_model = onnx.load(str(model))
    graph = graph_model.graph
    (float_input,) = graph.input
    batch_dim = float_input.type.tensor_type.shape.dim[0]
    batch: int | str = batch_dim.dim_param or batch_dim.dim_value
    uint8_input = helper.make_tensor_value_info("tensor", TensorProto.UINT8, [batch, *TENSOR_SHAPE])
    graph.input.remove(float_input)
    graph.input.insert(0, uint8_input)
    graph.initializer.append(numpy_helper.from_array(np.array(255.0, np.float32), "tensor_scale"))
    conversion = [
        helper.make_node("Transpose", ["tensor"], ["tensor_chw"], perm=[0, 3, 1, 2]),
        helper.make_node("Cast", ["tensor_chw"], ["tensor_float"], to=TensorProto.FLOAT),
        helper.make_node("Div", ["tensor_float", "tensor_scale"], [float_input.name]),
    ]
    for node in reversed(conversion):
        graph.node.insert(0, node)
    onnx.save(graph_model, str(out))
    return out


@dataclass
class Case:
    """One model and batch size: p50 µs of conversion + ``session.run`` per call, three ways."""

    model: str
    batch: int
    calls: int
    paced_calls: int
    warm_p50_us: dict[str, float]
    paced_p50_us: dict[str, float]
    # Median over calls of the µs one way took more than another, on the same frames moments apart:
    # "transposed-contiguous" is what this commit saved, "contiguous-uint8_graph" what the lever would.
    saved_us_median_of_pairs: dict[str, dict[str, float]]
    outputs_equal: bool


@dataclass
class ModelInputReport:
    cases: list[Case] = field(default_factory=list)
    machine: MachineInfo = field(default_factory=machine_info)


SAVINGS: Final[tuple[tuple[str, str], ...]] = (("transposed", "contiguous"), ("contiguous", "uint8_graph"))


def time_case(model: Path, batch: int, tensors: list[np.ndarray], calls: int, paced_calls: int) -> Case:
    # One session per way, each with the detector's setting: with a shared session the way run
    # first after another session's call would find the weights colder than the others do.
    with tempfile.TemporaryDirectory(prefix="triscan-model-input-") as scratch:
        uint8_model = with_uint8_input(model, Path(scratch) / "uint8.onnx")
        sessions = {
            name: ort.InferenceSession(
                str(path), sess_options=session_options(1), providers=["CPUExecutionProvider"]
            )
            for name, path in (("transposed", model), ("contiguous", model), ("uint8_graph", uint8_model))
        }
    conversions: dict[str, Callable[[Sequence[np.ndarray]], np.ndarray]] = {
        "transposed": transposed_input,
        "contiguous": contiguous_input,
        "uint8_graph": np.stack,
    }

    def way_of(name: str) -> Way:
        session, convert = sessions[name], conversions[name]
        feed = session.get_inputs()[0].name
        return lambda frames: session.run(None, {feed: convert(frames)})[0]

    ways = {name: way_of(name) for name in sessions}

    def frames_of(i: int) -> list[np.ndarray]:
        return [tensors[(i * batch + k) % len(tensors)] for k in range(batch)]

    for i in range(3):  # first calls: arenas, caches
        for run_way in ways.values():
            run_way(frames_of(i))
    outputs_equal = all(
        all(np.array_equal(ways["transposed"](frames_of(i)), run(frames_of(i))) for run in ways.values())
        for i in range(4)
    )
    p50s, saved = {}, {}
    names = list(ways)
    for regime, period_s, count in (("warm", 0.0, calls), ("paced", PACED_PERIOD_S, paced_calls)):
        times: dict[str, list[float]] = {name: [] for name in ways}
        for i in range(count):
            # Every way on the same frames, one right after the other, the order rotated every call:
            # a pair's difference cancels whatever the VM was doing at that moment.
            frames = frames_of(i)
            for name in names[i % 3 :] + names[: i % 3]:
                if period_s:
                    time.sleep(period_s)
                started = time.perf_counter_ns()
                ways[name](frames)
                times[name].append((time.perf_counter_ns() - started) / 1e3)
        p50s[regime] = {name: round(float(np.median(t)), 1) for name, t in times.items()}
        saved[regime] = {
            f"{a}-{b}": round(float(np.median(np.subtract(times[a], times[b]))), 1) for a, b in SAVINGS
        }
        log.info(
            "%s, batch %d, %s: p50 µs %s, saved per call (median of pairs, µs) %s",
            *(model.name, batch, regime, p50s[regime], saved[regime]),
        )
    return Case(model.name, batch, calls, paced_calls, p50s["warm"], p50s["paced"], saved, outputs_equal)


def run(calls: int, paced_calls: int) -> ModelInputReport:
    encoder = EncoderCore("zero")
    tensors = [t.tensor for scan in recorded_scans(SCANS) if (t := encoder.push(scan)) is not None]
    report = ModelInputReport()
    for model, batch in ((default_model_path(), 1), (default_model_path(batched=True), FLEET_BATCH)):
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
