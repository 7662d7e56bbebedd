"""fp32 ONNX → static INT8 (QDQ) ONNX, calibrated on the data set's own validation PNGs.

The INT8 model is ONNX Runtime static quantisation in QDQ format with per-channel weight scales and
MinMax activation ranges, calibrated on validation PNGs fed through exactly the run-time conversion
(:func:`common.encoding.to_model_input`). Three parts of the network stay float. The detection head's
decode tail (DFL softmax, box arithmetic, class sigmoid, the final concat of pixel boxes with 0–1
scores): one 8-bit scale spanning boxes up to 384 px and scores below 1 rounds scores to a few levels
(measured: 28 % of candidate detections changed class). The box logits feeding it (the last conv of
each box branch): the DFL reads a box edge as the softmax-weighted mean of 16 bins, and 8-bit logits
move that mean, which costs box tightness (mAP@0.5:0.95), not detections. And the leading modules of
the backbone, which read the sparse 0/1 raster at full resolution: quantising the stem is where a
trained pico model lost the most mAP@0.5 (24 points with percentile ranges), and the modules after
it hold most of what INT8 still lost in mAP@0.5:0.95. On the pico's val split, with the box logits
float, keeping modules past 0–4 float bought nothing further, so the stem and the stride-8 stage,
modules 0–4, stay float. They are the layers with the fewest channels: no measurable speed cost.
``python -m training.int8_recipes`` compares the recipes by mAP for any model.
Whether INT8 ships is decided by evaluation, not here.

Choosing the calibration images lives here as well (:func:`calibration_images`): which frames the
ranges are fitted to is part of the quantisation recipe, recorded in the model's metadata.
"""

from __future__ import annotations

import json
import logging
import re
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal, cast, get_args

import numpy as np

from common.encoding import to_model_input
from common.model_spec import META_PREFIX
from training.onnx_model import ExportError, input_name, provenance, save_checked, set_metadata
from training.png import read_tensor_png
from training.recipe import load_recipe

log = logging.getLogger(__name__)

_SHIPPED = load_recipe().export  # the defaults below are the shipped recipe's
DEFAULT_CALIB_COUNT: int = _SHIPPED.calib_count
PERCENTILE = 99.999  # share of calibration values the "percentile" activation ranges keep
ENTROPY_BINS = 2048  # histogram resolution for KL calibration, as TensorRT uses
ENTROPY_QUANTIZED_BINS = 128  # ONNX Runtime's default target bin count for the KL search

CalibMethod = Literal["minmax", "entropy", "percentile"]
CALIB_METHODS: tuple[str, ...] = get_args(CalibMethod)
DEFAULT_CALIB_METHOD = cast(CalibMethod, _SHIPPED.calib_method)
ActivationType = Literal["uint8", "int8"]
ACTIVATION_TYPES: tuple[str, ...] = get_args(ActivationType)
DEFAULT_ACTIVATION_TYPE = cast(ActivationType, _SHIPPED.activations)
DEFAULT_FLOAT_LEADING_MODULES: int = _SHIPPED.float_modules
if DEFAULT_CALIB_METHOD not in CALIB_METHODS or DEFAULT_ACTIVATION_TYPE not in ACTIVATION_TYPES:
    raise ValueError(f"the shipped recipe names an unknown INT8 setting: {_SHIPPED}")


# --- calibration data ----------------------------------------------------------------------------------


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
    return spread_evenly(images, count)


def spread_evenly(items: Sequence[Path], count: int) -> list[Path]:
    """``count`` items at evenly spaced positions, first and last included (all when there are fewer)."""
    if count >= len(items):
        return list(items)
    picks = np.unique(np.round(np.linspace(0, len(items) - 1, count)).astype(np.int64))
    return [items[i] for i in picks]


def calibration_reader(feed_name: str, images: Sequence[Path]) -> Any:
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
            return None if path is None else {feed_name: to_model_input(read_tensor_png(path))}

        def rewind(self) -> None:
            self._iter = iter(self._paths)

    return PngCalibrationReader()


# --- INT8 quantisation ---------------------------------------------------------------------------------


_MODULE_PATH = re.compile(r"/model\.(\d+)/")  # ONNX node names follow Ultralytics module paths


def _module_index(node_name: str) -> int | None:
    """The Ultralytics module index N of a ``/model.N/…`` node name; None for any other node."""
    return int(m[1]) if (m := _MODULE_PATH.match(node_name)) else None


