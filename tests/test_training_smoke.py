"""train → export → eval end to end on a tiny generated set, offline (two CPU epochs, one resume)."""

from __future__ import annotations

import gzip
import json
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

from common.inference import OnnxDetector
from training.dataset import DatasetConfig, generate_dataset
from training.evaluate import VAL_CONF, VAL_IOU, VAL_MAX_DET, dataset_samples, evaluate

if TYPE_CHECKING:
    import torch

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    from training.offline import configure_offline
    from training.train import TrainConfig, train

    root = tmp_path_factory.mktemp("smoke")
    configure_offline(root / "yolo")
    data = root / "data"
    generate_dataset(
        DatasetConfig(out=data, scenarios=3, positions=2, seed=3, frame_stride=4), progress=False
    )
    config = TrainConfig(
        data=data / "data.yaml", out=root / "run", epochs=2, batch=8, workers=0, device="cpu"
    )
    first = train(config, stop_after=1)
    assert first["epochs_run"] == 1 and not first["diverged"]
    import torch

    # Stopped by --stop-after, not finished: last.pt must still hold the optimizer to be resumable.
    last = torch.load(root / "run" / "weights" / "last.pt", map_location="cpu", weights_only=False)
    assert last["optimizer"] is not None and last["epoch"] == 0
    # Resumed elsewhere from the gzipped checkpoint, as a run committed to training/checkpoints/ is.
    saved = root / "run_last.pt.gz"
    with gzip.open(saved, "wb") as out:
        out.write((root / "run" / "weights" / "last.pt").read_bytes())
    summary = train(replace(config, out=root / "resumed"), resume=True, resume_from=saved)
    assert summary["epochs_run"] == 2 and not summary["diverged"]
    return data, Path(summary["best_weights"])


def test_training_writes_weights_and_a_summary(trained_run: tuple[Path, Path]) -> None:
    _, best = trained_run
    assert best.is_file() and best.name == "best.pt"
    summary = json.loads((best.parent.parent / "train_summary.json").read_text())
    assert summary["device"] == "cpu" and summary["config"]["epochs"] == 2
    # Resumed in another directory at epoch 2: the curve still starts at epoch 1 (from the checkpoint).
    rows = (best.parent.parent / "results.csv").read_text().splitlines()
    assert [row.split(",")[0] for row in rows[1:]] == ["1", "2"]


def test_export_then_eval_runs_through_the_runtime_detector(
    trained_run: tuple[Path, Path], tmp_path: Path
) -> None:
    from training.onnx_export import export_onnx

    data, best = trained_run
    onnx_path = export_onnx(best, tmp_path / "smoke.onnx", padding="zero")
    detector = OnnxDetector(
        onnx_path, conf_threshold=VAL_CONF, iou_threshold=VAL_IOU, max_detections=VAL_MAX_DET
    )
    report = evaluate(detector, dataset_samples(data, "val"), tmp_path / "eval", source="smoke")
    assert report.images > 0 and report.instances > 0
    assert all(0.0 <= v <= 1.0 for v in report.overall.values())
    written = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    assert written["model_id"] == detector.model_id and written["images"] == report.images
    for png in report.files.values():
        assert Path(png).is_file() and Path(png).stat().st_size > 1000
    assert np.isfinite(report.mean_timings_ms["inference_ms"])


def _one_epoch_from(init: Path, data: Path, out: Path, activation: str = "silu", dfl_bins: int = 16) -> Path:
    """One CPU epoch of ``activation``'s YOLOv8n from ``init`` on the smoke set; its ``last.pt``."""
    from training.train import TrainConfig, train

    config = TrainConfig(
        data=data / "data.yaml",
        out=out,
        epochs=1,
        batch=8,
        workers=0,
        device="cpu",
        activation=activation,
        init=init,
        dfl_bins=dfl_bins,
    )
    summary = train(config)
    assert summary["epochs_run"] == 1 and summary["config"]["init"] == str(init)
    return out / "weights" / "last.pt"


def _network(checkpoint: Path) -> Any:
    """The checkpoint's DetectionModel (an ``nn.Module`` with its YAML dict as ``.yaml``)."""
    import torch

    saved = torch.load(checkpoint, map_location="cpu", weights_only=False)
    return saved.get("ema") or saved["model"]


