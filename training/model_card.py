"""``triscan card``: write models/MODEL_CARD.md and MODEL_CARD.json from the files that measured them.

Every figure in the card is read from an artefact a command wrote — the data set's summary.json, the
training run's results.csv and checkpoint, ``triscan export``'s JSON and ``triscan eval``'s
metrics.json — so the card can be regenerated and cannot drift from what was measured.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import platform
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from common.model_spec import (
    MODELS_DIR,
    SHIPPED_DIR,
    SHIPPED_FP32_MODEL,
    SHIPPED_MODEL,
    file_model_id,
    file_sha256,
    network_of_stem,
    network_title,
)
from training.quantization import float_modules_label

log = logging.getLogger(__name__)

GATE_MARGIN = 0.05  # the gate sits this far below the gate set's mAP@0.5 measured at export time
CURVE_GAP_GOAL_POINTS = 0.5  # a lighter network's val mAP@0.5 may trail the larger one's by this much
# results.csv's validation columns (Ultralytics' names; B: boxes)
_VAL_MAP50, _VAL_MAP50_95 = "metrics/mAP50(B)", "metrics/mAP50-95(B)"
_VAL_PRECISION, _VAL_RECALL = "metrics/precision(B)", "metrics/recall(B)"


Json = dict[str, Any]  # a JSON object as ``json`` reads and writes it


def _read_json(path: Path) -> Json:
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found")
    return dict(json.loads(path.read_text()))


@dataclass(frozen=True)
class Figures:
    """Precision, recall, mAP@0.5 and mAP@0.5:0.95, under metrics.json's names."""

    precision: float
    recall: float
    map50: float
    map50_95: float

    @classmethod
    def read(cls, figures: Mapping[str, Any]) -> Figures:
        return cls(figures["precision"], figures["recall"], figures["mAP50"], figures["mAP50-95"])

    def to_json(self) -> Json:
        return {
            "precision": self.precision,
            "recall": self.recall,
            "mAP50": self.map50,
            "mAP50-95": self.map50_95,
        }


@dataclass(frozen=True)
class Counted:
    """:class:`Figures` over a counted set of objects: one class, or the objects on the seam."""

    instances: int
    figures: Figures

    @classmethod
    def read(cls, figures: Mapping[str, Any]) -> Counted:
        return cls(figures["instances"], Figures.read(figures))

    def to_json(self) -> Json:
        return {"instances": self.instances, **self.figures.to_json()}


@dataclass(frozen=True)
class Evaluation:
    """The parts of ``triscan eval``'s metrics.json the card shows."""

    model_id: str
    images: int
    instances: int
    overall: Figures
    per_class: dict[str, Counted]
    seam_crossing: Counted | None  # None when the evaluation had no seam figures
    mean_timings_ms: dict[str, float]  # encode_ms, inference_ms, nms_ms

    @classmethod
    def read(cls, path: Path) -> Evaluation:
        m = _read_json(path)
        return cls(
            model_id=m["model_id"],
            images=m["images"],
            instances=m["instances"],
            overall=Figures.read(m["overall"]),
            per_class={name: Counted.read(row) for name, row in m["per_class"].items()},
            seam_crossing=Counted.read(m["seam_crossing"]) if m.get("seam_crossing") else None,
            mean_timings_ms=m["mean_timings_ms"],
        )


@dataclass(frozen=True)
class GridCell:
    """One model under one condition in a ``triscan eval`` grid (summary.json)."""

    images: int
    instances: int
    figures: Figures
    per_class_map50: dict[str, float]

    @classmethod
    def read(cls, cell: Mapping[str, Any]) -> GridCell:
        return cls(cell["images"], cell["instances"], Figures.read(cell), cell["per_class_mAP50"])

    def to_json(self) -> Json:
        return {
            "images": self.images,
            "instances": self.instances,
            **self.figures.to_json(),
            "per_class_mAP50": self.per_class_map50,
        }


@dataclass(frozen=True)
class Grid:
    """A ``triscan eval --fresh N --noise …`` grid: the worlds, the models and every cell."""

    worlds: Json  # the world spec as eval wrote it (seed, scenarios, positions, frame_stride, …)
    models: dict[str, str]  # file stem → model id
    results: dict[str, dict[str, GridCell]]  # condition → file stem → cell

    @classmethod
    def read(cls, path: Path) -> Grid:
        grid = _read_json(path)
        return cls(
            worlds=grid["worlds"],
            models=grid["models"],
            results={
                condition: {stem: GridCell.read(cell) for stem, cell in row.items()}
                for condition, row in grid["results"].items()
            },
        )

    def cells_of(self, model_id: str) -> dict[str, GridCell]:
        """One model's cells, by condition."""
        stems = [stem for stem, mid in self.models.items() if mid == model_id]
        if not stems:
            raise ValueError(
                f"the conditions grid has no cells of {model_id} (it has {sorted(self.models.values())})"
            )
        return {condition: row[stems[0]] for condition, row in self.results.items()}


@dataclass(frozen=True)
class ExportedFile:
    """One file ``triscan export`` wrote, as its report names it."""

    path: Path
    bytes: int
    sha256: str

    @classmethod
    def read(cls, entry: Mapping[str, Any]) -> ExportedFile:
        return cls(Path(entry["path"]), entry["bytes"], entry["sha256"])


