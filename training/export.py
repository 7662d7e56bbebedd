"""``triscan export``: trained YOLOv8n → fixed-shape fp32 ONNX and a static INT8 (QDQ) ONNX.

The robot runs ONNX Runtime, never torch, so the checkpoint is exported once here with the shape it
will always see: ``float32[1, 3, 64, 384]`` (batch 1, no dynamic axes: a fixed graph lets ONNX Runtime
plan memory once and keeps the INT8 calibration valid for every input). Besides Ultralytics' own
metadata (names, imgsz, stride) each file carries ``triscan.*`` metadata — padding mode, class list,
source weights — so a detector can refuse a model trained on the other padding instead of silently
mixing ``zero`` and ``wrap`` (README, "The encoding").

The INT8 model is ONNX Runtime static quantisation in QDQ format with per-channel weight scales and
percentile activation ranges, calibrated on validation PNGs fed through exactly the run-time
conversion (:func:`common.encoding.to_model_input`). The detection head's decode tail (DFL softmax,
box arithmetic, class sigmoid, the final concat of pixel boxes with 0–1 scores) stays float: one
8-bit scale spanning boxes up to 384 px and scores below 1 rounds scores to a few levels (measured:
28 % of candidate detections changed class). Whether INT8 ships is decided by evaluation, not here.

Each model also gets a ``-batch`` variant with a free batch axis (:func:`add_batch_axis`): the same
graph and weights, so a detector serving a fleet can run several robots' frames in one call without
running a model that was never evaluated.
"""

from __future__ import annotations

import json
import logging
import re
import shutil
import statistics
import tempfile
import time
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np

from common.encoding import IMAGE_WIDTH, PADDINGS, RANGE_ROWS, STACK_DEPTH, to_model_input
from common.inference import session_options
from common.model_spec import (
    CLASS_NAMES,
    INPUT_SHAPE,
    META_CLASSES,
    META_PADDING,
    META_PREFIX,
    NUM_ANCHORS,
    batch_variant_path,
    file_sha256,
)

log = logging.getLogger(__name__)

BOX_CHANNELS = 4  # output rows 0–3: cx, cy, w, h in input pixels; rows 4…: per-class scores in [0, 1]
DEFAULT_CALIB_COUNT = 200
CONFIDENT_SCORE = 0.25  # Ultralytics' default predict threshold: anchors above it are candidate detections
SHA_PREFIX = 12
PERCENTILE = 99.999  # share of calibration values the "percentile" activation ranges keep
ENTROPY_BINS = 2048  # histogram resolution for KL calibration, as TensorRT uses
ENTROPY_QUANTIZED_BINS = 128  # ONNX Runtime's default target bin count for the KL search

CalibMethod = Literal["minmax", "entropy", "percentile"]
CALIB_METHODS: tuple[str, ...] = get_args(CalibMethod)
ActivationType = Literal["uint8", "int8"]
ACTIVATION_TYPES: tuple[str, ...] = get_args(ActivationType)


class ExportError(ValueError):
    """An export or quantisation that cannot produce a model the robot may run.

    A ``ValueError``: it always comes from what was handed in (weights, data set, model file), and
    ``triscan`` reports those as a one-line error instead of a traceback.
    """


# --- small helpers -------------------------------------------------------------------------------------


def dataset_padding(dataset_dir: Path) -> str | None:
    """The padding a data set was generated with, or None if the directory does not say.

    ``summary.json`` (written by ``triscan dataset``) is authoritative; the comment line of
    ``data.yaml`` is the fallback for a set whose summary was not copied along.
    """
    summary = dataset_dir / "summary.json"
    if summary.is_file():
        padding = json.loads(summary.read_text()).get("config", {}).get("padding")
        if padding in PADDINGS:
            return str(padding)
    data_yaml = dataset_dir / "data.yaml"
    if data_yaml.is_file():
        match = re.search(r"padding (\w+)", data_yaml.read_text())
        if match and match.group(1) in PADDINGS:
            return match.group(1)
    return None


