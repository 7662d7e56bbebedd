"""The model card is rendered from the artefacts that measured the model, and follows its own rules."""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import pytest

from common.model_spec import (
    SHIPPED_DIR,
    SHIPPED_FP32_MODEL,
    SHIPPED_INT8_MODEL,
    SHIPPED_MODEL,
    file_model_id,
    file_sha256,
    model_stem,
    network_of_stem,
)
from training.model_card import (
    STATUS_MARK,
    CurveComparison,
    GridSection,
    _float_parts_of_int8,
    card_status,
    checkpoint_epoch,
    refresh_files,
    refresh_status,
    shipped_card_dirs,
    write_card,
)

CLASSES = ("chair", "box", "desk", "doorframe")


def figures(map50: float) -> dict[str, float]:
    return {"precision": 0.95, "recall": 0.94, "mAP50": map50, "mAP50-95": map50 - 0.2}


def metrics(model_id: str, map50: float) -> dict[str, Any]:
    """A metrics.json as `triscan eval` writes it."""
    return {
        "model_id": model_id,
        "source": "x",
        "images": 10,
        "instances": 40,
        "padding": "zero",
        "overall": figures(map50),
        "per_class": {name: {"instances": 10, **figures(map50)} for name in CLASSES},
        "seam_crossing": {},
        "mean_timings_ms": {"encode_ms": 0.1, "inference_ms": 1.0, "nms_ms": 0.1},
        "files": {},
    }


def grid_cell(map50: float) -> dict[str, Any]:
    return {"images": 10, "instances": 40, **figures(map50), "per_class_mAP50": dict.fromkeys(CLASSES, map50)}


def write_results(path: Path, val_maps: list[tuple[float, float]]) -> Path:
    """An Ultralytics results.csv, one row per epoch from 1 with its val mAP@0.5 and mAP@0.5:0.95."""
    columns = ["epoch", "time", "train/box_loss", "metrics/precision(B)", "metrics/recall(B)"]
    columns += ["metrics/mAP50(B)", "metrics/mAP50-95(B)"]
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(columns)
        writer.writerows(
            [epoch, 100 * epoch, 1.0, 0.95, 0.95, map50, map50_95]
            for epoch, (map50, map50_95) in enumerate(val_maps, start=1)
        )
    return path


def artefacts(tmp_path: Path, grid_int8: dict[str, float]) -> dict[str, Any]:
    """Data set summary, run directory, export report and evaluations of a pico model pair."""
    import torch

    data = tmp_path / "data"
    data.mkdir(parents=True)
    config = {
        "scenarios": 480, "positions": 30, "seed": 0, "frame_stride": 15, "padding": "zero",
        "noise_sigma_m": [0.01, 0.03], "dropout_rate": [0.0, 0.1], "spurious_rate": [0.0, 0.01],
        "clutter": 3, "invalid": "sentinel",
    }  # fmt: skip
    splits = {"train": 408, "val": 48, "test": 24}
    (data / "summary.json").write_text(json.dumps({"config": config, "scenarios": splits, "samples": splits}))
    run = tmp_path / "run"
    (run / "weights").mkdir(parents=True)
    torch.save({"epoch": 1}, run / "weights" / "best.pt")  # 0-based: epoch 2
    write_results(run / "results.csv", [(0.95, 0.6), (0.98, 0.7)])
    fp32_id, int8_id = "triscan-yolov8p-zero@aaaaaaaaaaaa", "triscan-yolov8p-zero-int8@bbbbbbbbbbbb"
    export = {
        "padding": "zero",
        "fp32": {"path": "models/triscan-yolov8p-zero.onnx", "bytes": 1, "sha256": "a" * 64},
        "int8": {"path": "models/triscan-yolov8p-zero-int8.onnx", "bytes": 1, "sha256": "b" * 64},
        "latency_ms_1_thread": {"fp32": 1.2, "int8": 0.8},
        "calibration_method": "minmax",
        "calibration_images": 200,
        "float_leading_modules": 5,
        "float_box_logits": True,
    }
    paths = {}
    for name, value in {
        "export": export,
        "fp32": metrics(fp32_id, 0.99),
        "int8": metrics(int8_id, 0.99),  # equal on the test split
        "gate": metrics(fp32_id, 0.99),
        "grid": {
            "worlds": {"seed": 9000, "scenarios": 20, "positions": 90, "frame_stride": 15},
            "models": {"triscan-yolov8p-zero": fp32_id, "triscan-yolov8p-zero-int8": int8_id},
            "results": {
                condition: {
                    "triscan-yolov8p-zero": grid_cell(0.98),
                    "triscan-yolov8p-zero-int8": grid_cell(m),
                }
                for condition, m in grid_int8.items()
            },
        },
    }.items():
        paths[name] = tmp_path / f"{name}.json"
        paths[name].write_text(json.dumps(value))
    return {"data": data, "run": run, **paths}


