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

**DFL as one expectation.** ONNX Runtime's ``Softmax`` still works row by row, and a pico head has
2,016 rows of 12 bins. The expectation ``Σ softmax(x)_i · w_i`` equals
``Σ e^(x_i − m) · w_i / Σ e^(x_i − m)`` for the row's maximum ``m``, so
``ReduceMax → Sub → Exp → MatMul([w, 1]) → Split → Div`` computes it with whole-tensor kernels, the
numerator and the denominator in one ``MatMul``. The same numbers summed in another order: box edges
move by float32 rounding, which the detector's whole-pixel box grid absorbs (docs/training.md, "The
five-class model", has what it saves and what it was checked on).

:func:`main` applies the rewrites a file lacks to a file already exported (fp32, INT8 or ``-batch``:
the DFL stays float in every one), checks its outputs against the original's, and records them.
"""

from __future__ import annotations

import argparse
import logging
import os
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np

from common.model_spec import META_PREFIX
from training.onnx_model import ExportError, cpu_session, provenance, save_checked, set_metadata

log = logging.getLogger(__spec__.name if __spec__ else __name__)

DFL_SOFTMAX_LAST_AXIS: Final[str] = "dfl_softmax_last_axis"
DFL_EXPECTATION: Final[str] = "dfl_expectation"
META_REWRITES: Final[str] = f"{META_PREFIX}rewrites"
META_REWRITTEN_FROM: Final[str] = f"{META_PREFIX}rewritten_from"
# How far a rewritten file's raw outputs may lie from the original's: box edges are pixels up to ~480,
# where one float32 step is 3e-5, and the expectation sums its terms in another order.
OUTPUT_TOLERANCE: Final[float] = 1e-3


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


def dfl_expectation(model: Any) -> None:
    """Replace the last-axis DFL ``Softmax → MatMul`` in place by one max-shifted expectation (see the
    module docstring); raises if :func:`dfl_softmax_on_last_axis` has not made that pattern."""
    from onnx import helper, numpy_helper

    graph = model.graph
    softmaxes = [n for n in graph.node if n.op_type == "Softmax"]
    if len(softmaxes) != 1 or [a.i for a in softmaxes[0].attribute if a.name == "axis"] != [-1]:
        raise ExportError(
            "expected the head's one DFL Softmax on the last axis: run dfl_softmax_on_last_axis first"
        )
    (softmax,) = softmaxes
    consumers = [n for n in graph.node if softmax.output[0] in n.input]
    initializers = {t.name: t for t in graph.initializer}
    if len(consumers) != 1 or consumers[0].op_type != "MatMul" or consumers[0].input[1] not in initializers:
        raise ExportError("the DFL softmax does not feed one MatMul with the bin weights")
    (matmul,) = consumers
    weight = numpy_helper.to_array(initializers[matmul.input[1]])
    if weight.ndim != 2 or weight.shape[1] != 1:
        raise ExportError(f"the DFL MatMul weights are not one column: {weight.shape}")
    prefix = (
        softmax.name.rsplit("/", 1)[0] + "/"
    )  # /model.<head>/dfl/: the quantiser's head-decode rule keeps it float
    names = {
        key: f"{prefix}expectation_{key}"
        for key in ("max", "axes", "shifted", "exp", "weights", "sums", "split", "num", "den")
    }
    graph.initializer.extend(
        [
            numpy_helper.from_array(
                np.concatenate([weight, np.ones_like(weight)], axis=1).astype(np.float32), names["weights"]
            ),
        ]
    )
    opset = next(o.version for o in model.opset_import if o.domain in ("", "ai.onnx"))
    if opset < 13:  # the softmax rewrite before this one needs 13 as well
        raise ExportError(f"the DFL expectation needs ONNX opset 13 or later, the file has {opset}")
    graph.initializer.append(numpy_helper.from_array(np.array([1, 1], np.int64), names["split"]))
    split = helper.make_node(
        "Split", [names["sums"], names["split"]], [names["num"], names["den"]], name=names["split"], axis=-1
    )
    if opset >= 18:  # ReduceMax takes its axes as an input from opset 18 on
        graph.initializer.append(numpy_helper.from_array(np.array([-1], np.int64), names["axes"]))
        reduce_max = helper.make_node(
            "ReduceMax", [softmax.input[0], names["axes"]], [names["max"]], name=names["max"], keepdims=1
        )
    else:
        reduce_max = helper.make_node(
            "ReduceMax", [softmax.input[0]], [names["max"]], name=names["max"], axes=[-1], keepdims=1
        )
    nodes = [
        reduce_max,
        helper.make_node("Sub", [softmax.input[0], names["max"]], [names["shifted"]], name=names["shifted"]),
        helper.make_node("Exp", [names["shifted"]], [names["exp"]], name=names["exp"]),
        helper.make_node("MatMul", [names["exp"], names["weights"]], [names["sums"]], name=names["sums"]),
        split,
        helper.make_node(
            "Div", [names["num"], names["den"]], [matmul.output[0]], name=f"{prefix}expectation"
        ),
    ]
    position = list(graph.node).index(softmax)
    graph.node.remove(softmax)
    graph.node.remove(matmul)
    for offset, node in enumerate(nodes):
        graph.node.insert(position + offset, node)
    if not any(matmul.input[1] in n.input for n in graph.node):
        graph.initializer.remove(initializers[matmul.input[1]])
    stale = {softmax.output[0]}
    kept = [v for v in graph.value_info if v.name not in stale]
    del graph.value_info[:]
    graph.value_info.extend(kept)


# Every rewrite an export applies, in order; a file's ``triscan.rewrites`` lists those it has.
REWRITES: Final[dict[str, Callable[[Any], None]]] = {
    DFL_SOFTMAX_LAST_AXIS: dfl_softmax_on_last_axis,
    DFL_EXPECTATION: dfl_expectation,
}


def rewrites_of(model: Any) -> list[str]:
    """The rewrites a model's metadata says it has (none for a file exported without them)."""
    value = next((p.value for p in model.metadata_props if p.key == META_REWRITES), "")
    return [name for name in value.split(",") if name]