def _resolve_padding(requested: str | None, dataset_dir: Path | None) -> str:
    """Padding to record in the model: the data set's when known, checked against the caller's.

    A mismatch is an error, not a warning: a ``wrap`` model fed ``zero`` tensors (or the reverse)
    still produces plausible-looking detections, so nothing downstream would catch it.
    """
    if requested is not None and requested not in PADDINGS:
        raise ExportError(f"padding must be one of {PADDINGS}, got {requested!r}")
    derived = dataset_padding(dataset_dir) if dataset_dir is not None else None
    if derived is not None and requested is not None and derived != requested:
        raise ExportError(f"padding {requested!r} requested but the data set {dataset_dir} uses {derived!r}")
    if derived is not None:
        return derived
    if requested is None:
        log.warning("padding not derivable from the training data set; recording the default 'zero'")
        return "zero"
    return requested


def _check_io(model: Any, path: Path, batch: int | str = 1) -> None:
    """Fail unless the graph takes ``float32[B,3,64,384]`` and returns ``float32[B,4+nc,504]``.

    ``B`` is 1 for the robot's fixed-shape models and the symbolic ``batch`` for their batch variants.
    """
    import onnx

    def signature(value: Any) -> tuple[int, tuple[int | str, ...]]:
        tensor = value.type.tensor_type
        return tensor.elem_type, tuple(
            d.dim_value if d.HasField("dim_value") else d.dim_param for d in tensor.shape.dim
        )

    def described(value: Any) -> str:
        elem_type, dims = signature(value)
        return f"{onnx.helper.tensor_dtype_to_np_dtype(elem_type)}{list(dims)}"

    name = _input_name(model)
    (graph_input,) = (i for i in model.graph.input if i.name == name)
    expected_in = (batch, *INPUT_SHAPE[1:])
    if signature(graph_input) != (onnx.TensorProto.FLOAT, expected_in):
        raise ExportError(f"{path}: input must be float32{list(expected_in)}, got {described(graph_input)}")
    expected_out = (batch, BOX_CHANNELS + len(CLASS_NAMES), NUM_ANCHORS)
    outputs = model.graph.output
    if len(outputs) != 1 or signature(outputs[0]) != (onnx.TensorProto.FLOAT, expected_out):
        got = ", ".join(described(o) for o in outputs)
        raise ExportError(f"{path}: output must be float32{list(expected_out)}, got {got}")


def _save_checked(model: Any, out: Path, batch: int | str = 1) -> None:
    """Write a model only once it passes the ONNX checker and has the robot's input and output."""
    import onnx

    onnx.checker.check_model(model, full_check=True)
    _check_io(model, out, batch)
    out.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(out))


def _set_metadata(model: Any, values: dict[str, str]) -> None:
    """Add or overwrite metadata entries, keeping every other entry (Ultralytics' included)."""
    existing = {prop.key: prop for prop in model.metadata_props}
    for key, value in values.items():
        prop = existing.get(key) or model.metadata_props.add()
        prop.key, prop.value = key, value


# --- fp32 export ---------------------------------------------------------------------------------------


