"""``triscan eval --bag``: a model scored on a recorded ROS bag, scan by scan as the robot would run it.

The bag's LaserScans go through :class:`common.encoding.ScanStacker` with the model's own padding,
invalid-return rule and raster yaw (its metadata), and each stacked tensor through
:class:`common.inference.OnnxDetector` and :func:`common.postprocess.detections_from_boxes`, so a
detection's ``x_m``/``y_m`` is the very position the robot would publish, in the laser frame. A tensor
stacks scans t−2, t−1 and t and is labelled for its middle scan (the simulator labels scan t−1), so the
detections of the tensor that ends with scan j are scored against the people of scan j−1.

What is scored, inside a :class:`Scope` (a bearing window and the model's 4 m full scale; a detection
or a person outside it is not counted at all):

* **People's centres** (``--people-topic``): DR-SPAAM's protocol (VisualComputingInstitute/
  2D_lidar_person_detection, ``dr_spaam/utils/precision_recall.py``), see
  :func:`precision_recall_curve`: AP and peak F1 at association radii 0.3 m and 0.5 m.
* **Leg clusters** (``--legs-topic``, the leg_tracker development set): leg recall and precision at
  0.4 m at the operating confidence (:func:`leg_hits`), counted only inside the window where the legs
  were extracted.
* **Every bag**: detections per class at the operating confidence and per minute; on a bag declared
  people-free, the person detections per minute are its false people per minute.

Nothing here needs torch: numpy, scipy, onnxruntime and rosbags.
"""

from __future__ import annotations

import json
import logging
import math
from collections import Counter, deque
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Final, NamedTuple

import numpy as np
from scipy.optimize import linear_sum_assignment

from common.encoding import R_MAX_M, ScanError, ScanStacker
from common.inference import OnnxDetector
from common.messages import Detection, Odometry, Scan
from common.model_spec import CLASS_NAMES, PERSON, PERSON_ID
from common.moving_people import DEFAULT_MOTION_CONFIRM, MotionConfirm
from common.postprocess import DEFAULT_CONF, DEFAULT_IOU, detections_from_boxes
from training.evaluate import VAL_CONF

log = logging.getLogger(__name__)

CENTRE_RADII_M: Final[tuple[float, ...]] = (0.3, 0.5)  # DR-SPAAM's association radii
# A leg cluster is the mean point of one leg's near surface, a person's centre lies between the two
# legs: 0.4 m covers a stride's half-spread plus the leg's radius.
LEG_RADIUS_M: Final[float] = 0.4
PERSON_RANGE_BANDS: Final[tuple[str, ...]] = ("0-1", "1-2", "2-3", "3-4")  # metres, up to the full scale
_NS_PER_MIN: Final[float] = 60e9


class RealEvalError(ValueError):
    """A bag that cannot be scored as asked (missing topic, labels that cannot be paired with scans)."""


# --------------------------------------------------------------------------------------------------
# Scope
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Scope:
    """Where things are scored: bearings ``[min_deg, max_deg]`` (counter-clockwise from forward, in
    (−180, 180]) and ranges up to ``max_range_m`` from the sensor."""

    min_deg: float = -180.0
    max_deg: float = 180.0
    max_range_m: float = R_MAX_M

    def __post_init__(self) -> None:
        if not -180.0 <= self.min_deg < self.max_deg <= 180.0:
            raise RealEvalError(
                f"a bearing window needs -180 <= min < max <= 180 degrees, got {self.min_deg}..{self.max_deg}"
            )
        if not self.max_range_m > 0.0:
            raise RealEvalError(f"max range must be > 0 m, got {self.max_range_m}")

    def contains(self, xy: np.ndarray) -> np.ndarray:
        """``bool[K]``: which sensor-frame points ``float[K, 2]`` lie inside."""
        points = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        bearing = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
        within_range = np.hypot(points[:, 0], points[:, 1]) <= self.max_range_m
        return within_range & (bearing >= self.min_deg) & (bearing <= self.max_deg)

    def within(self, other: Scope) -> Scope:
        """The part of this scope that also lies in ``other``."""
        return Scope(
            max(self.min_deg, other.min_deg),
            min(self.max_deg, other.max_deg),
            min(self.max_range_m, other.max_range_m),
        )


