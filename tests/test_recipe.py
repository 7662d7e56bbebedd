"""The recipe file is the one home of `triscan train`/`export` defaults and of the eval presets."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import pytest

from services.cli import main
from training.recipe import SHIPPED_RECIPE, load_recipe, recipe_name


def test_the_shipped_recipe_is_the_default_of_the_training_and_export_code() -> None:
    from training.quantization import (
        DEFAULT_ACTIVATION_TYPE,
        DEFAULT_CALIB_COUNT,
        DEFAULT_CALIB_METHOD,
        DEFAULT_FLOAT_LEADING_MODULES,
    )
    from training.train import TrainConfig

    recipe = load_recipe()
    config = TrainConfig(data=Path("d.yaml"), out=Path("o"))
    assert (config.epochs, config.batch, config.patience, config.workers, config.seed, config.fraction) == (
        recipe.train.epochs, recipe.train.batch, recipe.train.patience, recipe.train.workers,
        recipe.train.seed, recipe.train.fraction,
    )  # fmt: skip
    assert config.recipe == SHIPPED_RECIPE
    export = recipe.export
    defaults = (DEFAULT_CALIB_COUNT, DEFAULT_CALIB_METHOD, DEFAULT_FLOAT_LEADING_MODULES)
    assert export.activations == DEFAULT_ACTIVATION_TYPE
    assert defaults == (export.calib_count, export.calib_method, export.float_modules)
    assert recipe_name(SHIPPED_RECIPE) == "training/recipes/default.toml"


def _write(tmp_path: Path, old: str, new: str) -> Path:
    text = SHIPPED_RECIPE.read_text()
    assert old in text
    path = tmp_path / "recipe.toml"
    path.write_text(text.replace(old, new))
    return path


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("patience = 6", "patients = 6", r"\[train\]: missing patience"),
        ("[export]\n", "[export]\nhalf = true\n", r"\[export\]: unknown half"),
        ("[dataset]", "[datasets]", "unknown table"),
        ("clutter = 3", "clutter = ", "Invalid value"),
    ],
)
def test_a_recipe_with_a_wrong_setting_is_refused_by_name(
    tmp_path: Path, old: str, new: str, message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        load_recipe(_write(tmp_path, old, new))


@pytest.fixture
def trained(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """The configs `triscan train` hands to training (nothing is trained)."""
    import training.train

    configs: list[Any] = []

    def fake_train(config: Any, **_: Any) -> dict[str, Any]:
        configs.append(config)
        return {"best_weights": "w", "epochs_run": 0}

    monkeypatch.setattr(training.train, "train", fake_train)
    return configs


def test_triscan_train_takes_unset_flags_from_the_recipe(tmp_path: Path, trained: list[Any]) -> None:
    shipped = load_recipe().train
    assert main(["train", "--data", "d.yaml", "--patience", "3"]) == 0
    assert trained[-1].patience == 3 and trained[-1].epochs == shipped.epochs
    assert trained[-1].recipe == SHIPPED_RECIPE
    other = _write(tmp_path, "epochs = 30", "epochs = 7")
    assert main(["train", "--data", "d.yaml", "--recipe", str(other)]) == 0
    assert trained[-1].epochs == 7 and trained[-1].patience == shipped.patience
    assert trained[-1].recipe == other
    assert trained[-1].lr0 is None  # the recipe's, unless --lr0 says otherwise
    assert main(["train", "--data", "d.yaml", "--lr0", "0.0003"]) == 0
    assert trained[-1].lr0 == 0.0003


def test_triscan_export_takes_unset_flags_from_the_recipe(monkeypatch: pytest.MonkeyPatch) -> None:
    import training.export

    calls: list[dict[str, Any]] = []
    monkeypatch.setattr(training.export, "export_models", lambda *a, **k: calls.append(k) or {})
    assert main(["export", "--weights", "w.pt", "--data", "d", "--calib-count", "8"]) == 0
    export = load_recipe().export
    assert calls[-1]["calib_count"] == 8 and calls[-1]["box_grid"] == export.box_grid
    assert (calls[-1]["method"], calls[-1]["float_leading_modules"], calls[-1]["activation_type"]) == (
        export.calib_method, export.float_modules, export.activations,
    )  # fmt: skip


@pytest.fixture
def grids(monkeypatch: pytest.MonkeyPatch) -> list[tuple[Any, list[str]]]:
    """The worlds and conditions `triscan eval` scores (no model is loaded, nothing simulated)."""
    import common.inference
    import training.evaluate

    seen: list[tuple[Any, list[str]]] = []
    monkeypatch.setattr(common.inference, "OnnxDetector", lambda *a, **k: object())
    monkeypatch.setattr(
        training.evaluate, "condition_matrix", lambda d, noise, worlds, out: seen.append((worlds, noise))
    )
    monkeypatch.setattr(training.evaluate, "format_condition_table", lambda reports: "")
    return seen


def test_the_unseen_preset_is_the_cards_protocol_and_a_flag_overrides_it(
    grids: list[tuple[Any, list[str]]],
) -> None:
    from training.evaluate import FreshWorlds

    unseen = load_recipe().preset("unseen")
    assert main(["eval", "--model", "a.onnx", "--preset", "unseen"]) == 0
    assert grids[-1] == (
        FreshWorlds(9000, 20, 90, 15, 0),
        ["clean", "sigma3", "drop5", "drop5+sigma3", "drop10+sigma3+spur1"],
    )
    assert (
        main(["eval", "--model", "a.onnx", "--preset", "unseen", "--seed", "5", "--noise", "clean", "sigma3"])
        == 0
    )
    assert grids[-1] == (
        FreshWorlds(5, unseen.fresh, unseen.positions, unseen.frame_stride, 0),
        ["clean", "sigma3"],
    )


def test_an_unknown_preset_or_a_recipe_without_one_is_one_line(caplog: pytest.LogCaptureFixture) -> None:
    assert main(["eval", "--model", "a.onnx", "--preset", "nope"]) == 2
    assert "has no eval preset 'nope' (it has: unseen, gate)" in caplog.text
    assert main(["eval", "--model", "a.onnx", "--fresh", "2", "--recipe", "r.toml"]) == 2
    assert "--recipe names the file of a --preset" in caplog.text


def test_the_dataset_recipe_names_dataset_flags() -> None:
    """[dataset] holds `triscan dataset` flags: each is one of its options."""
    from services.cli import build_parser, command_parser
    from services.cli.dataset import COMMAND

    options = {
        action.dest for action in command_parser(build_parser(COMMAND), "dataset")._actions
        if isinstance(action, argparse.Action)
    }  # fmt: skip
    assert set(vars(load_recipe().dataset)) <= options


def test_the_presets_are_the_protocols_the_shipped_card_measured() -> None:
    import json

    from common.model_spec import SHIPPED_DIR

    card = json.loads((SHIPPED_DIR / "MODEL_CARD.json").read_text())
    recipe = load_recipe()
    for preset, worlds, conditions in (
        (recipe.preset("unseen"), card["unseen_worlds"]["worlds"], list(card["unseen_worlds"]["fp32"])),
        (recipe.preset("gate"), card["quality_gate"], ["clean"]),
    ):
        assert (preset.seed, preset.fresh, preset.positions, preset.frame_stride) == (
            worlds["seed"], worlds["scenarios"], worlds["positions"], worlds["frame_stride"],
        )  # fmt: skip
        assert list(preset.noise) == conditions