def export_onnx(weights: Path, out: Path, *, opset: int | None = None, padding: str | None = None) -> Path:
    """Export an Ultralytics checkpoint to a fixed-shape fp32 ONNX file at ``out``.

    ``padding`` is read from the data set the checkpoint was trained on (its ``train_args.data``)
    when that set is still on disk; ``padding`` must then agree with it. If neither says, ``zero``
    (the paper's default) is recorded with a warning.

    Ultralytics writes the ONNX next to the file it loaded, so the checkpoint is copied into a scratch
    directory first: exporting never litters the run directory or the working directory.
    """
    weights = Path(weights)
    out = Path(out)
    if not weights.is_file():
        raise FileNotFoundError(f"weights {weights} not found")
    from training.offline import configure_offline

    configure_offline()
    import onnx
    from ultralytics import YOLO

    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="triscan-export-") as scratch:
        local = Path(scratch) / weights.name
        shutil.copyfile(weights, local)
        yolo = YOLO(str(local), task="detect")
        names = [yolo.names[i] for i in sorted(yolo.names)]
        if tuple(names) != CLASS_NAMES:
            raise ExportError(f"{weights} predicts {names}, not the triscan classes {list(CLASS_NAMES)}")
        data = (getattr(yolo, "ckpt", None) or {}).get("train_args", {}).get("data")
        dataset_dir = Path(data).parent if data else None
        if dataset_dir is not None and not dataset_dir.is_dir():
            dataset_dir = None
        recorded_padding = _resolve_padding(padding, dataset_dir)
        exported = yolo.export(
            format="onnx",
            imgsz=(RANGE_ROWS, IMAGE_WIDTH),
            batch=1,
            dynamic=False,
            simplify=True,
            opset=opset,
            nms=False,  # NMS runs in common/inference.py, where its thresholds are configurable
            device="cpu",  # the same graph whatever accelerator this machine has
            verbose=False,
        )
        model = onnx.load(str(exported))
    _set_metadata(
        model,
        {
            META_PADDING: recorded_padding,
            META_CLASSES: json.dumps(list(CLASS_NAMES)),
            f"{META_PREFIX}source_weights": f"{weights.name} sha256:{file_sha256(weights)[:SHA_PREFIX]}",
            f"{META_PREFIX}precision": "fp32",
        },
    )
    _save_checked(model, out)
    log.info(
        "exported %s → %s (opset %d, padding %s, %.1f MB, %.1f s)",
        weights,
        out,
        next(o.version for o in model.opset_import if o.domain in ("", "ai.onnx")),
        recorded_padding,
        out.stat().st_size / 1e6,
        time.perf_counter() - started,
    )
    return out


# --- calibration data ----------------------------------------------------------------------------------


def read_tensor_png(path: Path) -> np.ndarray:
    """A data-set PNG as the run-time ``uint8[64, 384, 3]`` tensor (PNG red plane = channel 0 = t−2).

    Pillow returns planes in file order (R, G, B), which is the order ``training.png`` wrote them;
    OpenCV would return B, G, R and silently swap the oldest and newest scan.
    """
    from PIL import Image

    with Image.open(path) as image:
        tensor = np.asarray(image.convert("RGB"), dtype=np.uint8)
    if tensor.shape != (RANGE_ROWS, IMAGE_WIDTH, STACK_DEPTH):
        raise ExportError(f"{path}: expected a {IMAGE_WIDTH}×{RANGE_ROWS} RGB image, got {tensor.shape}")
    return tensor


def calibration_images(dataset_dir: Path, count: int = DEFAULT_CALIB_COUNT, split: str = "val") -> list[Path]:
    """``count`` PNGs of one split, spread evenly over its sorted file list (deterministic).

    Names sort by scenario, position and frame, so an even stride touches every scenario of the split
    instead of the first few hundred frames of one room; calibration then sees every layout.
    """
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    split_dir = Path(dataset_dir) / "images" / split
    if not split_dir.is_dir():
        raise FileNotFoundError(f"{split_dir} not found: pass a directory written by `triscan dataset`")
    images = sorted(split_dir.glob("*.png"))
    if not images:
        raise ExportError(f"no PNG images in {split_dir}")
    return _spread(images, count)


def _spread(items: Sequence[Path], count: int) -> list[Path]:
    """``count`` items at evenly spaced positions, first and last included (all when there are fewer)."""
    if count >= len(items):
        return list(items)
    picks = np.unique(np.round(np.linspace(0, len(items) - 1, count)).astype(np.int64))
    return [items[i] for i in picks]


def _input_name(model: Any) -> str:
    """The single non-initializer input of an ONNX graph (``images`` for Ultralytics exports)."""
    initializers = {t.name for t in model.graph.initializer}
    names = [i.name for i in model.graph.input if i.name not in initializers]
    if len(names) != 1:
        raise ExportError(f"expected one graph input, found {names}")
    return str(names[0])