# Where the leg_tracker development set kept leg clusters (shared/real/leg_tracker/README.md): ±15° of
# forward (−15°…+10° in bag 4) and 5 m; its scans are scored there and nowhere else.
_LEG_TRACKER_WINDOW: Final[Scope] = Scope(-15.0, 15.0, 5.0)
LEG_TRACKER_WINDOWS: Final[dict[str, Scope]] = {
    **{f"positive_{n}_extracted.bag": _LEG_TRACKER_WINDOW for n in (1, 2, 3, 6, 7)},
    "positive_4_extracted.bag": Scope(-15.0, 10.0, 5.0),
}


# --------------------------------------------------------------------------------------------------
# Metrics (pure)
# --------------------------------------------------------------------------------------------------


class FrameDetections(NamedTuple):
    """One labelled frame: its detections' scores ``float[D]`` and centres ``float[D, 2]``, and its
    people's centres ``float[P, 2]`` (all sensor frame, metres)."""

    scores: np.ndarray
    xy: np.ndarray
    people: np.ndarray


def within_radius(a_xy: np.ndarray, b_xy: np.ndarray, radius: float) -> np.ndarray:
    """``bool[A, B]``: pairs no farther apart than ``radius`` (DR-SPAAM's cost is ``distance > r``)."""
    a = np.asarray(a_xy, dtype=np.float64).reshape(-1, 1, 2)
    b = np.asarray(b_xy, dtype=np.float64).reshape(1, -1, 2)
    return np.hypot(*(a - b).transpose(2, 0, 1)) <= radius


class _FrameMatching:
    """One frame's accepted detections and its people, re-assigned as DR-SPAAM does after each
    detection: ``linear_sum_assignment`` on the binary cost ``distance > r``; only the assigned pairs
    within ``r`` are true positives (the assignment also pairs what lies too far apart)."""

    def __init__(self, people_xy: np.ndarray, radius: float) -> None:
        self._people = np.asarray(people_xy, dtype=np.float64).reshape(-1, 2)
        self._radius = radius
        self._accepted: list[np.ndarray] = []
        self.matched = 0

    def add(self, xy: np.ndarray) -> int:
        """Accept a detection at ``xy``; the change in this frame's true positives (0 or 1)."""
        self._accepted.append(np.asarray(xy, dtype=np.float64).reshape(2))
        if not len(self._people):
            return 0
        far = ~within_radius(self._people, np.stack(self._accepted), self._radius)
        rows, cols = linear_sum_assignment(far)
        matched = int(np.count_nonzero(~far[rows, cols]))
        gained, self.matched = matched - self.matched, matched
        return gained


@dataclass(frozen=True)
class PrCurve:
    """Precision and recall after each detection of a run, highest score first."""

    thresholds: np.ndarray
    recalls: np.ndarray
    precisions: np.ndarray
    people: int

    @property
    def ap(self) -> float | None:
        """Trapezoidal area under the curve through its points (sklearn's ``auc``, as DR-SPAAM): the
        curve starts at the first detection's recall, not at 0. None without people; 0 without
        detections."""
        if self.people == 0:
            return None
        r, p = self.recalls, self.precisions
        return float(np.sum(np.diff(r) * (p[1:] + p[:-1]) / 2.0)) if r.size else 0.0

    @property
    def peak_f1(self) -> float | None:
        """The best F1 along the curve (None without people; 0 without detections)."""
        if self.people == 0:
            return None
        r, p = self.recalls, self.precisions
        if not r.size:
            return 0.0
        return float(np.max(2.0 * p * r / np.clip(p + r, 1e-16, None)))


