"""The models shipped in models/: same boxes as their checkpoints, same figures as Ultralytics, a gate.

Each card is checked: every shipped network's files and card share a directory (the paper's YOLOv8n in
models/, the default pico in models/yolov8p-dfl12/, the people preview in models/yolov8p-relu-dfl12/),
and the default is the one
``common.model_spec.SHIPPED_DIR`` names.
The gate threshold is not picked to pass: it is read from the card, where it is derived from the
held-out figures the card reports (see the card's "Quality gate" section).
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from dataclasses import dataclass
from fnmatch import fnmatch
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from common.inference import OnnxDetector, model_facts
from common.model_spec import MODELS_DIR, SHIPPED_DIR, model_stem
from training.evaluate import VAL_CONF, VAL_IOU, VAL_MAX_DET, dataset_samples, evaluate, fresh_samples


@dataclass(frozen=True)
class ShippedModel:
    """One card and the files it names, all in the card's directory."""

    directory: Path

    @property
    def card(self) -> dict[str, Any]:
        return json.loads((self.directory / "MODEL_CARD.json").read_text())

    def file(self, kind: str) -> Path:
        return self.directory / self.card["files"][kind]

    @property
    def gate(self) -> dict[str, Any]:
        return self.card["quality_gate"]

    @property
    def gate_worlds(self) -> dict[str, Any]:
        """What the gate's worlds hold besides furniture, and the model's own raster yaw."""
        return {
            "people": self.gate.get("people", 0),
            "clutter": self.gate.get("clutter", 0),
            "raster_yaw_deg": model_facts(self.file("fp32")).raster_yaw_deg,
        }


CARDS = [ShippedModel(card.parent) for card in sorted(MODELS_DIR.glob("**/MODEL_CARD.json"))]
DEFAULT = ShippedModel(SHIPPED_DIR)
FP32 = DEFAULT.file("fp32")
# The padding ablation's wrap model (the first recipe: YOLOv8n, epoch 3, clean scans; README, "Padding
# ablation"); it ships without a card of its own.
WRAP = MODELS_DIR / f"{model_stem('yolov8n', 'wrap')}.onnx"


@pytest.fixture(params=CARDS, ids=lambda m: m.directory.relative_to(MODELS_DIR.parent).as_posix())
def shipped(request: pytest.FixtureRequest) -> ShippedModel:
    return request.param


def test_the_default_model_has_its_card_and_every_card_ships_its_files() -> None:
    assert DEFAULT in CARDS and len(CARDS) >= 2
    for model in CARDS:
        for kind in ("fp32", "int8", "checkpoint", "fp32_batch", "int8_batch"):
            assert model.file(kind).is_file(), (model.directory, kind)


@pytest.fixture(scope="module")
def offline(tmp_path_factory: pytest.TempPathFactory) -> None:
    from training.offline import configure_offline

    configure_offline(tmp_path_factory.mktemp("yolo"))


@pytest.fixture(scope="module")
def unseen_set(tmp_path_factory: pytest.TempPathFactory) -> Callable[[ShippedModel], Path]:
    """A small data set from seeds no model was trained on, per gate setting, made when first asked."""
    from training.dataset import DatasetConfig, generate_dataset

    root, made = tmp_path_factory.mktemp("unseen"), {}

    def of_gate(model: ShippedModel) -> Path:
        gate, worlds = model.gate, model.gate_worlds
        key = (gate["seed"], gate["scenarios"], gate["positions"], gate["frame_stride"], *worlds.values())
        if key not in made:
            made[key] = root / "-".join(map(str, key))
            generate_dataset(
                DatasetConfig(
                    out=made[key],
                    scenarios=gate["scenarios"],
                    positions=gate["positions"],
                    seed=gate["seed"],
                    frame_stride=gate["frame_stride"],
                    **worlds,
                ),
                progress=False,
            )
        return made[key]

    return of_gate


def test_the_detector_runs_the_file_the_default_card_recommends() -> None:
    """`SHIPPED_MODEL` (what runs when no model is given) and the card's recommendation agree."""
    from common.model_spec import SHIPPED_CHECKPOINT, SHIPPED_FP32_MODEL, SHIPPED_INT8_MODEL, SHIPPED_MODEL

    assert DEFAULT.file(DEFAULT.card["recommended"]) == SHIPPED_MODEL
    assert (DEFAULT.file("fp32"), DEFAULT.file("int8")) == (SHIPPED_FP32_MODEL, SHIPPED_INT8_MODEL)
    assert DEFAULT.file("checkpoint") == SHIPPED_CHECKPOINT


def _docker_pattern(pattern: str) -> re.Pattern[str]:
    """A .dockerignore pattern as Docker (moby/patternmatcher) reads it: ``*`` and ``?`` stay within
    one path segment, ``**`` spans any number of them (none included)."""
    out = ""
    i = 0
    while i < len(pattern):
        if pattern.startswith("**/", i):
            out, i = out + "(?:.*/)?", i + 3
        elif pattern.startswith("**", i):
            out, i = out + ".*", i + 2
        else:
            out += {"*": "[^/]*", "?": "[^/]"}.get(pattern[i], re.escape(pattern[i]))
            i += 1
    return re.compile(out + "$")