def _calibration_reader(input_name: str, images: Sequence[Path]) -> Any:
    """A ``CalibrationDataReader`` yielding each PNG through the run-time conversion.

    Built inside a function so that importing this module does not import onnxruntime.quantization.
    """
    from onnxruntime.quantization import CalibrationDataReader

    class PngCalibrationReader(CalibrationDataReader):  # type: ignore[misc]
        """Feeds ``to_model_input(read_tensor_png(png))`` once per image, then None."""

        def __init__(self) -> None:
            self._paths = list(images)
            self._iter = iter(self._paths)

        def get_next(self) -> dict[str, np.ndarray] | None:
            path = next(self._iter, None)
            return None if path is None else {input_name: to_model_input(read_tensor_png(path))}

        def rewind(self) -> None:
            self._iter = iter(self._paths)

    return PngCalibrationReader()


# --- INT8 quantisation ---------------------------------------------------------------------------------


def head_decode_nodes(model: Any) -> list[str]:
    """Names of the detection head's decode nodes: everything after its per-stride conv branches.

    Ultralytics names ONNX nodes by module path; the Detect head is the last module
    (``/model.22/``) and its branches are ``cv2.*`` (box distributions) and ``cv3.*`` (class logits).
    The rest of the head — reshapes, concats, DFL softmax and conv, box arithmetic, sigmoid, the output
    concat — mixes pixel-scale boxes with 0–1 scores and is left in float.
    """
    head_ids = [int(m.group(1)) for n in model.graph.node if (m := re.match(r"/model\.(\d+)/", n.name))]
    if not head_ids:
        raise ExportError("no /model.N/ node names: not an Ultralytics YOLO ONNX export")
    prefix = f"/model.{max(head_ids)}/"
    branches = (f"{prefix}cv2.", f"{prefix}cv3.")
    tail = [n.name for n in model.graph.node if n.name.startswith(prefix) and not n.name.startswith(branches)]
    output = model.graph.output[0].name
    producers = {o: n.name for n in model.graph.node for o in n.output}
    if producers.get(output) not in tail:
        raise ExportError(f"the head's decode tail under {prefix} does not produce the output {output!r}")
    return tail


def _entropy_ranges(model_path: Path, reader: Any, cache: Path, scratch: Path) -> None:
    """Activation ranges by KL-divergence (TensorRT's method) over 2048-bin histograms, saved to ``cache``.

    ``quantize_static`` cannot pass a bin count to its entropy calibrator, whose default of 128 bins
    equals the 128 quantised bins: the search then has a single candidate, the full range, and
    "entropy" silently reproduces MinMax (measured: identical scales on every tensor). Computing the
    ranges here and handing them over through ONNX Runtime's calibration cache restores the method.
    """
    from onnxruntime.quantization.calibrate import CalibrationMethod, create_calibrator, save_tensors_data
    from onnxruntime.quantization.registry import QDQRegistry, QLinearOpsRegistry

    calibrator = create_calibrator(
        model_path,
        sorted(set(QLinearOpsRegistry) | set(QDQRegistry)),  # what quantize_static calibrates by default
        augmented_model_path=str(scratch / "entropy-augmented.onnx"),
        calibrate_method=CalibrationMethod.Entropy,
        extra_options={"num_bins": ENTROPY_BINS, "num_quantized_bins": ENTROPY_QUANTIZED_BINS},
    )
    calibrator.collect_data(reader)
    save_tensors_data(calibrator.compute_data(), cache)
    reader.rewind()


