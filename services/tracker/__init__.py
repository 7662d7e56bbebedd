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


def tracker_config(args: argparse.Namespace) -> TrackerConfig:
    """The tracker rules of the arguments :func:`add_tracker_arguments` added (unset: the defaults)."""
    from services.tracker.core import TrackerConfig

    if args.person_confirm_travel is None:
        return TrackerConfig()
    return TrackerConfig(person_confirm_travel_m=args.person_confirm_travel)