def card_of(tmp_path: Path, grid_int8: dict[str, float], **extra: Any) -> dict[str, Any]:
    a = artefacts(tmp_path, grid_int8)
    return write_card(
        dataset_dir=a["data"], run_dir=a["run"], export_json=a["export"], eval_test_fp32=a["fp32"],
        eval_test_int8=a["int8"], eval_gate=a["gate"],
        gate={"seed": 1000, "scenarios": 6, "positions": 15, "frame_stride": 15},
        out_dir=tmp_path / "card", train_command="triscan train --arch p", conditions=a["grid"], **extra,
    )  # fmt: skip


def test_int8_is_recommended_only_within_half_a_point_under_every_condition(tmp_path: Path) -> None:
    close = card_of(tmp_path / "close", {"clean": 0.978, "drop5+sigma3": 0.976})
    assert close["recommended"] == "int8"
    # equal on the test split and clean, a point behind under one condition: fp32 stays the default
    behind = card_of(tmp_path / "behind", {"clean": 0.98, "drop10+sigma3+spur1": 0.97})
    assert behind["recommended"] == "fp32"
    assert behind["int8_minus_fp32_map50"]["drop10+sigma3+spur1"] == pytest.approx(-0.01)


def test_card_names_the_network_the_randomised_data_and_every_condition(tmp_path: Path) -> None:
    grid = tmp_path / "compare.json"
    grid.write_text(
        json.dumps(
            {
                "worlds": {"seed": 9000, "scenarios": 20, "positions": 90, "frame_stride": 15},
                "models": {"triscan-yolov8p-zero": "p@1", "triscan-yolov8n-zero": "n@2"},
                "results": {
                    "clean": {
                        "triscan-yolov8p-zero": grid_cell(0.98),
                        "triscan-yolov8n-zero": grid_cell(0.985),
                    }
                },
            }
        )
    )
    card = card_of(
        tmp_path,
        {"clean": 0.98, "sigma3": 0.979},
        grids=[GridSection("Networks compared", grid, "Same data.")],
    )
    text = (tmp_path / "card" / "MODEL_CARD.md").read_text()
    assert card["network"] == "yolov8p" and text.startswith("# Model card: triscan YOLOv8p")
    assert "--noise-sigma 0.01 0.03 --dropout 0 0.1 --spurious 0 0.01 --clutter 3`" in text
    assert "minmax ranges from 200 val images, modules 0–4, box logits, head decode in float |" in text
    assert (
        "`triscan eval --model models/triscan-yolov8p-zero.onnx --model models/triscan-yolov8p-zero-int8.onnx"
        in text
    )
    assert "## Unseen worlds under LiDAR imperfections" in text and "| sigma3 | 10 | 0.980 |" in text
    assert "## Networks compared" in text and "| clean | 0.980 / 0.780 | 0.985 / 0.785 |" in text
    saved = json.loads((tmp_path / "card" / "MODEL_CARD.json").read_text())
    assert set(saved["unseen_worlds"]["int8"]) == {"clean", "sigma3"}
    compared = saved["grids"]["Networks compared"]
    assert compared["models"]["triscan-yolov8n-zero"] == "n@2"
    assert compared["results"]["clean"]["triscan-yolov8n-zero"]["mAP50"] == 0.985