def quantize_int8(
    fp32_onnx: Path,
    out: Path,
    calibration_images: Sequence[Path],
    *,
    per_channel: bool = True,
    method: CalibMethod = "percentile",
    activation_type: ActivationType = "uint8",
    keep_head_float: bool = True,
    preprocess: bool = True,
) -> Path:
    """Statically quantise an fp32 ONNX model to INT8 (QDQ) at ``out``.

    Weights are symmetric signed 8-bit, by default with one scale per output channel: fused conv+BN
    weights differ by orders of magnitude between channels, and with MinMax ranges one per-tensor
    scale gave 1.4× the box error (with the default percentile ranges the two were within noise, so
    per-channel stays as the safer choice at no measured speed cost). Activations default to unsigned
    8-bit, ONNX Runtime's advice for x86 CPUs; ``int8`` is its advice for ARM (on this x86 machine it
    ran 3× slower than ``uint8``, slower than fp32, so build the ARM model for ARM and time it there).

    ``method`` picks the activation ranges. ``percentile`` (the default) keeps 99.999 % of each
    tensor's calibration values in an asymmetric range and clips the rare outliers that otherwise
    stretch the 256 levels: on an epoch-1 checkpoint it moved candidate boxes by 0.25 px on average
    where ``minmax`` (every value representable) moved them 1.15 px, with no class flips against
    1.3 %. ``entropy`` is TensorRT's KL search; it clipped too hard on these sparse scans (6 px).

    ``preprocess`` runs ONNX Runtime's ``quant_pre_process`` (shape inference and graph
    optimisation) first, which its quantiser recommends so that every tensor has a known shape.
    """
    fp32_onnx, out = Path(fp32_onnx), Path(out)
    if method not in CALIB_METHODS:
        raise ValueError(f"method must be one of {CALIB_METHODS}, got {method!r}")
    if activation_type not in ACTIVATION_TYPES:
        raise ValueError(f"activation_type must be one of {ACTIVATION_TYPES}, got {activation_type!r}")
    if not fp32_onnx.is_file():
        raise FileNotFoundError(f"fp32 model {fp32_onnx} not found")
    images = list(calibration_images)
    if not images:
        raise ValueError("calibration_images is empty: static quantisation needs real inputs to calibrate")
    missing = [p for p in images if not Path(p).is_file()]
    if missing:
        raise FileNotFoundError(f"{len(missing)} calibration image(s) missing, e.g. {missing[0]}")
    import onnx
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    started = time.perf_counter()
    source = onnx.load(str(fp32_onnx))
    with tempfile.TemporaryDirectory(prefix="triscan-quant-") as scratch:
        model_in = fp32_onnx
        if preprocess:
            model_in = Path(scratch) / "preprocessed.onnx"
            quant_pre_process(str(fp32_onnx), str(model_in))
        # Found on the graph actually quantised: pre-processing may fuse or rename nodes.
        graph_in = onnx.load(str(model_in))
        exclude = head_decode_nodes(graph_in) if keep_head_float else []
        reader = _calibration_reader(_input_name(graph_in), images)
        cache = None
        if method == "entropy":
            cache = Path(scratch) / "entropy-ranges.json"
            _entropy_ranges(model_in, reader, cache, Path(scratch))
        quantize_static(
            str(model_in),
            str(Path(scratch) / "int8.onnx"),
            reader,
            quant_format=QuantFormat.QDQ,
            per_channel=per_channel,
            activation_type=QuantType.QUInt8 if activation_type == "uint8" else QuantType.QInt8,
            weight_type=QuantType.QInt8,
            nodes_to_exclude=exclude,
            calibrate_method={
                "minmax": CalibrationMethod.MinMax,
                "entropy": CalibrationMethod.Entropy,
                "percentile": CalibrationMethod.Percentile,
            }[method],
            extra_options={
                "WeightSymmetric": True,
                # Percentile ranges are symmetric by default, wasting half of uint8 on post-SiLU tensors
                # that barely go below zero; the asymmetric ones halved the error again.
                "CalibTensorRangeSymmetric": False,
                "CalibPercentile": PERCENTILE,
            },
            calibration_cache_path=cache,
        )
        model = onnx.load(str(Path(scratch) / "int8.onnx"))
    # The quantiser keeps the graph but not always the file's metadata: copy it all, then say what changed.
    _set_metadata(model, {prop.key: prop.value for prop in source.metadata_props})
    _set_metadata(
        model,
        {
            f"{META_PREFIX}precision": "int8",
            f"{META_PREFIX}quantization": json.dumps(
                {
                    "format": "QDQ",
                    "weights": "int8 symmetric " + ("per-channel" if per_channel else "per-tensor"),
                    "activations": activation_type,
                    "calibration": f"percentile {PERCENTILE} asymmetric"
                    if method == "percentile"
                    else method,
                    "calibration_images": len(images),
                    "float_head_nodes": len(exclude),
                    "source_fp32": f"{fp32_onnx.name} sha256:{file_sha256(fp32_onnx)[:SHA_PREFIX]}",
                },
                sort_keys=True,
            ),
        },
    )
    _save_checked(model, out)
    log.info(
        "quantised %s → %s (%s, %d calibration images, %d head nodes float, %.1f MB, %.1f s)",
        fp32_onnx,
        out,
        method,
        len(images),
        len(exclude),
        out.stat().st_size / 1e6,
        time.perf_counter() - started,
    )
    return out


