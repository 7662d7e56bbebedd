"""CLEAR MOT (Bernardin & Stiefelhagen, 2008): how well tracks follow the true objects, frame by frame.

Per frame, a target keeps the hypothesis it was matched to in the frame before if that one is still
within ``gate_m``; the targets and hypotheses left are matched by minimum total distance within the
gate (scipy's ``linear_sum_assignment``). A matched target whose hypothesis differs from the one it
was last matched to counts one **ID switch**. Unmatched targets are **misses**, unmatched hypotheses
**false positives**, except those within the gate of an *ignored* object: one that exists but is no
target in that frame (occluded, or hit by too few beams), the "don't care" of the MOT benchmarks. A
tracker that keeps a still chair while a person walks in front of it is right, not wrong; each
ignored object excuses at most one hypothesis (the nearest), so a duplicate there still counts.

* ``MOTA = 1 − (misses + false positives + ID switches) / targets``
* ``MOTP`` = mean distance of the matched pairs, metres (lower is better).

The default gate, 0.75 m, is the one leg_tracker's benchmarks use for people.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Hashable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Final

import numpy as np
from scipy.optimize import linear_sum_assignment

from common.messages import Tracks
from common.model_spec import PERSON
from services.tracker.core import REPORTED_STATES

DEFAULT_GATE_M: Final[float] = 0.75
GROUPS: Final[tuple[str, ...]] = ("furniture", "people")
"""Scored apart, each against the tracks of its own classes: their goals differ, and a model may
predict furniture only."""


def group_of(class_name: str) -> str:
    return "people" if class_name == PERSON else "furniture"


def hypotheses_of(tracks: Tracks) -> dict[str, dict[int, tuple[float, float]]]:
    """A tracks message's reported tracks by group (of their class), in the laser frame of its scan."""
    out: dict[str, dict[int, tuple[float, float]]] = {group: {} for group in GROUPS}
    for t in tracks.tracks:
        if t.state in REPORTED_STATES:
            out[group_of(t.class_name)][t.track_id] = (t.x_m, t.y_m)
    return out


Points = Mapping[Any, tuple[float, float]]  # any hashable id; Any, as Mapping keys are invariant


@dataclass
class MotScore:
    targets: int = 0
    matches: int = 0
    misses: int = 0
    false_positives: int = 0
    id_switches: int = 0
    distance_sum_m: float = 0.0
    ignored: int = 0  # hypotheses on an object that is there but no target (not false positives)

    @property
    def mota(self) -> float:
        if self.targets == 0:
            return math.nan
        return 1.0 - (self.misses + self.false_positives + self.id_switches) / self.targets

    @property
    def motp_m(self) -> float:
        return self.distance_sum_m / self.matches if self.matches else math.nan

    def merged(self, other: MotScore) -> MotScore:
        """The score of both sequences together (independent sequences: no switch across them)."""
        return MotScore(
            *(getattr(self, f.name) + getattr(other, f.name) for f in dataclasses.fields(MotScore))
        )

    def to_dict(self) -> dict[str, float | int]:
        return {
            "mota": self.mota,
            "motp_m": self.motp_m,
            "id_switches": self.id_switches,
            "misses": self.misses,
            "false_positives": self.false_positives,
            "targets": self.targets,
            "matches": self.matches,
            "ignored": self.ignored,
        }


@dataclass
class ClearMot:
    """Accumulates CLEAR MOT over frames of one sequence (one robot); feed frames in time order."""

    gate_m: float = DEFAULT_GATE_M
    score: MotScore = field(default_factory=MotScore)
    _current: dict[Hashable, Hashable] = field(default_factory=dict)  # target → hypothesis, last frame
    _last: dict[Hashable, Hashable] = field(default_factory=dict)  # target → hypothesis, last ever

    def update(self, targets: Points, hypotheses: Points, ignored: Points | None = None) -> None:
        score = self.score
        score.targets += len(targets)
        pairs: dict[Hashable, Hashable] = {}
        for target, hypothesis in self._current.items():
            kept = target in targets and hypothesis in hypotheses
            if kept and _distance(targets[target], hypotheses[hypothesis]) <= self.gate_m:
                pairs[target] = hypothesis
        free_targets = [t for t in targets if t not in pairs]
        taken = set(pairs.values())
        free_hypotheses = [h for h in hypotheses if h not in taken]
        if free_targets and free_hypotheses:
            cost = np.array(
                [[_distance(targets[t], hypotheses[h]) for h in free_hypotheses] for t in free_targets]
            )
            gated = cost > self.gate_m
            rows, cols = linear_sum_assignment(np.where(gated, 1e6, cost))
            for r, c in zip(rows, cols, strict=True):
                if not gated[r, c]:
                    pairs[free_targets[r]] = free_hypotheses[c]
        for target, hypothesis in pairs.items():
            if target in self._last and self._last[target] != hypothesis:
                score.id_switches += 1
            self._last[target] = hypothesis
            score.distance_sum_m += _distance(targets[target], hypotheses[hypothesis])
        score.matches += len(pairs)
        score.misses += len(targets) - len(pairs)
        taken = set(pairs.values())
        unmatched = [h for h in hypotheses if h not in taken]
        excused = _excused(unmatched, hypotheses, ignored or {}, self.gate_m)
        score.ignored += excused
        score.false_positives += len(unmatched) - excused
        self._current = pairs


def clear_mot(frames: Iterable[tuple[Points, Points]], gate_m: float = DEFAULT_GATE_M) -> MotScore:
    """CLEAR MOT of one sequence of ``(targets, hypotheses)`` frames, each a map id → (x, y)."""
    accumulator = ClearMot(gate_m)
    for targets, hypotheses in frames:
        accumulator.update(targets, hypotheses)
    return accumulator.score


def _excused(unmatched: list[Hashable], hypotheses: Points, ignored: Points, gate_m: float) -> int:
    """How many unmatched hypotheses lie on an ignored object, each object excusing one at most."""
    if not unmatched or not ignored:
        return 0
    objects = list(ignored.values())
    cost = np.array([[_distance(hypotheses[h], o) for o in objects] for h in unmatched])
    rows, cols = linear_sum_assignment(np.where(cost > gate_m, 1e6, cost))
    return sum(1 for r, c in zip(rows, cols, strict=True) if cost[r, c] <= gate_m)


def _distance(a: tuple[float, float], b: tuple[float, float]) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])