def test_network_of_a_model_file() -> None:
    assert network_of_stem(SHIPPED_FP32_MODEL.stem) == "yolov8p-dfl12"
    assert network_of_stem(SHIPPED_INT8_MODEL.stem) == "yolov8p-dfl12"
    assert network_of_stem("triscan-yolov8n-zero") == "yolov8n"
    assert network_of_stem("triscan-yolov8p-zero-int8-batch") == "yolov8p"
    assert network_of_stem("triscan-yolov8p-relu-wrap-int8") == "yolov8p-relu"
    assert model_stem("yolov8p", "zero") == "triscan-yolov8p-zero"
    empty = model_stem("yolov8p", "zero", "empty")
    assert empty == "triscan-yolov8p-zero-invalid-empty"
    assert network_of_stem(f"{empty}-int8") == "yolov8p"
    with pytest.raises(ValueError):
        network_of_stem("yolov8n")


def test_a_stripped_checkpoint_is_dated_by_the_validation_figures_it_keeps(tmp_path: Path) -> None:
    import torch

    history = [
        {"epoch": 1.0, "metrics/mAP50(B)": 0.95, "metrics/mAP50-95(B)": 0.6, "metrics/precision(B)": 0.9,
         "metrics/recall(B)": 0.9},
        {"epoch": 2.0, "metrics/mAP50(B)": 0.98, "metrics/mAP50-95(B)": 0.7, "metrics/precision(B)": 0.95,
         "metrics/recall(B)": 0.95},
    ]  # fmt: skip
    stripped = tmp_path / "best.pt"
    figures = {k: v for k, v in history[0].items() if k != "epoch"}
    torch.save({"epoch": -1, "train_metrics": figures | {"fitness": 0.6}}, stripped)
    assert checkpoint_epoch(stripped, history) == 1
    torch.save({"epoch": 4}, stripped)  # unstripped: its own epoch, 0-based
    assert checkpoint_epoch(stripped, history) == 5
    torch.save({"epoch": -1}, stripped)
    with pytest.raises(ValueError, match="stripped"):
        checkpoint_epoch(stripped, history)


@pytest.mark.parametrize(
    ("report", "said"),
    [
        (
            {"float_leading_modules": 5, "float_box_logits": True},
            "modules 0–4, box logits, head decode in float",
        ),
        (
            {"float_leading_modules": 5, "float_box_logits": True, "float_head_convs": True},
            "modules 0–4, the Detect head's convs, head decode in float",
        ),
        ({"float_leading_modules": 1, "float_box_logits": False}, "stem, head decode in float"),
        ({"float_leading_modules": 0, "float_box_logits": False}, "head decode in float"),
        ({"float_stem": True}, "stem and head decode in float"),  # a report from before the leading rule
        ({}, "head decode in float"),  # and from before the stem rule
    ],
)
def test_the_card_says_what_int8_kept_float_for_old_and_new_reports(
    report: dict[str, Any], said: str
) -> None:
    assert _float_parts_of_int8(report) == said


def test_the_card_sets_the_curve_beside_another_networks_epoch_for_epoch(tmp_path: Path) -> None:
    # this pico run: epochs 1-2 (0.95 / 0.60, 0.98 / 0.70); YOLOv8n ran one epoch more
    longer = write_results(tmp_path / "n.csv", [(0.96, 0.62), (0.99, 0.72), (0.995, 0.75)])
    card = card_of(tmp_path / "behind", {"clean": 0.98}, curves=CurveComparison("yolov8n", longer))
    text = (tmp_path / "behind" / "card" / "MODEL_CARD.md").read_text()
    assert "## Against YOLOv8n after the same epochs" in text
    assert "| 2 | 0.980 | 0.990 | 0.700 | 0.720 |" in text
    assert (
        "After 2 epochs, the last both ran: `yolov8p` is 1.00 points of mAP@0.5 behind `yolov8n` (outside"
        in text
    )
    curves = card["curves"]
    assert curves["last_common_epoch"] == 2 and [row["epoch"] for row in curves["rows"]] == [1, 2]
    assert curves["map50_gap_points"] == pytest.approx(1.0) and curves[
        "map50_95_gap_points"
    ] == pytest.approx(2.0)
    close = write_results(tmp_path / "close.csv", [(0.95, 0.6), (0.983, 0.69)])
    card_of(tmp_path / "close", {"clean": 0.98}, curves=CurveComparison("yolov8n", close))
    assert (
        "0.30 points of mAP@0.5 behind `yolov8n` (within the 0.5-point goal)"
        in (tmp_path / "close" / "card" / "MODEL_CARD.md").read_text()
    )


