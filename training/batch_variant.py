"""A copy of a fixed-shape triscan model with a free batch axis, proven to compute the same.

Each exported model also gets a ``-batch`` variant (:func:`add_batch_axis`): the same graph and
weights, so a detector serving a fleet can run several robots' frames in one call without running a
model that was never evaluated. ``triscan batch-model`` makes one for any fixed-shape triscan model.
"""

from __future__ import annotations

import logging
import shutil
import tempfile
from pathlib import Path

import numpy as np

from common.model_spec import INPUT_SHAPE, META_PREFIX
from training.onnx_model import ExportError, check_io, cpu_session, provenance, save_checked, set_metadata

log = logging.getLogger(__name__)

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
    check_io(model, model_path)  # only a fixed batch-1 triscan model is a known starting point
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
    set_metadata(
        model,
        {f"{META_PREFIX}batch": BATCH_AXIS, f"{META_PREFIX}batch_source": provenance(model_path)},
    )
    with tempfile.TemporaryDirectory(prefix="triscan-batch-") as scratch:
        candidate = Path(scratch) / out.name
        save_checked(model, candidate, BATCH_AXIS)
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
    one, many = cpu_session(single), cpu_session(batched)
    name = one.get_inputs()[0].name
    expected = np.concatenate([one.run(None, {name: frames[i : i + 1]})[0] for i in range(len(frames))])
    got = many.run(None, {many.get_inputs()[0].name: frames})[0]
    if got.shape != expected.shape or not np.allclose(got, expected, rtol=0, atol=atol):
        worst = float(np.abs(got - expected).max()) if got.shape == expected.shape else float("nan")
        raise ExportError(
            f"{batched}: a batch of {len(frames)} differs from the frames run one by one through {single} "
            f"(shape {list(got.shape)} vs {list(expected.shape)}, max |diff| {worst:.3g})"
        )
