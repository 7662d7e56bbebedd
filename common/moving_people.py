"""Motion confirmation of person candidates: walking legs that a still sensor sees move.

The three stacked scans show a walking leg as pixels that move between them, and a still sensor
shows almost nothing else that does. On real recordings the network often sees a walker only at a low
score (a real leg looks unlike a simulated one), while the false people it reports sit on walls and
furniture, which do not move. So a person candidate below the detector's threshold is confirmed when a
cluster of moving pixels lies where it stands: its score is raised to :attr:`MotionConfirm.score`.
Where the network proposed nothing at all (a walker seen through a gap in a near wall, whose legs
look like no simulated person), a person box about the cluster is added at
:attr:`MotionConfirm.add_score`, below every confirmed candidate. Confident boxes are left as they are.

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

from common.encoding import (
    ANGLE_COLUMNS,
    R_MAX_M,
    RANGE_ROWS,
    ROW_SCALE,
    SENTINEL_ROW,
    arc_pixel_boxes,
    disc_polar,
)
from common.messages import Odometry
from common.model_spec import PERSON_FOOTPRINT_RADIUS_M

_PADDED_WIDTH: Final[int] = ANGLE_COLUMNS + 2
# A scan sees a leg's near side: a cluster's centre lies about one leg radius beyond its pixels.
LEG_DEPTH_M: Final[float] = 0.05
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

    @property
    def centre_reach_m(self) -> float:
        """How far a cluster's centre can lie from any of its pixels: half its widest extent, plus
        the push to a leg's far side."""
        return self.max_extent_m / 2.0 + LEG_DEPTH_M

    # A cluster with no person candidate within ``match_m`` becomes a person box (the footprint disc
    # of the labels about its centre) scoring this: just above the detector's default threshold, so
    # it is reported there (not at a threshold above it), and below the confirmed candidates and
    # nearly all of the network's reported people. None adds nothing.
    add_score: float | None = 0.26


DEFAULT_MOTION_CONFIRM: Final = MotionConfirm()


