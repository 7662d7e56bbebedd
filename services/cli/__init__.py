"""The ``triscan`` command: one entry point, one module per subcommand.

Only the chosen subcommand's arguments are built, and each handler imports its heavy modules itself,
so ``triscan`` and ``triscan --help`` on the robot's base install load neither training, torch,
Ultralytics, PyBullet nor rerun. A command whose optional dependencies are missing names the extra to
install and exits 2.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence

from services.cli import (
    batch_model,
    card,
    dataset,
    evaluate,
    export,
    replay,
    show,
    sim_bag,
    status,
    train,
    up,
)
from services.cli.command import Command
from services.runtime import LOG_FORMAT, TerseArgumentParser

log = logging.getLogger(__name__)

COMMANDS: tuple[Command, ...] = tuple(
    module.COMMAND
    for module in (dataset, show, train, export, batch_model, evaluate, card, up, status, replay, sim_bag)
)
DESCRIPTION = "2D LiDAR object detection: one subcommand per job (`triscan COMMAND --help` for its options)."
FIRST_PARTY = frozenset({"common", "services", "training", "security", "bench"})  # never an extra's


def chosen_command(argv: Sequence[str]) -> Command | None:
    """The subcommand ``argv`` names: its first word that is not an option (``triscan`` has no option
    that takes a value)."""
    by_name = {command.name: command for command in COMMANDS}
    first = next((word for word in argv if not word.startswith("-")), None)
    return by_name.get(first) if first is not None else None


def build_parser(chosen: Command | None = None) -> argparse.ArgumentParser:
    """``triscan``'s parser, with the arguments of ``chosen`` alone (the others are listed by name)."""
    parser = TerseArgumentParser(prog="triscan", description=DESCRIPTION, allow_abbrev=False)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        p = sub.add_parser(command.name, help=command.help, description=command.help, allow_abbrev=False)
        if command is chosen:
            command.add_arguments(p)
            p.set_defaults(run=command.run)
    return parser


def command_parser(parser: argparse.ArgumentParser, name: str) -> argparse.ArgumentParser:
    """The subparser of subcommand ``name``."""
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


def missing_extra(command: Command, exc: ModuleNotFoundError) -> str | None:
    """The one-line advice when ``exc`` is a module of ``command``'s extras, else None (a bug)."""
    top = (exc.name or "").split(".")[0]
    if not command.extras or not top or top in FIRST_PARTY:
        return None
    extras = " and ".join(command.extras)
    noun = "extra" if len(command.extras) == 1 else "extras"
    return (
        f"triscan {command.name} needs the {extras} {noun}: pip install 'triscan[{','.join(command.extras)}]'"
    )


def main(argv: Sequence[str] | None = None) -> int:
    import sys

    words = list(sys.argv[1:] if argv is None else argv)
    chosen = chosen_command(words)
    logging.basicConfig(level=logging.INFO, format=LOG_FORMAT)
    try:
        parser = build_parser(chosen)
        args, unknown = parser.parse_known_args(words)
        if unknown:  # argparse would report them as the top parser's: name the subcommand instead
            command_parser(parser, args.command).error(f"unrecognized arguments: {' '.join(unknown)}")
        if args.verbose:
            logging.getLogger().setLevel(logging.DEBUG)
        return int(args.run(args))
    except ModuleNotFoundError as exc:
        advice = None if chosen is None else missing_extra(chosen, exc)
        if advice is None:
            raise
        log.debug("%s", exc)
        log.error("%s", advice)
        return 2
    except (FileExistsError, FileNotFoundError, ValueError) as exc:
        log.error("%s", exc)
        return 2
