"""The rules every ONNX file ``triscan export`` writes must meet: the robot's input and output, metadata.

The fp32 export, the INT8 quantisation and the batch variants are three ways of producing a model file,
and all three must hand the detector a graph it can run: one image input ``float32[B, 3, 64, 384]``,
one output ``float32[B, 4 + classes, 504]``, a file the ONNX checker accepts, and ``triscan.*``
metadata saying where it came from. Those rules live here once, so the three producers cannot drift
apart, and so does :class:`ExportError`, the one error all of them raise for a bad input.

onnx and onnxruntime are imported inside the functions: importing this module costs nothing.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from common.model_spec import FURNITURE_CLASSES, INPUT_SHAPE, META_CLASSES, NUM_ANCHORS, file_sha256

BOX_CHANNELS = 4  # output rows 0–3: cx, cy, w, h in input pixels; rows 4…: per-class scores in [0, 1]
SHA_PREFIX = 12  # hex digits of a source file's sha256 recorded in the metadata


class ExportError(ValueError):
    """An export or quantisation that cannot produce a model the robot may run.

    A ``ValueError``: it always comes from what was handed in (weights, data set, model file), and
    ``triscan`` reports those as a one-line error instead of a traceback.
    """


def check_io(model: Any, path: Path, batch: int | str = 1) -> None:
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

    name = input_name(model)
    (graph_input,) = (i for i in model.graph.input if i.name == name)
    expected_in = (batch, *INPUT_SHAPE[1:])
    if signature(graph_input) != (onnx.TensorProto.FLOAT, expected_in):
        raise ExportError(f"{path}: input must be float32{list(expected_in)}, got {described(graph_input)}")
    expected_out = (batch, BOX_CHANNELS + len(declared_class_names(model)), NUM_ANCHORS)
    outputs = model.graph.output
    if len(outputs) != 1 or signature(outputs[0]) != (onnx.TensorProto.FLOAT, expected_out):
        got = ", ".join(described(o) for o in outputs)
        raise ExportError(f"{path}: output must be float32{list(expected_out)}, got {got}")


def declared_class_names(model: Any) -> tuple[str, ...]:
    """The classes a model's metadata declares (``triscan.classes``); the paper's four without it."""
    for prop in model.metadata_props:
        if prop.key == META_CLASSES:
            return tuple(json.loads(prop.value))
    return FURNITURE_CLASSES


def save_checked(model: Any, out: Path, batch: int | str = 1) -> None:
    """Write a model only once it passes the ONNX checker and has the robot's input and output."""
    import onnx

    onnx.checker.check_model(model, full_check=True)
    check_io(model, out, batch)
    out.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(out))


def set_metadata(model: Any, values: dict[str, str]) -> None:
    """Add or overwrite metadata entries, keeping every other entry (Ultralytics' included)."""
    existing = {prop.key: prop for prop in model.metadata_props}
    for key, value in values.items():
        prop = existing.get(key) or model.metadata_props.add()
        prop.key, prop.value = key, value


def provenance(path: Path) -> str:
    """``<file name> sha256:<12 hex>``: how a model's metadata names the file it was made from."""
    return f"{path.name} sha256:{file_sha256(path)[:SHA_PREFIX]}"


def input_name(model: Any) -> str:
    """The single non-initializer input of an ONNX graph (``images`` for Ultralytics exports)."""
    initializers = {t.name for t in model.graph.initializer}
    names = [i.name for i in model.graph.input if i.name not in initializers]
    if len(names) != 1:
        raise ExportError(f"expected one graph input, found {names}")
    return str(names[0])


def cpu_session(onnx_path: Path, threads: int = 1) -> Any:
    """An ONNX Runtime CPU session with the detector's own session options, to run a written model."""
    import onnxruntime as ort

    from common.inference import session_options

    return ort.InferenceSession(str(onnx_path), session_options(threads), providers=["CPUExecutionProvider"])