def _flat_weights(network: Any) -> torch.Tensor:
    import torch

    return torch.cat([w.detach().float().flatten() for w in network.parameters()])


def test_fine_tuning_starts_from_the_given_weights(trained_run: tuple[Path, Path], tmp_path: Path) -> None:
    """``--init``: one more epoch from the shipped YOLOv8n's weights stays near them.

    That checkpoint is 30 epochs away from any random start. A run that ignored ``--init``
    would start from the same seeded random weights as this module's short run and end near its
    ``best.pt`` (which is why that file cannot serve as the start here: it is the seeded start).
    """
    import torch

    from common.model_spec import PAPER_CHECKPOINT

    data, seeded_run = trained_run
    last = _one_epoch_from(PAPER_CHECKPOINT, data, tmp_path / "tuned")
    start, tuned = _flat_weights(_network(PAPER_CHECKPOINT)), _flat_weights(_network(last))
    ignored_init = _flat_weights(_network(seeded_run))
    assert tuned.shape == start.shape == ignored_init.shape
    assert torch.linalg.norm(tuned - start) < 0.25 * torch.linalg.norm(ignored_init - start)


def test_a_relu_network_starts_from_trained_silu_weights(
    trained_run: tuple[Path, Path], tmp_path: Path
) -> None:
    """``--activation relu --init <SiLU .pt>``: the ReLU network, named as such, with the trained weights.

    Activations hold no weights, so every tensor of the shipped SiLU YOLOv8n carries over; a run that
    rebuilt the network from random weights, or kept SiLU, or named the result after the SiLU network
    (export and the card read the name back) fails here.
    """
    import torch

    from common.model_spec import PAPER_CHECKPOINT
    from training.architectures import network_of_checkpoint

    data, _ = trained_run
    last = _one_epoch_from(PAPER_CHECKPOINT, data, tmp_path / "relu", activation="relu")
    assert network_of_checkpoint(PAPER_CHECKPOINT) == "yolov8n"
    assert network_of_checkpoint(last) == "yolov8n-relu"
    tuned_network, start_network = _network(last), _network(PAPER_CHECKPOINT)
    kinds = {type(m) for m in tuned_network.modules()}
    assert torch.nn.ReLU in kinds and torch.nn.SiLU not in kinds
    assert tuned_network.yaml["nc"] == start_network.yaml["nc"] == 4
    start, tuned = _flat_weights(start_network), _flat_weights(tuned_network)
    assert tuned.shape == start.shape
    assert torch.linalg.norm(tuned - start) < 0.25 * torch.linalg.norm(start)


def test_fewer_dfl_bins_keep_every_trained_tensor_but_the_box_branch(
    trained_run: tuple[Path, Path], tmp_path: Path
) -> None:
    """``--dfl-bins 8 --init <16-bin .pt>``: a narrower box branch, everything else from the weights.

    The box branch is ``4 · bins`` wide, so its tensors cannot carry over as they are: they start cut
    from the trained branch (``training.box_branch``), and every other tensor (backbone, neck, class
    branch) from the trained ones. The run is named after the new network, which exports to the same
    output layout (the DFL decodes inside the graph).
    """
    import torch

    from common.model_spec import FURNITURE_CLASSES, NUM_ANCHORS, PAPER_CHECKPOINT
    from training.architectures import network_of_checkpoint
    from training.onnx_export import export_onnx

    data, _ = trained_run
    last = _one_epoch_from(PAPER_CHECKPOINT, data, tmp_path / "dfl8", dfl_bins=8)
    assert network_of_checkpoint(last) == "yolov8n-dfl8"
    tuned, start = _network(last), _network(PAPER_CHECKPOINT)
    head, start_head = tuned.model[-1], start.model[-1]
    assert (head.reg_max, start_head.reg_max) == (8, 16)
    assert [branch[-1].out_channels for branch in head.cv2] == [32, 32, 32]
    tuned_tensors, start_tensors = tuned.state_dict(), start.state_dict()
    kept = [k for k in start_tensors if not k.startswith(("model.22.cv2", "model.22.dfl"))]
    assert kept and all(tuned_tensors[k].shape == start_tensors[k].shape for k in kept)
    kept_weights = [k for k in kept if k.endswith(".weight")]
    tuned_flat = torch.cat([tuned_tensors[k].float().flatten() for k in kept_weights])
    start_flat = torch.cat([start_tensors[k].float().flatten() for k in kept_weights])
    assert torch.linalg.norm(tuned_flat - start_flat) < 0.25 * torch.linalg.norm(start_flat)
    from training.box_branch import bin_rows, kept_channels

    for branch, start_branch in zip(head.cv2, start_head.cv2, strict=True):
        cut = start_branch[2].weight.float()[bin_rows(16, 8)][:, kept_channels(start_branch[1].bn, 32)]
        assert torch.linalg.norm(branch[2].weight.float() - cut) < 0.25 * torch.linalg.norm(cut)
    import onnxruntime as ort

    onnx_path = export_onnx(last, tmp_path / "dfl8.onnx", padding="zero")
    outputs = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"]).get_outputs()
    assert outputs[0].shape == [1, 4 + len(FURNITURE_CLASSES), NUM_ANCHORS]  # the smoke set has no people


