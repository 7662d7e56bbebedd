"""Motion confirmation of person candidates: walking legs that a still sensor sees move.

The three stacked scans show a walking leg as pixels that move between them, and a still sensor
shows almost nothing else that does. On real recordings the network often sees a walker only at a low
score (a real leg looks unlike a simulated one), while the false people it reports sit on walls and
furniture, which do not move. So a person candidate below the detector's threshold is confirmed when a
cluster of moving pixels lies where it stands: its score is raised to :attr:`MotionConfirm.score`.
Nothing is added where the network proposed nothing, and confident boxes are left as they are.

The rule holds only while the sensor stands still: a turning or driving robot moves every return. The
tensor itself says whether it did (:func:`still_share`): nearly every pixel of the middle scan away
from the moving clusters has a lit pixel within one pixel in the scans before and after it. Walkers
move only their own pixels (and those they hide or reveal right beside them), a moving robot the
walls' and the furniture's as well.

Where the robot's odometry is known it decides instead (:func:`still_by_odometry`): it tells a
robot creeping along, whose scans barely move, from one that stands. Everything else works in the
raster's own frame (rows are range, columns are degrees, see :mod:`common.encoding`), so the model's
raster yaw does not matter.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Final

import numpy as np
from scipy.spatial.distance import cdist

from common.encoding import ANGLE_COLUMNS, R_MAX_M, RANGE_ROWS, ROW_SCALE, SENTINEL_ROW
from common.messages import Odometry

_PADDED_WIDTH: Final[int] = ANGLE_COLUMNS + 2
_NEIGHBOUR_OFFSETS: Final = np.array([dr * _PADDED_WIDTH + dc for dr in (-1, 0, 1) for dc in (-1, 0, 1)])


@dataclass(frozen=True)
class MotionConfirm:
    """The rule's settings, chosen on the real development recordings and checked not to cost the
    simulated person class any mAP (docs/people.md, "Motion confirmation")."""

    # A person candidate scoring at least this (and below the detector's threshold) may be confirmed.
    floor: float = 0.01
    # A confirmed candidate scores at least this: above the detector's default threshold (0.25), so
    # it is reported, and below most of the network's confident people, so it ranks after them.
    score: float = 0.3
    # The sensor counts as still when this share of the middle scan's pixels farther than
    # ``background_m`` from every moving cluster is matched in both neighbouring scans (with fewer than
    # ``background_min_pixels`` such pixels there is nothing to tell by, and it counts as still).
    still_share: float = 0.97
    background_m: float = 0.6
    background_min_pixels: int = 10
    # Where odometry is known it decides instead: still when the robot moved at most this much between
    # the tensor's three scans, which is standing (odometry's own jitter), not creeping: a robot
    # creeping at 0.1 m/s moves its scans less than a pixel (5.5 cm of range, 1° of bearing), yet in
    # the live simulation it made a third of the confirmations false (docs/people.md).
    odom_still_m: float = 0.005
    odom_still_rad: float = math.radians(0.2)
    link_m: float = 0.35  # moving pixels this close belong to one cluster (a leg, or both)
    stance_m: float = 0.3  # still pixels this close to a cluster join it: the planted leg
    max_extent_m: float = 0.9  # a wider cluster is a wall or a door, not a person
    min_moving_pixels: int = 2
    merge_m: float = 0.5  # clusters closer than this are one person (two legs found apart)
    match_m: float = 0.35  # a candidate whose box centre lies this close to a cluster is confirmed


DEFAULT_MOTION_CONFIRM: Final = MotionConfirm()


def add_motion_argument(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """``--no-motion-confirm``, for every command that runs a detector."""
    parser.add_argument(
        "--no-motion-confirm",
        dest="motion_confirm",
        action="store_false",
        help="report only the network's own people: no person candidate below the threshold is "
        "confirmed by walking legs on a still sensor (docs/people.md)",
    )


def motion_confirm_of(args: argparse.Namespace) -> MotionConfirm | None:
    """The settings :func:`add_motion_argument`'s flag asks for (None: off)."""
    return DEFAULT_MOTION_CONFIRM if getattr(args, "motion_confirm", True) else None