def apply_rewrites(model: Any) -> list[str]:
    """Apply in place every rewrite of :data:`REWRITES` the model lacks and record them all in its
    metadata; the names applied now."""
    done = rewrites_of(model)
    unknown = sorted(set(done) - set(REWRITES))
    if unknown:
        raise ExportError(f"the file records rewrites this version does not know: {unknown}")
    applied = [name for name in REWRITES if name not in done]
    for name in applied:
        REWRITES[name](model)
    set_metadata(
        model, {META_REWRITES: ",".join(name for name in REWRITES if name in done or name in applied)}
    )
    return applied


def _outputs(path: Path, inputs: Sequence[np.ndarray]) -> list[np.ndarray]:
    session = cpu_session(path)
    name = session.get_inputs()[0].name
    return [session.run(None, {name: x})[0] for x in inputs]


def _load(path: Path) -> Any:
    """An ONNX model from a file, or a one-line error saying why not."""
    import onnx

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path} is no file: give an ONNX file `triscan export` wrote")
    try:
        return onnx.load(str(path))
    except Exception as exc:  # protobuf's DecodeError and friends, with the file nowhere in them
        raise ExportError(f"{path} is not an ONNX model ({type(exc).__name__}: {exc})") from exc


def rewrite_file(source: Path, out: Path, checks: int = 8) -> list[str]:
    """Write ``source`` with the rewrites it lacks to ``out``, once its raw outputs on ``checks`` inputs
    (empty, and random scans' sparse lit pixels) lie within :data:`OUTPUT_TOLERANCE` of the source's;
    the names applied (none: ``out`` is a copy)."""
    from common.model_spec import INPUT_SHAPE

    source, out = Path(source), Path(out)
    if out.is_dir():
        raise ExportError(f"{out} is a directory: give -o the new file's path")
    if source.resolve() == out.resolve():
        raise ExportError(f"write the rewritten file beside {source}, not over it: its card names its hash")
    model = _load(source)
    applied = apply_rewrites(model)
    batch = model.graph.input[0].type.tensor_type.shape.dim[0]
    set_metadata(model, {META_REWRITTEN_FROM: provenance(source)})
    save_checked(model, out, batch.dim_param or batch.dim_value)
    rng = np.random.default_rng(0)
    inputs = [np.zeros(INPUT_SHAPE, np.float32)]
    inputs += [(rng.random(INPUT_SHAPE) < 0.02).astype(np.float32) for _ in range(checks - 1)]
    worst = max(
        float(np.abs(a - b).max())
        for a, b in zip(_outputs(source, inputs), _outputs(out, inputs), strict=True)
    )
    if worst > OUTPUT_TOLERANCE:
        out.unlink()
        raise ExportError(
            f"{out.name}: the rewrite moved an output by {worst:.3g} (> {OUTPUT_TOLERANCE}); not written"
        )
    log.info(
        "%s → %s: applied %s; outputs within %.2g of the source's", source, out, applied or "nothing", worst
    )
    return applied


# The simulated conditions a card's files are compared under: clean, and the harshest the cards report.
SAME_FIGURES_CONDITIONS: Final[tuple[str, ...]] = ("clean", "drop10+sigma3+spur1")
FIGURE_DIGITS: Final[int] = 3  # the cards print mAP to three decimals


def _figures(report: Any) -> dict[str, float]:
    """An evaluation's mAP figures, overall and per class, to the digits a card prints."""
    figures = {f"all {k}": report.overall[k] for k in ("mAP50", "mAP50-95")}
    for name, values in report.per_class.items():
        figures |= {f"{name} {k}": values[k] for k in ("mAP50", "mAP50-95") if k in values}
    return {k: round(v, FIGURE_DIGITS) for k, v in figures.items()}