def _in_build_context(relative: str, dockerignore: str) -> bool:
    """Whether ``relative`` reaches the build context: the last pattern matching it or one of its
    parent directories decides, a ``!`` pattern letting it in."""
    parts = relative.split("/")
    candidates = ["/".join(parts[: n + 1]) for n in range(len(parts))]
    included = True
    for line in dockerignore.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        negated = line.startswith("!")
        regex = _docker_pattern(line.removeprefix("!").strip("/"))
        if any(regex.match(c) for c in candidates):
            included = negated
    return included


def test_docker_pattern_matching() -> None:
    """The matcher the next test relies on, on Docker's documented cases."""
    ignore = "*\n!models/**/*.onnx\n**/*.pyc\n"
    assert _in_build_context("models/a.onnx", ignore)
    assert _in_build_context("models/yolov8p-dfl12/b.onnx", ignore)
    assert not _in_build_context("models/yolov8p-dfl12/b.pt", ignore)
    assert not _in_build_context("README.md", ignore)
    assert not _in_build_context("models/x/c.pyc", "!models/**\n**/*.pyc\n")
    assert not _in_build_context("models/sub/a.onnx", "*\n!models/*.onnx\n")


def test_every_dockerfile_copy_finds_files_in_the_build_context() -> None:
    """Each ``COPY`` from the build context (not from another stage) matches files .dockerignore lets
    in: what podman reported as "no items matching glob" only when an image was built."""
    root = MODELS_DIR.parent
    dockerignore = (root / ".dockerignore").read_text()
    copies = [
        line.split()[1:-1]
        for line in (root / "docker" / "Dockerfile").read_text().splitlines()
        if line.startswith("COPY ") and "--from=" not in line
    ]
    assert copies
    for sources in copies:
        for source in sources:
            matched = root.glob(source)
            files = [f for p in matched for f in ([p] if p.is_file() else p.rglob("*")) if f.is_file()]
            in_context = [f for f in files if _in_build_context(f.relative_to(root).as_posix(), dockerignore)]
            assert in_context, f"COPY {source}: nothing of it reaches the build context"


def test_the_robot_image_ships_the_default_model() -> None:
    """docker/Dockerfile's robot stage takes its venv from the stage that installs triscan from a copy of
    the repository: that copy holds the files the detector runs when given no model (the default and its
    -batch variant, wherever common.model_spec puts them) and what makes them the installed package, and
    .dockerignore lets them into the build context (it once kept a new default's directory out, and the
    build failed)."""
    from common.model_spec import SHIPPED_BATCH_MODEL, SHIPPED_MODEL

    root = MODELS_DIR.parent
    dockerignore = (root / ".dockerignore").read_text()
    stages = {
        stage.split("\n", 1)[0].split(" AS ")[-1].strip(): stage
        for stage in (root / "docker" / "Dockerfile").read_text().split("\nFROM ")
    }
    assert "COPY --from=venv-robot /opt/venv /opt/venv" in stages["robot"]
    installing = stages["venv-robot"]
    assert "pip-install.sh --project /tmp/triscan" in installing
    sources = [
        source
        for line in installing.splitlines()
        if line.startswith("COPY ") and "--from=" not in line
        for source in line.split()[1:-1]
    ]

    def copied(relative: str) -> bool:  # a directory copies what is below it; a glob only its own level
        return any(
            relative == s
            or relative.startswith(f"{s}/")
            or (fnmatch(relative, s) and relative.count("/") == s.count("/"))
            for s in sources
        )

    needed = [
        SHIPPED_MODEL,
        SHIPPED_BATCH_MODEL,
        SHIPPED_MODEL.parent / "MODEL_CARD.json",
        MODELS_DIR / "__init__.py",
    ]
    for path in [*needed, root / "pyproject.toml", root / "README.md"]:
        relative = path.relative_to(root).as_posix()
        assert copied(relative), (relative, sources)
        assert _in_build_context(relative, dockerignore), f"{relative} is left out by .dockerignore"


def test_card_files_exist_and_ids_match(shipped: ShippedModel) -> None:
    assert OnnxDetector(shipped.file("fp32")).model_id == shipped.card["model_ids"]["fp32"]
    assert OnnxDetector(shipped.file("int8")).model_id == shipped.card["model_ids"]["int8"]


@pytest.mark.parametrize("kind", ["fp32", "int8"])
def test_batch_variants_are_the_shipped_models_with_a_free_batch_axis(
    kind: str, shipped: ShippedModel
) -> None:
    """The ``-batch`` files say which file they were made from, by hash, and load as batch models."""
    onnx = pytest.importorskip("onnx")
    from common.model_spec import file_sha256 as sha256_of

    source, batch = shipped.file(kind), shipped.file(f"{kind}_batch")
    meta = {p.key: p.value for p in onnx.load(str(batch), load_external_data=False).metadata_props}
    assert meta["triscan.batch_source"] == f"{source.name} sha256:{sha256_of(source)[:12]}"
    detector = OnnxDetector(batch)
    assert detector.batched and detector.padding == "zero"
    assert not OnnxDetector(source).batched


