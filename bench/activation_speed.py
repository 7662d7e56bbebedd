"""What SiLU costs the network at run time: one architecture built with SiLU and with ReLU, timed in turns.

YOLOv8 follows every conv with SiLU, ``x·sigmoid(x)``. ONNX Runtime fuses a ReLU into the conv before
it (``Conv`` with an activation, ``QLinearConv`` with a clipped output range), but SiLU stays two
nodes after each conv: in fp32 one fused ``QuickGelu``, in INT8 a ``QLinearSigmoid`` lookup and a
``QLinearMul``. This builds the same untrained network (``training.architectures.model_yaml``) with
each activation, exports it the way ``triscan export`` does (fp32, then INT8 with the default recipe,
calibrated on simulated frames), times ``session.run`` of the four files run by run in turns (1 ONNX
Runtime thread, the detector's setting), and profiles each file's node time by operator type.

The same holds for the Detect head's DFL bins (``training.architectures``): ``--dfl-bins 16 8`` builds
every activation at each bin count, so the narrower box branch is priced in the same turns, and
``--float-head-convs`` quantises as the shipped default is (the head's convs kept float).

Speed does not depend on the weights, so no training is needed to price the activation; what ReLU
costs in accuracy only a trained model can say (``triscan train --activation relu``).

    python -m bench.activation_speed                 # the pico network
    python -m bench.activation_speed --arch n --out bench/results/activation_speed_n.json
    python -m bench.activation_speed --dfl-bins 16 8 --float-head-convs \
        --out bench/results/dfl_bins_speed.json
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
from collections import Counter
from dataclasses import asdict
from pathlib import Path
from typing import Any, Final

import numpy as np

from bench.harness import simulated_tensor
from bench.machine import machine_info
from bench.report import write_report
from training.architectures import DEFAULT_DFL_BINS, dfl_bins_tag

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

DEFAULT_OUT: Final[Path] = Path(__file__).resolve().parent / "results" / "activation_speed.json"
CALIBRATION_FRAMES: Final[int] = 16  # simulated frames: enough for ranges, speed does not depend on them


def untrained_checkpoint(
    arch: str, activation: str, directory: Path, dfl_bins: int = DEFAULT_DFL_BINS
) -> Path:
    """An Ultralytics checkpoint of the untrained network, with triscan's classes (what export checks)."""
    from ultralytics import YOLO
    from ultralytics.nn.tasks import DetectionModel

    from common.model_spec import CLASS_NAMES
    from training.architectures import model_yaml

    network_yaml = model_yaml(arch, directory, activation, dfl_bins)
    yolo = YOLO(network_yaml)
    yolo.model = DetectionModel(network_yaml, nc=len(CLASS_NAMES), verbose=False)  # as training sets it
    yolo.model.names = dict(enumerate(CLASS_NAMES))
    yolo.ckpt = {}
    path = directory / f"{Path(network_yaml).stem}.pt"
    yolo.save(str(path))
    return path


def calibration_frames(directory: Path, tensors: list[np.ndarray]) -> list[Path]:
    """The stacked tensors as PNGs, as ``triscan dataset`` writes them (what calibration reads)."""
    from training.png import write_rgb_png

    directory.mkdir(parents=True, exist_ok=True)
    frames = []
    for index, tensor in enumerate(tensors, start=1):
        path = directory / f"frame{index:03d}.png"
        write_rgb_png(path, tensor)
        frames.append(path)
    return frames


def node_time_by_op(model: Path, model_input: np.ndarray, runs: int) -> dict[str, float]:
    """Share (%) of the node time each operator type takes over ``runs`` profiled runs, largest first."""
    import onnxruntime as ort

    from common.inference import session_options

    options = session_options(1)
    options.enable_profiling = True
    with tempfile.TemporaryDirectory(prefix="triscan-profile-") as scratch:
        options.profile_file_prefix = str(Path(scratch) / "profile")
        session = ort.InferenceSession(str(model), sess_options=options, providers=["CPUExecutionProvider"])
        feed = {session.get_inputs()[0].name: model_input}
        for _ in range(runs):
            session.run(None, feed)
        events = json.loads(Path(session.end_profiling()).read_text())
    total: Counter[str] = Counter()
    for event in events:
        if event.get("cat") == "Node" and event["name"].endswith("_kernel_time"):
            total[event["args"]["op_name"]] += event["dur"]
    whole = sum(total.values()) or 1
    return {op: float(np.round(100.0 * us / whole, 1)) for op, us in total.most_common()}