def same_figures(source: Path, rewritten: Path, worlds: dict[str, Any], scratch: Path) -> int:
    """Check that a rewritten file keeps its source's card: on the given simulated worlds (a card's
    ``quality_gate``: seed, scenarios, positions, frame stride, people, clutter), under each of
    :data:`SAME_FIGURES_CONDITIONS`, it detects exactly the same boxes, scores and classes at the
    detector's defaults, what a robot gets, and scores the same mAP figures, overall and per class, to
    the digits a card prints, under the evaluation's settings (there float rounding may move a box of
    score 0.001 by a pixel). The number of frames compared; raises where they differ, or with none."""
    from common.inference import OnnxDetector
    from training.evaluate import VAL_CONF, VAL_IOU, VAL_MAX_DET, condition_spec, evaluate, fresh_samples

    robot = OnnxDetector(source), OnnxDetector(rewritten)
    scoring = [
        OnnxDetector(path, conf_threshold=VAL_CONF, iou_threshold=VAL_IOU, max_detections=VAL_MAX_DET)
        for path in (source, rewritten)
    ]
    first = robot[0]
    frames = 0
    for condition in SAME_FIGURES_CONDITIONS:
        samples = list(
            fresh_samples(
                worlds["seed"],
                worlds["scenarios"],
                worlds["positions"],
                first.padding,
                worlds["frame_stride"],
                spec=condition_spec(condition),
                invalid=first.invalid,
                clutter=worlds.get("clutter", 0),
                people=worlds.get("people", 0),
                raster_yaw_deg=first.raster_yaw_deg,
            )
        )
        if not samples:
            break
        for sample in samples:
            frames += 1
            expected, got = (detector.detect_boxes(sample.tensor)[:3] for detector in robot)
            if not all(np.array_equal(a, b) for a, b in zip(expected, got, strict=True)):
                raise ExportError(
                    f"{rewritten.name} detects other boxes than {source.name} at the detector's defaults "
                    f"({condition}, frame {frames}): evaluate the rewritten file and write a new card"
                )
        before, after = (
            _figures(evaluate(d, iter(samples), scratch / f"{condition}-{k}", source="rewrite", plots=False))
            for k, d in enumerate(scoring)
        )
        if before != after:
            moved = {k: (before[k], after.get(k)) for k in before if before[k] != after.get(k)}
            raise ExportError(
                f"{rewritten.name} scores other figures than {source.name} ({condition}): {moved}; "
                "evaluate the rewritten file and write a new card"
            )
    if not frames:
        raise ExportError(f"the worlds {worlds} hold no frame: nothing to compare the files on")
    return frames


def rewrite_card(directory: Path) -> dict[str, list[str]]:
    """Give a card's fp32 and INT8 files the rewrites they lack, in place, make their ``-batch``
    variants again and refresh the card's file table; the rewrites applied, per file kind.

    A card's accuracy figures were measured on its files, so a file is replaced only when the
    rewritten one detects what it did and scores what it did (:func:`same_figures`, on the card's
    quality-gate worlds). Every new file is made and checked beside the card first and only then moved
    over the old ones, so a failure leaves the card as it was.
    """
    import json

    from training.batch_variant import add_batch_axis
    from training.model_card import refresh_files

    card = json.loads((directory / "MODEL_CARD.json").read_text())
    applied: dict[str, list[str]] = {}
    # Beside the card, so that each move below is a rename on one file system.
    with tempfile.TemporaryDirectory(prefix=".triscan-rewrite-", dir=directory) as scratch:
        staged: dict[str, Path] = {}
        for kind in ("fp32", "int8"):
            source = directory / card["files"][kind]
            candidate = Path(scratch) / source.name
            names = rewrite_file(source, candidate)
            if not names:
                continue
            frames = same_figures(source, candidate, card["quality_gate"], Path(scratch))
            log.info("%s: the same detections and figures on %d frames", source.name, frames)
            batch_name = card["files"][f"{kind}_batch"]
            add_batch_axis(candidate, Path(scratch) / batch_name)  # names its source: same name, same bytes
            staged[card["files"][kind]] = candidate
            staged[batch_name] = Path(scratch) / batch_name
            applied[kind] = names
        for name, path in staged.items():
            os.replace(path, directory / name)
    if applied:
        refresh_files(directory)
    return applied


def main(argv: Sequence[str] | None = None) -> int:
    """Give an exported model file the graph rewrites of this version's export: ``-o`` writes a new
    file; ``--card`` rewrites a card's files in place, keeping its figures only where the detections
    stay the same (:func:`rewrite_card`)."""
    parser = argparse.ArgumentParser(prog="python -m training.onnx_rewrites", description=main.__doc__)
    parser.add_argument(
        "model", type=Path, help="an ONNX file `triscan export` wrote, or with --card a card's directory"
    )
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("-o", "--out", type=Path, help="where the rewritten file goes")
    where.add_argument(
        "--card", action="store_true", help="MODEL is a card's directory: rewrite its files in place"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        if args.card:
            if not (args.model / "MODEL_CARD.json").is_file():
                raise FileNotFoundError(
                    f"{args.model} holds no MODEL_CARD.json: give --card a card's directory"
                )
            rewrite_card(args.model)
        else:
            rewrite_file(args.model, args.out)
    except (ExportError, OSError, ValueError) as exc:
        log.error("error: %s", exc)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