class _Pixels:
    """The middle scan's lit pixels and, for each, whether the older and the newer scan have a lit
    pixel within one pixel of it (columns wrap, as bearings do): all the rule needs from a tensor, at
    the cost of a few gathers over a few hundred pixels."""

    def __init__(self, tensor: np.ndarray) -> None:
        older, newer = self._padded(tensor, 0), self._padded(tensor, 2)
        middle = self._padded(tensor, 1, wrap=False)
        # Flat indices of the middle scan's pixels in a plane padded by one pixel all round, and of
        # each one's 3×3 neighbourhood (a bool plane's flat indices are far quicker to find than rows
        # and columns of the uint8 tensor).
        centre = np.flatnonzero(middle)
        padded_rows, padded_columns = np.divmod(centre, _PADDED_WIDTH)
        self.rows, self.columns = padded_rows - 1, padded_columns - 1
        neighbourhood = centre[None, :] + _NEIGHBOUR_OFFSETS[:, None]
        self.matched = [plane.ravel()[neighbourhood].any(axis=0) for plane in (older, newer)]
        self.moving = ~(self.matched[0] & self.matched[1])  # unmatched in the older or the newer scan

    @cached_property
    def xy(self) -> np.ndarray:
        """Raster-frame positions (metres) of the pixels."""
        return _points_m(self.rows, self.columns)

    @staticmethod
    def _padded(tensor: np.ndarray, channel: int, wrap: bool = True) -> np.ndarray:
        """One scan's lit pixels over the bearing columns, sentinel row left out, padded by one pixel
        all round; with ``wrap`` the side columns repeat the opposite edge, since bearings wrap (359°
        lies beside 0°)."""
        padded = np.zeros((RANGE_ROWS + 1, _PADDED_WIDTH), dtype=bool)
        np.greater(tensor[:SENTINEL_ROW, :ANGLE_COLUMNS, channel], 0, out=padded[1 : SENTINEL_ROW + 1, 1:-1])
        if wrap:
            padded[:, 0] = padded[:, -2]
            padded[:, -1] = padded[:, 1]
        return padded


def _still_share(pixels: _Pixels, centres: np.ndarray, config: MotionConfirm) -> float:
    matched = ~pixels.moving
    if len(centres):
        matched = matched[cdist(pixels.xy, centres).min(axis=1) >= config.background_m]
    if len(matched) < config.background_min_pixels:
        return 1.0
    return float(matched.mean())


def still_share(tensor: np.ndarray, config: MotionConfirm = DEFAULT_MOTION_CONFIRM) -> float:
    """How still the sensor was over the tensor's three scans: the share of the middle scan's pixels
    away from the moving clusters (:func:`moving_people`) with a lit pixel within one pixel in both the
    older and the newer scan. 1.0 when too few such pixels are left to tell."""
    pixels = _Pixels(tensor)
    return _still_share(pixels, _moving_people(pixels, config), config)