@dataclass(frozen=True)
class ExportReport:
    """``triscan export``'s JSON report: the files, their latency and the INT8 recipe."""

    padding: str
    fp32: ExportedFile
    int8: ExportedFile
    batch: dict[str, ExportedFile]  # "fp32"/"int8" → the same graph with a free batch axis
    latency_ms_fp32: float  # session.run median, 1 ONNX Runtime thread
    latency_ms_int8: float
    calibration_method: str
    calibration_images: int
    float_parts: str  # what the INT8 file kept in float, in words

    @classmethod
    def read(cls, path: Path) -> ExportReport:
        export = _read_json(path)
        latency = export["latency_ms_1_thread"]
        return cls(
            padding=export["padding"],
            fp32=ExportedFile.read(export["fp32"]),
            int8=ExportedFile.read(export["int8"]),
            # Reports written before the batch variants existed simply have none.
            batch={
                kind: ExportedFile.read(export[f"{kind}_batch"])
                for kind in ("fp32", "int8")
                if f"{kind}_batch" in export
            },
            latency_ms_fp32=latency["fp32"],
            latency_ms_int8=latency["int8"],
            calibration_method=export["calibration_method"],
            calibration_images=export["calibration_images"],
            float_parts=_float_parts_of_int8(export),
        )


@dataclass(frozen=True)
class DatasetSummary:
    """The data set's summary.json, as ``triscan dataset`` wrote it."""

    config: Json  # the generation settings, flags by name
    scenarios: dict[str, int]  # split → scenarios
    samples: dict[str, int]  # split → samples

    @classmethod
    def read(cls, dataset_dir: Path) -> DatasetSummary:
        data = _read_json(dataset_dir / "summary.json")
        return cls(data["config"], data["scenarios"], data["samples"])


def read_results_csv(path: Path) -> list[dict[str, float]]:
    """An Ultralytics results.csv as a list of rows (keys stripped of padding)."""
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found")
    with path.open() as handle:
        return [{k.strip(): float(v) for k, v in row.items()} for row in csv.DictReader(handle)]


def training_history(run_dir: Path) -> list[dict[str, float]]:
    """results.csv of an Ultralytics run directory."""
    return read_results_csv(run_dir / "results.csv")


def checkpoint_epoch(weights: Path, history: list[dict[str, float]]) -> int:
    """1-based epoch a checkpoint was saved at (Ultralytics stores it 0-based).

    A run that finishes strips its checkpoints, epoch set to -1, but keeps the validation figures of
    the epoch the weights are from (``train_metrics``): that epoch is the row of results.csv with the
    same figures.
    """
    import torch

    checkpoint = torch.load(weights, map_location="cpu", weights_only=False)
    epoch = int(checkpoint.get("epoch", -2)) + 1
    if epoch >= 1:
        return epoch
    held = checkpoint.get("train_metrics") or {}
    keys = (_VAL_MAP50, _VAL_MAP50_95, _VAL_PRECISION, _VAL_RECALL)
    matches = [int(row["epoch"]) for row in history if held and all(row.get(k) == held.get(k) for k in keys)]
    if len(matches) != 1:
        raise ValueError(
            f"{weights} is stripped (no epoch) and its validation figures match {len(matches)} rows of "
            "results.csv: pass the run directory the checkpoint came from"
        )
    return matches[0]


def training_wall_time_s(history: list[dict[str, float]]) -> float:
    """Total training time: results.csv's clock restarts at each resume, so add up the segments."""
    total, previous = 0.0, 0.0
    for row in history:
        if row["time"] < previous:
            total += previous
        previous = row["time"]
    return total + previous


def _metrics_rows(metrics: Evaluation) -> list[str]:
    rows = ["| class | instances | P | R | mAP@0.5 | mAP@0.5:0.95 |", "|---|---:|---:|---:|---:|---:|"]
    for name, row in metrics.per_class.items():
        m = row.figures
        rows.append(
            f"| {name} | {row.instances} | {m.precision:.3f} | {m.recall:.3f} | {m.map50:.3f} "
            f"| {m.map50_95:.3f} |"
        )
    o = metrics.overall
    rows.append(
        f"| **all** | {metrics.instances} | {o.precision:.3f} | {o.recall:.3f} "
        f"| **{o.map50:.3f}** | **{o.map50_95:.3f}** |"
    )
    return rows


@dataclass(frozen=True)
class AblationEntry:
    """One padding mode's model in the card's ablation: its test split overall and on the seam."""

    model_id: str
    test: Figures
    seam_crossing: Counted

    def to_json(self) -> Json:
        return {
            "model_id": self.model_id,
            "test": self.test.to_json(),
            "seam_crossing": self.seam_crossing.to_json(),
        }


