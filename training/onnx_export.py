"""Trained YOLOv8n checkpoint → the fixed-shape fp32 ONNX file the robot runs, padding recorded.

The robot runs ONNX Runtime, never torch, so the checkpoint is exported once here with the shape it
will always see: ``float32[1, 3, 64, 384]`` (batch 1, no dynamic axes: a fixed graph lets ONNX Runtime
plan memory once and keeps the INT8 calibration valid for every input). Besides Ultralytics' own
metadata (names, imgsz, stride) each file carries ``triscan.*`` metadata — padding mode, invalid-return
rule, raster yaw, class list, source weights — so a detector can refuse a model trained on the other padding
instead of silently mixing ``zero`` and ``wrap`` (README, "The encoding"). Which padding to record is
decided here too
(:func:`resolve_padding`): the data set's word wins, and a caller who says otherwise gets an error.
"""

from __future__ import annotations

import json
import logging
import re
import shutil
import tempfile
import time
from pathlib import Path

from common.encoding import IMAGE_WIDTH, INVALID_RULES, PADDINGS, RANGE_ROWS, check_raster_yaw
from common.model_meta import metadata_entries
from common.model_spec import BOX_GRIDS, CLASS_NAMES, DEFAULT_BOX_GRID, META_PREFIX
from services.simulator.defaults import SCAN_PERIOD_S
from training.onnx_model import ExportError, provenance, save_checked, set_metadata
from training.onnx_rewrites import apply_rewrites

log = logging.getLogger(__name__)


def _summary_config(dataset_dir: Path | None) -> dict[str, object] | None:
    """The ``config`` a data set's ``summary.json`` records (``triscan dataset``), or None without one:
    the one reader of the settings every encoding choice below is derived from."""
    summary = dataset_dir / "summary.json" if dataset_dir is not None else None
    if summary is None or not summary.is_file():
        return None
    config = json.loads(summary.read_text()).get("config", {})
    return config if isinstance(config, dict) else {}


def dataset_padding(dataset_dir: Path) -> str | None:
    """The padding a data set was generated with, or None if the directory does not say.

    ``summary.json`` (written by ``triscan dataset``) is authoritative; the comment line of
    ``data.yaml`` is the fallback for a set whose summary was not copied along.
    """
    config = _summary_config(dataset_dir)
    if config is not None:
        padding = config.get("padding")
        if padding in PADDINGS:
            return str(padding)
    data_yaml = dataset_dir / "data.yaml"
    if data_yaml.is_file():
        match = re.search(r"padding (\w+)", data_yaml.read_text())
        if match and match.group(1) in PADDINGS:
            return match.group(1)
    return None


def dataset_invalid_rule(dataset_dir: Path | None) -> str:
    """Where the data set put invalid returns: its ``summary.json`` says; sets made before the option
    existed (no key) and sets whose summary is gone used the paper's sentinel row."""
    config = _summary_config(dataset_dir)
    if config is None:
        return "sentinel"
    rule = config.get("invalid", "sentinel")
    if rule not in INVALID_RULES:
        raise ExportError(f"{dataset_dir}/summary.json names an unknown invalid-return rule {rule!r}")
    return str(rule)


def resolve_invalid_rule(requested: str | None, dataset_dir: Path | None) -> str:
    """Invalid-return rule to record in the model: the data set's when its ``summary.json`` is on disk,
    checked against the caller's (as for the padding, a mismatch would pass unnoticed downstream);
    otherwise the caller's, else the paper's sentinel row."""
    if requested is not None and requested not in INVALID_RULES:
        raise ExportError(f"invalid must be one of {INVALID_RULES}, got {requested!r}")
    if _summary_config(dataset_dir) is None:
        return requested or "sentinel"
    derived = dataset_invalid_rule(dataset_dir)
    if requested is not None and requested != derived:
        raise ExportError(
            f"invalid rule {requested!r} requested but the data set {dataset_dir} uses {derived!r}"
        )
    return derived


def dataset_raster_yaw(dataset_dir: Path | None) -> float:
    """Degrees the data set turned its scans and labels by (``triscan dataset --raster-yaw``): its
    ``summary.json`` says, else the comment line of its ``data.yaml``; a set that says nothing (the
    paper's, and every set made before the option) used 0."""
    if dataset_dir is None:
        return 0.0
    data_yaml = dataset_dir / "data.yaml"
    value: object = 0.0
    if (config := _summary_config(dataset_dir)) is not None:
        value = config.get("raster_yaw_deg", 0.0)
    elif data_yaml.is_file() and (match := re.search(r"raster yaw (\S+?)\s*$", data_yaml.read_text(), re.M)):
        value = match.group(1)
    try:
        return check_raster_yaw(float(value))  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ExportError(f"{dataset_dir} records an invalid raster yaw {value!r}") from None


