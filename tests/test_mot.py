"""CLEAR MOT on sequences small enough to count by hand."""

from __future__ import annotations

import math

import pytest

from services.tracker.mot import ClearMot, clear_mot


def test_perfect_tracking_scores_one_and_motp_is_the_mean_offset() -> None:
    frames = [({"a": (0.0, 0.0), "b": (2.0, 0.0)}, {1: (0.1, 0.0), 2: (2.0, 0.3)})] * 3
    score = clear_mot(frames)
    assert (score.targets, score.matches, score.misses, score.false_positives, score.id_switches) == (
        6,
        6,
        0,
        0,
        0,
    )
    assert score.mota == 1.0 and score.motp_m == pytest.approx(0.2)  # (0.1 + 0.3) / 2 per frame


def test_misses_false_positives_and_a_switch_counted_by_hand() -> None:
    frames = [
        ({"a": (0.0, 0.0), "b": (5.0, 0.0)}, {1: (0.0, 0.0), 2: (5.0, 0.0)}),  # 2 matches
        ({"a": (0.0, 0.0), "b": (5.0, 0.0)}, {1: (0.0, 0.0)}),  # b missed
        ({"a": (0.0, 0.0), "b": (5.0, 0.0)}, {1: (0.0, 0.0), 3: (5.0, 0.0), 9: (9.0, 9.0)}),  # b: 2 → 3, FP 9
        ({"a": (0.0, 0.0)}, {1: (0.0, 0.0), 3: (0.8, 0.0)}),  # 3 is 0.8 m from a: outside the gate, FP
    ]
    score = clear_mot(frames)
    assert (score.targets, score.matches, score.misses, score.false_positives, score.id_switches) == (
        7,
        6,
        1,
        2,
        1,
    )
    assert score.mota == pytest.approx(1 - 4 / 7) and score.motp_m == 0.0


def test_a_target_keeps_its_hypothesis_while_within_the_gate_even_if_another_is_closer() -> None:
    frames = [
        ({"a": (0.0, 0.0)}, {1: (0.0, 0.0)}),
        ({"a": (0.0, 0.0)}, {1: (0.5, 0.0), 2: (0.0, 0.1)}),  # 1 still within 0.75 m: no switch, 2 is a FP
        ({"a": (0.0, 0.0)}, {1: (0.9, 0.0), 2: (0.0, 0.1)}),  # 1 left the gate: a switches to 2
    ]
    score = clear_mot(frames)
    assert (score.matches, score.false_positives, score.id_switches) == (3, 2, 1)
    assert score.motp_m == pytest.approx((0.0 + 0.5 + 0.1) / 3)


def test_nothing_to_score_is_nan_not_perfect() -> None:
    score = clear_mot([({}, {})])
    assert math.isnan(score.mota) and math.isnan(score.motp_m)


def test_a_hypothesis_on_an_ignored_object_is_no_false_positive_but_a_second_one_is() -> None:
    accumulator = ClearMot()
    # the chair is occluded (ignored): the track kept on it is right; a duplicate beside it is not
    accumulator.update(
        {"box": (3.0, 0.0)}, {1: (3.0, 0.0), 2: (1.0, 1.0), 3: (1.1, 1.0)}, {"chair": (1.0, 1.05)}
    )
    score = accumulator.score
    assert (score.matches, score.false_positives, score.ignored, score.misses) == (1, 1, 1, 0)
    # a target is matched before anything is excused: an ignored object never hides a miss
    accumulator.update({"box": (3.0, 0.0)}, {}, {"chair": (3.0, 0.0)})
    assert (accumulator.score.misses, accumulator.score.ignored) == (1, 1)