def _ablation_lines(ablation: dict[str, Path], command: str) -> tuple[list[str], dict[str, AblationEntry]]:
    """The zero vs wrap section: each model on its own padding's test split, overall and on the seam."""
    results = {padding: Evaluation.read(path) for padding, path in ablation.items()}
    rows = [
        "| padding | model | test P | R | mAP@0.5 | mAP@0.5:0.95 | seam objects | seam R | seam mAP@0.5 "
        "| seam mAP@0.5:0.95 |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    summary: dict[str, AblationEntry] = {}
    for padding, m in results.items():
        o, seam = m.overall, m.seam_crossing
        if seam is None:
            raise ValueError(f"{ablation[padding]} has no seam_crossing figures: rerun `triscan eval` on it")
        s = seam.figures
        rows.append(
            f"| `{padding}` | `{m.model_id}` | {o.precision:.3f} | {o.recall:.3f} "
            f"| {o.map50:.3f} | {o.map50_95:.3f} | {int(seam.instances)} | {s.recall:.3f} "
            f"| {s.map50:.3f} | {s.map50_95:.3f} |"
        )
        summary[padding] = AblationEntry(m.model_id, o, seam)
    lines = [
        "## Ablation: `zero` vs `wrap` padding",
        "",
        "Two models, one per padding mode, trained with the same recipe, seed and scenarios for the same "
        "epochs, each evaluated on the test split of its own data set (the same scenarios and scans; the "
        "tensors differ in columns 360–383 and the labels at the seam). With `wrap`, an object near 0° "
        "can be labelled twice (whole across the seam and as the copy in columns 0–23 or 360–383); the "
        "detector merges such copies, so the evaluation merges the labels the same way and compares boxes "
        "on the circle (IoU over ±360-column shifts). *Seam objects* are those whose footprint spans the "
        "0°/360° column boundary, found from the scene geometry: `zero` labels them with the clipped "
        "box on their centre's side (the paper's rule), `wrap` with the whole box when it fits within the "
        "24 padding columns and otherwise with the two pieces the image shows.",
        "",
        f"`wrap` run: `{command}`",
        "",
        *rows,
    ]
    return lines, summary


@dataclass(frozen=True)
class QualityGate:
    """What tests/test_shipped_model.py requires of the shipped model: the gate set and the bar."""

    seed: int
    scenarios: int
    positions: int
    frame_stride: int
    min_instances: int
    min_map50: float
    measured_map50: float
    people: int = 0  # the most people per motion (0: the paper's furniture-only worlds)
    clutter: int = 0  # the most unlabelled clutter items per motion

    def to_json(self) -> Json:
        """Every field, but people and clutter only if the gate's worlds hold them: a furniture-only
        card's JSON stays as it was."""
        return {k: v for k, v in self.__dict__.items() if v or k not in ("people", "clutter")}

    @property
    def worlds_flags(self) -> str:
        """What the gate's worlds hold besides furniture, as ``triscan eval --fresh`` flags."""
        return _worlds_flags(self.__dict__)


@dataclass(frozen=True)
class UnseenWorlds:
    """This card's fp32 and INT8 files on the same unseen worlds, by condition."""

    worlds: Json
    fp32: dict[str, GridCell]
    int8: dict[str, GridCell]

    def to_json(self) -> Json:
        return {
            "worlds": self.worlds,
            "fp32": {condition: cell.to_json() for condition, cell in self.fp32.items()},
            "int8": {condition: cell.to_json() for condition, cell in self.int8.items()},
        }


@dataclass
class ModelCard:
    """MODEL_CARD.json: the files, which one to run, the test figures and the shipped-model gate."""

    network: str
    directory: str  # where `triscan export` wrote the files
    files: dict[str, str]  # kind (fp32, int8, checkpoint, fp32_batch, int8_batch) → file name
    model_ids: dict[str, str]  # fp32/int8 → model id
    recommended: str  # "fp32" or "int8": the file the detector should run
    status: str  # card_status: whether the model spec makes this the default
    padding: str
    best_epoch: int
    epochs_run: int
    test: dict[str, Figures]  # fp32/int8 → test split figures
    quality_gate: QualityGate
    int8_minus_fp32_map50: dict[str, float]  # where measured → INT8 − fp32 mAP@0.5
    unseen_worlds: UnseenWorlds | None = None
    grids: Json | None = None  # section title → GridSection.figures
    curves: Json | None = None  # CurveComparison.figures
    ablation: dict[str, AblationEntry] | None = None  # padding → its model's figures
    recipe: str | None = None  # the recipe file whose defaults made the model

    def to_json(self) -> Json:
        card: Json = {
            "network": self.network,
            "directory": self.directory,
            "files": self.files,
            "model_ids": self.model_ids,
            "recommended": self.recommended,
            "status": self.status,
            "padding": self.padding,
            "best_epoch": self.best_epoch,
            "epochs_run": self.epochs_run,
            "test": {kind: figures.to_json() for kind, figures in self.test.items()},
            "quality_gate": self.quality_gate.to_json(),
            "int8_minus_fp32_map50": self.int8_minus_fp32_map50,
        }
        if self.unseen_worlds is not None:
            card["unseen_worlds"] = self.unseen_worlds.to_json()
        if self.recipe:
            card["recipe"] = self.recipe
        if self.grids:
            card["grids"] = self.grids
        if self.curves is not None:
            card["curves"] = self.curves
        if self.ablation:
            card["ablation"] = {padding: entry.to_json() for padding, entry in self.ablation.items()}
        return card


def write_card(
    *,
    dataset_dir: Path,
    run_dir: Path,
    export_json: Path,
    eval_test_fp32: Path,
    eval_test_int8: Path,
    eval_gate: Path,
    gate: dict[str, int],
    out_dir: Path,
    train_command: str,
    notes: str = "",
    ablation: dict[str, Path] | None = None,
    ablation_command: str = "",
    ablation_notes: str = "",
    conditions: Path | None = None,
    grids: list[GridSection] | None = None,
    curves: CurveComparison | None = None,
    recipe: str = "",
) -> Json:
    """Write the card pair into ``out_dir`` and return the JSON half, as written.

    ``ablation`` maps each padding mode to the ``metrics.json`` of its model's test-split evaluation.
    ``conditions`` is the ``summary.json`` of ``triscan eval --fresh N --noise …`` run on this card's
    fp32 and INT8 files: unseen worlds under LiDAR imperfections, which also decide whether INT8 is
    recommended. ``grids`` are further such grids (another network, another invalid-return rule) shown
    beside them; ``curves`` sets this run's validation curve beside another network's, epoch for epoch.
    ``recipe`` names the recipe file (:mod:`training.recipe`) the run and the export took their defaults
    from.
    """
    data = DatasetSummary.read(dataset_dir)
    export = ExportReport.read(export_json)
    test32, test8, gate_metrics = (Evaluation.read(p) for p in (eval_test_fp32, eval_test_int8, eval_gate))
    grid = Grid.read(conditions) if conditions is not None else None
    history = training_history(run_dir)
    best_epoch = checkpoint_epoch(run_dir / "weights" / "best.pt", history)
    best_row = next(r for r in history if int(r["epoch"]) == best_epoch)
    card = _model_card(export, test32, test8, gate_metrics, gate, history, best_epoch, grid)
    grid_figures = {section.title: section.figures() for section in grids or []}
    curve_figures = curves.figures(history) if curves is not None else None
    lines = [
        f"# Model card: triscan {network_title(card.network)} (`{card.files['fp32']}`)",
        "",
        "Generated by `triscan card` from the artefacts named below; rerun the commands to re-measure.",
        "",
        status_line(card.to_json()),
        "",
        notes.strip(),
        "",
        *_files_section(card, export),
        "",
        *_data_section(data),
        "",
        *_training_section(history, best_epoch, best_row, train_command),
        "",
        *(
            [f"Recipe (the defaults of `triscan train` and `triscan export`): `{recipe}`.", ""]
            if recipe
            else []
        ),
        *(
            curves.lines(curve_figures, card.network)
            if curves is not None and curve_figures is not None
            else []
        ),
        *_test_section(card, test32, test8),
        "",
        *(_conditions_section(card, conditions) if conditions is not None else []),
        *(line for section in grids or [] for line in section.lines(grid_figures[section.title])),
        *_latency_section(export, test32),
        "",
        *_gate_section(card, gate_metrics),
    ]
    card.grids = grid_figures
    card.curves = curve_figures
    card.recipe = recipe or None
    if ablation:
        ablation_lines, card.ablation = _ablation_lines(ablation, ablation_command)
        lines += ["", *ablation_lines]
        if ablation_notes.strip():
            lines += ["", ablation_notes.strip()]
    card_json = card.to_json()
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "MODEL_CARD.md").write_text("\n".join(lines) + "\n")
    (out_dir / "MODEL_CARD.json").write_text(json.dumps(card_json, indent=2) + "\n")
    log.info("wrote %s", out_dir / "MODEL_CARD.md")
    return card_json