def _module_ids(model: Any) -> list[int]:
    """The module index of every ``/model.N/…`` node."""
    ids = [i for n in model.graph.node if (i := _module_index(n.name)) is not None]
    if not ids:
        raise ExportError("no /model.N/ node names: not an Ultralytics YOLO ONNX export")
    return ids


def _detect_head(model: Any) -> tuple[str, tuple[str, str]]:
    """The Detect head's node-name prefix (``/model.<last>/``) and those of its per-stride conv branches
    (``cv2.`` box distributions, ``cv3.`` class logits), which every head rule below splits on."""
    prefix = f"/model.{max(_module_ids(model))}/"
    return prefix, (f"{prefix}cv2.", f"{prefix}cv3.")


def head_decode_nodes(model: Any) -> list[str]:
    """Names of the detection head's decode nodes: everything after its per-stride conv branches.

    Ultralytics names ONNX nodes by module path; the Detect head is the last module
    (``/model.22/``) and its branches are ``cv2.*`` (box distributions) and ``cv3.*`` (class logits).
    The rest of the head — reshapes, concats, DFL softmax and conv, box arithmetic, sigmoid, the output
    concat — mixes pixel-scale boxes with 0–1 scores and is left in float.
    """
    prefix, branches = _detect_head(model)
    tail = [n.name for n in model.graph.node if n.name.startswith(prefix) and not n.name.startswith(branches)]
    output = model.graph.output[0].name
    producers = {o: n.name for n in model.graph.node for o in n.output}
    if producers.get(output) not in tail:
        raise ExportError(f"the head's decode tail under {prefix} does not produce the output {output!r}")
    return tail


def leading_module_nodes(model: Any, count: int) -> list[str]:
    """Names of the nodes of the network's first ``count`` modules (``/model.0/`` … ``/model.<count-1>/``).

    Module 0 is the stem, a single 3→c conv, the only layer that sees the raster itself: a few lit
    pixels per column in a field of zeros. With percentile ranges on the trained pico network, keeping
    it float was the difference between test recall 0.96 and 0.63; the modules after it, still at
    high resolution on sparse activations, are the next most sensitive (module docstring). ``count``
    may reach up to the head, never into it.
    """
    head = max(_module_ids(model))
    if not 0 <= count <= head:
        raise ValueError(
            f"float leading modules must be 0 to {head} (the head is /model.{head}/), got {count}"
        )
    return [n.name for n in model.graph.node if (i := _module_index(n.name)) is not None and i < count]


def float_modules_label(count: int) -> str:
    """How reports name the first ``count`` modules kept float: "" (none), "stem", "modules 0–4"."""
    return {0: "", 1: "stem"}.get(count, f"modules 0–{count - 1}")


def _last_convs(model: Any, branch: int, what: str) -> list[str]:
    """Names of the nodes of the last conv of each stride's ``cv2`` (``branch`` 0) or ``cv3`` (1)."""
    prefix = _detect_head(model)[1][branch]  # /model.<head>/cv2. or cv3.
    pattern = re.compile(re.escape(prefix.rsplit("/", 1)[1]) + r"\d+\.2/")
    nodes = [n.name for n in model.graph.node if n.name.startswith(prefix) and pattern.search(n.name)]
    if not nodes:
        raise ExportError(f"no {what} convs under {prefix}: not an Ultralytics Detect head")
    return nodes


def box_logit_nodes(model: Any) -> list[str]:
    """Names of the box branches' last convs in the Detect head (``/model.<head>/cv2.<i>.2/…``).

    Their outputs are the 16-bin distance distributions the DFL decodes into box edges.
    """
    return _last_convs(model, 0, "box-logit")


def class_logit_nodes(model: Any) -> list[str]:
    """Names of the class branches' last convs in the Detect head (``/model.<head>/cv3.<i>.2/…``).

    Their outputs are the class logits the decode turns into scores. One uint8 range per stride covers
    every anchor's logit, and nearly all anchors are background far below zero, so a quantised logit
    moves in steps of up to half a logit (scores 0.38, 0.5, 0.62, …) and is cut at the largest value
    calibration saw: at a stride where no calibration image scored above 0.5, no detection ever can.
    """
    return _last_convs(model, 1, "class-logit")