def test_a_fine_tune_keeps_the_trained_weights_and_a_gentle_bias_warm_up(tmp_path: Path) -> None:
    """Ultralytics discards a loaded model's weights unless ``pretrained`` is set; a fresh run has none."""
    from training.recipe import load_recipe
    from training.train import TrainConfig, recipe

    fresh = recipe(TrainConfig(data=tmp_path / "data.yaml", out=tmp_path / "run"), "cpu")
    tuned = recipe(
        TrainConfig(data=tmp_path / "data.yaml", out=tmp_path / "run", init=tmp_path / "w.pt"), "cpu"
    )
    assert fresh["pretrained"] is False and "warmup_bias_lr" not in fresh
    assert tuned["pretrained"] is True and tuned["warmup_bias_lr"] == tuned["lr0"]
    assert tuned["lr0"] == load_recipe().train.ultralytics["lr0"]
    gentle = TrainConfig(data=tmp_path / "data.yaml", out=tmp_path / "run", init=tmp_path / "w.pt", lr0=2e-4)
    slower = recipe(gentle, "cpu")
    assert slower["lr0"] == slower["warmup_bias_lr"] == 2e-4  # --lr0 wins over the recipe's


def test_fine_tuning_refuses_weights_of_another_network(
    trained_run: tuple[Path, Path], tmp_path: Path
) -> None:
    from training.train import TrainConfig, initial_model

    data, best = trained_run
    with pytest.raises(ValueError, match="holds a yolov8n network, not yolov8p-relu: pass the --arch"):
        initial_model(
            TrainConfig(data=data / "data.yaml", out=tmp_path, arch="p", activation="relu", init=best)
        )
    with pytest.raises(FileNotFoundError, match="not found"):
        initial_model(TrainConfig(data=data / "data.yaml", out=tmp_path, init=tmp_path / "missing.pt"))


def test_triscan_train_fine_tunes_the_shipped_default_as_the_readme_says(
    trained_run: tuple[Path, Path], tmp_path: Path
) -> None:
    """`triscan train --init <the shipped .pt> --arch p …`, the README's command for your own rooms:
    the run trains the shipped network (12 DFL bins) from its weights, not a 16-bin one."""
    import torch

    from common.model_spec import SHIPPED_CHECKPOINT
    from services.cli import main as cli_main
    from training.architectures import network_of_checkpoint

    data, _ = trained_run
    out = tmp_path / "my_rooms"
    argv = ["train", "--init", str(SHIPPED_CHECKPOINT), "--arch", "p", "--data", str(data / "data.yaml")]
    argv += ["--out", str(out), "--epochs", "1", "--batch", "8", "--workers", "0", "--device", "cpu"]
    assert cli_main(argv) == 0
    tuned = out / "weights" / "last.pt"
    assert network_of_checkpoint(tuned) == network_of_checkpoint(SHIPPED_CHECKPOINT) == "yolov8p-dfl12"
    start, after = _flat_weights(_network(SHIPPED_CHECKPOINT)), _flat_weights(_network(tuned))
    assert after.shape == start.shape
    assert torch.linalg.norm(after - start) < 0.25 * torch.linalg.norm(start)