INT8_TOLERANCE = 0.005  # INT8 is recommended only within half a point of fp32's mAP@0.5, everywhere measured


def _int8_deltas(test32: Evaluation, test8: Evaluation, unseen: UnseenWorlds | None) -> dict[str, float]:
    """INT8 minus fp32 mAP@0.5 on the test split and, when measured, under every condition: what
    decides, with the latency, which file is recommended."""
    deltas = {"test split": float(test8.overall.map50 - test32.overall.map50)}
    if unseen is not None:
        fp32, int8 = unseen.fp32, unseen.int8
        deltas |= {
            condition: int8[condition].figures.map50 - fp32[condition].figures.map50 for condition in fp32
        }
    return deltas


def _model_card(
    export: ExportReport,
    test32: Evaluation,
    test8: Evaluation,
    gate_metrics: Evaluation,
    gate: dict[str, int],
    history: list[dict[str, float]],
    best_epoch: int,
    grid: Grid | None = None,
) -> ModelCard:
    """The card's figures, from the artefacts; the sections and the JSON are written from it."""
    unseen = (
        None
        if grid is None
        else UnseenWorlds(grid.worlds, grid.cells_of(test32.model_id), grid.cells_of(test8.model_id))
    )
    deltas = _int8_deltas(test32, test8, unseen)
    faster = export.latency_ms_int8 < export.latency_ms_fp32
    recommended = "int8" if faster and min(deltas.values()) >= -INT8_TOLERANCE else "fp32"
    min_map50 = math.floor((gate_metrics.overall.map50 - GATE_MARGIN) * 100) / 100
    return ModelCard(
        network=network_of_stem(export.fp32.path.stem),
        directory=export.fp32.path.parent.as_posix(),
        files={
            "fp32": export.fp32.path.name,
            "int8": export.int8.path.name,
            "checkpoint": f"{export.fp32.path.stem}.pt",
            **{f"{kind}_batch": entry.path.name for kind, entry in export.batch.items()},
        },
        model_ids={"fp32": test32.model_id, "int8": test8.model_id},
        recommended=recommended,
        status=card_status(export.fp32.path.name),
        padding=export.padding,
        best_epoch=best_epoch,
        epochs_run=len(history),
        test={"fp32": test32.overall, "int8": test8.overall},
        quality_gate=QualityGate(
            seed=gate["seed"],
            scenarios=gate["scenarios"],
            positions=gate["positions"],
            frame_stride=gate["frame_stride"],
            min_instances=gate_metrics.instances // 2,
            min_map50=min_map50,
            measured_map50=gate_metrics.overall.map50,
            people=gate.get("people", 0),
            clutter=gate.get("clutter", 0),
        ),
        int8_minus_fp32_map50=deltas,
        unseen_worlds=unseen,
    )