def add_motion_argument(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """``--no-motion-confirm``, for every command that runs a detector."""
    parser.add_argument(
        "--no-motion-confirm",
        dest="motion_confirm",
        action="store_false",
        help="report only the network's own people: walking legs on a still sensor neither confirm a "
        "person candidate below the threshold nor add a person (docs/people.md)",
    )


def motion_confirm_of(args: argparse.Namespace) -> MotionConfirm | None:
    """The settings :func:`add_motion_argument`'s flag asks for (None: off)."""
    return DEFAULT_MOTION_CONFIRM if getattr(args, "motion_confirm", True) else None


class _Pixels:
    """The middle scan's lit pixels and, for each, whether the older and the newer scan have a lit
    pixel within one pixel of it (columns wrap, as bearings do): all the rule needs from a tensor, at
    the cost of a few gathers over a few hundred pixels."""

    def __init__(self, tensor: np.ndarray) -> None:
        # The three scans' lit pixels over the bearing columns, sentinel row left out, padded by one
        # pixel all round, channels last as in the tensor; the older and the newer scan's side columns
        # repeat the opposite edge, since bearings wrap (359° lies beside 0°).
        lit = np.zeros((RANGE_ROWS + 1, _PADDED_WIDTH, 3), dtype=bool)
        np.greater(tensor[:SENTINEL_ROW, :ANGLE_COLUMNS], 0, out=lit[1 : SENTINEL_ROW + 1, 1:-1])
        lit[:, 0, ::2] = lit[:, -2, ::2]
        lit[:, -1, ::2] = lit[:, 1, ::2]
        # Flat indices (of one channel) of the middle scan's pixels, and of each one's 3×3
        # neighbourhood: a bool array's flat indices are far quicker to find than rows and columns of
        # the uint8 tensor.
        flat = lit.ravel()
        self._centre = centre = np.flatnonzero(flat[1::3])
        neighbourhood = 3 * (centre[None, :] + _NEIGHBOUR_OFFSETS[:, None])
        self._around = (lit[..., 0], lit[..., 2])
        self._unmatched = [~flat[neighbourhood + channel].any(axis=0) for channel in (0, 2)]
        self.moving = self._unmatched[0] | self._unmatched[1]  # unmatched in the older or the newer scan
        self._groups: dict[float, np.ndarray] = {}

    @cached_property
    def _padded_rows_columns(self) -> tuple[np.ndarray, np.ndarray]:
        return np.divmod(self._centre, _PADDED_WIDTH)

    @property
    def _padded_columns(self) -> np.ndarray:
        return self._padded_rows_columns[1]

    @cached_property
    def rows(self) -> np.ndarray:
        return self._padded_rows_columns[0] - 1

    @cached_property
    def columns(self) -> np.ndarray:
        return self._padded_columns - 1

    @cached_property
    def xy(self) -> np.ndarray:
        """Raster-frame positions (metres) of the pixels."""
        return _points_m(self.rows, self.columns)

    @cached_property
    def moving_xy(self) -> np.ndarray:
        return _points_m(self.rows[self.moving], self.columns[self.moving])

    @cached_property
    def unhidden(self) -> np.ndarray:
        """The moving pixels that moved where the scan that missed them saw their bearing no nearer: a
        wall pixel that a walker in front hides in one scan and not the next is their shadow, with no
        motion of its own."""
        unhidden = np.zeros(len(self.moving), dtype=bool)
        for plane, missing in zip(self._around, self._unmatched, strict=True):
            unhidden |= missing & (self._nearest_rows(plane)[self._padded_columns] >= self.rows - 1)
        return unhidden

    @cached_property
    def unhidden_xy(self) -> np.ndarray:
        return self.xy[self.unhidden]

    def moving_groups(self, link_m: float) -> np.ndarray:
        """:func:`_groups` of the moving pixels, worked out once per frame."""
        if link_m not in self._groups:
            self._groups[link_m] = _groups(self.moving_xy, link_m)
        return self._groups[link_m]

    @staticmethod
    def _nearest_rows(plane: np.ndarray) -> np.ndarray:
        """Per padded column, the nearest lit row of a padded plane within one column either side
        (``RANGE_ROWS`` where none is lit)."""
        nearest = np.where(plane.any(axis=0), plane.argmax(axis=0) - 1, RANGE_ROWS)
        widened = nearest.copy()
        np.minimum(widened[1:], nearest[:-1], out=widened[1:])
        np.minimum(widened[:-1], nearest[1:], out=widened[:-1])
        return widened


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
    """Single-linkage group label of each point (points closer than ``link_m`` share one): the smallest
    index in its group."""
    # Each point's neighbours (itself included) as one run of a flat list, point by point.
    points_at, neighbours = np.nonzero(cdist(points, points) < link_m)
    runs = np.flatnonzero(np.diff(points_at, prepend=-1))
    labels = np.arange(len(points))
    while True:  # each pass gives every point its smallest neighbour's label; a few passes for legs
        spread = np.minimum.reduceat(labels[neighbours], runs)
        while True:  # and follows labels to their own labels, so a moving wall's chain takes a few too
            jumped = spread[spread]
            if np.array_equal(jumped, spread):
                break
            spread = jumped
        if np.array_equal(spread, labels):
            return labels
        labels = spread


def _surely_moved(pixels: _Pixels, config: MotionConfirm) -> bool:
    """Whether :func:`still_share` must come out below ``config.still_share``, told from the groups of
    moving pixels alone (not their still pixels, extents, merges or the still test): the frames of a
    moving sensor, the costly ones, are turned away early.

    Every cluster centre lies within :attr:`MotionConfirm.centre_reach_m` of the moving pixels of one
    group small enough to be a cluster, so a moving pixel farther than that plus ``background_m`` from
    every such group is surely background, and surely unmatched. When those alone exceed the share of
    all pixels the rule allows, the still test fails whatever the clusters turn out to be.
    """
    moving_xy = pixels.moving_xy
    allowed = (1.0 - config.still_share) * len(pixels.moving)
    if len(moving_xy) <= max(allowed, config.background_min_pixels):
        return False
    labels = pixels.moving_groups(config.link_m)
    low = np.full((len(moving_xy), 2), np.inf)
    high = np.full((len(moving_xy), 2), -np.inf)
    np.minimum.at(low, labels, moving_xy)
    np.maximum.at(high, labels, moving_xy)
    sizes = np.bincount(labels, minlength=len(moving_xy))
    small = (sizes >= config.min_moving_pixels) & (np.hypot(*(high - low).T) <= config.max_extent_m)
    in_small = small[labels]
    reach = config.background_m + config.centre_reach_m
    far = ~in_small
    if in_small.any() and far.any():
        far[far] = cdist(moving_xy[far], moving_xy[in_small]).min(axis=1) > reach
    surely = int(far.sum())
    return surely >= config.background_min_pixels and surely > allowed


def moving_people(tensor: np.ndarray, config: MotionConfirm = DEFAULT_MOTION_CONFIRM) -> np.ndarray:
    """Raster-frame centres ``float64[K, 2]`` (metres) of clusters of the middle scan's moving pixels.

    A pixel of scan t−1 moves when scan t−2 or scan t has no lit pixel within one pixel of it.
    Moving pixels closer than ``link_m`` form a cluster, which takes in the still pixels within
    ``stance_m`` (a planted leg does not move while the other swings). A cluster wider than
    ``max_extent_m`` is dropped; its centre is the middle of its extent, pushed :data:`LEG_DEPTH_M`
    away from the sensor, since a scan sees only a leg's near side. Centres closer than ``merge_m``
    are one person. Only a still sensor's tensors mean anything here (:func:`still_share`).
    """
    return _moving_people(_Pixels(tensor), config)


def _moving_people(pixels: _Pixels, config: MotionConfirm) -> np.ndarray:
    if np.count_nonzero(pixels.moving) < config.min_moving_pixels:
        return np.zeros((0, 2))
    labels = pixels.moving_groups(config.link_m)
    sizes = np.bincount(labels)
    big = sizes >= config.min_moving_pixels
    if not big.any():  # lone moving pixels: a dropout or the noise, no leg
        return np.zeros((0, 2))
    kept = np.flatnonzero(big)
    # Only the kept groups' pixels take in still pixels, so only their distances are worked out.
    in_kept = big[labels]
    moving_xy, still_xy = pixels.moving_xy[in_kept], pixels.xy[~pixels.moving]
    labels = labels[in_kept]
    near_still = cdist(still_xy, moving_xy) < config.stance_m  # [still, kept moving]
    centres: list[tuple[int, np.ndarray]] = []
    for label in kept:
        members = labels == label
        size = int(sizes[label])
        points = np.concatenate([moving_xy[members], still_xy[near_still[:, members].any(axis=1)]])
        low, high = points.min(axis=0), points.max(axis=0)
        if math.hypot(*(high - low)) > config.max_extent_m:
            continue
        centre = (low + high) / 2.0
        distance = math.hypot(*centre)
        if distance == 0.0 or distance + LEG_DEPTH_M > R_MAX_M:
            continue
        centres.append((size, centre * (distance + LEG_DEPTH_M) / distance))
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


def _moves_itself(pixels: _Pixels, centre: np.ndarray, config: MotionConfirm) -> bool:
    """Whether the cluster about ``centre`` is more than a shadow: at least ``min_moving_pixels`` of
    the moving pixels within half the widest extent of it moved where nothing nearer hid them."""
    near = np.hypot(*(pixels.unhidden_xy - centre).T) <= config.centre_reach_m
    return int(near.sum()) >= config.min_moving_pixels


def footprint_box(centre: np.ndarray) -> np.ndarray:
    """The raster box (xyxy pixels) of a person standing at ``centre`` (raster-frame metres): the box
    the labels give them (the footprint disc about their position, by the labels' pixel rule), and
    every column when the sensor stands inside the disc."""
    bearing, lo, hi, range_min, range_max = disc_polar(centre, PERSON_FOOTPRINT_RADIUS_M)
    if hi - lo >= 360.0:
        # Every bearing: the pixel rule keeps the piece holding the centre's column, of which a centre
        # at 359.5° or more keeps none, so the circle is placed about one that keeps it all.
        bearing = 180.0
    (box,) = arc_pixel_boxes(bearing, lo, hi, range_min, range_max, "zero")
    return np.array(box, dtype=np.float32)


def confirm_people(
    tensor: np.ndarray,
    boxes: np.ndarray,
    scores: np.ndarray,
    class_ids: np.ndarray,
    person_id: int,
    config: MotionConfirm = DEFAULT_MOTION_CONFIRM,
    still: bool | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``scores`` with each moving cluster's best person candidate raised to at least ``config.score``,
    and the person boxes ``float32[K, 4]`` added for clusters with no candidate.

    Candidates are the person boxes scoring at least ``config.floor`` whose centre lies within
    ``match_m`` of a cluster; a cluster confirms one candidate, its highest-scoring, and a cluster
    with none gets a :func:`footprint_box` (when ``config.add_score`` is set). Nothing changes when the
    sensor moved. ``still`` is what odometry says of the tensor's three scans
    (:func:`still_by_odometry`); None, when it says nothing, leaves it to the tensor
    (:func:`still_share`).
    """
    scores = np.asarray(scores)
    unchanged = scores, np.zeros((0, 4), dtype=np.float32)
    candidates = np.flatnonzero((class_ids == person_id) & (scores >= config.floor))
    low = candidates[scores[candidates] < config.score]
    adding = config.add_score is not None
    if still is False or not (low.size or adding):
        return unchanged
    pixels = _Pixels(tensor)
    if np.count_nonzero(pixels.moving) < config.min_moving_pixels:  # most frames of a quiet room
        return unchanged
    moving_xy = pixels.moving_xy
    if not adding:
        # A cluster's centre lies within ``centre_reach_m`` of each of its moving pixels: with no
        # moving pixel that near a low candidate none can be confirmed, and the clusters, the costly
        # part, are never formed.
        reach = config.match_m + config.centre_reach_m
        if cdist(moving_xy, box_centres_m(boxes[low])).min() > reach:
            return unchanged
    if still is None and _surely_moved(pixels, config):
        return unchanged
    centres = _moving_people(pixels, config)
    if not len(centres) or (still is None and _still_share(pixels, centres, config) < config.still_share):
        return unchanged
    confirmed = scores.copy()
    distances = cdist(centres, box_centres_m(boxes[candidates]))
    added = []
    for index, centre in enumerate(centres):
        near = candidates[distances[index] < config.match_m]
        if near.size:
            best = near[np.argmax(scores[near])]
            confirmed[best] = max(confirmed[best], np.float32(config.score))
        elif adding and _moves_itself(pixels, centre, config):
            added.append(footprint_box(centre))
    return confirmed, np.array(added, dtype=np.float32).reshape(-1, 4)