def _points_m(rows: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """Raster-frame positions (metres) of pixel centres."""
    ranges = (rows + 0.5) / ROW_SCALE
    bearings = np.radians(columns.astype(np.float64))
    return np.stack([ranges * np.cos(bearings), ranges * np.sin(bearings)], axis=1)


def _groups(points: np.ndarray, link_m: float) -> np.ndarray:
    """Single-linkage group label of each point (points closer than ``link_m`` share one)."""
    linked = cdist(points, points) < link_m
    labels = np.arange(len(points))
    while True:  # each pass gives every point its smallest neighbour's label; a few passes for legs
        spread = np.where(linked, labels[None, :], len(points)).min(axis=1)
        if np.array_equal(spread, labels):
            return labels
        labels = spread


def moving_people(tensor: np.ndarray, config: MotionConfirm = DEFAULT_MOTION_CONFIRM) -> np.ndarray:
    """Raster-frame centres ``float64[K, 2]`` (metres) of clusters of the middle scan's moving pixels.

    A pixel of scan t−1 moves when scan t−2 or scan t has no lit pixel within one pixel of it.
    Moving pixels closer than ``link_m`` form a cluster, which takes in the still pixels within
    ``stance_m`` (a planted leg does not move while the other swings). A cluster wider than
    ``max_extent_m`` is dropped; its centre is the middle of its extent, pushed one leg radius (5 cm)
    away from the sensor, since a scan sees only a leg's near side. Centres closer than ``merge_m``
    are one person. Only a still sensor's tensors mean anything here (:func:`still_share`).
    """
    return _moving_people(_Pixels(tensor), config)


def _moving_people(pixels: _Pixels, config: MotionConfirm) -> np.ndarray:
    if pixels.moving.sum() < config.min_moving_pixels:
        return np.zeros((0, 2))
    moving_xy, still_xy = pixels.xy[pixels.moving], pixels.xy[~pixels.moving]
    labels = _groups(moving_xy, config.link_m)
    near_still = cdist(still_xy, moving_xy) < config.stance_m  # [still, moving]
    centres: list[tuple[int, np.ndarray]] = []
    sizes = np.bincount(labels)
    for label in np.flatnonzero(sizes >= config.min_moving_pixels):
        members = labels == label
        size = int(sizes[label])
        points = np.concatenate([moving_xy[members], still_xy[near_still[:, members].any(axis=1)]])
        low, high = points.min(axis=0), points.max(axis=0)
        if math.hypot(*(high - low)) > config.max_extent_m:
            continue
        centre = (low + high) / 2.0
        distance = math.hypot(*centre)
        if distance == 0.0 or distance + 0.05 > R_MAX_M:
            continue
        centres.append((size, centre * (distance + 0.05) / distance))
    merged: list[np.ndarray] = []
    for _, centre in sorted(centres, key=lambda item: -item[0]):  # the most moving pixels first
        if all(math.hypot(*(centre - kept)) >= config.merge_m for kept in merged):
            merged.append(centre)
    return np.array(merged, dtype=np.float64).reshape(-1, 2)


def still_by_odometry(
    poses: Sequence[Odometry | None], config: MotionConfirm = DEFAULT_MOTION_CONFIRM
) -> bool | None:
    """Whether the robot stood still over a tensor's scans, by their odometry poses (oldest first):
    None when a pose is unknown, False when one lies in another frame or more than the tolerance from
    the newest."""
    newest, older = poses[-1], [pose for pose in poses[:-1] if pose is not None]
    if newest is None or len(older) < len(poses) - 1:
        return None
    return all(
        newest.break_from(pose, jump_m=config.odom_still_m, jump_rad=config.odom_still_rad) is None
        for pose in older
    )


def box_centres_m(boxes: np.ndarray) -> np.ndarray:
    """Raster-frame positions (metres) of boxes' centres (xyxy pixels)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    bearings = np.radians((boxes[:, 0] + boxes[:, 2]) / 2.0 - 0.5)  # column c is centred on c°
    ranges = (boxes[:, 1] + boxes[:, 3]) / 2.0 / ROW_SCALE
    return np.stack([ranges * np.cos(bearings), ranges * np.sin(bearings)], axis=1)


def confirm_people(
    tensor: np.ndarray,
    boxes: np.ndarray,
    scores: np.ndarray,
    class_ids: np.ndarray,
    person_id: int,
    config: MotionConfirm = DEFAULT_MOTION_CONFIRM,
    still: bool | None = None,
) -> np.ndarray:
    """``scores`` with each moving cluster's best person candidate raised to at least ``config.score``.

    Candidates are the person boxes scoring at least ``config.floor`` whose centre lies within
    ``match_m`` of a cluster; a cluster confirms one candidate, its highest-scoring. The scores come
    back unchanged when no candidate lies below ``config.score`` or the sensor moved. ``still`` is
    what odometry says of the tensor's three scans (:func:`still_by_odometry`); None, when it says
    nothing, leaves it to the tensor (:func:`still_share`).
    """
    scores = np.asarray(scores)
    candidates = np.flatnonzero((class_ids == person_id) & (scores >= config.floor))
    low = candidates[scores[candidates] < config.score]
    if still is False or not low.size:
        return scores
    pixels = _Pixels(tensor)
    # A cluster's centre lies within half its widest extent (and the 5 cm push) of each of its moving
    # pixels: with no moving pixel that near a low candidate none can be confirmed, and the clusters,
    # the costly part, are never formed.
    reach = config.match_m + config.max_extent_m / 2.0 + 0.05
    moving_xy = pixels.xy[pixels.moving]
    if not len(moving_xy) or cdist(moving_xy, box_centres_m(boxes[low])).min() > reach:
        return scores
    centres = _moving_people(pixels, config)
    if not len(centres) or (still is None and _still_share(pixels, centres, config) < config.still_share):
        return scores
    confirmed = scores.copy()
    distances = cdist(centres, box_centres_m(boxes[candidates]))
    for row in distances:
        near = candidates[row < config.match_m]
        if near.size:
            best = near[np.argmax(scores[near])]
            confirmed[best] = max(confirmed[best], np.float32(config.score))
    return confirmed