def test_continued_runs_are_compared_in_epochs_from_the_start_of_training(tmp_path: Path) -> None:
    # both runs continued from 30 epochs of their own network: their epochs 1-2 are training's 31-32
    other = write_results(tmp_path / "n.csv", [(0.96, 0.62), (0.99, 0.72)])
    card = card_of(
        tmp_path / "c", {"clean": 0.98}, curves=CurveComparison("yolov8n", other, epochs_before=30)
    )
    text = (tmp_path / "c" / "card" / "MODEL_CARD.md").read_text()
    assert "both runs continuing from 30 epochs of their own network" in text
    assert "| 32 | 0.980 | 0.990 | 0.700 | 0.720 |" in text and "| 2 | 0.980" not in text
    assert "After 32 epochs, the last both ran: `yolov8p` is 1.00 points" in text
    assert card["curves"]["epochs_before"] == 30 and card["curves"]["last_common_epoch"] == 2
    with pytest.raises(ValueError, match=">= 0"):
        CurveComparison("yolov8n", other, epochs_before=-1)


def test_epochs_before_needs_a_curve_to_count(caplog: pytest.LogCaptureFixture) -> None:
    from services.cli import main

    assert main(["card", "--data", "d", "--run-dir", "r", "--export-report", "e", "--eval-fp32", "f",
                 "--eval-int8", "i", "--eval-gate", "g", "--train-command", "t",
                 "--compare-curve-epochs-before", "30"]) == 2  # fmt: skip
    assert "give both" in caplog.text
    caplog.clear()
    assert main(["card", "--data", "d", "--run-dir", "r", "--export-report", "e", "--eval-fp32", "f",
                 "--eval-int8", "i", "--eval-gate", "g", "--train-command", "t",
                 "--gate-people", "-1"]) == 2  # fmt: skip
    assert "--gate-people must be >= 0, got -1" in caplog.text


def test_a_curve_without_a_common_epoch_is_refused(tmp_path: Path) -> None:
    empty = write_results(tmp_path / "none.csv", [])
    with pytest.raises(ValueError, match="shares no epoch"):
        card_of(tmp_path, {"clean": 0.98}, curves=CurveComparison("yolov8n", empty))
    with pytest.raises(FileNotFoundError, match=r"missing\.csv"):
        card_of(tmp_path / "b", {"clean": 0.98}, curves=CurveComparison("yolov8n", tmp_path / "missing.csv"))


@pytest.mark.parametrize("text", ["yolov8n", "=x.csv", "yolov8n="])
def test_compare_curve_takes_network_equals_csv(text: str) -> None:
    import argparse

    from services.cli.card import network_and_csv

    assert network_and_csv("yolov8n=runs/n/results.csv") == ("yolov8n", Path("runs/n/results.csv"))
    with pytest.raises(argparse.ArgumentTypeError, match="NETWORK=RESULTS_CSV"):
        network_and_csv(text)