def precision_recall_curve(frames: Sequence[FrameDetections], radius: float) -> PrCurve:
    """DR-SPAAM's curve over a run (``_prec_rec_2d`` in its ``utils/precision_recall.py``).

    Every detection of the run is sorted by score (highest first; equal scores later-first, as its
    reversed stable sort). After each one, that frame's accepted detections are matched one-to-one to
    its people on the binary cost ``distance > radius``; true positives are the pairs within the
    radius, summed over frames, so precision = TP / accepted detections and recall = TP / people.
    """
    people = sum(len(f.people) for f in frames)
    scores = np.concatenate([np.asarray(f.scores, np.float64).reshape(-1) for f in frames] or [np.zeros(0)])
    xy = np.concatenate([np.asarray(f.xy, np.float64).reshape(-1, 2) for f in frames] or [np.zeros((0, 2))])
    frame_of = np.concatenate(
        [np.full(len(f.scores), i, np.int64) for i, f in enumerate(frames)] or [np.zeros(0, np.int64)]
    )
    order = np.argsort(scores, kind="stable")[::-1]
    matchings = [_FrameMatching(f.people, radius) for f in frames]
    recalls = np.empty(order.size)
    precisions = np.empty(order.size)
    true_positives = 0
    for accepted, index in enumerate(order, start=1):
        true_positives += matchings[frame_of[index]].add(xy[index])
        precisions[accepted - 1] = true_positives / accepted
        recalls[accepted - 1] = true_positives / people if people else math.nan
    return PrCurve(scores[order], recalls, precisions, people)


def leg_hits(detections_xy: np.ndarray, legs_xy: np.ndarray, radius: float = LEG_RADIUS_M) -> tuple[int, int]:
    """(legs with a person detection within ``radius``, person detections within ``radius`` of a leg).

    Not one-to-one: one person detection stands for both legs of its person, and two legs closer than
    the clustering distance are one cluster.
    """
    near = within_radius(detections_xy, legs_xy, radius)
    return int(near.any(axis=0).sum()), int(near.any(axis=1).sum())


def ratio(numerator: int, denominator: int) -> float | None:
    return numerator / denominator if denominator else None


# --------------------------------------------------------------------------------------------------
# Labels and scans
# --------------------------------------------------------------------------------------------------


class Positions(NamedTuple):
    """One label message: its header stamp (0 when unset), frame and points ``float[K, 2]``."""

    stamp_ns: int
    frame_id: str
    xy: np.ndarray


def positions_of(message: Any, topic: str) -> np.ndarray:
    """``float[K, 2]`` x/y of a label message: ``geometry_msgs/PoseArray`` (``poses``), or a list of
    people with a ``position`` (``people_msgs/People``) or ``pos`` (``PositionMeasurementArray``)."""
    if hasattr(message, "poses"):
        points = [pose.position for pose in message.poses]
    elif hasattr(message, "people"):
        points = [getattr(p, "position", None) or p.pos for p in message.people]
    else:
        raise RealEvalError(
            f"{topic} holds {message.__msgtype__}: no positions in it (a PoseArray or a people list)"
        )
    return np.array([[float(p.x), float(p.y)] for p in points], dtype=np.float64).reshape(-1, 2)