def test_a_fine_tune_keeps_the_checkpoints_network_unless_told_otherwise(tmp_path: Path) -> None:
    """``triscan train --arch p --init <the shipped .pt>`` fine-tunes the network the file holds: the
    shipped pico's 12 DFL bins, not a 16-bin branch restarted from random weights."""
    from common.model_spec import PAPER_CHECKPOINT, SHIPPED_CHECKPOINT
    from training.architectures import network_of_checkpoint, parse_network_name
    from training.train import network_choices

    arch, activation, bins = parse_network_name(network_of_checkpoint(SHIPPED_CHECKPOINT))
    assert (arch, bins) == ("p", 12)
    assert network_choices("p", SHIPPED_CHECKPOINT, None, None) == (activation, 12)
    assert network_choices("p", SHIPPED_CHECKPOINT, "relu", None) == ("relu", 12)
    assert network_choices("p", SHIPPED_CHECKPOINT, None, 8) == (activation, 8)
    # Without weights, or with another architecture's (which initial_model then refuses), the defaults.
    assert network_choices("p", None, None, None) == ("silu", 16)
    assert network_choices("p", PAPER_CHECKPOINT, None, None) == ("silu", 16)
    assert network_choices("p", tmp_path / "missing.pt", None, None) == ("silu", 16)


def test_validation_sees_the_images_unpadded(trained_run: tuple[Path, Path]) -> None:
    """Stock rect validation letterboxes 64 rows to 96; ours must validate the 64×384 run-time tensor."""
    from ultralytics.cfg import get_cfg
    from ultralytics.data.utils import check_det_dataset

    from training.train import validation_dataset

    data, _ = trained_run
    args = get_cfg(overrides={"imgsz": 384, "rect": True, "task": "detect"})
    dataset = validation_dataset(
        args, check_det_dataset(str(data / "data.yaml")), str(data / "images" / "val"), 4, 32
    )
    assert len(dataset) > 0
    assert {tuple(shape) for shape in dataset.batch_shapes} == {(64, 384)}
    assert dataset[0]["img"].shape == (3, 64, 384)


def test_pico_architecture_is_ultralytics_yolov8_at_width_0125(tmp_path: Path) -> None:
    from training.architectures import model_name, model_yaml
    from training.offline import configure_offline

    configure_offline(tmp_path / "yolo")
    from ultralytics import YOLO

    pico, nano = YOLO(model_yaml("p", tmp_path)), YOLO(model_yaml("n", tmp_path))
    n_pico = sum(p.numel() for p in pico.model.parameters())
    n_nano = sum(p.numel() for p in nano.model.parameters())
    assert n_pico < 0.4 * n_nano  # 0.91 M against 3.0 M once the head has triscan's 4 classes
    assert len(pico.model.model) == len(nano.model.model)  # the same graph, thinner
    assert pico.model.model[0].conv.out_channels * 2 == nano.model.model[0].conv.out_channels
    assert model_name("p") == "yolov8p"
    with pytest.raises(ValueError, match="arch must be one of"):
        model_yaml("q", tmp_path)


def test_relu_networks_are_the_same_graph_with_relu_in_place_of_silu(tmp_path: Path) -> None:
    from torch import nn

    from training.architectures import model_yaml
    from training.offline import configure_offline

    configure_offline(tmp_path / "yolo")
    from ultralytics import YOLO

    for arch in ("p", "n"):
        relu_yaml = model_yaml(arch, tmp_path, "relu")
        assert Path(relu_yaml).name == f"yolov8{arch}-relu.yaml"
        silu, relu = YOLO(model_yaml(arch, tmp_path)).model, YOLO(relu_yaml).model
        activations = {type(m.act) for m in relu.modules() if hasattr(m, "act")}
        assert activations == {nn.ReLU}, activations
        assert nn.SiLU in {type(m.act) for m in silu.modules() if hasattr(m, "act")}
        assert sum(p.numel() for p in relu.parameters()) == sum(p.numel() for p in silu.parameters())
    with pytest.raises(ValueError, match="activation must be one of"):
        model_yaml("p", tmp_path, "gelu")