# --- batch variants ------------------------------------------------------------------------------------

BATCH_AXIS = "batch"
_BATCH_CHECK_FRAMES = 3  # frames run one by one and as one batch to prove the variant computes the same


def add_batch_axis(model_path: Path, out: Path) -> Path:
    """Write a copy of a fixed-shape triscan model whose batch axis is free, for a detector serving a fleet.

    The copy is the same graph, weights and (for INT8) quantisation scales: only the graph's batch
    dimension becomes the symbolic ``batch`` and the leading ``1`` of every Reshape target becomes
    ``0`` ("copy the input's dimension"), the head's only places that spell the batch size out. A
    re-export with ``dynamic=True`` would instead re-trace the network and, for INT8, re-calibrate it:
    a new model to evaluate rather than the evaluated one. Before writing, ``_BATCH_CHECK_FRAMES``
    frames are run one by one through the source and as one batch through the copy; any difference
    beyond float rounding refuses the copy (measured on the shipped models: bit-identical).
    """
    import onnx
    from onnx import numpy_helper

    model_path, out = Path(model_path), Path(out)
    if not model_path.is_file():
        raise FileNotFoundError(f"model {model_path} not found")
    model = onnx.load(str(model_path))
    _check_io(model, model_path)  # only a fixed batch-1 triscan model is a known starting point
    initializers = {t.name: t for t in model.graph.initializer}
    rewritten: set[str] = set()
    for node in model.graph.node:
        if node.op_type != "Reshape" or node.input[1] in rewritten:
            continue  # Reshapes may share one shape initializer
        target = initializers.get(node.input[1])
        shape = numpy_helper.to_array(target).copy() if target is not None else None
        if shape is None or shape.ndim != 1 or shape.size == 0 or shape[0] != 1:
            raise ExportError(
                f"{model_path}: Reshape {node.name!r} has a target shape other than a constant [1, ...]; "
                "re-export with `dynamic=True` instead"
            )
        shape[0] = 0
        target.CopyFrom(numpy_helper.from_array(shape, target.name))
        rewritten.add(node.input[1])
    for value in (*model.graph.input, *model.graph.output):
        dim = value.type.tensor_type.shape.dim[0]
        dim.Clear()
        dim.dim_param = BATCH_AXIS
    del model.graph.value_info[:]  # inferred shapes still say batch 1; infer them again
    model = onnx.shape_inference.infer_shapes(model, strict_mode=True)
    _set_metadata(
        model,
        {
            f"{META_PREFIX}batch": BATCH_AXIS,
            f"{META_PREFIX}batch_source": f"{model_path.name} sha256:{file_sha256(model_path)[:SHA_PREFIX]}",
        },
    )
    with tempfile.TemporaryDirectory(prefix="triscan-batch-") as scratch:
        candidate = Path(scratch) / out.name
        _save_checked(model, candidate, BATCH_AXIS)
        _check_batch_equivalence(model_path, candidate)
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(candidate, out)
    log.info("batch variant of %s → %s (%d Reshape targets rewritten)", model_path, out, len(rewritten))
    return out


def _check_batch_equivalence(single: Path, batched: Path, atol: float = 1e-4) -> None:
    """Raise unless a batch through ``batched`` equals its frames run one by one through ``single``."""
    rng = np.random.default_rng(0)
    # Sparse binary frames like real rasters (a few % of pixels hit), distinct per frame.
    frames = (rng.random((_BATCH_CHECK_FRAMES, *INPUT_SHAPE[1:])) < 0.03).astype(np.float32)
    one, many = _session(single), _session(batched)
    name = one.get_inputs()[0].name
    expected = np.concatenate([one.run(None, {name: frames[i : i + 1]})[0] for i in range(len(frames))])
    got = many.run(None, {many.get_inputs()[0].name: frames})[0]
    if got.shape != expected.shape or not np.allclose(got, expected, rtol=0, atol=atol):
        worst = float(np.abs(got - expected).max()) if got.shape == expected.shape else float("nan")
        raise ExportError(
            f"{batched}: a batch of {len(frames)} differs from the frames run one by one through {single} "
            f"(shape {list(got.shape)} vs {list(expected.shape)}, max |diff| {worst:.3g})"
        )