def pair_labels(scan_stamps: Sequence[int], labels: Sequence[Positions], topic: str) -> dict[int, np.ndarray]:
    """Each label message's points keyed by the stamp of the scan it belongs to.

    Labels with header stamps belong to the scan of the nearest stamp, within half the median scan
    interval. Labels whose stamps are all zero (the leg_tracker set) belong to the scans in bag order:
    the i-th message to the i-th scan, so their counts must agree.
    """
    if not labels:
        raise RealEvalError(f"{topic} holds no messages")
    if all(label.stamp_ns == 0 for label in labels):
        if len(labels) != len(scan_stamps):
            raise RealEvalError(
                f"{topic} has {len(labels)} messages without stamps for {len(scan_stamps)} scans: "
                "cannot pair them in bag order"
            )
        return {stamp: label.xy for stamp, label in zip(scan_stamps, labels, strict=True)}
    stamps = np.asarray(sorted(scan_stamps), dtype=np.int64)
    tolerance = np.median(np.diff(stamps)) / 2.0 if stamps.size > 1 else 0.0
    paired: dict[int, np.ndarray] = {}
    for label in labels:
        nearest = int(stamps[np.argmin(np.abs(stamps - label.stamp_ns))])
        if abs(nearest - label.stamp_ns) <= tolerance:
            paired[nearest] = label.xy
    if not paired:
        raise RealEvalError(f"no message of {topic} is stamped within half a scan interval of a scan")
    if len(paired) < len(labels):
        log.warning(
            "%s: %d of %d messages match no scan stamp", topic, len(labels) - len(paired), len(labels)
        )
    return paired


@contextmanager
def _opened(bag: Path) -> Iterator[Any]:
    """An open rosbags reader of ``bag``; a file that is not a readable bag is a one-line error."""
    from services.bag_replay import _open_reader

    if not bag.exists():
        raise FileNotFoundError(f"bag {bag} not found")
    stack = ExitStack()
    try:
        reader = stack.enter_context(_open_reader([bag]))
    except Exception as exc:  # rosbags raises a zoo of types (UnicodeDecodeError too) for a bad file
        raise RealEvalError(f"{bag} is not a readable ROS bag: {exc}") from None
    with stack:
        yield reader


def _scan_connection(reader: Any, bag: Path, topic: str | None) -> Any:
    from services.bag_replay import scan_connections

    connections = scan_connections(reader, [topic] if topic else [])
    if len(connections) > 1:
        raise RealEvalError(
            f"{bag} has LaserScan topics {sorted(c.topic for c in connections)}: name one with --topic"
        )
    return connections[0]


def read_scans(reader: Any, connection: Any, rejected: Counter[str]) -> list[Scan]:
    """The topic's scans in bag order, validated as the ROS bridge does; refused ones counted by reason.

    Each carries the robot's pose where the bag holds odometry (``/odom``, else ``/tf``), paired as
    ``triscan replay`` pairs it: the detector's motion confirmation asks it whether the robot stood.
    """
    from services.bag_replay import ODOM_AUTO, _update_odometry, odom_connection
    from services.ros2_bridge.laser_scan import ScanRejectedError, fields_of_message, to_triscan_scan
    from services.ros2_bridge.odometry import OdometryPairing

    odom = odom_connection(reader, ODOM_AUTO)
    pairing = OdometryPairing()
    scans: list[Scan] = []
    for topic_connection, _, raw in reader.messages(connections=[connection, *([odom] if odom else [])]):
        message = reader.deserialize(raw, topic_connection.msgtype)
        if odom is not None and topic_connection.topic == odom.topic:
            _update_odometry(pairing, message, 0)
            continue
        try:
            scans.append(pairing.attach(to_triscan_scan(fields_of_message(message), "eval", len(scans))))
        except ScanRejectedError as exc:
            rejected[exc.reason] += 1
    return scans


def narrowed(scan: Scan, field_of_view_deg: float) -> Scan:
    """``scan`` as a sensor with a field of view of ``field_of_view_deg`` about the same heading takes
    it: the beams at bearings in [−half, half) of forward, with the same angular step, so a 768-beam
    270° development recording becomes the 512-beam 180° geometry of the demo recording's sensor."""
    beams = len(scan.ranges)
    step = abs(scan.angle_increment)
    if not 0.0 < field_of_view_deg <= math.degrees(beams * step) + 1e-6:
        raise RealEvalError(
            f"field of view {field_of_view_deg:g}° must be above 0 and at most the scan's own "
            f"{math.degrees(beams * step):.1f}°"
        )
    # Bearings in [−π, π): a scan may start anywhere (0 rad, say), and the kept beams are taken in
    # their scan direction from the first one past −half, across the scan's end if they wrap.
    angles = np.mod(scan.angle_min + scan.angle_increment * np.arange(beams) + math.pi, 2 * math.pi) - math.pi
    half = math.radians(field_of_view_deg) / 2.0
    keep = np.flatnonzero((angles >= -half - 1e-9) & (angles < half - 1e-9))
    if not keep.size:
        raise RealEvalError(f"no beam of the scan lies within ±{field_of_view_deg / 2:g}° of forward")
    order = np.argsort(angles[keep] if scan.angle_increment > 0 else -angles[keep], kind="stable")
    keep = keep[order]
    return scan.model_copy(update={"ranges": scan.ranges[keep], "angle_min": float(angles[keep[0]])})