def head_conv_nodes(model: Any) -> list[str]:
    """Names of every node in the Detect head's per-stride conv branches (``cv2.*`` boxes, ``cv3.*``
    classes), the box logits among them.

    Kept float together they are the whole path from the neck to the decode: measured on the
    50-epoch pico, INT8 then lost 0.2 points of val mAP@0.5:0.95 against fp32 instead of 0.8, for
    about a quarter more time per frame (README, "A longer pico run").
    """
    prefix, branches = _detect_head(model)
    nodes = [n.name for n in model.graph.node if n.name.startswith(branches)]
    if not nodes:
        raise ExportError(f"no conv branches under {prefix}: not an Ultralytics Detect head")
    return nodes


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


def _checked_calibration_inputs(
    fp32_onnx: Path, images: Sequence[Path], method: str, activation_type: str
) -> list[Path]:
    """The calibration images as a list, once the arguments of :func:`quantize_int8` are known good."""
    if method not in CALIB_METHODS:
        raise ValueError(f"method must be one of {CALIB_METHODS}, got {method!r}")
    if activation_type not in ACTIVATION_TYPES:
        raise ValueError(f"activation_type must be one of {ACTIVATION_TYPES}, got {activation_type!r}")
    if not fp32_onnx.is_file():
        raise FileNotFoundError(f"fp32 model {fp32_onnx} not found")
    checked = list(images)
    if not checked:
        raise ValueError("calibration_images is empty: static quantisation needs real inputs to calibrate")
    missing = [p for p in checked if not Path(p).is_file()]
    if missing:
        raise FileNotFoundError(f"{len(missing)} calibration image(s) missing, e.g. {missing[0]}")
    return checked