def test_the_card_takes_its_status_from_the_model_spec(tmp_path: Path) -> None:
    """A card of files other than the spec's default says it ships beside the default; only the
    default's fp32 file name makes a card the default."""
    card = card_of(tmp_path, {"clean": 0.98})
    text = (tmp_path / "card" / "MODEL_CARD.md").read_text()
    assert card["status"] == "beside the default" and "the default model" not in text
    assert f"{STATUS_MARK} shipped beside the default** (`models/{SHIPPED_DIR.name}/`)" in text
    assert "`--model models/triscan-yolov8p-zero-int8.onnx`" in text  # the card's recommended file
    assert card_status(SHIPPED_FP32_MODEL.name) == "default"
    assert card_status(SHIPPED_INT8_MODEL.name) == card_status("triscan-yolov8n-zero.onnx") != "default"


def test_a_status_refresh_rewrites_the_status_and_nothing_else(tmp_path: Path) -> None:
    card_of(tmp_path, {"clean": 0.98})
    out = tmp_path / "card"
    before_md, before_json = (
        (out / "MODEL_CARD.md").read_text(),
        json.loads((out / "MODEL_CARD.json").read_text()),
    )
    claimed = before_json | {"files": before_json["files"] | {"fp32": SHIPPED_FP32_MODEL.name}}
    (out / "MODEL_CARD.json").write_text(json.dumps(claimed, indent=2) + "\n")
    refreshed = refresh_status(out)
    assert refreshed["status"] == "default" and list(refreshed) == list(before_json)
    text = (out / "MODEL_CARD.md").read_text()
    assert f"{STATUS_MARK} the default model.**" in text and f"runs `{SHIPPED_MODEL.name}`" in text
    status = [p for p in before_md.split("\n\n") if p.startswith(STATUS_MARK)]
    assert len(status) == 1 and text.replace(text.split("\n\n")[2], status[0]) == before_md
    (out / "MODEL_CARD.md").write_text(text + f"\n{STATUS_MARK} twice**\n")
    with pytest.raises(ValueError, match="2 status paragraphs"):
        refresh_status(out)


def test_the_shipped_cards_status_is_what_the_spec_writes(tmp_path: Path) -> None:
    """Refreshing every shipped card from the spec changes none of them (`python -m training.model_card`
    wrote them), and exactly one, the spec's default directory, says it is the default."""
    import shutil

    statuses = {}
    for directory in shipped_card_dirs():
        copy = tmp_path / directory.name
        shutil.copytree(directory, copy, ignore=shutil.ignore_patterns("*.onnx", "*.pt"))
        statuses[directory] = refresh_status(copy)["status"]
        for name in ("MODEL_CARD.md", "MODEL_CARD.json"):
            assert (copy / name).read_text() == (directory / name).read_text(), (directory, name)
    assert [d for d, status in statuses.items() if status == "default"] == [SHIPPED_DIR]
    assert len(statuses) >= 2


def test_a_files_refresh_rewrites_the_file_table_and_ids_from_the_files_and_nothing_else(
    tmp_path: Path,
) -> None:
    """Every shipped card's table already matches its files; a card whose files changed gets their sizes,
    hashes and model ids, and its figures stay as they were."""
    import shutil

    for directory in shipped_card_dirs():
        copy = tmp_path / directory.name
        shutil.copytree(directory, copy, ignore=shutil.ignore_patterns("*.pt"))
        refresh_files(copy)
        for name in ("MODEL_CARD.md", "MODEL_CARD.json"):
            assert (copy / name).read_text() == (directory / name).read_text(), (directory, name)
    card = json.loads((copy / "MODEL_CARD.json").read_text())
    int8 = copy / card["files"]["int8"]
    int8.write_bytes(int8.read_bytes() + b"\0")  # another file (ONNX Runtime would not load it; no matter)
    before = (copy / "MODEL_CARD.md").read_text()
    refreshed = refresh_files(copy)
    assert refreshed["model_ids"]["int8"] == file_model_id(int8) != card["model_ids"]["int8"]
    assert {k: v for k, v in refreshed.items() if k != "model_ids"} == {
        k: v for k, v in card.items() if k != "model_ids"
    }
    after = (copy / "MODEL_CARD.md").read_text()
    changed = [line for line in after.splitlines() if line not in before.splitlines()]
    assert len(changed) == 1 and f"| {int8.stat().st_size} | `{file_sha256(int8)[:16]}…` |" in changed[0]
    (copy / card["files"]["fp32"]).unlink()
    with pytest.raises(FileNotFoundError):
        refresh_files(copy)