def read_positions(reader: Any, bag: Path, topic: str) -> list[Positions]:
    connections = [c for c in reader.connections if c.topic == topic]
    if not connections:
        raise RealEvalError(
            f"no topic {topic} in {bag}; it has {sorted({c.topic for c in reader.connections})}"
        )
    labels = []
    for connection, _, raw in reader.messages(connections=connections):
        message = reader.deserialize(raw, connection.msgtype)
        stamp = message.header.stamp
        labels.append(
            Positions(
                int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec),
                str(message.header.frame_id),
                positions_of(message, topic),
            )
        )
    return labels


def _check_frame(labels: Sequence[Positions], scan_frame: str, topic: str) -> None:
    frames = {label.frame_id for label in labels if label.frame_id and len(label.xy)}
    if frames - {scan_frame}:
        raise RealEvalError(
            f"{topic} is in frame {sorted(frames)}, the scans in {scan_frame!r}: "
            "positions must be in the laser frame"
        )


# --------------------------------------------------------------------------------------------------
# Running the model
# --------------------------------------------------------------------------------------------------


def middle_scan_detections(
    detector: OnnxDetector, scans: Sequence[Scan], conf: float, rejected: Counter[str]
) -> Iterator[tuple[int, list[Detection]]]:
    """``(stamp of the middle scan, detections)`` per tensor of the scan stream: every detection above
    ``conf``, and person detections down to the detector's own threshold (for the curve)."""
    stacker = ScanStacker.for_model(detector)
    stamps: deque[int] = deque(maxlen=3)
    poses: deque[Odometry | None] = deque(maxlen=3)
    for scan in scans:
        try:
            tensor = stacker.push_scan(
                scan.ranges, scan.angle_min, scan.angle_increment, scan.range_min, scan.range_max
            )
        except ScanError:
            rejected["bad_scan"] += 1  # the FIFO is unchanged: the robot's encoder drops it the same way
            continue
        stamps.append(scan.stamp_ns)
        poses.append(scan.odom)
        if tensor is None:
            continue
        boxes, scores, class_ids, _ = detector.detect_boxes(tensor, detector.still_by_odometry(list(poses)))
        keep = (class_ids == PERSON_ID) | (scores > np.float32(conf))
        yield (
            stamps[1],
            detections_from_boxes(boxes[keep], scores[keep], class_ids[keep], detector.raster_yaw_deg),
        )  # laser-frame bearings and positions, whatever the raster's yaw


def _xy(detections: Sequence[Detection]) -> np.ndarray:
    return np.array([[d.x_m, d.y_m] for d in detections], dtype=np.float64).reshape(-1, 2)


@dataclass(frozen=True)
class BagEvalConfig:
    bag: Path
    topic: str | None = None  # the LaserScan topic; None: the bag's only one
    people_topic: str | None = None  # person centres in the laser frame
    legs_topic: str | None = None  # leg clusters in the laser frame
    stream_bag: Path | None = None  # the full recording the labelled scans were cut from
    scope: Scope = field(default_factory=Scope)
    legs_window: Scope | None = None  # None: the development set's window for its bags, else everywhere
    people_free: bool = False
    conf: float = DEFAULT_CONF
    # Score the recording as a sensor with this narrower field of view about the same heading would
    # see it (degrees): only its beams within half of it either side of forward (None: all of them).
    field_of_view_deg: float | None = None

    def legs_scope(self) -> Scope:
        window = self.legs_window or LEG_TRACKER_WINDOWS.get(self.bag.name, Scope(max_range_m=math.inf))
        return self.scope.within(window)