def test_triscan_batch_model_makes_a_batch_variant_of_any_shipped_model(tmp_path: Path) -> None:
    """The wrap ablation model ships without one; ``triscan batch-model`` makes it, and refuses twice."""
    pytest.importorskip("onnx")
    from services.cli import main as cli_main

    out = tmp_path / "wrap-batch.onnx"
    assert cli_main(["batch-model", str(WRAP), "--out", str(out)]) == 0
    detector = OnnxDetector(out)
    assert detector.batched and detector.padding == "wrap"
    assert cli_main(["batch-model", str(out), "--out", str(tmp_path / "again.onnx")]) == 2
    assert not (tmp_path / "again.onnx").exists()


def test_the_wrap_ablation_model_ships_with_its_padding() -> None:
    assert OnnxDetector(WRAP).padding == "wrap"
    with pytest.raises(ValueError, match="padding"):
        OnnxDetector(WRAP, padding="zero")  # a wrap model is never fed zero-padded tensors
    assert OnnxDetector(FP32).padding == "zero"


def test_onnx_gives_the_checkpoints_boxes_within_one_pixel(offline: None, shipped: ShippedModel) -> None:
    import torch
    from ultralytics import YOLO
    from ultralytics.utils.nms import non_max_suppression
    from ultralytics.utils.ops import clip_boxes

    from common.encoding import to_model_input

    torch_model = YOLO(str(shipped.file("checkpoint"))).model.float().eval()
    # The network's own boxes: a model that rounds them to whole pixels is compared before rounding, and
    # without motion confirmation (common.moving_people), which Ultralytics does not do.
    detector = OnnxDetector(
        shipped.file("fp32"), conf_threshold=0.25, iou_threshold=0.45, box_grid="none", motion_confirm=None
    )
    compared = 0
    for sample in fresh_samples(shipped.gate["seed"], 1, 12, "zero", shipped.gate["frame_stride"]):
        with torch.no_grad():
            raw = torch_model(torch.from_numpy(to_model_input(sample.tensor)))[0]
        expected = non_max_suppression(raw, 0.25, 0.45, max_det=100)[0]
        clip_boxes(expected[:, :4], (64, 384))
        boxes, _, classes, _ = detector.detect_boxes(sample.tensor)
        assert len(boxes) == len(expected), sample.name
        order = np.lexsort((boxes[:, 0], classes))
        theirs = expected.numpy()
        their_order = np.lexsort((theirs[:, 0], theirs[:, 5]))
        np.testing.assert_array_equal(classes[order], theirs[their_order, 5].astype(np.int64))
        np.testing.assert_allclose(boxes[order], theirs[their_order, :4], atol=1.0)
        compared += len(boxes)
    assert compared > 20


def test_eval_matches_ultralytics_val_within_0_01(
    unseen_set: Callable[[ShippedModel], Path], offline: None, shipped: ShippedModel, tmp_path: Path
) -> None:
    from ultralytics import YOLO

    fp32 = shipped.file("fp32")
    unseen = unseen_set(shipped)
    detector = OnnxDetector(  # Ultralytics' val neither rounds boxes to whole pixels nor confirms by motion
        fp32,
        conf_threshold=VAL_CONF,
        iou_threshold=VAL_IOU,
        max_detections=VAL_MAX_DET,
        box_grid="none",
        motion_confirm=None,
    )
    ours = evaluate(detector, dataset_samples(unseen, "train"), tmp_path / "ours", source="gate", plots=False)
    theirs = YOLO(str(fp32), task="detect").val(
        data=str(unseen / "data.yaml"),
        split="train",
        batch=1,
        conf=VAL_CONF,
        iou=VAL_IOU,
        max_det=VAL_MAX_DET,
        plots=False,
        project=str(tmp_path),
        name="val",
        device="cpu",
        verbose=False,
    )
    assert abs(ours.overall["mAP50"] - float(theirs.box.map50)) < 0.01
    assert abs(ours.overall["mAP50-95"] - float(theirs.box.map)) < 0.01


@pytest.mark.parametrize("model", ["fp32", "int8"])
def test_quality_gate_on_unseen_scenarios(model: str, shipped: ShippedModel, tmp_path: Path) -> None:
    """`triscan eval --fresh` on the gate's scenarios: simulated through ScanStacker, never trained on."""
    gate = shipped.gate
    detector = OnnxDetector(
        shipped.file(model),
        conf_threshold=VAL_CONF,
        iou_threshold=VAL_IOU,
        max_detections=VAL_MAX_DET,
    )
    seed, scenarios, positions, stride = (gate[k] for k in ("seed", "scenarios", "positions", "frame_stride"))
    samples = fresh_samples(seed, scenarios, positions, "zero", stride, **shipped.gate_worlds)
    report = evaluate(detector, samples, tmp_path, source="gate", plots=False)
    assert report.instances >= gate["min_instances"]
    assert report.overall["mAP50"] >= gate["min_map50"], report.overall
