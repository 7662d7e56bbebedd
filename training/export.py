"""``triscan export``: trained YOLOv8n → the four ONNX files the robot may load, described and checked.

One command writes them all from one checkpoint and its data set, so that what ships always comes as
a consistent set: the fixed-shape fp32 model (:mod:`training.onnx_export`), its static INT8 (QDQ)
quantisation calibrated on the set's val split (:mod:`training.quantization`), and a ``-batch``
variant of each with a free batch axis for a detector serving a fleet (:mod:`training.batch_variant`).
The report it returns names every file by size and sha256 and adds the sanity figures of
:mod:`training.export_checks` — INT8 vs fp32 on val images the calibrator did not see, and the
single-thread ``session.run`` time of each — which the model card quotes.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

from common.model_spec import DEFAULT_BOX_GRID, batch_variant_path, file_sha256, model_stem
from training.architectures import network_of_checkpoint
from training.batch_variant import add_batch_axis
from training.export_checks import compare_outputs, median_latency_ms
from training.onnx_export import dataset_invalid_rule, dataset_raster_yaw, export_onnx, resolve_padding
from training.onnx_model import declared_class_names
from training.quantization import (
    DEFAULT_ACTIVATION_TYPE,
    DEFAULT_CALIB_COUNT,
    DEFAULT_CALIB_METHOD,
    DEFAULT_FLOAT_LEADING_MODULES,
    ActivationType,
    CalibMethod,
    calibration_images,
    quantize_int8,
    spread_evenly,
)

log = logging.getLogger(__name__)


def _describe(path: Path) -> dict[str, Any]:
    return {"path": str(path), "bytes": path.stat().st_size, "sha256": file_sha256(path)}


def export_models(
    weights: Path,
    dataset_dir: Path,
    models_dir: Path,
    *,
    name: str | None = None,
    padding: str | None = None,
    calib_count: int = DEFAULT_CALIB_COUNT,
    method: CalibMethod = DEFAULT_CALIB_METHOD,
    activation_type: ActivationType = DEFAULT_ACTIVATION_TYPE,
    float_leading_modules: int = DEFAULT_FLOAT_LEADING_MODULES,
    keep_box_logits_float: bool = True,
    keep_class_logits_float: bool = True,
    keep_head_convs_float: bool = False,
    compare_count: int = 20,
    timing_runs: int = 200,
    box_grid: str = DEFAULT_BOX_GRID,
) -> dict[str, Any]:
    """Write ``<name>.onnx`` (fp32) and ``<name>-int8.onnx`` into ``models_dir``, each with its batch
    variant (``-batch``, :func:`add_batch_axis`) for a detector serving many robots; describe them.
    ``name`` None: ``triscan-<network>-<padding>[-invalid-<rule>]`` (:func:`common.model_spec.model_stem`),
    the network read from the checkpoint and the rule from the data set, so a pico model is never
    written under YOLOv8n's name, nor an ``--invalid empty`` model under the sentinel one's.

    ``dataset_dir`` (or its ``data.yaml``) is the set the weights were trained on: it supplies the
    calibration images (its ``val`` split), the padding and the raster yaw; ``padding``, when given,
    must match it.
    The returned dict holds each file's path, size and sha256, plus the raw-output differences INT8
    vs fp32 on ``compare_count`` val images the calibrator did not see (a sanity check; the accuracy
    verdict belongs to the evaluation on the test split) and, unless ``timing_runs`` is 0, the median
    single-thread ``session.run`` time of each on this machine. ``box_grid`` goes into every file's
    metadata (:func:`export_onnx`).
    """
    weights, dataset_dir, models_dir = Path(weights), Path(dataset_dir), Path(models_dir)
    if dataset_dir.is_file():  # a data.yaml, as `triscan train --data` takes
        dataset_dir = dataset_dir.parent
    if not weights.is_file():
        raise FileNotFoundError(f"weights {weights} not found")
    recorded_padding = resolve_padding(padding, dataset_dir)
    recorded_invalid = dataset_invalid_rule(dataset_dir)
    recorded_yaw = dataset_raster_yaw(dataset_dir)
    if name is None:
        name = model_stem(network_of_checkpoint(weights), recorded_padding, recorded_invalid)
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", name):
        raise ValueError(f"name must be a plain file stem ([A-Za-z0-9._-]), got {name!r}")
    calibration = calibration_images(dataset_dir, calib_count)
    fp32 = export_onnx(
        weights,
        models_dir / f"{name}.onnx",
        padding=recorded_padding,
        invalid=recorded_invalid,
        raster_yaw_deg=recorded_yaw,
        box_grid=box_grid,
    )
    int8 = quantize_int8(
        fp32,
        models_dir / f"{name}-int8.onnx",
        calibration,
        method=method,
        activation_type=activation_type,
        float_leading_modules=float_leading_modules,
        keep_box_logits_float=keep_box_logits_float,
        keep_class_logits_float=keep_class_logits_float,
        keep_head_convs_float=keep_head_convs_float,
    )
    fp32_batch = add_batch_axis(fp32, batch_variant_path(fp32))
    int8_batch = add_batch_axis(int8, batch_variant_path(int8))
    # Judge on val images the calibrator did not see: ranges fitted to an image flatter its own error.
    unseen = sorted(set(calibration_images(dataset_dir, 10**9)) - set(calibration))
    compare = spread_evenly(unseen, compare_count) if unseen else calibration[:compare_count]
    result = {
        "fp32": _describe(fp32),
        "int8": _describe(int8),
        "fp32_batch": _describe(fp32_batch),
        "int8_batch": _describe(int8_batch),
        "padding": recorded_padding,
        "raster_yaw_deg": recorded_yaw,
        "box_grid": box_grid,
        "classes": list(declared_class_names(_onnx_load(fp32))),
        "calibration_images": len(calibration),
        "calibration_method": method,
        "float_leading_modules": float_leading_modules,
        "float_box_logits": keep_box_logits_float,
        "float_class_logits": keep_class_logits_float,
        "float_head_convs": keep_head_convs_float,
        "int8_vs_fp32": compare_outputs(fp32, int8, compare),
    }
    log.info("INT8 vs fp32 on %d unseen val images: %s", len(compare), result["int8_vs_fp32"])
    if timing_runs > 0:
        fp32_ms, int8_ms = median_latency_ms([fp32, int8], compare[0], runs=timing_runs)
        result["latency_ms_1_thread"] = {"fp32": fp32_ms, "int8": int8_ms}
        log.info("median session.run, 1 thread: fp32 %.2f ms, INT8 %.2f ms", fp32_ms, int8_ms)
    return result


def _onnx_load(path: Path) -> Any:
    import onnx

    return onnx.load(str(path))