@dataclass
class BagReport:
    """What ``triscan eval --bag`` prints and writes for one model."""

    bag: str
    topic: str
    model: str
    classes: list[str]
    has_person_class: bool
    conf: float
    scope: dict[str, float]
    scans: int
    tensors: int
    minutes: float
    detections: dict[str, int]  # per class, above conf, inside the scope
    per_minute: dict[str, float]
    people: dict[str, Any] | None = None
    legs: dict[str, Any] | None = None
    false_people_per_minute: float | None = None
    skipped: dict[str, int] = field(default_factory=dict)
    # Confident person detections in the scope by the band their middle range falls in: where a model
    # reports people no label explains (near walkers, or far walls) shows without a labelled bag.
    person_by_range_m: dict[str, int] | None = None


@dataclass
class _LabelledBag:
    topic: str
    stream: list[Scan]
    people: dict[int, np.ndarray] | None
    legs: dict[int, np.ndarray] | None
    skipped: dict[str, int]


def _load(config: BagEvalConfig) -> _LabelledBag:
    rejected: Counter[str] = Counter()
    with _opened(config.bag) as reader:
        connection = _scan_connection(reader, config.bag, config.topic)
        scans = read_scans(reader, connection, rejected)
        labels = {
            kind: read_positions(reader, config.bag, topic)
            for kind, topic in (("people", config.people_topic), ("legs", config.legs_topic))
            if topic is not None
        }
    if not scans:
        raise RealEvalError(f"no usable scan on {connection.topic} in {config.bag}: refused {dict(rejected)}")
    if config.field_of_view_deg is not None:
        scans = [narrowed(scan, config.field_of_view_deg) for scan in scans]
    stamps = [scan.stamp_ns for scan in scans]
    paired: dict[str, dict[int, np.ndarray]] = {}
    for kind, positions in labels.items():
        topic = config.people_topic if kind == "people" else config.legs_topic
        assert topic is not None
        _check_frame(positions, scans[0].frame_id, topic)
        paired[kind] = pair_labels(stamps, positions, topic)
    stream = scans
    if config.stream_bag is not None:
        with _opened(config.stream_bag) as full:
            same_topic = connection.topic in {c.topic for c in full.connections}
            full_connection = _scan_connection(
                full, config.stream_bag, connection.topic if same_topic else None
            )
            stream = read_scans(full, full_connection, rejected)
        if config.field_of_view_deg is not None:
            stream = [narrowed(scan, config.field_of_view_deg) for scan in stream]
        if not set(stamps) & {scan.stamp_ns for scan in stream}:
            raise RealEvalError(f"no scan of {config.bag} has its stamp in {config.stream_bag}")
    return _LabelledBag(connection.topic, stream, paired.get("people"), paired.get("legs"), dict(rejected))


