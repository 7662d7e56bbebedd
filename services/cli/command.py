"""What one ``triscan`` subcommand is: its name, its arguments, its handler and the extras it needs."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

FROM_RECIPE = "(default: the recipe's)"  # the help of an option whose unset value is the recipe's


@dataclass(frozen=True)
class Command:
    """A subcommand. ``add_arguments`` runs only when the subcommand is chosen, so a command may import
    its option lists there; ``run`` imports its heavy modules itself and returns the exit code.
    ``extras`` are the ``pip install 'triscan[...]'`` extras whose modules it imports."""

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    extras: tuple[str, ...] = ()


def given_or_default(args: argparse.Namespace, defaults: object, names: tuple[str, ...]) -> dict[str, Any]:
    """Each of ``names``: the flag's value where the command line gave one (not None), else the
    attribute of that name of ``defaults`` (a recipe table)."""
    return {
        name: getattr(defaults, name) if getattr(args, name) is None else getattr(args, name)
        for name in names
    }


def add_recipe_argument(p: argparse.ArgumentParser, role: str) -> None:
    """``--recipe FILE``, whose ``role`` says what the command reads from it; unset, the shipped recipe
    (``training.recipe.SHIPPED_RECIPE``)."""
    p.add_argument(
        "--recipe", type=Path, default=None, help=f"{role} (default: training/recipes/default.toml)"
    )


def add_recipe_option(
    p: argparse.ArgumentParser, flag: str, *, help: str = FROM_RECIPE, **kwargs: Any
) -> None:
    """An option that is None unless given, so that :func:`given_or_default` (or the command) takes the
    recipe's value in its place."""
    p.add_argument(flag, default=None, help=help, **kwargs)
