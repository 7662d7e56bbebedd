"""The tracker service (:mod:`services.tracker.__main__`) and its pure core (:mod:`services.tracker.core`).

The command-line rules live here, free of the core's numpy and scipy imports, so that every
``triscan`` command that offers them still starts at once.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from services.tracker.core import TrackerConfig


def add_tracker_arguments(parser: argparse.ArgumentParser) -> None:
    """The tracker rules a user may change: for the tracker service, ``triscan up`` (which passes them on),
    ``triscan eval --tracks`` and ``bench.tracking``."""
    parser.add_argument(
        "--person-confirm-travel", type=float, default=None, metavar="M",
        help="confirm a person track only once it has moved M metres, as leg_tracker starts people: drops "
        "still look-alikes (table legs, broken-up walls) and people who stand all the time they are seen "
        "(default: off; docs/tracking.md has both effects measured)",
    )  # fmt: skip
    parser.add_argument(
        "--person-confirm-hits", type=int, default=None, metavar="N",
        help="confirm a person track at its Nth detection (default: the tracker's, "
        "services.tracker.core.TrackerConfig; furniture: 3)",
    )  # fmt: skip
    parser.add_argument(
        "--person-resume", type=float, default=None, metavar="S",
        help="a person found again within S seconds near where their track was lost takes its id back "
        "(default: the tracker's, services.tracker.core.TrackerConfig; 0: off)",
    )  # fmt: skip

    parser.add_argument(
        "--person-show-coast", type=float, default=None, metavar="S",
        help="leave a person track out of the output S seconds after it was last seen, though it keeps "
        "its id if found again before it ends (default: the tracker's, services.tracker.core.TrackerConfig)",
    )  # fmt: skip
    parser.add_argument(
        "--person-show-coast-share", type=float, default=None, metavar="F",
        help="and sooner after a short track: at most F times the track's age at its last hit (default: "
        "the tracker's, services.tracker.core.TrackerConfig)",
    )  # fmt: skip


RULE_FLAGS: dict[str, str] = {
    "person_confirm_travel_m": "--person-confirm-travel",
    "person_confirm_hits": "--person-confirm-hits",
    "person_resume_s": "--person-resume",
    "person_show_coast_s": "--person-show-coast",
    "person_show_coast_share": "--person-show-coast-share",
}
"""The :class:`~services.tracker.core.TrackerConfig` fields a user may set, and their flags."""


def given_rules(**values: float | None) -> dict[str, float]:
    """The rules of :data:`RULE_FLAGS` that were given (None: the tracker's default), by field."""
    unknown = set(values) - set(RULE_FLAGS)
    if unknown:
        raise ValueError(f"not a tracker rule: {sorted(unknown)}")
    return {field: value for field, value in values.items() if value is not None}


COUNT_RULES: frozenset[str] = frozenset({"person_confirm_hits"})
"""The rules of :data:`RULE_FLAGS` that are whole numbers; every other one is a float."""


def rule_flags(rules: dict[str, float]) -> list[str]:
    """The tracker's command-line flags for ``rules`` (:func:`given_rules`), each value written as its
    flag parses it (a numpy float as a plain one)."""
    return [
        arg
        for field, value in rules.items()
        for arg in (RULE_FLAGS[field], str(int(value)) if field in COUNT_RULES else repr(float(value)))
    ]


def rules_of(args: argparse.Namespace) -> dict[str, float]:
    """The rules given by the arguments :func:`add_tracker_arguments` added (:func:`given_rules`)."""
    return given_rules(
        **{field: getattr(args, flag[2:].replace("-", "_")) for field, flag in RULE_FLAGS.items()}
    )


def tracker_config(args: argparse.Namespace) -> TrackerConfig:
    """The tracker rules of the arguments :func:`add_tracker_arguments` added (unset: the defaults)."""
    from services.tracker.core import TrackerConfig

    return TrackerConfig(**rules_of(args))  # type: ignore[arg-type]  # each rule is a number field