def evaluate_bag(detector: OnnxDetector, config: BagEvalConfig) -> BagReport:
    """Score ``detector`` on ``config.bag`` (see the module docstring)."""
    if not 0.0 <= config.conf <= 1.0:
        raise RealEvalError(f"conf must lie in [0, 1], got {config.conf}")
    bag = _load(config)
    classes = list(detector.class_names)
    has_person = PERSON in classes
    counts = dict.fromkeys(classes, 0)
    person_bands = dict.fromkeys(PERSON_RANGE_BANDS, 0)
    centre_frames: list[FrameDetections] = []
    legs_scope = config.legs_scope()
    legs = Counter[str]()
    furniture_on_legs = Counter[str]()
    tensors, labelled = 0, set()
    rejected = Counter(bag.skipped)
    for stamp, detections in middle_scan_detections(detector, bag.stream, config.conf, rejected):
        tensors += 1
        in_scope = [
            d for d, inside in zip(detections, config.scope.contains(_xy(detections)), strict=True) if inside
        ]
        confident = [d for d in in_scope if d.score > config.conf]
        for d in confident:
            counts[d.class_name] += 1
            if d.class_id == PERSON_ID:
                band = min(int((d.range_min_m + d.range_max_m) / 2.0), len(PERSON_RANGE_BANDS) - 1)
                person_bands[PERSON_RANGE_BANDS[band]] += 1
        people = None if bag.people is None else bag.people.get(stamp)
        if people is not None:
            labelled.add(stamp)
            persons = [d for d in in_scope if d.class_id == PERSON_ID]
            centre_frames.append(
                FrameDetections(
                    np.array([d.score for d in persons]), _xy(persons), people[config.scope.contains(people)]
                )
            )
        leg_xy = None if bag.legs is None else bag.legs.get(stamp)
        if leg_xy is not None:
            labelled.add(stamp)
            leg_xy = leg_xy[legs_scope.contains(leg_xy)]
            near = [d for d in detections if d.score > config.conf and legs_scope.contains(_xy([d]))[0]]
            persons = [d for d in near if d.class_id == PERSON_ID]
            found, on_legs = leg_hits(_xy(persons), leg_xy)
            legs.update(legs=len(leg_xy), found=found, detections=len(persons), on_legs=on_legs, frames=1)
            for d in near:
                if d.class_id != PERSON_ID and within_radius(_xy([d]), leg_xy, LEG_RADIUS_M).any():
                    furniture_on_legs[d.class_name] += 1
    if tensors == 0:
        raise RealEvalError(f"{config.bag}: fewer than three usable scans, no tensor to score")
    stamps = np.asarray([scan.stamp_ns for scan in bag.stream], dtype=np.int64)
    interval_ns = float(np.median(np.diff(stamps))) if stamps.size > 1 else 0.0
    minutes = tensors * interval_ns / _NS_PER_MIN
    skipped = dict(rejected)
    for kind, labels in (("people", bag.people), ("legs", bag.legs)):
        if labels is not None and (unscored := len(set(labels) - labelled)):
            skipped[f"{kind}_scans_without_tensor"] = unscored
    report = BagReport(
        bag=str(config.bag),
        topic=bag.topic,
        model=detector.model_id,
        classes=classes,
        has_person_class=has_person,
        conf=config.conf,
        scope=asdict(config.scope),
        scans=len(bag.stream),
        tensors=tensors,
        minutes=minutes,
        detections=counts,
        per_minute={name: n / minutes for name, n in counts.items()} if minutes else {},
        skipped=skipped,
        person_by_range_m=person_bands if has_person else None,
    )
    if bag.people is not None:
        report.people = {"frames": len(centre_frames), "people": sum(len(f.people) for f in centre_frames)}
        for radius in CENTRE_RADII_M:
            curve = precision_recall_curve(centre_frames, radius)
            report.people[f"r{radius:g}"] = {"ap": curve.ap, "peak_f1": curve.peak_f1}
    if bag.legs is not None:
        report.legs = {
            "radius_m": LEG_RADIUS_M,
            "scope": asdict(legs_scope),
            "frames": legs["frames"],
            "legs": legs["legs"],
            "legs_found": legs["found"],
            "recall": ratio(legs["found"], legs["legs"]),
            "person_detections": legs["detections"],
            "on_legs": legs["on_legs"],
            "precision": ratio(legs["on_legs"], legs["detections"]),
            "furniture_on_legs": dict(furniture_on_legs),
        }
    if config.people_free and has_person and minutes:
        report.false_people_per_minute = counts[PERSON] / minutes
    return report


# --------------------------------------------------------------------------------------------------
# Output
# --------------------------------------------------------------------------------------------------