# --- measurement ---------------------------------------------------------------------------------------


def _session(onnx_path: Path, threads: int = 1) -> Any:
    import onnxruntime as ort

    return ort.InferenceSession(str(onnx_path), session_options(threads), providers=["CPUExecutionProvider"])


def compare_outputs(
    fp32_onnx: Path, int8_onnx: Path, images: Iterable[Path], *, confident: float = CONFIDENT_SCORE
) -> dict[str, float]:
    """Absolute differences of raw outputs INT8 vs fp32 (boxes in px, scores in 0–1) over ``images``.

    Raw outputs, before thresholds and NMS, so the numbers say how far quantisation moved the network
    itself, independent of any decode setting. Over all anchors they are dominated by background
    cells, whose boxes nobody reads; the ``confident_*`` entries restrict them to anchors where fp32
    scores some class ≥ ``confident`` — the candidate detections — and add the share of those whose
    best class is unchanged. They are absent when no anchor is confident (an untrained model).
    """
    reference, quantised = _session(fp32_onnx), _session(int8_onnx)
    name = reference.get_inputs()[0].name
    box_diffs, score_diffs, kept_boxes, kept_scores, agree = [], [], [], [], []
    for path in images:
        x = to_model_input(read_tensor_png(path))
        a = reference.run(None, {name: x})[0][0]
        b = quantised.run(None, {name: x})[0][0]
        box, score = np.abs(a[:BOX_CHANNELS] - b[:BOX_CHANNELS]), np.abs(a[BOX_CHANNELS:] - b[BOX_CHANNELS:])
        box_diffs.append(box)
        score_diffs.append(score)
        mask = a[BOX_CHANNELS:].max(axis=0) >= confident
        kept_boxes.append(box[:, mask])
        kept_scores.append(score[:, mask])
        agree.append(np.argmax(a[BOX_CHANNELS:, mask], axis=0) == np.argmax(b[BOX_CHANNELS:, mask], axis=0))
    if not box_diffs:
        raise ValueError("compare_outputs needs at least one image")
    boxes, scores = np.stack(box_diffs), np.stack(score_diffs)
    result = {
        "images": float(len(box_diffs)),
        "box_max_abs_px": float(boxes.max()),
        "box_mean_abs_px": float(boxes.mean()),
        "score_max_abs": float(scores.max()),
        "score_mean_abs": float(scores.mean()),
        "confident_anchors": float(sum(m.size for m in agree)),
    }
    if result["confident_anchors"]:
        confident_boxes = np.concatenate(kept_boxes, axis=1)
        confident_scores = np.concatenate(kept_scores, axis=1)
        result |= {
            "confident_box_max_abs_px": float(confident_boxes.max()),
            "confident_box_mean_abs_px": float(confident_boxes.mean()),
            "confident_score_max_abs": float(confident_scores.max()),
            "confident_score_mean_abs": float(confident_scores.mean()),
            "confident_class_agreement": float(np.concatenate(agree).mean()),
        }
    return result


def median_latency_ms(
    onnx_paths: Sequence[Path], image: Path, *, runs: int = 200, warmup: int = 20, threads: int = 1
) -> list[float]:
    """Median single-image ``session.run`` time in ms of each model, after ``warmup`` untimed runs.

    The models take turns run by run, so a background load (training, another process) slows them
    alike instead of whichever happened to be measured second; the median ignores scheduler hiccups
    better than the mean. One intra-op thread by default, like the robot's detector, which shares its
    cores with the encoder and Zenoh.
    """
    if runs < 1 or warmup < 0:
        raise ValueError(f"runs must be >= 1 and warmup >= 0, got {runs}, {warmup}")
    sessions = [_session(Path(p), threads) for p in onnx_paths]
    x = to_model_input(read_tensor_png(image))
    feeds = [{s.get_inputs()[0].name: x} for s in sessions]
    for session, feed in zip(sessions, feeds, strict=True):
        for _ in range(warmup):
            session.run(None, feed)
    times: list[list[float]] = [[] for _ in sessions]
    for _ in range(runs):
        for session, feed, samples in zip(sessions, feeds, times, strict=True):
            started = time.perf_counter()
            session.run(None, feed)
            samples.append((time.perf_counter() - started) * 1e3)
    return [statistics.median(samples) for samples in times]


