"""The recipe file: the settings a model is made and measured with, read by ``triscan train``,
``triscan export``, ``triscan eval --preset`` and ``triscan card``.

:data:`SHIPPED_RECIPE` (``training/recipes/default.toml``) is the shipped models' recipe and the home of
those commands' defaults; a flag given on the command line overrides the recipe's value.
"""

from __future__ import annotations

import functools
import tomllib
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, Final, TypeVar

SHIPPED_RECIPE: Final[Path] = Path(__file__).with_name("recipes") / "default.toml"

T = TypeVar("T")


@dataclass(frozen=True)
class DatasetRecipe:
    """``triscan dataset`` flags of the data set the models trained on."""

    scenarios: int
    positions: int
    seed: int
    frame_stride: int
    padding: str
    noise_sigma: tuple[float, float]
    dropout: tuple[float, float]
    spurious: tuple[float, float]
    clutter: int


@dataclass(frozen=True)
class TrainRecipe:
    """``triscan train``'s defaults, and the Ultralytics arguments no flag changes."""

    epochs: int
    batch: int
    patience: int
    workers: int
    seed: int
    fraction: float
    ultralytics: dict[str, Any]


@dataclass(frozen=True)
class ExportRecipe:
    """``triscan export``'s defaults."""

    box_grid: str
    calib_count: int
    calib_method: str
    float_modules: int
    activations: str


@dataclass(frozen=True)
class EvalPreset:
    """Fresh simulated worlds and the LiDAR conditions they are scored under (``triscan eval``)."""

    fresh: int
    seed: int
    positions: int
    frame_stride: int
    noise: tuple[str, ...]


@dataclass(frozen=True)
class Recipe:
    path: Path
    dataset: DatasetRecipe
    train: TrainRecipe
    export: ExportRecipe
    presets: dict[str, EvalPreset]

    def preset(self, name: str) -> EvalPreset:
        if name not in self.presets:
            raise ValueError(f"{self.path} has no eval preset {name!r} (it has: {', '.join(self.presets)})")
        return self.presets[name]


def _record(cls: type[T], table: Any, where: str) -> T:
    """``cls`` from a TOML table whose keys are exactly its fields (lists become tuples)."""
    if not isinstance(table, dict):
        raise ValueError(f"{where}: expected a table")
    names = {f.name for f in fields(cls)}  # type: ignore[arg-type]
    if missing := names - table.keys():
        raise ValueError(f"{where}: missing {', '.join(sorted(missing))}")
    if unknown := table.keys() - names:
        raise ValueError(f"{where}: unknown {', '.join(sorted(unknown))}")
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in table.items()})


@functools.cache
def load_recipe(path: Path = SHIPPED_RECIPE) -> Recipe:
    """The recipe in ``path``; a missing or unknown setting is a ValueError naming the file."""
    try:
        raw = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: {exc}") from None
    if unknown := raw.keys() - {"dataset", "train", "export", "eval"}:
        raise ValueError(f"{path}: unknown table(s) {', '.join(sorted(unknown))}")
    return Recipe(
        path=path,
        dataset=_record(DatasetRecipe, raw.get("dataset"), f"{path} [dataset]"),
        train=_record(TrainRecipe, raw.get("train"), f"{path} [train]"),
        export=_record(ExportRecipe, raw.get("export"), f"{path} [export]"),
        presets={
            name: _record(EvalPreset, table, f"{path} [eval.{name}]")
            for name, table in raw.get("eval", {}).items()
        },
    )


def recipe_name(path: Path) -> str:
    """``path`` as the card quotes it: relative to the source tree when inside it
    (``training/recipes/default.toml``), else as given."""
    root = Path(__file__).resolve().parents[1]
    try:
        return path.resolve().relative_to(root).as_posix()
    except ValueError:
        return path.as_posix()