def _float_parts_of_int8(export: Mapping[str, Any]) -> str:
    """What the INT8 file kept in float, from ``triscan export``'s report (older reports, older rules)."""
    if "float_leading_modules" in export:
        leading = float_modules_label(int(export["float_leading_modules"]))
        parts = [leading] if leading else []
        if export.get("float_head_convs"):
            parts.append("the Detect head's convs")
        elif export.get("float_box_logits"):
            parts.append("box logits")
        return ", ".join([*parts, "head decode"]) + " in float"
    # Reports from before the leading-modules rule: the stem alone or nothing but the head's decode.
    return "stem and head decode in float" if export.get("float_stem") else "head decode in float"


def _files_section(card: ModelCard, export: ExportReport) -> list[str]:
    """The shipped files with their sizes and hashes, and which one the detector should run."""
    fp32, int8 = export.fp32, export.int8
    recipe = f"{export.calibration_method} ranges from {export.calibration_images} val images, " + (
        export.float_parts
    )
    return [
        "## Files",
        "",
        "| file | what | bytes | sha256 |",
        "|---|---|---:|---|",
        f"| `{card.files['fp32']}` | ONNX fp32, input float32[1,3,64,384] | {fp32.bytes} | "
        f"`{fp32.sha256[:16]}…` |",
        f"| `{card.files['int8']}` | ONNX INT8 static QDQ, per-channel weights, uint8 activations, "
        f"{recipe} | {int8.bytes} | `{int8.sha256[:16]}…` |",
        *(
            f"| `{card.files[f'{kind}_batch']}` | the {kind} file with a free batch axis (same graph "
            "and weights, outputs checked equal) for `python -m services.detector --batch N` | "
            f"{entry.bytes} | `{entry.sha256[:16]}…` |"
            for kind, entry in export.batch.items()
        ),
        f"| `{card.files['checkpoint']}` | Ultralytics checkpoint of the same weights "
        "(optimizer stripped) | | |",
        "",
        f"Recommended for the detector: **{card.recommended}** (INT8 ships as default only if it is "
        "faster and its mAP@0.5 is within 0.5 points of fp32's on the test split and, where measured, "
        "on unseen worlds under every LiDAR condition; measured INT8 − fp32: "
        + ", ".join(f"{name} {delta * 100:+.2f}" for name, delta in card.int8_minus_fp32_map50.items())
        + " points).",
    ]


def _randomisation_flags(cfg: Mapping[str, Any]) -> str:
    """The data set's domain randomisation as ``triscan dataset`` flags ('' for the paper's clean set)."""
    from services.simulator.lidar import DEFAULT_SPEC  # the data set was simulated, so PyBullet is here

    flags = []
    sigma = cfg.get("noise_sigma_m")
    if sigma is not None and list(sigma) != [DEFAULT_SPEC.noise_sigma_m] * 2:
        flags.append(f"--noise-sigma {sigma[0]:g} {sigma[1]:g}")
    for key, flag in (("dropout_rate", "--dropout"), ("spurious_rate", "--spurious")):
        low, high = cfg.get(key) or (0.0, 0.0)
        if high > 0:
            flags.append(f"{flag} {low:g} {high:g}")
    if cfg.get("clutter"):
        flags.append(f"--clutter {cfg['clutter']}")
    if cfg.get("invalid", "sentinel") != "sentinel":
        flags.append(f"--invalid {cfg['invalid']}")
    flags += [_flag(flag, cfg[key]) for key, flag, _ in _SET_OPTIONS if cfg.get(key)]
    return "".join(f" {flag}" for flag in flags)


def _flag(flag: str, value: Any) -> str:
    """``flag value`` as a command line reads it: a float without trailing zeros (``180``, ``0.5``)."""
    return f"{flag} {value:g}" if isinstance(value, float) else f"{flag} {value}"


# Data set options the paper's set does not use (its summary.json records each only if it is set):
# the key, the ``triscan dataset`` flag and what the card's data line says of it (None: nothing).
_SET_OPTIONS: tuple[tuple[str, str, Callable[[Any], str] | None], ...] = (
    ("people", "--people", lambda _: "people walking and standing in each motion, labelled `person`"),
    ("sensor", "--sensor", lambda _: "a LiDAR profile per scenario (`--sensor`)"),
    ("raster_yaw_deg", "--raster-yaw", lambda yaw: f"the raster turned {yaw:g}°"),
    ("open_space", "--open-space", lambda _: "a share of the rooms open spaces"),
    ("door_watch", "--door-watch", None),
)


def _data_section(data: DatasetSummary) -> list[str]:
    """The command that generated the data set and its split sizes, from its summary.json."""
    cfg = data.config
    randomised = _randomisation_flags(cfg)
    return [
        "## Data",
        "",
        f"`triscan dataset --scenarios {cfg['scenarios']} --positions {cfg['positions']} "
        f"--seed {cfg['seed']} --frame-stride {cfg['frame_stride']} --padding {cfg['padding']}"
        f"{randomised}` — "
        + (
            "domain-randomised (per scenario: range noise σ, dropouts, spurious short returns drawn from "
            "the ranges given; unlabelled clutter per motion; labels of the true geometry), "
            if randomised
            else ""
        )
        + "".join(f"{describe(cfg[key])}, " for key, _, describe in _SET_OPTIONS if describe and cfg.get(key))
        + f"padding **{cfg['padding']}**, "
        f"scenarios train/val/test {data.scenarios['train']}/{data.scenarios['val']}/"
        f"{data.scenarios['test']}, samples {data.samples['train']}/{data.samples['val']}/"
        f"{data.samples['test']} (every {cfg['frame_stride']}th three-scan window of each motion).",
    ]