def _fmt(value: float | None, digits: int = 3) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def report_rows(report: BagReport) -> list[tuple[str, str]]:
    """The table's rows for one model: (metric, value)."""
    rows = [
        ("model", report.model),
        (
            "classes",
            ", ".join(report.classes)
            + ("" if report.has_person_class else "  (this model has no person class)"),
        ),
        ("scans / tensors", f"{report.scans} / {report.tensors} ({report.minutes:.2f} min)"),
        (
            "scope",
            f"{report.scope['min_deg']:g}..{report.scope['max_deg']:g}°, {report.scope['max_range_m']:g} m",
        ),
    ]
    for name in CLASS_NAMES:
        n = report.detections.get(name)
        value = "not a class of this model" if n is None else f"{n} ({report.per_minute.get(name, 0.0):.1f})"
        rows.append((f"{name} detections (/min)", value))
    if report.person_by_range_m is not None:
        bands = ", ".join(f"{band} m {n}" for band, n in report.person_by_range_m.items())
        rows.append(("person detections by range", bands))
    if report.false_people_per_minute is not None:
        rows.append(("false people per minute", f"{report.false_people_per_minute:.2f}"))
    if report.people is not None:
        rows.append(("labelled frames / people", f"{report.people['frames']} / {report.people['people']}"))
        for radius in CENTRE_RADII_M:
            scores = report.people[f"r{radius:g}"]
            rows.append((f"AP@{radius:g} m / peak F1", f"{_fmt(scores['ap'])} / {_fmt(scores['peak_f1'])}"))
    if report.legs is not None:
        legs = report.legs
        window = legs["scope"]
        rows += [
            ("leg window", f"{window['min_deg']:g}..{window['max_deg']:g}°, {window['max_range_m']:g} m"),
            ("leg frames / legs", f"{legs['frames']} / {legs['legs']}"),
            (f"leg recall @{legs['radius_m']:g} m", f"{_fmt(legs['recall'])} ({legs['legs_found']})"),
            (
                f"leg precision @{legs['radius_m']:g} m",
                f"{_fmt(legs['precision'])} ({legs['on_legs']} of {legs['person_detections']})",
            ),
            (
                "furniture on legs",
                ", ".join(f"{k} {v}" for k, v in legs["furniture_on_legs"].items()) or "none",
            ),
        ]
    if report.skipped:
        rows.append(("skipped", ", ".join(f"{k} {v}" for k, v in sorted(report.skipped.items()))))
    return rows


def format_reports(reports: Sequence[BagReport]) -> str:
    """One column per model, one row per metric."""
    columns = [report_rows(r) for r in reports]
    names = [name for name, _ in columns[0]]
    for rows in columns[1:]:
        names += [name for name, _ in rows if name not in names]
    values = [dict(rows) for rows in columns]
    width = max(len(n) for n in names)
    header = f"{reports[0].bag} {reports[0].topic}"
    lines = [header]
    for name in names:
        lines.append(f"{name:<{width}}  " + "  |  ".join(v.get(name, "") for v in values))
    return "\n".join(lines)


def write_reports(reports: Sequence[BagReport], out_dir: Path) -> Path:
    """``<out_dir>/<bag stem>.json``: the reports, one per model."""
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{Path(reports[0].bag).stem}.json"
    path.write_text(json.dumps([asdict(r) for r in reports], indent=2) + "\n")
    return path


def detector_for(
    model: Path, threads: int | None = None, motion_confirm: MotionConfirm | None = DEFAULT_MOTION_CONFIRM
) -> OnnxDetector:
    """The robot's detector settings, with the validation protocol's confidence floor (as ``triscan
    eval`` on simulated worlds), so the precision-recall curve reaches low confidences."""
    return OnnxDetector(
        model,
        conf_threshold=VAL_CONF,
        iou_threshold=DEFAULT_IOU,
        intra_op_threads=threads,
        motion_confirm=motion_confirm,
    )