# --- both models ---------------------------------------------------------------------------------------


def _describe(path: Path) -> dict[str, Any]:
    return {"path": str(path), "bytes": path.stat().st_size, "sha256": file_sha256(path)}


def export_models(
    weights: Path,
    dataset_dir: Path,
    models_dir: Path,
    *,
    name: str,
    padding: str | None = None,
    calib_count: int = DEFAULT_CALIB_COUNT,
    method: CalibMethod = "percentile",
    activation_type: ActivationType = "uint8",
    compare_count: int = 20,
    timing_runs: int = 200,
) -> dict[str, Any]:
    """Write ``<name>.onnx`` (fp32) and ``<name>-int8.onnx`` into ``models_dir``, each with its batch
    variant (``-batch``, :func:`add_batch_axis`) for a detector serving many robots; describe them.

    ``dataset_dir`` (or its ``data.yaml``) is the set the weights were trained on: it supplies the
    calibration images (its ``val`` split) and the padding; ``padding``, when given, must match it.
    The returned dict holds each file's path, size and sha256, plus the raw-output differences INT8
    vs fp32 on ``compare_count`` val images the calibrator did not see (a sanity check; the accuracy
    verdict belongs to the evaluation on the test split) and, unless ``timing_runs`` is 0, the median
    single-thread ``session.run`` time of each on this machine.
    """
    weights, dataset_dir, models_dir = Path(weights), Path(dataset_dir), Path(models_dir)
    if dataset_dir.is_file():  # a data.yaml, as `triscan train --data` takes
        dataset_dir = dataset_dir.parent
    if not weights.is_file():
        raise FileNotFoundError(f"weights {weights} not found")
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", name):
        raise ValueError(f"name must be a plain file stem ([A-Za-z0-9._-]), got {name!r}")
    recorded_padding = _resolve_padding(padding, dataset_dir)
    calibration = calibration_images(dataset_dir, calib_count)
    fp32 = export_onnx(weights, models_dir / f"{name}.onnx", padding=recorded_padding)
    int8 = quantize_int8(
        fp32,
        models_dir / f"{name}-int8.onnx",
        calibration,
        method=method,
        activation_type=activation_type,
    )
    fp32_batch = add_batch_axis(fp32, batch_variant_path(fp32))
    int8_batch = add_batch_axis(int8, batch_variant_path(int8))
    # Judge on val images the calibrator did not see: ranges fitted to an image flatter its own error.
    unseen = sorted(set(calibration_images(dataset_dir, 10**9)) - set(calibration))
    compare = _spread(unseen, compare_count) if unseen else calibration[:compare_count]
    result = {
        "fp32": _describe(fp32),
        "int8": _describe(int8),
        "fp32_batch": _describe(fp32_batch),
        "int8_batch": _describe(int8_batch),
        "padding": recorded_padding,
        "classes": list(CLASS_NAMES),
        "calibration_images": len(calibration),
        "calibration_method": method,
        "int8_vs_fp32": compare_outputs(fp32, int8, compare),
    }
    log.info("INT8 vs fp32 on %d unseen val images: %s", len(compare), result["int8_vs_fp32"])
    if timing_runs > 0:
        fp32_ms, int8_ms = median_latency_ms([fp32, int8], compare[0], runs=timing_runs)
        result["latency_ms_1_thread"] = {"fp32": fp32_ms, "int8": int8_ms}
        log.info("median session.run, 1 thread: fp32 %.2f ms, INT8 %.2f ms", fp32_ms, int8_ms)
    return result