def resolve_raster_yaw(requested: float | None, dataset_dir: Path | None) -> float:
    """Raster yaw to record in the model: the data set's when its ``summary.json`` or ``data.yaml`` is
    on disk, checked against the caller's (a model run on tensors turned otherwise than its training
    set's misplaces every object); otherwise the caller's, else 0."""
    wanted = None if requested is None else check_raster_yaw(requested)
    if dataset_dir is None or not any((dataset_dir / n).is_file() for n in ("summary.json", "data.yaml")):
        return wanted or 0.0
    derived = dataset_raster_yaw(dataset_dir)
    if wanted is not None and wanted != derived:
        raise ExportError(f"raster yaw {wanted:g} requested but the data set {dataset_dir} uses {derived:g}")
    return derived


def resolve_padding(requested: str | None, dataset_dir: Path | None) -> str:
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


def export_onnx(
    weights: Path,
    out: Path,
    *,
    opset: int | None = None,
    padding: str | None = None,
    invalid: str | None = None,
    raster_yaw_deg: float | None = None,
    rewrite_dfl: bool = True,
    box_grid: str = DEFAULT_BOX_GRID,
) -> Path:
    """Export an Ultralytics checkpoint to a fixed-shape fp32 ONNX file at ``out``.

    ``padding`` is read from the data set the checkpoint was trained on (its ``train_args.data``)
    when that set is still on disk; ``padding`` must then agree with it. If neither says, ``zero``
    (the paper's default) is recorded with a warning. ``invalid``, the invalid-return rule, likewise
    (:func:`resolve_invalid_rule`; the sentinel row when neither says), and ``raster_yaw_deg``
    (:func:`resolve_raster_yaw`; 0 when neither says).

    ``box_grid`` (``none``, ``pixel``) is recorded for the detector: whether it rounds the boxes to
    whole pixels after NMS (:func:`common.postprocess.snap_boxes_to_pixels`).

    ``rewrite_dfl`` applies the DFL rewrites of :mod:`training.onnx_rewrites` (the same detections,
    faster); off only to measure what they buy (docs/benchmarks.md, dfl_rewrite).

    Ultralytics writes the ONNX next to the file it loaded, so the checkpoint is copied into a scratch
    directory first: exporting never litters the run directory or the working directory.
    """
    weights = Path(weights)
    out = Path(out)
    if box_grid not in BOX_GRIDS:
        raise ExportError(f"box_grid must be one of {BOX_GRIDS}, got {box_grid!r}")
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
        if tuple(names) != CLASS_NAMES[: len(names)]:
            raise ExportError(
                f"{weights} predicts {names}, not the first {len(names)} triscan classes {list(CLASS_NAMES)}"
            )
        data = (getattr(yolo, "ckpt", None) or {}).get("train_args", {}).get("data")
        dataset_dir = Path(data).parent if data else None
        if dataset_dir is not None and not dataset_dir.is_dir():
            dataset_dir = None
        recorded_padding = resolve_padding(padding, dataset_dir)
        recorded_invalid = resolve_invalid_rule(invalid, dataset_dir)
        recorded_yaw = resolve_raster_yaw(raster_yaw_deg, dataset_dir)
        exported = yolo.export(
            format="onnx",
            imgsz=(RANGE_ROWS, IMAGE_WIDTH),
            batch=1,
            dynamic=False,
            simplify=True,
            opset=opset,
            nms=False,  # NMS runs in common/postprocess.py, where its thresholds are configurable
            device="cpu",  # the same graph whatever accelerator this machine has
            verbose=False,
        )
        model = onnx.load(str(exported))
    if rewrite_dfl:
        apply_rewrites(model)  # records them in the metadata
    set_metadata(
        model,
        {
            **metadata_entries(
                padding=recorded_padding,
                invalid=recorded_invalid,
                box_grid=box_grid,
                classes=names,
                # Every triscan data set stacks scans one simulator period apart (training.dataset).
                stack_period_s=SCAN_PERIOD_S,
                raster_yaw_deg=recorded_yaw,
            ),
            f"{META_PREFIX}source_weights": provenance(weights),
            f"{META_PREFIX}precision": "fp32",
        },
    )
    save_checked(model, out)
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