def _training_section(
    history: list[dict[str, float]], best_epoch: int, best_row: dict[str, float], train_command: str
) -> list[str]:
    """The training command, the shipped epoch, the wall time and the per-epoch validation table."""
    return [
        "## Training",
        "",
        f"`{train_command}`",
        "",
        f"Epochs run: {len(history)}; shipped epoch: **{best_epoch}** (best val mAP@0.5:0.95, Ultralytics' "
        f"fitness: {best_row[_VAL_MAP50_95]:.3f}, val mAP@0.5 {best_row[_VAL_MAP50]:.3f}). "
        f"Training wall time: {training_wall_time_s(history) / 3600:.2f} h on "
        f"{platform.machine()} CPU, {os.cpu_count()} cores, shared with other work (device: cpu).",
        "",
        "| epoch | train box loss | val P | val R | val mAP@0.5 | val mAP@0.5:0.95 |",
        "|---:|---:|---:|---:|---:|---:|",
        *(
            f"| {int(r['epoch'])} | {r['train/box_loss']:.3f} | {r[_VAL_PRECISION]:.3f} | "
            f"{r[_VAL_RECALL]:.3f} | {r[_VAL_MAP50]:.3f} | {r[_VAL_MAP50_95]:.3f} |"
            for r in history
        ),
    ]


def _test_section(card: ModelCard, test32: Evaluation, test8: Evaluation) -> list[str]:
    """Per-class test-split figures of both files, with the command that measured them."""
    return [
        "## Test metrics (held-out test scenarios, through `OnnxDetector`)",
        "",
        f"fp32 — `triscan eval --model {card.directory}/{card.files['fp32']} --data DATA --split test` "
        f"({test32.images} images):",
        "",
        *_metrics_rows(test32),
        "",
        f"INT8 — same command with `--model {card.directory}/{card.files['int8']}` ({test8.images} images):",
        "",
        *_metrics_rows(test8),
    ]


def _latency_section(export: ExportReport, test32: Evaluation) -> list[str]:
    """session.run medians from the export report, and the end-to-end split from the evaluation."""
    timings = test32.mean_timings_ms
    return [
        "## Latency of one frame (this machine, 1 ONNX Runtime thread, session.run only)",
        "",
        f"fp32 {export.latency_ms_fp32:.2f} ms, INT8 {export.latency_ms_int8:.2f} ms (median, from "
        "`triscan export`; end-to-end figures with "
        f"encoding and NMS: eval mean {timings['encode_ms']:.2f} + "
        f"{timings['inference_ms']:.2f} + {timings['nms_ms']:.2f} ms).",
    ]


def _gate_section(card: ModelCard, gate_metrics: Evaluation) -> list[str]:
    """What tests/test_shipped_model.py requires of the shipped model, and where the bar comes from."""
    gate = card.quality_gate
    return [
        "## Quality gate",
        "",
        f"`tests/test_shipped_model.py` simulates {gate.scenarios} scenarios with seed {gate.seed} "
        f"(never trained on), {gate.positions} positions each, every {gate.frame_stride}th window, "
        + (f"with `{gate.worlds_flags.strip()}`, " if gate.worlds_flags else "")
        + f"and requires mAP@0.5 ≥ **{gate.min_map50:.2f}**: the {gate_metrics.overall.map50:.3f} measured "
        f"on that exact, deterministic set when the card was written, less {GATE_MARGIN:.2f}. A larger "
        "drop means the model file, encoder, simulator or decoding changed behaviour.",
    ]


def _worlds_flags(worlds: Mapping[str, Any]) -> str:
    """The ``triscan eval --fresh`` flags for what a grid's worlds hold besides the paper's room."""
    keys = ("clutter", "people", "open_space")
    return "".join(f" {_flag('--' + key.replace('_', '-'), worlds[key])}" for key in keys if worlds.get(key))


def _conditions_section(card: ModelCard, path: Path) -> list[str]:
    """This card's fp32 and INT8 on unseen worlds (``path``: their grid), clean and under LiDAR
    imperfections, per class."""
    unseen = card.unseen_worlds
    if unseen is None:
        raise ValueError("the card has no unseen-worlds figures to show")
    worlds, fp32, int8 = unseen.worlds, unseen.fp32, unseen.int8
    classes = list(next(iter(fp32.values())).per_class_map50)
    lines = [
        "## Unseen worlds under LiDAR imperfections",
        "",
        f"`triscan eval --model {card.directory}/{card.files['fp32']} "
        f"--model {card.directory}/{card.files['int8']} "
        f"--fresh {worlds['scenarios']} --seed {worlds['seed']} --positions {worlds['positions']} "
        f"--frame-stride {worlds['frame_stride']}{_worlds_flags(worlds)} --noise {' '.join(fp32)}` "
        f"({path.name}): "
        f"{worlds['scenarios']} scenarios of a seed never trained on, the same worlds under every "
        "condition (σ: range noise; drop: share of beams returned invalid; spur: share returned short), "
        "labels of the true geometry, both files fed identical tensors.",
        "",
        "| condition | images | fp32 mAP@0.5 | fp32 mAP@0.5:0.95 | INT8 mAP@0.5 | INT8 mAP@0.5:0.95 "
        "| INT8 − fp32 |",
        "|---|---:|---:|---:|---:|---:|---:|",
        *(
            f"| {condition} | {fp32[condition].images} | {fp32[condition].figures.map50:.3f} "
            f"| {fp32[condition].figures.map50_95:.3f} | {int8[condition].figures.map50:.3f} "
            f"| {int8[condition].figures.map50_95:.3f} "
            f"| {(int8[condition].figures.map50 - fp32[condition].figures.map50) * 100:+.2f} |"
            for condition in fp32
        ),
        "",
        "Per class, mAP@0.5:",
        "",
        "| condition | " + " | ".join(f"{name} fp32 | {name} INT8" for name in classes) + " |",
        "|---|" + "---:|" * (2 * len(classes)),
        *(
            f"| {condition} | "
            + " | ".join(
                f"{cells[condition].per_class_map50[name]:.3f}" for name in classes for cells in (fp32, int8)
            )
            + " |"
            for condition in fp32
        ),
        "",
    ]
    return lines


