"""The tracker service (:mod:`services.tracker.__main__`) and its pure core (:mod:`services.tracker.core`).

The command-line rules live here, free of the core's numpy and scipy imports, so that every
``triscan`` command that offers them still starts at once.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from services.tracker.core import TrackerConfig


_DEFAULT = "default: the tracker's, services.tracker.core.TrackerConfig"


@dataclass(frozen=True)
class _Rule:
    flag: str
    kind: type[int] | type[float]
    metavar: str
    help: str


_RULES: dict[str, _Rule] = {
    "person_confirm_travel_m": _Rule(
        "--person-confirm-travel", float, "M",
        "confirm a person track only once it has moved M metres, as leg_tracker starts people: drops still "
        "look-alikes (table legs, broken-up walls) and people who stand all the time they are seen "
        "(default: off; docs/tracking.md has both effects measured)",
    ),
    "person_confirm_hits": _Rule(
        "--person-confirm-hits", int, "N",
        f"confirm a person track at its Nth detection ({_DEFAULT}; furniture: 3)",
    ),
    "person_coast_penalty_m": _Rule(
        "--person-coast-penalty", float, "M",
        "a person track that missed its last scan pays M metres more for a detection, so the track that "
        f"followed its person takes it ({_DEFAULT}; 0: off)",
    ),
    "person_resume_s": _Rule(
        "--person-resume", float, "S",
        "a person found again within S seconds near where their track was lost takes its id back "
        f"({_DEFAULT}; 0: off)",
    ),
    "person_show_coast_s": _Rule(
        "--person-show-coast", float, "S",
        "leave a person track out of the output S seconds after it was last seen, though it keeps its id if "
        f"found again before it ends ({_DEFAULT})",
    ),
    "person_show_coast_share": _Rule(
        "--person-show-coast-share", float, "F",
        f"and sooner after a short track: at most F times the track's age at its last hit ({_DEFAULT})",
    ),
}  # fmt: skip


def add_tracker_arguments(parser: argparse.ArgumentParser) -> None:
    """The tracker rules a user may change: for the tracker service, ``triscan up`` (which passes them on),
    ``triscan eval --tracks`` and ``bench.tracking``."""
    for field, rule in _RULES.items():
        parser.add_argument(
            rule.flag, dest=field, type=rule.kind, default=None, metavar=rule.metavar, help=rule.help
        )


RULE_FLAGS: dict[str, str] = {field: rule.flag for field, rule in _RULES.items()}
"""The :class:`~services.tracker.core.TrackerConfig` fields a user may set, and their flags."""


def given_rules(**values: float | None) -> dict[str, float]:
    """The rules of :data:`RULE_FLAGS` that were given (None: the tracker's default), by field."""
    unknown = set(values) - set(RULE_FLAGS)
    if unknown:
        raise ValueError(f"not a tracker rule: {sorted(unknown)}")
    return {field: value for field, value in values.items() if value is not None}


def rule_flags(rules: dict[str, float]) -> list[str]:
    """The tracker's command-line flags for ``rules`` (:func:`given_rules`), each value written as its
    flag parses it (a numpy float as a plain one)."""
    flags = []
    for field, value in rules.items():
        kind = _RULES[field].kind
        written = kind(value)
        if kind is int and written != value:
            raise ValueError(f"{RULE_FLAGS[field]} takes a whole number, got {value!r}")
        flags += [RULE_FLAGS[field], repr(written)]
    return flags


def rules_of(args: argparse.Namespace) -> dict[str, float]:
    """The rules given by the arguments :func:`add_tracker_arguments` added (:func:`given_rules`)."""
    return given_rules(**{field: getattr(args, field) for field in _RULES})


def tracker_config(args: argparse.Namespace) -> TrackerConfig:
    """The tracker rules of the arguments :func:`add_tracker_arguments` added (unset: the defaults)."""
    from services.tracker.core import TrackerConfig

    return TrackerConfig(**rules_of(args))  # type: ignore[arg-type]  # each rule is a number field