def test_each_card_embeds_its_notes_verbatim() -> None:
    """The notes files are the cards' inputs (`triscan card --notes`, `--compare-notes`): a card and its
    notes say the same thing, so the notes can regenerate the card."""
    for directory in shipped_card_dirs():
        text = (directory / "MODEL_CARD.md").read_text()
        notes = sorted(directory.glob("*_notes.md"))
        assert notes, directory
        for path in notes:
            assert path.read_text().strip() in text, path


def test_the_models_readme_states_each_cards_figures() -> None:
    """models/README.md's table quotes the cards: each shipped card's test-split and clean unseen-world
    figures and its export latency, in the row that links the card."""
    import re

    readme = (SHIPPED_DIR.parent / "README.md").read_text()
    for directory in shipped_card_dirs():
        card = json.loads((directory / "MODEL_CARD.json").read_text())
        link = (directory / "MODEL_CARD.md").relative_to(SHIPPED_DIR.parent).as_posix()
        (row,) = [line for line in readme.splitlines() if f"]({link})" in line]

        def pair(figures: dict[str, float]) -> str:
            return f"{figures['mAP50']:.3f} / {figures['mAP50-95']:.3f}"

        test, unseen = card["test"], card["unseen_worlds"]
        assert f"fp32 {pair(test['fp32'])}, INT8 {pair(test['int8'])}" in row, directory
        clean = f"fp32 {pair(unseen['fp32']['clean'])}, INT8 {pair(unseen['int8']['clean'])}"
        assert clean in row, directory
        latency = re.search(r"^fp32 \S+ ms, INT8 \S+ ms", (directory / "MODEL_CARD.md").read_text(), re.M)
        assert latency and latency.group(0) in row, directory
        assert (card["status"] == "default") == ("**default**" in row), directory


def test_a_people_card_names_the_worlds_its_figures_come_from(tmp_path: Path) -> None:
    """A five-class model's data, gate and unseen worlds hold people: the card's commands say so, and a
    furniture card's gate stays as it was."""
    plain = card_of(tmp_path / "plain", {"clean": 0.98})
    assert "people" not in plain["quality_gate"] and "clutter" not in plain["quality_gate"]
    a = artefacts(tmp_path / "people", {"clean": 0.98})
    summary = json.loads((a["data"] / "summary.json").read_text())
    summary["config"].update(people=4, sensor="random", raster_yaw_deg=180.0, open_space=0.5)
    (a["data"] / "summary.json").write_text(json.dumps(summary))
    grid = json.loads(a["grid"].read_text())
    grid["worlds"].update(clutter=3, people=4, open_space=0.0)
    a["grid"].write_text(json.dumps(grid))
    card = write_card(
        dataset_dir=a["data"], run_dir=a["run"], export_json=a["export"], eval_test_fp32=a["fp32"],
        eval_test_int8=a["int8"], eval_gate=a["gate"],
        gate={"seed": 1000, "scenarios": 6, "positions": 15, "frame_stride": 15, "people": 4, "clutter": 3},
        out_dir=tmp_path / "card", train_command="triscan train --arch p", conditions=a["grid"],
    )  # fmt: skip
    text = (tmp_path / "card" / "MODEL_CARD.md").read_text()
    assert "--clutter 3 --people 4 --sensor random --raster-yaw 180 --open-space 0.5`" in text
    assert "labelled `person`, a LiDAR profile per scenario (`--sensor`), the raster turned 180°, " in text
    assert "every 15th window, with `--clutter 3 --people 4`, and requires" in text
    assert "--frame-stride 15 --clutter 3 --people 4 --noise clean`" in text  # no open space: no flag
    assert card["quality_gate"]["people"] == 4 and card["quality_gate"]["clutter"] == 3