@dataclass(frozen=True)
class GridSection:
    """A further ``triscan eval`` grid for the card: other models on the same unseen worlds."""

    title: str
    summary: Path
    intro: str = ""

    def figures(self) -> dict[str, Any]:
        """The card JSON's copy: the worlds, each model's id, and mAP@0.5 / mAP@0.5:0.95 per condition."""
        grid = Grid.read(self.summary)
        return {
            "worlds": grid.worlds,
            "models": grid.models,
            "results": {
                condition: {
                    stem: {
                        "mAP50": cell.figures.map50,
                        "mAP50-95": cell.figures.map50_95,
                        "per_class_mAP50": cell.per_class_map50,
                    }
                    for stem, cell in row.items()
                }
                for condition, row in grid.results.items()
            },
        }

    def lines(self, grid: dict[str, Any]) -> list[str]:
        """The card's section, from this grid's :meth:`figures`."""
        stems = list(grid["models"])
        lines = [f"## {self.title}", ""]
        if self.intro.strip():
            lines += [self.intro.strip(), ""]
        worlds = grid["worlds"]
        lines += [
            f"{worlds['scenarios']} unseen scenarios (seed {worlds['seed']}), {self.summary.name}; "
            "mAP@0.5 / mAP@0.5:0.95 per model:",
            "",
            "| condition | " + " | ".join(f"`{stem}`" for stem in stems) + " |",
            "|---|" + "---:|" * len(stems),
            *(
                f"| {condition} | "
                + " | ".join(f"{row[stem]['mAP50']:.3f} / {row[stem]['mAP50-95']:.3f}" for stem in stems)
                + " |"
                for condition, row in grid["results"].items()
            ),
            "",
        ]
        return lines


@dataclass(frozen=True)
class CurveComparison:
    """This run's validation curve beside another network's trained on the same data, epoch for epoch.

    A lighter network is worth shipping only if it stays close to the larger one after the same
    training: here, within :data:`CURVE_GAP_GOAL_POINTS` of its val mAP@0.5 after the same epochs.
    Final models alone would compare a converged run with a stopped one, so the card compares the
    curves at every epoch both ran (Ultralytics' own val figures, one row per epoch of results.csv).
    When both runs continued (``--init``) from runs of ``epochs_before`` epochs each, the card counts
    epochs from the start of training, so the comparison names the total training both had.
    """

    network: str  # the other run's network, as files are named: yolov8n
    results_csv: Path
    epochs_before: int = 0  # epochs each network trained before these runs (their --init weights)

    def __post_init__(self) -> None:
        if self.epochs_before < 0:
            raise ValueError(f"epochs before the compared runs must be >= 0, got {self.epochs_before}")

    def rows(self, history: list[dict[str, float]]) -> list[dict[str, float]]:
        """One row per epoch both runs have: each run's val mAP@0.5 and mAP@0.5:0.95."""
        other = {int(row["epoch"]): row for row in read_results_csv(self.results_csv)}
        return [
            {
                "epoch": int(row["epoch"]),
                "this_map50": row[_VAL_MAP50],
                "other_map50": other[int(row["epoch"])][_VAL_MAP50],
                "this_map50_95": row[_VAL_MAP50_95],
                "other_map50_95": other[int(row["epoch"])][_VAL_MAP50_95],
            }
            for row in history
            if int(row["epoch"]) in other
        ]

    def figures(self, history: list[dict[str, float]]) -> dict[str, Any]:
        """The card JSON's copy: every common epoch, and the gaps (other − this, in points) at the last."""
        rows = self.rows(history)
        if not rows:
            raise ValueError(f"{self.results_csv} shares no epoch with this run's results.csv")
        last = rows[-1]
        return {
            "network": self.network,
            "results_csv": self.results_csv.as_posix(),
            "last_common_epoch": last["epoch"],
            "epochs_before": self.epochs_before,
            "map50_gap_points": round(100 * (last["other_map50"] - last["this_map50"]), 2),
            "map50_95_gap_points": round(100 * (last["other_map50_95"] - last["this_map50_95"]), 2),
            "goal_map50_gap_points": CURVE_GAP_GOAL_POINTS,
            "rows": rows,
        }

    def lines(self, figures: dict[str, Any], network: str) -> list[str]:
        """The card's section, from :meth:`figures`; ``network`` is this card's."""
        rows, last = figures["rows"], figures["last_common_epoch"]
        shown = [row for row in rows if row["epoch"] == 1 or row["epoch"] % 5 == 0 or row["epoch"] == last]
        this, other = network, self.network  # the short names: table headers stay narrow
        within = figures["map50_gap_points"] <= CURVE_GAP_GOAL_POINTS
        before = self.epochs_before
        continued = (
            f", both runs continuing from {before} epochs of their own network on the same data (`--init`); "
            f"val figures per epoch, counted from the start of training ({before + 1} is these runs' first):"
            if before
            else ", val figures per epoch:"
        )
        return [
            f"## Against {network_title(other)} after the same epochs",
            "",
            f"`{other}` trained on the same data with the same recipe (`{self.results_csv.as_posix()}`)"
            + continued,
            "",
            f"| epoch | {this} mAP@0.5 | {other} mAP@0.5 | {this} mAP@0.5:0.95 | {other} mAP@0.5:0.95 |",
            "|---:|---:|---:|---:|---:|",
            *(
                f"| {before + row['epoch']} | {row['this_map50']:.3f} | {row['other_map50']:.3f} | "
                f"{row['this_map50_95']:.3f} | {row['other_map50_95']:.3f} |"
                for row in shown
            ),
            "",
            f"After {before + last} epochs, the last both ran: `{this}` is {figures['map50_gap_points']:.2f} "
            f"points of mAP@0.5 behind `{other}` ({'within' if within else 'outside'} the "
            f"{CURVE_GAP_GOAL_POINTS:g}-point goal); in mAP@0.5:0.95 it is "
            f"{figures['map50_95_gap_points']:.2f} points behind (a negative figure: ahead).",
            "",
        ]