def _quantize_static(
    model_in: Path,
    reader: Any,
    exclude: list[str],
    scratch: Path,
    *,
    method: CalibMethod,
    per_channel: bool,
    activation_type: ActivationType,
) -> Any:
    """ONNX Runtime's ``quantize_static`` with triscan's settings; the quantised model, loaded."""
    import onnx
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    cache = None
    if method == "entropy":
        cache = scratch / "entropy-ranges.json"
        _entropy_ranges(model_in, reader, cache, scratch)
    quantize_static(
        str(model_in),
        str(scratch / "int8.onnx"),
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
    return onnx.load(str(scratch / "int8.onnx"))


def _quantization_record(
    fp32_onnx: Path,
    *,
    method: CalibMethod,
    per_channel: bool,
    activation_type: ActivationType,
    calibration_count: int,
    float_head_nodes: int,
    float_leading_modules: int,
    float_leading_nodes: int,
    float_box_logit_nodes: int,
    float_class_logit_nodes: int,
    float_head_conv_nodes: int,
) -> str:
    """The ``triscan.quantization`` metadata value: how this INT8 file was made, as sorted JSON."""
    return json.dumps(
        {
            "format": "QDQ",
            "weights": "int8 symmetric " + ("per-channel" if per_channel else "per-tensor"),
            "activations": activation_type,
            "calibration": f"percentile {PERCENTILE} asymmetric" if method == "percentile" else method,
            "calibration_images": calibration_count,
            "float_box_logit_nodes": float_box_logit_nodes,
            "float_class_logit_nodes": float_class_logit_nodes,
            "float_head_conv_nodes": float_head_conv_nodes,
            "float_head_nodes": float_head_nodes,
            "float_leading_modules": float_leading_modules,
            "float_leading_nodes": float_leading_nodes,
            "source_fp32": provenance(fp32_onnx),
        },
        sort_keys=True,
    )


def quantize_int8(
    fp32_onnx: Path,
    out: Path,
    calibration_images: Sequence[Path],
    *,
    per_channel: bool = True,
    method: CalibMethod = DEFAULT_CALIB_METHOD,
    activation_type: ActivationType = DEFAULT_ACTIVATION_TYPE,
    keep_head_float: bool = True,
    float_leading_modules: int = DEFAULT_FLOAT_LEADING_MODULES,
    keep_box_logits_float: bool = True,
    keep_class_logits_float: bool = True,
    keep_head_convs_float: bool = False,
    preprocess: bool = True,
) -> Path:
    """Statically quantise an fp32 ONNX model to INT8 (QDQ) at ``out``.

    Weights are symmetric signed 8-bit, by default with one scale per output channel: fused conv+BN
    weights differ by orders of magnitude between channels, and with MinMax ranges one per-tensor
    scale gave 1.4× the box error (with the default percentile ranges the two were within noise, so
    per-channel stays as the safer choice at no measured speed cost). Activations default to unsigned
    8-bit, ONNX Runtime's advice for x86 CPUs; ``int8`` is its advice for ARM (on this x86 machine it
    ran 3× slower than ``uint8``, slower than fp32, so build the ARM model for ARM and time it there).

    ``method`` picks the activation ranges. ``minmax`` (the default) makes every calibration value
    representable. ``percentile`` keeps 99.999 % of each tensor's values in an asymmetric range and
    clips the rare outliers: on an untrained epoch-1 checkpoint it moved candidate boxes less
    (0.25 px against 1.15), but on the trained pico network with everything but the head's decode
    quantised it fell to test mAP@0.5 0.745 against fp32's 0.985, where ``minmax`` kept 0.982; with
    the stem float as well, ``minmax`` matched fp32. Accuracy, not raw-output distance, decides, and
    ``python -m training.int8_recipes`` reruns that comparison for any model. ``entropy`` is
    TensorRT's KL search; it clipped too hard on these sparse scans (6 px).

    ``float_leading_modules`` leaves the first N modules float (:func:`leading_module_nodes`; 1 is the
    stem alone, 0 quantises it too), ``keep_box_logits_float`` the box branches' last convs
    (:func:`box_logit_nodes`), ``keep_class_logits_float`` the class branches' last convs
    (:func:`class_logit_nodes`), ``keep_head_convs_float`` every conv branch of the Detect head, box
    logits included (:func:`head_conv_nodes`), ``keep_head_float`` the head's decode tail
    (:func:`head_decode_nodes`).

    ``preprocess`` runs ONNX Runtime's ``quant_pre_process`` (shape inference and graph
    optimisation) first, which its quantiser recommends so that every tensor has a known shape.
    """
    fp32_onnx, out = Path(fp32_onnx), Path(out)
    images = _checked_calibration_inputs(fp32_onnx, calibration_images, method, activation_type)
    import onnx
    from onnxruntime.quantization.shape_inference import quant_pre_process

    started = time.perf_counter()
    source = onnx.load(str(fp32_onnx))
    with tempfile.TemporaryDirectory(prefix="triscan-quant-") as scratch:
        model_in = fp32_onnx
        if preprocess:
            model_in = Path(scratch) / "preprocessed.onnx"
            # ONNX's own shape inference gives every tensor of a fixed-shape triscan graph its shape
            # (the quantised graph came out the same with and without the symbolic pass), and the
            # symbolic pass cannot infer the DFL's ReduceMax (training.onnx_rewrites), whose axes are
            # an input: it stops there.
            quant_pre_process(str(fp32_onnx), str(model_in), skip_symbolic_shape=True)
        # Found on the graph actually quantised: pre-processing may fuse or rename nodes.
        graph_in = onnx.load(str(model_in))
        head = head_decode_nodes(graph_in) if keep_head_float else []
        leading = leading_module_nodes(graph_in, float_leading_modules)
        box_logits = box_logit_nodes(graph_in) if keep_box_logits_float else []
        class_logits = class_logit_nodes(graph_in) if keep_class_logits_float else []
        head_convs = head_conv_nodes(graph_in) if keep_head_convs_float else []
        reader = calibration_reader(input_name(graph_in), images)
        model = _quantize_static(
            model_in,
            reader,
            sorted(set(head + leading + box_logits + class_logits + head_convs)),
            Path(scratch),
            method=method,
            per_channel=per_channel,
            activation_type=activation_type,
        )
    # The quantiser keeps the graph but not always the file's metadata: copy it all, then say what changed.
    set_metadata(model, {prop.key: prop.value for prop in source.metadata_props})
    quantization = _quantization_record(
        fp32_onnx,
        method=method,
        per_channel=per_channel,
        activation_type=activation_type,
        calibration_count=len(images),
        float_head_nodes=len(head),
        float_leading_modules=float_leading_modules,
        float_leading_nodes=len(leading),
        float_box_logit_nodes=len(box_logits),
        float_class_logit_nodes=len(class_logits),
        float_head_conv_nodes=len(head_convs),
    )
    set_metadata(model, {f"{META_PREFIX}precision": "int8", f"{META_PREFIX}quantization": quantization})
    save_checked(model, out)
    log.info(
        "quantised %s → %s (%s, %d calibration images, float: %d head, %d box-logit, %d nodes of %d leading"
        " modules; %.1f MB, %.1f s)",
        fp32_onnx,
        out,
        method,
        len(images),
        len(head),
        len(box_logits),
        len(leading),
        float_leading_modules,
        out.stat().st_size / 1e6,
        time.perf_counter() - started,
    )
    return out