def file_label(activation: str, dfl_bins: int, precision: str) -> str:
    """``silu fp32``, ``relu-dfl8 int8``: a timed file's name in the report (bins only when not 16)."""
    return f"{'-'.join(filter(None, (activation, dfl_bins_tag(dfl_bins))))} {precision}"


def run(
    arch: str,
    runs: int,
    profile_runs: int,
    dfl_bins: tuple[int, ...] = (DEFAULT_DFL_BINS,),
    float_head_convs: bool = False,
) -> dict[str, Any]:
    """Build, export, quantise and time the network with each activation and bin count; see the
    module docstring."""
    from common.encoding import to_model_input
    from training.architectures import ACTIVATIONS, check_dfl_bins, model_name
    from training.export_checks import median_latency_ms
    from training.offline import configure_offline
    from training.onnx_export import export_onnx
    from training.quantization import quantize_int8

    with tempfile.TemporaryDirectory(prefix="triscan-activation-") as tmp:
        scratch = Path(tmp)
        configure_offline()
        # One simulated world per frame, each simulated once: frame 1 is also the timed and profiled input.
        tensors = [simulated_tensor(seed) for seed in range(1, CALIBRATION_FRAMES + 1)]
        frames = calibration_frames(scratch / "frames", tensors)
        files: dict[str, Path] = {}
        for bins in map(check_dfl_bins, dfl_bins):
            for activation in ACTIVATIONS:
                weights = untrained_checkpoint(arch, activation, scratch, bins)
                fp32 = export_onnx(weights, scratch / f"{weights.stem}.onnx", padding="zero")
                files[file_label(activation, bins, "fp32")] = fp32
                files[file_label(activation, bins, "int8")] = quantize_int8(
                    fp32,
                    scratch / f"{weights.stem}-int8.onnx",
                    frames,
                    keep_head_convs_float=float_head_convs,
                )
        medians = median_latency_ms(list(files.values()), frames[0], runs=runs)
        model_input = to_model_input(tensors[0])
        profiles = {name: node_time_by_op(path, model_input, profile_runs) for name, path in files.items()}
    median_ms = {name: round(ms, 4) for name, ms in zip(files, medians, strict=True)}
    for name, ms in median_ms.items():
        reference = median_ms.get(file_label("silu", DEFAULT_DFL_BINS, name.split()[-1]))
        versus = f" ({100 * (1 - ms / reference):.1f} % less than SiLU at 16 bins)" if reference else ""
        log.info(
            "%s %s, session.run median of %d in turns: %.3f ms%s", model_name(arch), name, runs, ms, versus
        )
    return {
        "network": model_name(arch),
        "runs": runs,
        "profile_runs": profile_runs,
        "dfl_bins": list(dfl_bins),
        "int8_head_convs_float": float_head_convs,
        "median_ms": median_ms,
        # ReLU against SiLU at the same bins: "fp32", "int8" at 16 bins, "dfl8 fp32" and so on otherwise.
        "relu_saves_percent": {
            " ".join(filter(None, (dfl_bins_tag(bins), precision))): round(
                100
                * (
                    1
                    - median_ms[file_label("relu", bins, precision)]
                    / median_ms[file_label("silu", bins, precision)]
                ),
                1,
            )
            for bins in dfl_bins
            for precision in ("fp32", "int8")
        },
        "node_time_percent_by_op": profiles,
        "machine": asdict(machine_info()),
    }


def main(argv: list[str] | None = None) -> int:
    from training.architectures import ARCHS, DFL_BINS

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--arch", choices=ARCHS, default="p", help="network scale (default: pico)")
    parser.add_argument("--runs", type=int, default=2000, help="timed runs of each file")
    parser.add_argument("--profile-runs", type=int, default=200, help="profiled runs of each file")
    parser.add_argument(
        "--dfl-bins", type=int, nargs="+", choices=DFL_BINS, default=[DEFAULT_DFL_BINS],
        help="build each activation at each of these DFL bin counts (default: Ultralytics' 16)",
    )  # fmt: skip
    parser.add_argument(
        "--float-head-convs",
        action="store_true",
        help="INT8 with the Detect head's convs float (the default's)",
    )
    parser.add_argument("--out", type=Path, default=None, help=f"default {DEFAULT_OUT}")
    args = parser.parse_args(argv)
    if args.runs < 1 or args.profile_runs < 1:
        parser.error("--runs and --profile-runs must be >= 1")
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    report = run(args.arch, args.runs, args.profile_runs, tuple(args.dfl_bins), args.float_head_convs)
    write_report(report, args.out or DEFAULT_OUT, echo=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
