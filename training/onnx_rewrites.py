"""Exact rewrites of the exported ONNX graph that make ONNX Runtime faster on a CPU.

Each rewrite computes the same numbers in a layout ONNX Runtime runs faster; it is applied once at
export (:func:`training.onnx_export.export_onnx`) and named in the file's ``triscan.rewrites`` metadata.

**DFL softmax on the last axis.** Ultralytics decodes each box side from a 16-bin distribution:
``Reshape(b, 4, 16, a) → Transpose(0, 2, 1, 3) → Softmax(axis=1) → Conv 1×1 (16 → 1, weights 0…15)``.
A softmax over a non-innermost axis makes ONNX Runtime transpose internally around a strided kernel:
one node of ~130 took 10 % of the pico network's time (ORT profile, 1 thread). Transposing to
``(b, 4, a, 16)`` instead puts the bins innermost, ``Softmax(axis=-1)`` runs contiguous, and the 1×1
conv becomes a ``MatMul`` with the same 16 weights as a column: the same sums in the same order.
Outputs are bit-equal; docs/benchmarks.md (dfl_rewrite) has what it saves.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from training.onnx_model import ExportError

DFL_SOFTMAX_LAST_AXIS = "dfl_softmax_last_axis"


def dfl_softmax_on_last_axis(model: Any) -> None:
    """Rewrite the head's DFL in place (see the module docstring); raises if the pattern is not there."""
    from onnx import numpy_helper
    from onnx.helper import make_node

    graph = model.graph
    softmaxes = [n for n in graph.node if n.op_type == "Softmax"]
    if len(softmaxes) != 1:
        raise ExportError(f"expected the head's one DFL Softmax, found {len(softmaxes)}")
    (softmax,) = softmaxes
    producers = {output: node for node in graph.node for output in node.output}
    transpose = producers.get(softmax.input[0])
    consumers = [n for n in graph.node if softmax.output[0] in n.input]
    perm = [list(a.ints) for a in transpose.attribute if a.name == "perm"] if transpose is not None else []
    axis = [a.i for a in softmax.attribute if a.name == "axis"]
    if (
        transpose is None
        or transpose.op_type != "Transpose"
        or perm != [[0, 2, 1, 3]]
        or axis != [1]
        or len(consumers) != 1
        or consumers[0].op_type != "Conv"
    ):
        raise ExportError("the DFL is not Transpose(0, 2, 1, 3) → Softmax(axis=1) → Conv: not a YOLOv8 head?")
    (conv,) = consumers
    initializers = {t.name: t for t in graph.initializer}
    weight = numpy_helper.to_array(initializers[conv.input[1]])  # (1, bins, 1, 1)
    if weight.shape[0] != 1 or weight.shape[2:] != (1, 1) or len(conv.input) != 2:
        raise ExportError(f"the DFL conv is not a bias-free 1×1 conv to one channel: weight {weight.shape}")
    for attribute in transpose.attribute:
        if attribute.name == "perm":
            attribute.ints[:] = [0, 1, 3, 2]  # (b, 4, bins, a) → (b, 4, a, bins)
    for attribute in softmax.attribute:
        if attribute.name == "axis":
            attribute.i = -1
    column = f"{conv.input[1]}_column"
    graph.initializer.append(numpy_helper.from_array(weight.reshape(-1, 1).astype(np.float32), column))
    matmul = make_node("MatMul", [softmax.output[0], column], [conv.output[0]], name=f"{conv.name}_as_matmul")
    position = list(graph.node).index(conv)
    graph.node.remove(conv)
    graph.node.insert(position, matmul)  # (b, 4, a, 1): the Reshape after it already flattens to (b, 4, a)
    if not any(conv.input[1] in n.input for n in graph.node):
        graph.initializer.remove(initializers[conv.input[1]])
    stale = {transpose.output[0], softmax.output[0], conv.output[0]}  # shapes recorded for the old layout
    kept = [v for v in graph.value_info if v.name not in stale]
    del graph.value_info[:]
    graph.value_info.extend(kept)
