"""ONNX export and INT8 quantisation: the files the robot loads, their shape, metadata and numerics.

The network under test is an untrained YOLOv8n with 4 classes whose convolutions are re-initialised
(Kaiming) so that activations survive 22 layers: with Ultralytics' default init the head's inputs
are ~0 and every output is its bias, which would make any numeric comparison pass vacuously.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from common.encoding import to_model_input
from common.inference import OnnxDetector
from common.model_spec import CLASS_NAMES, INPUT_SHAPE, NUM_ANCHORS, batch_variant_path, file_sha256
from training.batch_variant import BATCH_AXIS, add_batch_axis
from training.dataset import DatasetConfig, generate_dataset
from training.export import export_models
from training.export_checks import compare_outputs, median_latency_ms
from training.int8_recipes import compare_recipes, format_recipe_table
from training.offline import configure_offline
from training.onnx_export import export_onnx
from training.onnx_model import BOX_CHANNELS, ExportError, check_io
from training.onnx_rewrites import (
    DFL_EXPECTATION,
    DFL_SOFTMAX_LAST_AXIS,
    dfl_expectation,
    dfl_softmax_on_last_axis,
    rewrite_card,
    rewrite_file,
    same_figures,
)
from training.png import read_tensor_png, write_rgb_png
from training.quantization import (
    DEFAULT_FLOAT_LEADING_MODULES,
    box_logit_nodes,
    calibration_images,
    calibration_reader,
    class_logit_nodes,
    head_conv_nodes,
    head_decode_nodes,
    leading_module_nodes,
    quantize_int8,
)

pytest.importorskip("ultralytics")
onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")
torch = pytest.importorskip("torch")

CALIB_COUNT = 8


pytestmark = pytest.mark.slow


def onnx_metadata(path: Path) -> dict[str, str]:
    """All ``metadata_props`` of an ONNX file (Ultralytics' and ours)."""
    return {prop.key: prop.value for prop in onnx.load(str(path)).metadata_props}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny ``wrap`` set: not the default padding, so reading it from the set is observable."""
    out = tmp_path_factory.mktemp("export_ds") / "set"
    generate_dataset(
        DatasetConfig(
            out=out, scenarios=3, positions=2, seed=3, padding="wrap", frame_stride=4, invalid="empty"
        ),
        progress=False,
    )
    return out


def _save_checkpoint(path: Path, data_yaml: Path | None, names: dict[int, str]) -> Path:
    """An Ultralytics checkpoint of a lively 4-class YOLOv8n, saved the way Ultralytics saves one."""
    configure_offline()
    from ultralytics import YOLO
    from ultralytics.nn.tasks import DetectionModel

    torch.manual_seed(0)
    yolo = YOLO("yolov8n.yaml")
    yolo.model = DetectionModel("yolov8n.yaml", nc=len(names), verbose=False)
    for module in yolo.model.modules():
        if isinstance(module, torch.nn.Conv2d) and module.weight.requires_grad:  # the DFL conv is fixed
            torch.nn.init.kaiming_normal_(module.weight, nonlinearity="relu")
    for branch in yolo.model.model[-1].cv3:
        torch.nn.init.zeros_(branch[-1].bias)  # scores near 0.5, where an error is visible
    yolo.model.names = names
    yolo.ckpt = {"train_args": {"data": str(data_yaml)}} if data_yaml else {}
    yolo.save(str(path))
    return path


@pytest.fixture(scope="module")
def weights(tmp_path_factory: pytest.TempPathFactory, dataset: Path) -> Path:
    path = tmp_path_factory.mktemp("weights") / "last.pt"
    return _save_checkpoint(path, dataset / "data.yaml", dict(enumerate(CLASS_NAMES)))


@pytest.fixture(scope="module")
def fp32(tmp_path_factory: pytest.TempPathFactory, weights: Path) -> Path:
    return export_onnx(weights, tmp_path_factory.mktemp("models") / "model.onnx")


@pytest.fixture(scope="module")
def int8(tmp_path_factory: pytest.TempPathFactory, fp32: Path, dataset: Path) -> Path:
    out = tmp_path_factory.mktemp("models_q") / "model-int8.onnx"
    return quantize_int8(fp32, out, calibration_images(dataset, CALIB_COUNT))


def _run(path: Path, x: np.ndarray) -> np.ndarray:
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return session.run(None, {session.get_inputs()[0].name: x})[0]


def _dims(value: Any) -> list[int]:
    return [d.dim_value for d in value.type.tensor_type.shape.dim]


# --- fp32 export ---------------------------------------------------------------------------------------


def test_fp32_file_is_valid_with_fixed_input_and_output(fp32: Path) -> None:
    model = onnx.load(str(fp32))
    onnx.checker.check_model(model, full_check=True)
    (graph_input,) = model.graph.input
    assert graph_input.type.tensor_type.elem_type == onnx.TensorProto.FLOAT
    assert _dims(graph_input) == list(INPUT_SHAPE) == [1, 3, 64, 384]
    assert all(d.HasField("dim_value") for d in graph_input.type.tensor_type.shape.dim), "no dynamic axes"
    assert _dims(model.graph.output[0]) == [1, BOX_CHANNELS + len(CLASS_NAMES), NUM_ANCHORS] == [1, 9, 504]


def test_shape_check_rejects_dynamic_axes_and_other_outputs(fp32: Path) -> None:
    model = onnx.load(str(fp32))
    dim = model.graph.input[0].type.tensor_type.shape.dim[0]
    dim.dim_param = "batch"  # what `dynamic=True` would have produced
    with pytest.raises(ExportError, match="input must be"):
        check_io(model, fp32)
    model = onnx.load(str(fp32))
    model.graph.output[0].type.tensor_type.shape.dim[2].dim_value = 2100  # a 640×320-sized anchor grid
    with pytest.raises(ExportError, match="output must be"):
        check_io(model, fp32)


def test_fp32_metadata_keeps_ultralytics_and_adds_triscan(fp32: Path, weights: Path) -> None:
    meta = onnx_metadata(fp32)
    assert meta["imgsz"] == "[64, 384]" and meta["stride"] == "32" and meta["task"] == "detect"
    assert "doorframe" in meta["names"]
    assert meta["triscan.padding"] == "wrap", "padding must come from the training data set"
    assert meta["triscan.invalid"] == "empty", "so must the invalid-return rule"
    assert OnnxDetector(fp32).invalid == "empty"
    assert json.loads(meta["triscan.classes"]) == list(CLASS_NAMES)
    assert meta["triscan.source_weights"] == f"last.pt sha256:{file_sha256(weights)[:12]}"
    assert meta["triscan.precision"] == "fp32"
    assert meta["triscan.rewrites"] == f"{DFL_SOFTMAX_LAST_AXIS},{DFL_EXPECTATION}"
    assert meta["triscan.box_grid"] == "none" and OnnxDetector(fp32).box_grid == "none"


def test_the_dfl_is_one_expectation_over_the_innermost_axis_and_a_second_rewrite_is_refused(
    fp32: Path,
) -> None:
    """The rewrites' numbers are the torch model's (next test); here their shape, once and only once."""
    model = onnx.load(str(fp32))
    dfl = [n for n in model.graph.node if "/dfl/" in n.name]
    assert not any(n.op_type in ("Softmax", "Conv") for n in dfl)
    assert [n.op_type for n in dfl if n.op_type in ("ReduceMax", "Sub", "Exp", "MatMul", "Div")] == [
        "ReduceMax",
        "Sub",
        "Exp",
        "MatMul",
        "Div",
    ]
    (transpose,) = [n for n in dfl if n.op_type == "Transpose"]
    assert [list(a.ints) for a in transpose.attribute if a.name == "perm"] == [[0, 1, 3, 2]]
    with pytest.raises(ExportError, match="DFL"):
        dfl_softmax_on_last_axis(model)  # already rewritten: the patterns are gone
    with pytest.raises(ExportError, match="DFL"):
        dfl_expectation(model)


def test_rewrite_file_gives_an_old_export_the_rewrites_with_its_outputs(
    weights: Path, tmp_path: Path
) -> None:
    """A file exported without the rewrites gets both, within float rounding of its own outputs, and
    says what it was made from; a file that has them is copied as it is."""
    plain = export_onnx(weights, tmp_path / "plain.onnx", rewrite_dfl=False)
    assert "triscan.rewrites" not in onnx_metadata(plain)
    rewritten = tmp_path / "rewritten.onnx"
    assert rewrite_file(plain, rewritten) == [DFL_SOFTMAX_LAST_AXIS, DFL_EXPECTATION]
    meta = onnx_metadata(rewritten)
    assert meta["triscan.rewrites"] == f"{DFL_SOFTMAX_LAST_AXIS},{DFL_EXPECTATION}"
    assert meta["triscan.rewritten_from"] == f"plain.onnx sha256:{file_sha256(plain)[:12]}"
    x = np.random.default_rng(1).random(INPUT_SHAPE, dtype=np.float32)
    expected, got = _run(plain, x), _run(rewritten, x)
    assert np.std(expected[0, :BOX_CHANNELS]) > 1.0
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-3)
    assert rewrite_file(rewritten, tmp_path / "again.onnx") == []
    with pytest.raises(ExportError, match="beside"):
        rewrite_file(rewritten, rewritten)


def test_same_figures_counts_the_frames_and_refuses_a_file_that_detects_otherwise(tmp_path: Path) -> None:
    from common.model_spec import MODELS_DIR

    directory = MODELS_DIR / "yolov8p-relu-dfl12"
    card = json.loads((directory / "MODEL_CARD.json").read_text())
    fp32_file, int8_file = (directory / card["files"][kind] for kind in ("fp32", "int8"))
    worlds = {"seed": 5, "scenarios": 1, "positions": 2, "frame_stride": 15, "people": 2}
    frames = same_figures(fp32_file, fp32_file, worlds, tmp_path)
    assert frames > 0 and frames % 2 == 0  # the same worlds under each of the two conditions
    with pytest.raises(ExportError, match="other boxes"):
        same_figures(fp32_file, int8_file, worlds, tmp_path)  # quantised: not the same boxes
    with pytest.raises(ExportError, match="no frame"):
        same_figures(fp32_file, fp32_file, worlds | {"scenarios": 0}, tmp_path)


def test_the_expectation_rewrite_holds_below_opset_18(weights: Path, tmp_path: Path) -> None:
    """Below opset 18 ReduceMax takes its axes as an attribute."""
    opset = 17
    plain = export_onnx(weights, tmp_path / "plain.onnx", opset=opset, rewrite_dfl=False)
    rewritten = tmp_path / "rewritten.onnx"
    assert rewrite_file(plain, rewritten) == [DFL_SOFTMAX_LAST_AXIS, DFL_EXPECTATION]
    nodes = {n.op_type: n for n in onnx.load(str(rewritten)).graph.node if "/dfl/expectation" in n.name}
    assert [a.name for a in nodes["ReduceMax"].attribute if a.name == "axes"] == ["axes"]
    assert len(nodes["ReduceMax"].input) == 1
    x = np.random.default_rng(2).random(INPUT_SHAPE, dtype=np.float32)
    np.testing.assert_allclose(_run(rewritten, x), _run(plain, x), rtol=0, atol=1e-3)


def test_rewrite_file_refuses_a_rewrite_that_moves_the_outputs(
    weights: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import training.onnx_rewrites as rewrites

    plain = export_onnx(weights, tmp_path / "plain.onnx", rewrite_dfl=False)
    monkeypatch.setattr(rewrites, "OUTPUT_TOLERANCE", 0.0)  # float rounding alone now moves too much
    with pytest.raises(ExportError, match="moved an output"):
        rewrite_file(plain, tmp_path / "rewritten.onnx")
    assert not (tmp_path / "rewritten.onnx").exists()


def test_rewrite_card_replaces_files_without_the_rewrites_and_refreshes_the_card(
    weights: Path, dataset: Path, tmp_path: Path
) -> None:
    """A card whose files lack the rewrites gets them in place, with new -batch variants made from the
    new files and a file table that names them; what the card measured stays."""
    import shutil

    from common.model_spec import MODELS_DIR, file_model_id

    directory = tmp_path / "card"
    directory.mkdir()
    card = json.loads((MODELS_DIR / "yolov8p-relu-dfl12" / "MODEL_CARD.json").read_text())
    card["quality_gate"] |= {"scenarios": 1, "positions": 2}
    (directory / "MODEL_CARD.json").write_text(json.dumps(card, indent=2) + "\n")
    shutil.copy(MODELS_DIR / "yolov8p-relu-dfl12" / "MODEL_CARD.md", directory)
    files = card["files"]
    plain = export_onnx(weights, directory / files["fp32"], rewrite_dfl=False, box_grid="pixel")
    quantize_int8(plain, directory / files["int8"], calibration_images(dataset, CALIB_COUNT))
    for kind in ("fp32", "int8"):
        add_batch_axis(directory / files[kind], directory / files[f"{kind}_batch"])
    before = {name: file_sha256(directory / files[name]) for name in ("fp32", "int8")}

    assert rewrite_card(directory) == {
        kind: [DFL_SOFTMAX_LAST_AXIS, DFL_EXPECTATION] for kind in ("fp32", "int8")
    }
    refreshed = json.loads((directory / "MODEL_CARD.json").read_text())
    text = (directory / "MODEL_CARD.md").read_text()
    for kind in ("fp32", "int8"):
        path, batch = directory / files[kind], directory / files[f"{kind}_batch"]
        meta, batch_meta = onnx_metadata(path), onnx_metadata(batch)
        assert meta["triscan.rewrites"] == f"{DFL_SOFTMAX_LAST_AXIS},{DFL_EXPECTATION}"
        assert meta["triscan.rewritten_from"] == f"{path.name} sha256:{before[kind][:12]}"
        assert batch_meta["triscan.batch_source"] == f"{path.name} sha256:{file_sha256(path)[:12]}"
        assert refreshed["model_ids"][kind] == file_model_id(path)
        assert f"`{file_sha256(batch)[:16]}…`" in text
    assert {k: v for k, v in refreshed.items() if k != "model_ids"} == {
        k: v for k, v in card.items() if k != "model_ids"
    }
    assert sorted(p.name for p in directory.iterdir()) == sorted(
        [*(name for kind, name in files.items() if kind != "checkpoint"), "MODEL_CARD.json", "MODEL_CARD.md"]
    )
    assert rewrite_card(directory) == {}  # nothing left to do


def test_rewrite_card_leaves_a_card_whose_files_have_every_rewrite_as_it_is(tmp_path: Path) -> None:
    import shutil

    from common.model_spec import MODELS_DIR

    directory = tmp_path / "card"
    shutil.copytree(MODELS_DIR / "yolov8p-relu-dfl12", directory)
    before = {p.name: p.read_bytes() for p in directory.iterdir()}
    assert rewrite_card(directory) == {}
    assert {p.name: p.read_bytes() for p in directory.iterdir()} == before


def test_fp32_output_equals_the_torch_model(fp32: Path, weights: Path) -> None:
    from ultralytics import YOLO

    model = YOLO(str(weights)).model.float().eval()
    x = np.random.default_rng(0).random(INPUT_SHAPE, dtype=np.float32)
    with torch.no_grad():
        expected = model(torch.from_numpy(x))
    expected = (expected[0] if isinstance(expected, tuple | list) else expected).numpy()
    got = _run(fp32, x)
    assert got.shape == expected.shape
    assert np.std(expected[0, :BOX_CHANNELS]) > 1.0, "outputs must depend on the input for this test to bite"
    # Scores in [0, 1] within 1e-4. Boxes are in pixels up to ~480 where one float32 ulp is 3e-5 and the
    # exported graph has conv+BN folded, so they are compared in normalised coordinates (÷ 384) to 1e-4.
    np.testing.assert_allclose(got[0, BOX_CHANNELS:], expected[0, BOX_CHANNELS:], rtol=0, atol=1e-4)
    np.testing.assert_allclose(
        got[0, :BOX_CHANNELS] / 384, expected[0, :BOX_CHANNELS] / 384, rtol=0, atol=1e-4
    )


def test_export_refuses_a_padding_or_invalid_rule_that_contradicts_the_training_set(
    weights: Path, tmp_path: Path
) -> None:
    with pytest.raises(ExportError, match="padding"):
        export_onnx(weights, tmp_path / "m.onnx", padding="zero")
    with pytest.raises(ExportError, match="invalid rule 'sentinel' requested but the data set"):
        export_onnx(weights, tmp_path / "m.onnx", invalid="sentinel")
    with pytest.raises(ExportError, match="invalid must be one of"):
        export_onnx(weights, tmp_path / "m.onnx", invalid="dark")
    assert not (tmp_path / "m.onnx").exists()


def test_export_rejects_missing_weights_and_foreign_classes(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="weights"):
        export_onnx(tmp_path / "nope.pt", tmp_path / "m.onnx")
    foreign = _save_checkpoint(tmp_path / "foreign.pt", None, {0: "cat", 1: "dog", 2: "car", 3: "tree"})
    with pytest.raises(ExportError, match="triscan classes"):
        export_onnx(foreign, tmp_path / "m.onnx")


# --- INT8 ----------------------------------------------------------------------------------------------


def test_int8_is_qdq_with_per_channel_conv_weights(int8: Path) -> None:
    model = onnx.load(str(int8))
    onnx.checker.check_model(model, full_check=True)
    ops = [n.op_type for n in model.graph.node]
    assert ops.count("QuantizeLinear") > 50 and ops.count("DequantizeLinear") > 50
    initializers = {t.name: t for t in model.graph.initializer}
    conv_weights = {n.input[1] for n in model.graph.node if n.op_type == "Conv"}
    per_channel = quantised = 0
    for node in model.graph.node:
        if node.op_type != "DequantizeLinear" or node.output[0] not in conv_weights:
            continue
        quantised += 1
        weight = initializers[node.input[0]]
        scale = initializers[node.input[1]]
        assert weight.data_type == onnx.TensorProto.INT8
        axis = [a.i for a in node.attribute if a.name == "axis"]
        if axis == [0] and len(scale.dims) == 1 and scale.dims[0] == weight.dims[0] > 1:
            per_channel += 1
    kept_float = set(leading_module_nodes(model, DEFAULT_FLOAT_LEADING_MODULES)) | set(
        head_decode_nodes(model)
    )
    kept_float |= set(box_logit_nodes(model)) | set(class_logit_nodes(model))
    convs = [n for n in model.graph.node if n.op_type == "Conv"]
    expected = sum(n.name not in kept_float for n in convs)
    assert expected >= 40 and quantised == expected, (
        f"{quantised} of {len(convs)} convs quantised, not {expected}"
    )
    assert per_channel == quantised, f"only {per_channel} of {quantised} int8 conv weights are per-channel"
    assert _dims(model.graph.input[0]) == list(INPUT_SHAPE)


def test_int8_keeps_the_head_decode_in_float(int8: Path) -> None:
    model = onnx.load(str(int8))
    tail = set(head_decode_nodes(model))
    assert {"Sigmoid", "Exp", "Concat"} <= {n.op_type for n in model.graph.node if n.name in tail}
    produced_by = {o: n for n in model.graph.node for o in n.output}
    for node in model.graph.node:
        if node.op_type == "QuantizeLinear":
            producer = produced_by.get(node.input[0])
            assert producer is None or producer.name not in tail, f"{producer.name} output is quantised"
    assert produced_by[model.graph.output[0].name].op_type == "Concat"


def _conv_weights_are_int8(model: onnx.ModelProto, nodes: list[str]) -> list[bool]:
    """For each conv among ``nodes``: does it read DequantizeLinear'd int8 weights (i.e. was it quantised)?"""
    produced_by = {o: n for n in model.graph.node for o in n.output}
    wanted = set(nodes)
    convs = [n for n in model.graph.node if n.name in wanted and n.op_type == "Conv"]
    assert convs, "no conv among the nodes"
    return [(w := produced_by.get(c.input[1])) is not None and w.op_type == "DequantizeLinear" for c in convs]


def test_int8_keeps_the_leading_modules_and_head_logits_float_unless_asked(
    int8: Path, fp32: Path, dataset: Path, tmp_path: Path
) -> None:
    model = onnx.load(str(int8))
    leading = leading_module_nodes(model, DEFAULT_FLOAT_LEADING_MODULES)
    assert {n.split("/")[1] for n in leading} == {f"model.{i}" for i in range(DEFAULT_FLOAT_LEADING_MODULES)}
    assert not any(_conv_weights_are_int8(model, leading))
    assert not any(_conv_weights_are_int8(model, box_logit_nodes(model)))
    assert len(box_logit_nodes(model)) == 3  # one per stride
    assert not any(_conv_weights_are_int8(model, class_logit_nodes(model)))
    assert len(class_logit_nodes(model)) == 3
    assert not set(class_logit_nodes(model)) & set(box_logit_nodes(model))
    after = sorted(set(leading_module_nodes(model, DEFAULT_FLOAT_LEADING_MODULES + 1)) - set(leading))
    assert all(_conv_weights_are_int8(model, after)), "the module after the float ones is quantised"
    feed = model.graph.input[0].name
    assert not any(n.op_type == "QuantizeLinear" and n.input[0] == feed for n in model.graph.node)

    quantised = quantize_int8(
        fp32, tmp_path / "all.onnx", calibration_images(dataset, CALIB_COUNT),
        float_leading_modules=0, keep_box_logits_float=False, keep_class_logits_float=False,
    )  # fmt: skip
    everything = onnx.load(str(quantised))
    assert all(_conv_weights_are_int8(everything, leading_module_nodes(everything, 1)))
    assert all(_conv_weights_are_int8(everything, box_logit_nodes(everything)))
    assert all(_conv_weights_are_int8(everything, class_logit_nodes(everything)))
    record = json.loads(onnx_metadata(quantised)["triscan.quantization"])
    assert record["float_leading_modules"] == record["float_leading_nodes"] == 0
    assert record["float_box_logit_nodes"] == record["float_class_logit_nodes"] == 0
    assert record["float_head_conv_nodes"] == 0

    head_float = quantize_int8(
        fp32, tmp_path / "head.onnx", calibration_images(dataset, CALIB_COUNT), keep_head_convs_float=True
    )
    head_model = onnx.load(str(head_float))
    convs = head_conv_nodes(head_model)
    assert set(box_logit_nodes(head_model)) < set(convs)  # the box logits and more
    assert {n.split("/")[2][:3] for n in convs} == {"cv2", "cv3"}  # /model.22/cv2.0/...: both branches
    assert not any(_conv_weights_are_int8(head_model, convs))
    logits = set(box_logit_nodes(model)) | set(class_logit_nodes(model))
    assert all(_conv_weights_are_int8(model, sorted(set(convs) - logits)))  # default
    assert json.loads(onnx_metadata(head_float)["triscan.quantization"])["float_head_conv_nodes"] == len(
        convs
    )
    with pytest.raises(ValueError, match="float leading modules must be 0 to 22"):
        quantize_int8(
            fp32, tmp_path / "bad.onnx", calibration_images(dataset, CALIB_COUNT), float_leading_modules=23
        )


def test_int8_metadata_is_carried_over(int8: Path, fp32: Path) -> None:
    meta, source = onnx_metadata(int8), onnx_metadata(fp32)
    for key in ("names", "imgsz", "stride", "triscan.padding", "triscan.classes", "triscan.source_weights"):
        assert meta[key] == source[key]
    assert meta["triscan.precision"] == "int8"
    quant = json.loads(meta["triscan.quantization"])
    assert quant["format"] == "QDQ" and "per-channel" in quant["weights"]
    assert quant["calibration"] == "minmax" and quant["activations"] == "uint8"
    assert (
        quant["float_leading_modules"] == DEFAULT_FLOAT_LEADING_MODULES and quant["float_leading_nodes"] > 10
    )
    assert quant["float_box_logit_nodes"] == quant["float_class_logit_nodes"] == 3
    assert quant["float_head_nodes"] > 10
    assert quant["calibration_images"] == CALIB_COUNT


def test_int8_runs_and_tracks_fp32(int8: Path, fp32: Path, dataset: Path) -> None:
    images = calibration_images(dataset, 6, split="test")  # not the calibration images
    x = to_model_input(read_tensor_png(images[0]))
    assert np.isfinite(_run(int8, x)).all()
    diff = compare_outputs(fp32, int8, images)
    # One raster pixel is 1° × 6.3 cm: an INT8 box must stay within it. Scores here sit near 0.5, so a
    # quantised output concat (one scale for 0–480 px and 0–1 scores) would be off by ~0.5.
    assert diff["box_max_abs_px"] < 1.0, diff
    assert diff["score_max_abs"] < 0.02, diff
    assert diff["confident_anchors"] == len(images) * NUM_ANCHORS, "every score is near 0.5 here"
    assert diff["confident_class_agreement"] > 0.5, diff


def _activation_scales(path: Path) -> dict[str, float]:
    """Scale of every activation QuantizeLinear (weights are stored already quantised)."""
    model = onnx.load(str(path))
    initializers = {t.name: onnx.numpy_helper.to_array(t) for t in model.graph.initializer}
    return {
        n.input[0]: float(initializers[n.input[1]])
        for n in model.graph.node
        if n.op_type == "QuantizeLinear" and n.input[0] not in initializers
    }


def test_calibration_method_changes_the_activation_ranges(fp32: Path, dataset: Path, tmp_path: Path) -> None:
    # Only the stem float, so that most tensors are quantised and their ranges can be compared.
    images = calibration_images(dataset, CALIB_COUNT)
    percentile, minmax = (
        quantize_int8(fp32, tmp_path / f"{method}.onnx", images, method=method, float_leading_modules=1)
        for method in ("percentile", "minmax")
    )
    a, b = _activation_scales(percentile), _activation_scales(minmax)
    assert a.keys() == b.keys() and len(a) > 50
    # Percentile clips outliers, so its ranges are never wider than MinMax's and, where a tensor has
    # tails (17 of 218 with this random-weight net and 8 images), narrower. Equal ranges everywhere
    # would mean the method was silently ignored, as ONNX Runtime's own "entropy" does with 128 bins.
    assert all(a[k] <= b[k] * (1 + 1e-6) for k in a)
    assert sum(a[k] < b[k] * 0.99 for k in a) >= 10
    with pytest.raises(ValueError, match="method"):
        quantize_int8(fp32, tmp_path / "x.onnx", [tmp_path / "a.png"], method="kl")  # type: ignore[arg-type]


def test_latency_is_measured_for_each_model_in_turn(fp32: Path, int8: Path, dataset: Path) -> None:
    image = calibration_images(dataset, 1)[0]
    times = median_latency_ms([fp32, int8], image, runs=5, warmup=1)
    assert len(times) == 2 and all(0 < t < 10_000 for t in times)
    with pytest.raises(ValueError, match="runs"):
        median_latency_ms([fp32], image, runs=0)


def test_quantize_rejects_empty_or_missing_calibration(fp32: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="empty"):
        quantize_int8(fp32, tmp_path / "q.onnx", [])
    with pytest.raises(FileNotFoundError, match="calibration image"):
        quantize_int8(fp32, tmp_path / "q.onnx", [tmp_path / "missing.png"])
    with pytest.raises(FileNotFoundError, match="fp32 model"):
        quantize_int8(tmp_path / "none.onnx", tmp_path / "q.onnx", [tmp_path / "missing.png"])
    assert not (tmp_path / "q.onnx").exists()


# --- calibration data ----------------------------------------------------------------------------------


def test_calibration_images_are_deterministic_sorted_and_spread(dataset: Path) -> None:
    every = sorted((dataset / "images" / "val").glob("*.png"))
    assert len(every) >= 10
    picks = calibration_images(dataset, 5)
    assert picks == calibration_images(dataset, 5)
    assert picks[0] == every[0] and picks[-1] == every[-1] and len(set(picks)) == 5
    positions = [every.index(p) for p in picks]
    gaps = np.diff(positions)
    assert positions == sorted(positions) and gaps.max() - gaps.min() <= 1, positions
    assert calibration_images(dataset, 10**6) == every
    test_split = calibration_images(dataset, 3, split="test")
    assert all(p.parent.name == "test" for p in test_split)


def test_calibration_images_reject_bad_arguments(dataset: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="count"):
        calibration_images(dataset, 0)
    with pytest.raises(FileNotFoundError, match="triscan dataset"):
        calibration_images(tmp_path, 5)
    (tmp_path / "images" / "val").mkdir(parents=True)
    with pytest.raises(ExportError, match="no PNG"):
        calibration_images(tmp_path, 5)


def test_calibration_feeds_the_run_time_tensor_in_png_channel_order(tmp_path: Path) -> None:
    tensor = np.zeros((64, 384, 3), dtype=np.uint8)
    tensor[10, 20, 0] = 255  # scan t−2 only: would move to channel 2 if read as BGR
    tensor[30, 40, 2] = 255  # scan t only
    write_rgb_png(tmp_path / "a.png", tensor)
    np.testing.assert_array_equal(read_tensor_png(tmp_path / "a.png"), tensor)
    reader = calibration_reader("images", [tmp_path / "a.png"])
    feed = reader.get_next()
    assert feed is not None and set(feed) == {"images"}
    np.testing.assert_array_equal(feed["images"], to_model_input(tensor))
    assert feed["images"][0, 0, 10, 20] == 1.0 and feed["images"][0, 2, 30, 40] == 1.0
    assert reader.get_next() is None
    reader.rewind()
    assert reader.get_next() is not None


def test_read_tensor_png_rejects_other_sizes(tmp_path: Path) -> None:
    write_rgb_png(tmp_path / "small.png", np.zeros((64, 360, 3), dtype=np.uint8))
    with pytest.raises(ExportError, match="384"):
        read_tensor_png(tmp_path / "small.png")


# --- batch variants ------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["fp32", "int8"])
def test_batch_variant_is_the_same_network_with_a_free_batch_axis(
    kind: str, request: pytest.FixtureRequest, tmp_path: Path
) -> None:
    source: Path = request.getfixturevalue(kind)
    out = add_batch_axis(source, tmp_path / batch_variant_path(source).name)
    assert out.name == source.stem + "-batch.onnx"
    model = onnx.load(str(out))
    onnx.checker.check_model(model, full_check=True)
    dims = [
        [d.dim_param or d.dim_value for d in v.type.tensor_type.shape.dim]
        for v in (*model.graph.input, *model.graph.output)
    ]
    assert dims == [[BATCH_AXIS, 3, 64, 384], [BATCH_AXIS, 4 + len(CLASS_NAMES), 504]]
    meta, source_meta = onnx_metadata(out), onnx_metadata(source)
    assert meta["triscan.batch"] == BATCH_AXIS
    assert meta["triscan.batch_source"] == f"{source.name} sha256:{file_sha256(source)[:12]}"
    assert {k: v for k, v in meta.items() if not k.startswith("triscan.batch")} == source_meta
    # The same weights: every initializer except the Reshape targets is byte-identical.
    before = {t.name: t.raw_data for t in onnx.load(str(source)).graph.initializer}
    after = {t.name: t.raw_data for t in model.graph.initializer}
    changed = sorted(name for name in before if before[name] != after[name])
    reshape_targets = {n.input[1] for n in model.graph.node if n.op_type == "Reshape"}
    assert changed and set(changed) <= reshape_targets
    # Five different frames in one call equal each frame alone through the source model.
    frames = (np.random.default_rng(1).random((5, 3, 64, 384)) < 0.05).astype(np.float32)
    together = _run(out, frames)
    alone = np.concatenate([_run(source, frames[i : i + 1]) for i in range(5)])
    assert np.std(alone[:, :BOX_CHANNELS]) > 1.0, "outputs must differ between frames for this to bite"
    np.testing.assert_allclose(together, alone, rtol=0, atol=1e-4)


def test_batch_variant_refuses_what_it_cannot_rewrite(fp32: Path, tmp_path: Path) -> None:
    once = add_batch_axis(fp32, tmp_path / "once.onnx")
    with pytest.raises(ExportError, match="input must be"):  # already free: not a known starting point
        add_batch_axis(once, tmp_path / "twice.onnx")
    with pytest.raises(FileNotFoundError):
        add_batch_axis(tmp_path / "missing.onnx", tmp_path / "x.onnx")
    assert not (tmp_path / "twice.onnx").exists() and not (tmp_path / "x.onnx").exists()


# --- both models ---------------------------------------------------------------------------------------


def test_export_models_writes_and_describes_both_files(weights: Path, dataset: Path, tmp_path: Path) -> None:
    result = export_models(
        weights,
        dataset,
        tmp_path / "models",
        name="triscan-test",
        padding="wrap",
        calib_count=4,
        compare_count=3,
        timing_runs=2,
        box_grid="pixel",
    )
    assert result["box_grid"] == "pixel"
    for key in ("fp32", "int8", "fp32_batch", "int8_batch"):  # every file tells the detector
        assert OnnxDetector(result[key]["path"]).box_grid == "pixel"
    assert Path(result["fp32"]["path"]) == tmp_path / "models" / "triscan-test.onnx"
    assert Path(result["int8"]["path"]) == tmp_path / "models" / "triscan-test-int8.onnx"
    assert Path(result["fp32_batch"]["path"]) == tmp_path / "models" / "triscan-test-batch.onnx"
    assert Path(result["int8_batch"]["path"]) == tmp_path / "models" / "triscan-test-int8-batch.onnx"
    for kind in ("fp32", "int8", "fp32_batch", "int8_batch"):
        path = Path(result[kind]["path"])
        assert result[kind]["bytes"] == path.stat().st_size
        assert result[kind]["sha256"] == file_sha256(path)
    assert result["int8"]["bytes"] < result["fp32"]["bytes"] / 2
    assert result["padding"] == "wrap" and result["calibration_images"] == 4
    assert math.isfinite(result["int8_vs_fp32"]["box_max_abs_px"])
    assert set(result["latency_ms_1_thread"]) == {"fp32", "int8"}
    with pytest.raises(ExportError, match="padding"):
        export_models(weights, dataset, tmp_path / "other", name="x", padding="zero", calib_count=4)
    with pytest.raises(ValueError, match="name"):
        export_models(weights, dataset, tmp_path / "other", name="../x", padding="wrap", calib_count=4)
    # no name: the files are named after the checkpoint's network, the set's padding and its
    # invalid-return rule (this set's is not the sentinel row)
    unnamed = export_models(
        weights, dataset, tmp_path / "unnamed", calib_count=4, compare_count=1, timing_runs=0
    )
    assert Path(unnamed["fp32"]["path"]).name == "triscan-yolov8n-wrap-invalid-empty.onnx"
    assert Path(unnamed["int8"]["path"]).name == "triscan-yolov8n-wrap-invalid-empty-int8.onnx"
    assert onnx_metadata(Path(unnamed["int8"]["path"]))["triscan.invalid"] == "empty"


def test_checkpoints_name_their_network(tmp_path: Path) -> None:
    from training.architectures import model_yaml, network_of_checkpoint

    configure_offline()
    from ultralytics import YOLO

    for arch, network in (("p", "yolov8p"), ("n", "yolov8n")):
        yolo = YOLO(model_yaml(arch, tmp_path))
        yolo.ckpt = {}
        yolo.save(str(tmp_path / f"{arch}.pt"))
        assert network_of_checkpoint(tmp_path / f"{arch}.pt") == network


def test_network_names_read_back_into_arch_activation_and_dfl_bins() -> None:
    from training.architectures import ACTIVATIONS, ARCHS, DFL_BINS, network_name, parse_network_name

    for arch in ARCHS:
        for activation in ACTIVATIONS:
            for bins in DFL_BINS:
                assert parse_network_name(network_name(arch, activation, bins)) == (arch, activation, bins)
    assert network_name("p", "relu", 8) == "yolov8p-relu-dfl8" and network_name("n") == "yolov8n"
    for bad in (
        "yolov8x",
        "yolov8p-gelu",
        "resnet18",
        "yolov8",
        "yolov8p-dfl16",
        "yolov8p-dfl3",
        "yolov8p-dfl8-relu",
        "yolov8p-relu-dfl8-x",
    ):
        with pytest.raises(ValueError, match="not a triscan network name"):
            parse_network_name(bad)


# --- INT8 recipes --------------------------------------------------------------------------------------


def test_int8_recipes_score_every_recipe_beside_fp32_on_the_same_samples(fp32: Path, dataset: Path) -> None:
    scores = compare_recipes(
        fp32, dataset, methods=["minmax"], float_modules=[1, 3], box_logits=(False, True), split="test",
        every=1, calib_count=CALIB_COUNT, head_convs=True,
    )  # fmt: skip
    assert [s.recipe for s in scores] == [
        "fp32",
        "minmax, stem float, box logits int8",
        "minmax, stem float, box logits float",
        "minmax, stem float, Detect head convs float",
        "minmax, modules 0–2 float, box logits int8",
        "minmax, modules 0–2 float, box logits float",
        "minmax, modules 0–2 float, Detect head convs float",
    ]
    assert scores[0].delta_map50 == 0.0
    for s in scores[1:]:  # each Δ is its own mAP minus the reference's, not a copied figure
        assert s.delta_map50 == pytest.approx(s.map50 - scores[0].map50, abs=2e-4)
        assert s.worst_class in CLASS_NAMES and 0.0 <= s.worst_class_map50 <= s.map50 + 1e-9 <= 1.0 + 1e-9
    table = format_recipe_table(scores)
    assert table.count("\n") == 8 and "| minmax, modules 0–2 float, box logits float |" in table
    class_logits = compare_recipes(
        fp32, dataset, methods=["minmax"], float_modules=[3], box_logits=(True,), class_logits=(False, True),
        split="test", every=1, calib_count=CALIB_COUNT,
    )  # fmt: skip
    assert [s.recipe for s in class_logits] == [
        "fp32",
        "minmax, modules 0–2 float, box logits float, class logits int8",
        "minmax, modules 0–2 float, box logits float",
    ]
    assert class_logits[2].map50 == scores[5].map50, "the same recipe scores the same"
    with pytest.raises(ValueError, match="every"):
        compare_recipes(fp32, dataset, methods=["minmax"], every=0)