STATUS_MARK = "**Status:"  # opens the card's status paragraph, the one part of the card the spec writes
DEFAULT_STATUS = "default"


def card_status(fp32_name: str) -> str:
    """``default`` for the card of the files ``common.model_spec`` ships as the default, else ``beside
    the default``: the spec alone decides, so no two cards can both claim it."""
    return DEFAULT_STATUS if fp32_name == SHIPPED_FP32_MODEL.name else "beside the default"


def status_line(card: dict[str, Any]) -> str:
    """The card's status paragraph, from its ``status`` and the model spec."""
    if card["status"] == DEFAULT_STATUS:
        return (
            f"{STATUS_MARK} the default model.** `common/model_spec.py` ships these files: the detector "
            f"runs `{SHIPPED_MODEL.name}` when given no model (`$TRISCAN_MODEL` or `--model` names another)."
        )
    default_dir = f"models/{SHIPPED_DIR.relative_to(MODELS_DIR).as_posix()}/"
    recommended = f"{card['directory']}/{card['files'][card['recommended']]}"
    return (
        f"{STATUS_MARK} shipped beside the default** (`{default_dir}`): run it by name, "
        f"`--model {recommended}` or `TRISCAN_MODEL={recommended}`."
    )


def refresh_status(directory: Path) -> dict[str, Any]:
    """Rewrite a written card's status (the JSON's ``status``, the markdown's status paragraph) from the
    model spec, leaving every figure as it is: changing which model is the default needs no artefact
    of any run. Returns the card's JSON."""
    json_path, md_path = directory / "MODEL_CARD.json", directory / "MODEL_CARD.md"
    card = _read_json(json_path)
    status = card_status(card["files"]["fp32"])
    at = list(card).index("recommended") + 1 if "recommended" in card else len(card)
    items = [(k, v) for k, v in card.items() if k != "status"]
    card = dict([*items[:at], ("status", status), *items[at:]])
    paragraphs = md_path.read_text().split("\n\n")
    found = [i for i, paragraph in enumerate(paragraphs) if paragraph.startswith(STATUS_MARK)]
    if len(found) != 1:
        raise ValueError(f"{md_path} has {len(found)} status paragraphs ({STATUS_MARK} …), expected one")
    paragraphs[found[0]] = status_line(card)
    md_path.write_text("\n\n".join(paragraphs))
    json_path.write_text(json.dumps(card, indent=2) + "\n")
    return card


def refresh_files(directory: Path) -> dict[str, Any]:
    """Rewrite a written card's file table (bytes, sha256) and model ids from the files on disk, leaving
    every figure as it is: for files whose detections a change kept (a graph rewrite, checked by
    :func:`training.onnx_rewrites.rewrite_card`). Returns the card's JSON."""
    json_path, md_path = directory / "MODEL_CARD.json", directory / "MODEL_CARD.md"
    card = _read_json(json_path)
    text = md_path.read_text()
    for kind, name in card["files"].items():
        path = directory / name
        if kind == "checkpoint":
            continue
        row = re.compile(rf"^(\| `{re.escape(name)}` \|.*\| )\d+ \| `[0-9a-f]{{16}}…` \|$", re.MULTILINE)
        if len(row.findall(text)) != 1:
            raise ValueError(f"{md_path} has no single file-table row for {name}")
        cells = f"{path.stat().st_size} | `{file_sha256(path)[:16]}…` |"
        text = row.sub(rf"\g<1>{cells}", text)  # cells: digits, hex, a backtick and "…"
        if kind in card.get("model_ids", {}):
            card["model_ids"][kind] = file_model_id(path)
    md_path.write_text(text)
    json_path.write_text(json.dumps(card, indent=2) + "\n")
    return card


def shipped_card_dirs(models_dir: Path = MODELS_DIR) -> list[Path]:
    """Every directory under ``models_dir`` that holds a card."""
    return sorted(card.parent for card in models_dir.glob("**/MODEL_CARD.json"))


def main(argv: list[str] | None = None) -> int:
    """``python -m training.model_card``: refresh the status of every shipped card from the spec."""
    import argparse

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--models", type=Path, default=MODELS_DIR, help="the directory of the cards")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cards = {directory: refresh_status(directory) for directory in shipped_card_dirs(args.models)}
    defaults = [directory for directory, card in cards.items() if card["status"] == DEFAULT_STATUS]
    for directory, card in cards.items():
        log.info("%s: %s", directory, card["status"])
    if len(defaults) != 1:
        log.error("%d cards are the default (%s): common/model_spec.py names one", len(defaults), defaults)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
