"""The tracker's pure core: detections in, tracks with stable ids and velocities out, per robot.

Method (docs/tracking.md has the reasoning and the scores):

* **Frame.** With odometry on the detections, tracks live in the odometry frame: a detection at
  ``(x_m, y_m)`` in the laser frame is moved by the robot's pose, so a chair stays put while the robot
  drives past it. Without odometry they live in the laser frame and every object moves with the robot.
* **Filter.** A constant-velocity Kalman filter per track, state ``(x, y, vx, vy)``. Its motion and
  measurement noise are the same on both axes and the first covariance is diagonal, so the covariance
  stays two identical 2×2 blocks (position, velocity) and one block is all a track keeps: the filter
  is a handful of float operations, not matrix calls, which keeps 20 objects far under the cost goal.
* **Motion models per class** (:data:`MOTION_MODELS`): furniture barely accelerates, so its velocity
  stays near zero and its position does not drift with noisy detections; people accelerate freely.
  In the laser frame the robot's own motion moves everything, so all classes get the free model.
  The model follows the track's class, and a track whose class changes group starts its velocity
  afresh under the new one (:meth:`_Track.use`).
* **Assignment.** Cost = distance from each track's predicted position to each detection, plus a
  penalty when the classes differ (a detection whose class flickers still continues its track) and
  when a person track missed its last scan (the one that followed its person is the likelier owner);
  pairs farther than ``gate_m`` are never matched. The optimum is scipy's
  ``linear_sum_assignment`` (the Hungarian method's job, done by a maintained library). Before it, of
  two person detections of one scan closer than ``duplicate_m`` only the higher-scoring one is kept:
  one person, seen twice.
* **Life cycle.** A new detection opens a ``tentative`` track; ``confirm_hits`` hits confirm it
  (``person_confirm_hits`` a person's); a confirmed track that misses is ``coasting`` (predicted,
  not updated) until ``delete_after_s`` pass without a hit; a coasting person's velocity decays
  (``person_coast_decay_s``), since people stop and turn, and a track that kept walking would leave
  them; a tentative track is deleted after ``tentative_misses`` misses. In the odometry frame, of
  two established tracks of one furniture class closer than ``duplicate_m``, the younger is retired:
  one object followed twice. With ``person_confirm_travel_m`` set, a person track also has to move
  that far to be confirmed. The class is the one with the most summed score over the track, the
  score a running mean.
* **People found again.** A person track confirmed near where a person track was lost a moment
  before takes that track's id back (``person_resume_s``, ``person_resume_speed_mps``): the
  detector loses people for seconds behind furniture and each other, and to anyone following
  someone a new id is a new person. A lost track still coasting is retired then.
* **Ids** come from one counter per core. An id stays with the object it was given to (a person
  found again may take theirs back), never another one: not of the robot, not of any robot.

Bad input loses nothing else (counted by reason in :class:`TrackerCounters`):

* an odometry jump (more than ``jump_m`` or ``jump_rad`` between two scans) or a reset (the odometry
  frame renamed, or odometry appearing where tracks lived in the laser frame) resets that robot's
  tracks (``resets``);
* NaN odometry is refused (``odom_refused["not_finite"]``): the robot's last pose stands in for that
  scan, as it does for a scan that lost its odometry (``odom_refused["missing"]``);
* detections not newer than the last (by scan stamp) are dropped (``dropped["out_of_order"]``); an
  older ``seq`` with a newer stamp is a restarted pipeline, which resets the tracks (``resets``);
* a robot silent for ``forget_after_s`` is forgotten with its tracks (``forgotten_robots``,
  ``tracks_forgotten``).
"""

from __future__ import annotations

import colorsys
import logging
import math
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final

import numpy as np
from scipy.optimize import linear_sum_assignment

from common.encoding import wrap_angle
from common.keys import parse_key
from common.messages import (
    MAX_TRACKS,
    ODOM_JUMP_M,
    ODOM_JUMP_RAD,
    Detection,
    Detections,
    MessageError,
    Odometry,
    Track,
    TrackFrame,
    Tracks,
    TrackState,
    decode_message,
)
from common.model_spec import CLASS_NAMES, FURNITURE_CLASSES, PERSON_ID

log = logging.getLogger(__name__)

REPORTED_STATES: Final[tuple[TrackState, ...]] = ("confirmed", "coasting")
"""The tracks a consumer should treat as objects (ROS 2 output, scoring): a tentative track may be noise."""
POSES_KEPT: Final[int] = 4  # per robot: the middle scan's pose is the one before the newest
DEFAULT_FORGET_AFTER_S: Final[float] = 10.0
DEFAULT_MAX_ROBOTS: Final[int] = 1024
_NS_PER_S: Final[float] = 1e9


_GOLDEN_RATIO_CONJUGATE: Final[float] = 0.6180339887498949


def track_colour(track_id: int) -> tuple[int, int, int]:
    """A track's display colour, RGB 0–255, from its id alone: the same in every viewer and every frame.

    Hues step by the golden ratio, so consecutive ids (tracks opened together) get far-apart colours.
    """
    hue = (track_id * _GOLDEN_RATIO_CONJUGATE) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.7, 0.95)
    return round(r * 255), round(g * 255), round(b * 255)


@dataclass(frozen=True)
class MotionModel:
    """Noise of a constant-velocity model: white acceleration, first velocity spread, measurement."""

    accel_std_mps2: float
    initial_speed_std_mps: float
    measurement_std_m: float


STILL: Final[MotionModel] = MotionModel(
    accel_std_mps2=0.05, initial_speed_std_mps=0.05, measurement_std_m=0.15
)
FREE: Final[MotionModel] = MotionModel(accel_std_mps2=2.0, initial_speed_std_mps=1.0, measurement_std_m=0.12)
MOTION_MODELS: Final[dict[str, MotionModel]] = {
    name: (STILL if name in FURNITURE_CLASSES else FREE) for name in CLASS_NAMES
}
"""Furniture is still (it moves only when someone moves it, and then the gate still holds); people walk."""


@dataclass(frozen=True)
class TrackerConfig:
    gate_m: float = 0.8
    class_penalty_m: float = 0.3
    # A person track that missed its last scan pays this much more for a detection than one that did
    # not: of two tracks that could take it, the one that followed its person a scan ago is the
    # likelier owner (DeepSORT's matching cascade, softened to a cost). Without it, a person who
    # turned back to where a coasting track of theirs had stopped was taken by that track from the
    # one following them, and back (measured: bench.tracking, docs/tracking.md). 0: off.
    person_coast_penalty_m: float = 0.05
    confirm_hits: int = 3
    # People are confirmed sooner: a passer-by is often seen for a second or two, and each scan of a
    # person's tentative track is a person missed, while furniture is seen for long and a false chair
    # confirmed stays. One person's second box of a scan opens no track of its own (_one_per_person),
    # so two hits confirm no such duplicate (measured: bench.tracking, docs/tracking.md).
    person_confirm_hits: int = 2
    tentative_misses: int = 2
    delete_after_s: float = 1.5
    still_delete_after_s: float = 30.0
    # A person track that misses is predicted with its velocity decaying at this time constant: people
    # stop and turn where a detector loses them, and a track that walked on at full speed would come
    # back too far off to be found again (a new track, an ID switch). In the laser frame (no odometry)
    # it also slows what the robot's own motion adds to a coasting person's track. 0: no decay.
    person_coast_decay_s: float = 0.2
    # A second detection this close to a track its scan already updated is the same object seen twice:
    # a split desk or a doorframe's two jambs lie up to about 0.6 m from the track's centre, and so do a
    # walking person's two detections, one on each leg of a long stride. Two people closer than this
    # share a track until they part: the one whose detections score lower is not updated, and if they
    # stay together past delete_after_s their track ends and takes its id back when they part
    # (person_resume_s) (measured: bench.tracking, docs/tracking.md).
    duplicate_m: float = 0.6
    jump_m: float = ODOM_JUMP_M
    jump_rad: float = ODOM_JUMP_RAD
    score_smoothing: float = 0.3  # weight of the newest detection's score in the track's running score
    # A person track is confirmed only once it has also moved this far (0: never asked), leg_tracker's
    # rule for starting a person (its dist_travelled_together_to_initiate_leg_pair, 0.5 m): a still
    # cluster of points that looks like legs is more often a table leg or a broken-up wall than a
    # person, at the price of someone who stands the whole time they are seen.
    person_confirm_travel_m: float = 0.0
    # A person track confirmed where a person track was lost a moment before takes that track's id
    # back: a detector loses people for seconds behind furniture and each other, and a new id each time
    # is an id switch for every consumer that follows someone. It takes the nearest person track last
    # hit within person_resume_s before the new track's first detection, whose last filtered position
    # is no farther from the new track's start than gate_m plus person_resume_speed_mps for every
    # second between. 0: off.
    person_resume_s: float = 15.0
    person_resume_speed_mps: float = 1.5  # a brisk walk: the simulator's people walk up to 1.6 m/s
    # A coasting person track is left out of the message this long after its last hit, though kept to
    # be found again until delete_after_s: a person unseen for a second has walked on, and their track
    # standing where they were lost was a false person to every consumer (on the fresh worlds of
    # docs/tracking.md, most of the people's false positives were such tracks).
    person_show_coast_s: float = 0.8
    # ... and at most this share of the track's age at its last hit (from its first detection; a
    # resumed track's from its first life's): a person track followed for a few scans and lost was
    # more often a false person than one followed for seconds (on the fresh worlds of docs/tracking.md
    # most people's false positives were such short tracks, coasting). A tentative person track (one
    # hit) so leaves the message at its first miss.
    person_show_coast_share: float = 0.3

    def __post_init__(self) -> None:
        if not (self.gate_m > 0 and self.confirm_hits >= 1 and self.tentative_misses >= 1):
            raise ValueError(f"invalid tracker config: {self}")
        hits = self.person_confirm_hits
        if not (type(hits) is int and hits >= 1):  # not a bool, which the tracker's flag cannot take
            raise ValueError(f"person confirm hits must be a whole number >= 1, got {hits!r}")
        if not (self.delete_after_s > 0 and self.jump_m > 0 and self.jump_rad > 0):
            raise ValueError(f"invalid tracker config: {self}")
        if not self.person_coast_decay_s >= 0:  # NaN included
            raise ValueError(f"person coast decay must be >= 0 seconds, got {self.person_coast_decay_s:g}")
        if not self.person_show_coast_s >= 0:  # NaN included
            raise ValueError(f"person show coast must be >= 0 seconds, got {self.person_show_coast_s:g}")
        penalty = self.person_coast_penalty_m
        if not (penalty >= 0 and math.isfinite(penalty)):
            raise ValueError(f"person coast penalty must be finite and >= 0 metres, got {penalty:g}")
        if not self.person_show_coast_share >= 0:  # NaN included
            raise ValueError(f"person show coast share must be >= 0, got {self.person_show_coast_share:g}")
        travel = self.person_confirm_travel_m
        if not travel >= 0:  # NaN included
            raise ValueError(f"person confirm travel must be >= 0 metres, got {travel:g}")
        resume = (self.person_resume_s, self.person_resume_speed_mps)
        if not all(value >= 0 and math.isfinite(value) for value in resume):
            raise ValueError(
                f"person resume must be finite and >= 0 seconds and m/s, got {resume[0]:g} s and "
                f"{resume[1]:g} m/s"
            )


@dataclass
class TrackerCounters:
    """What the tracker did; published as its stats (``triscan status`` shows them)."""

    received: int = 0
    published: int = 0
    tracks_created: int = 0
    tracks_deleted: int = 0
    tracks_forgotten: int = 0
    tracks_resumed: int = 0  # new person tracks that took a lost one's id back (person_resume_s)
    tracks_merged: int = 0  # furniture tracks retired as a second track of an object (duplicate_m)
    forgotten_robots: int = 0
    duplicates: int = 0  # second detections of one object (a track's, or a person in one scan): no track
    rejected: Counter[str] = field(default_factory=Counter)  # payloads that are no detections message
    dropped: Counter[str] = field(default_factory=Counter)  # valid messages not used: out_of_order
    resets: Counter[str] = field(default_factory=Counter)  # odom_jump, odom_reset, frame_change, restart
    odom_refused: Counter[str] = field(default_factory=Counter)  # not_finite, missing

    def to_dict(self) -> dict[str, object]:
        return {
            "received": self.received,
            "published": self.published,
            "tracks_created": self.tracks_created,
            "tracks_deleted": self.tracks_deleted,
            "tracks_forgotten": self.tracks_forgotten,
            "tracks_resumed": self.tracks_resumed,
            "tracks_merged": self.tracks_merged,
            "forgotten_robots": self.forgotten_robots,
            "duplicates": self.duplicates,
            "rejected": dict(self.rejected),
            "dropped": dict(self.dropped),
            "resets": dict(self.resets),
            "odom_refused": dict(self.odom_refused),
        }


class _Track:
    """One track's filter state; the covariance is one 2×2 block (see the module docstring)."""

    __slots__ = (
        "class_id",
        "class_scores",
        "first_stamp_ns",
        "hits",
        "last_hit_ns",
        "misses",
        "model",
        "moved_m",
        "origin",
        "p_pp",
        "p_pv",
        "p_vv",
        "retired",
        "score",
        "state",
        "track_id",
        "vx",
        "vy",
        "x",
        "y",
    )

    def __init__(self, track_id: int, x: float, y: float, det: Detection, stamp_ns: int, model: MotionModel):
        self.track_id = track_id
        self.x, self.y, self.vx, self.vy = x, y, 0.0, 0.0
        self.origin, self.moved_m = (x, y), 0.0  # the farthest the filtered position got from its start
        self.model = model
        self.p_pp = model.measurement_std_m**2
        self.p_pv = 0.0
        self.p_vv = model.initial_speed_std_mps**2
        self.class_scores = [0.0] * len(CLASS_NAMES)
        self.class_id = 0
        self._add_score(det)
        self.score = det.score
        self.hits, self.misses = 1, 0
        self.first_stamp_ns = self.last_hit_ns = stamp_ns
        self.state: TrackState = "tentative"
        # A new track took this one's id (``person_resume_s``), or an older one follows its object
        # (``_merge_furniture``): gone after this scan.
        self.retired = False

    def _add_score(self, det: Detection) -> None:
        """Sum the detection's score into its class's and keep ``class_id``, the class with the most."""
        scores = self.class_scores
        scores[det.class_id] += det.score
        self.class_id = max(range(len(scores)), key=scores.__getitem__)

    def use(self, model: MotionModel) -> None:
        """Follow ``model`` from now on. A track whose class turned from a person into furniture, or
        back, starts its velocity afresh from the new model's prior: what it learnt under the other
        model is wrong for this one (a box first seen as a person would otherwise drift on at a
        walker's speed, as furniture barely corrects its velocity)."""
        if model is self.model:
            return
        self.model = model
        self.vx = self.vy = 0.0
        self.p_pv = 0.0
        self.p_vv = model.initial_speed_std_mps**2

    def predict(self, dt: float, model: MotionModel) -> None:
        if dt <= 0.0:
            return
        q = model.accel_std_mps2**2
        self.x += self.vx * dt
        self.y += self.vy * dt
        dt2 = dt * dt
        self.p_pp += 2.0 * dt * self.p_pv + dt2 * self.p_vv + q * dt2 * dt2 / 4.0
        self.p_pv += dt * self.p_vv + q * dt2 * dt / 2.0
        self.p_vv += q * dt2

    def update(
        self, x: float, y: float, det: Detection, stamp_ns: int, model: MotionModel, smooth: float
    ) -> None:
        s = self.p_pp + model.measurement_std_m**2
        k_p, k_v = self.p_pp / s, self.p_pv / s
        rx, ry = x - self.x, y - self.y
        self.x += k_p * rx
        self.y += k_p * ry
        self.vx += k_v * rx
        self.vy += k_v * ry
        self.moved_m = max(self.moved_m, math.hypot(self.x - self.origin[0], self.y - self.origin[1]))
        self.p_vv -= k_v * self.p_pv
        self.p_pv *= 1.0 - k_p
        self.p_pp *= 1.0 - k_p
        self._add_score(det)
        self.score += smooth * (det.score - self.score)
        self.hits += 1
        self.misses = 0
        self.last_hit_ns = stamp_ns


@dataclass
class _Robot:
    tracks: list[_Track] = field(default_factory=list)
    ended: list[_Track] = field(default_factory=list)  # confirmed person tracks that ended lately
    seq: int = -1
    scan_stamp_ns: int = -1
    frame: TrackFrame = "laser"
    odom: Odometry | None = None  # the last good pose
    poses: OrderedDict[int, Odometry] = field(default_factory=OrderedDict)  # the last scans' by stamp
    last_seen_s: float = 0.0


class TrackerCore:
    """Detections in, :class:`~common.messages.Tracks` out; see the module docstring.

    :meth:`handle_sample`, :meth:`forget_silent` and :meth:`snapshot` may be called from several
    threads (Zenoh callbacks, housekeeping); :meth:`update` holds the same lock.
    """

    def __init__(
        self,
        config: TrackerConfig | None = None,
        *,
        first_track_id: int = 1,
        forget_after_s: float = DEFAULT_FORGET_AFTER_S,
        max_robots: int = DEFAULT_MAX_ROBOTS,
        clock: Callable[[], float] = time.monotonic,
        wall_clock_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        self.config = config or TrackerConfig()
        self.forget_after_s = forget_after_s
        self.max_robots = max_robots
        self.clock = clock
        self.wall_clock_ns = wall_clock_ns
        self.counters = TrackerCounters()
        self._next_id = first_track_id
        self._robots: dict[str, _Robot] = {}
        self._lock = threading.RLock()

    @property
    def robot_ids(self) -> list[str]:
        return list(self._robots)

    def snapshot(self) -> dict[str, object]:
        with self._lock:
            live = [t for r in self._robots.values() for t in r.tracks]
            return {
                **self.counters.to_dict(),
                "robots": len(self._robots),
                "tracks": len(live),
                "confirmed": sum(t.state != "tentative" for t in live),
            }

    def handle_sample(self, key: str, payload: bytes) -> Tracks | None:
        """One Zenoh sample on a detections key: the key names the robot, the payload must agree."""
        with self._lock:
            self.counters.received += 1
            try:
                robot_id, _ = parse_key(key)
            except ValueError as exc:
                return self._reject("bad_key", str(exc))
            try:
                message = decode_message(payload, Detections)
            except MessageError as exc:
                return self._reject(exc.reason, str(exc))
            if message.robot_id != robot_id:
                return self._reject(
                    "robot_id_mismatch", f"key says {robot_id!r}, payload {message.robot_id!r}"
                )
            return self._update(message)

    def update(self, message: Detections) -> Tracks | None:
        """One decoded detections message → that robot's tracks, or None if it was dropped (counted)."""
        with self._lock:
            self.counters.received += 1
            return self._update(message)

    def forget_silent(self) -> list[str]:
        """Drop robots (and their tracks) silent for longer than ``forget_after_s``; returns their ids."""
        with self._lock:
            now = self.clock()
            silent = [rid for rid, r in self._robots.items() if now - r.last_seen_s > self.forget_after_s]
            for robot_id in silent:
                self.counters.tracks_forgotten += len(self._robots.pop(robot_id).tracks)
                log.info("robot %s silent for %.0f s: its tracks forgotten", robot_id, self.forget_after_s)
            self.counters.forgotten_robots += len(silent)
            return silent

    def _reject(self, reason: str, detail: str) -> Tracks | None:
        """Count and log a refused payload; returns None, what the caller returns for it."""
        self.counters.rejected[reason] += 1
        log.warning("detections rejected (%s): %s", reason, detail)
        return None

    def _reset(self, robot: _Robot, robot_id: str, reason: str) -> None:
        self.counters.resets[reason] += 1
        self.counters.tracks_deleted += len(robot.tracks)
        log.info("%s: tracks reset (%s)", robot_id, reason)
        robot.tracks = []
        robot.ended = []  # their places are in the old frame
        robot.poses.clear()  # poses of the old odometry frame place nothing in the new one

    def _robot_of(self, robot_id: str) -> _Robot | None:
        robot = self._robots.get(robot_id)
        if robot is None:
            if len(self._robots) >= self.max_robots:
                self.forget_silent()
            if len(self._robots) >= self.max_robots:
                self._reject("too_many_robots", f"{robot_id}: already tracking {self.max_robots} robots")
                return None
            robot = self._robots[robot_id] = _Robot()
        return robot

    def _pose_for(self, robot: _Robot, robot_id: str, odom: Odometry | None) -> Odometry | None:
        """The pose this message's detections are placed with (None: laser frame), resetting on a jump."""
        if odom is not None and not odom.finite:
            self.counters.odom_refused["not_finite"] += 1
            odom = None
        elif odom is None and robot.frame == "odom":
            self.counters.odom_refused["missing"] += 1
        if odom is None:
            return robot.odom if robot.frame == "odom" else None
        last = robot.odom
        if robot.frame == "laser":
            if robot.tracks or robot.ended:
                self._reset(robot, robot_id, "frame_change")
        elif last is not None and (broken := odom.break_from(last, self.config.jump_m, self.config.jump_rad)):
            self._reset(robot, robot_id, broken)
        robot.frame = "odom"
        robot.odom = odom
        return odom

    def _update(self, message: Detections) -> Tracks | None:
        robot_id = message.robot_id
        robot = self._robot_of(robot_id)
        if robot is None:
            return None
        stamp = message.scan_stamp_ns
        if robot.scan_stamp_ns >= 0:
            if stamp <= robot.scan_stamp_ns:
                self.counters.dropped["out_of_order"] += 1
                log.debug(
                    "%s: detections of seq %d not newer than seq %d: dropped",
                    robot_id,
                    message.seq,
                    robot.seq,
                )
                return None
            if message.seq <= robot.seq:
                self._reset(robot, robot_id, "restart")
        dt = (stamp - robot.scan_stamp_ns) / _NS_PER_S if robot.scan_stamp_ns >= 0 else 0.0
        robot.seq, robot.scan_stamp_ns, robot.last_seen_s = message.seq, stamp, self.clock()
        pose = self._pose_for(robot, robot_id, message.odom)
        laser = pose is None
        models = [FREE if laser else MOTION_MODELS[CLASS_NAMES[t.class_id]] for t in robot.tracks]
        decay = self.config.person_coast_decay_s
        for track, model in zip(robot.tracks, models, strict=True):
            track.use(model)
            if decay > 0.0 and track.misses and track.class_id == PERSON_ID:
                keep = math.exp(-dt / decay)
                track.vx, track.vy = track.vx * keep, track.vy * keep
            track.predict(dt, model)
        if pose is not None and pose is message.odom:  # a stand-in pose is no pose of this scan
            robot.poses[stamp] = pose
            while len(robot.poses) > POSES_KEPT:
                robot.poses.popitem(last=False)
        # The boxes are the middle scan's, so they are placed with its pose (see _middle_pose).
        placing = pose if message.pose_stamp_ns is None or pose is None else self._middle_pose(robot, message)
        if pose is not None and placing is None:
            self.counters.dropped["unplaced"] += 1
            self.counters.published += 1
            return self._message(message, robot, pose)  # nothing updated: no track misses this scan
        detections = self._one_per_person(message.detections)
        points = self._placed(detections, placing)
        matches, unmatched = self._assign(robot.tracks, detections, points)
        smooth = self.config.score_smoothing
        for ti, di in matches:
            track, det = robot.tracks[ti], detections[di]
            track.update(points[di][0], points[di][1], det, stamp, models[ti], smooth)
            if track.state != "tentative":
                track.state = "confirmed"
            elif self._confirms(track):
                self._confirm(robot, track, robot.tracks)
        matched = {ti for ti, _ in matches}
        resume_ns = self.config.person_resume_s * _NS_PER_S
        robot.ended = [e for e in robot.ended if stamp - e.last_hit_ns <= resume_ns]
        kept: list[_Track] = []
        for ti, track in enumerate(robot.tracks):
            if ti not in matched:
                track.misses += 1
                if track.state == "confirmed":
                    track.state = "coasting"
            if track.retired or self._alive(track, stamp, models[ti] is STILL):
                kept.append(track)  # a retired track leaves below, with those retired by new tracks
            else:
                self.counters.tracks_deleted += 1
                if resume_ns > 0 and track.state != "tentative" and track.class_id == PERSON_ID:
                    robot.ended.append(track)
        for di in unmatched:
            det = detections[di]
            if self._duplicate(points[di], det, kept):
                self.counters.duplicates += 1
                continue
            model = FREE if laser else MOTION_MODELS[det.class_name]
            kept.append(_Track(self._next_id, points[di][0], points[di][1], det, stamp, model))
            self._next_id += 1
            self.counters.tracks_created += 1
            if self._confirms(kept[-1]):
                self._confirm(robot, kept[-1], kept)  # the tracks deleted this scan are in robot.ended
        if not laser:
            self._merge_furniture(kept)
        retired = [t for t in kept if t.retired]
        if retired:
            kept = [t for t in kept if not t.retired]
            self.counters.tracks_deleted += len(retired)
        if len(kept) > MAX_TRACKS:  # only a flood of detections gets here: keep the established tracks
            kept.sort(key=lambda t: (t.state == "tentative", -t.hits))
            self.counters.tracks_deleted += len(kept) - MAX_TRACKS
            del kept[MAX_TRACKS:]
        robot.tracks = kept
        self.counters.published += 1
        return self._message(message, robot, pose)

    def _one_per_person(self, detections: list[Detection]) -> list[Detection]:
        """``detections`` less each person detection closer than ``duplicate_m`` to a higher-scoring
        one (the earlier of two equal ones), in their order: one person seen twice. A second box of one
        person, left in, opens a track beside the person's, and the two take turns at the person's
        detections until one of them carries on under the other's id; before assignment, the
        person's track is also updated by the better of the two boxes. Distances are in the laser
        frame, which the odometry frame only turns and shifts."""
        people = [i for i, d in enumerate(detections) if d.class_id == PERSON_ID]
        if len(people) < 2:
            return detections
        limit = self.config.duplicate_m
        kept: list[Detection] = []
        chosen: set[int] = set()
        for i in sorted(people, key=lambda i: -detections[i].score):  # stable: ties keep their order
            det = detections[i]
            if all(math.hypot(k.x_m - det.x_m, k.y_m - det.y_m) >= limit for k in kept):
                kept.append(det)
                chosen.add(i)
        if len(chosen) == len(people):
            return detections
        self.counters.duplicates += len(people) - len(chosen)
        return [d for i, d in enumerate(detections) if d.class_id != PERSON_ID or i in chosen]

    def _confirm(self, robot: _Robot, track: _Track, live: list[_Track]) -> None:
        """Confirm a tentative track. A person takes back the id of the nearest person track lost a
        moment before (``person_resume_s``): one that ended, which leaves the robot's list of ended
        tracks, or one still coasting, which is retired: a track that coasted away from where its
        person was found again would otherwise stand beside the new one. A track hit in the scan of
        the new track's first detection, or later, was seen beside it: someone else. ``live`` holds
        the tracks that may still be coasting."""
        track.state = "confirmed"
        resume_s = self.config.person_resume_s
        if resume_s <= 0 or track.class_id != PERSON_ID:
            return
        coasting = [t for t in live if t.state == "coasting" and not t.retired and t.class_id == PERSON_ID]
        best: tuple[float, _Track] | None = None
        for lost in (*robot.ended, *coasting):
            gap_s = (track.first_stamp_ns - lost.last_hit_ns) / _NS_PER_S
            if not 0 < gap_s <= resume_s:
                continue
            distance = math.hypot(track.origin[0] - lost.x, track.origin[1] - lost.y)
            reach = self.config.gate_m + self.config.person_resume_speed_mps * gap_s
            if distance <= reach and (best is None or distance < best[0]):
                best = (distance, lost)
        if best is None:
            return
        lost = best[1]
        if lost in robot.ended:  # by identity: a track is no value
            robot.ended.remove(lost)
        else:
            lost.retired = True
        track.track_id, track.first_stamp_ns = lost.track_id, lost.first_stamp_ns
        self.counters.tracks_resumed += 1

    def _merge_furniture(self, tracks: list[_Track]) -> None:
        """Retire the younger of two established tracks of one furniture class closer than
        ``duplicate_m``: one object followed twice (a big desk seen in part from close by, where each
        part's box has its own centre, starts a second track before the first is confirmed, and the
        duplicate rule guards only against confirmed ones). The older keeps its id; a consumer that
        counts chairs sees one chair. Only in the odometry frame, where furniture stands still: in the
        laser frame every track moves with the robot, and there the rule cost the real recordings
        person tracks (a detection the retired track would have taken opened a new one)."""
        established = sorted(
            (
                t
                for t in tracks
                if t.state != "tentative" and not t.retired and CLASS_NAMES[t.class_id] in FURNITURE_CLASSES
            ),
            key=lambda t: (t.first_stamp_ns, t.track_id),
        )
        if len(established) < 2:
            return
        # Every pair is looked at, oldest first, but only the close ones in Python: a room's worth of
        # furniture is a few hundred pairs a scan, nearly all far apart. The margin leaves the exact
        # comparison to math.hypot below.
        xy = np.array([(t.x, t.y) for t in established])
        apart = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
        near = apart < self.config.duplicate_m + 1e-6
        for i, j in zip(*np.nonzero(np.triu(near, 1)), strict=True):  # row by row: older i first
            older, younger = established[i], established[j]
            if (
                not older.retired
                and not younger.retired
                and younger.class_id == older.class_id
                and math.hypot(younger.x - older.x, younger.y - older.y) < self.config.duplicate_m
            ):
                younger.retired = True
                self.counters.tracks_merged += 1

    def _confirms(self, track: _Track) -> bool:
        """Whether a tentative track has earned confirmation: enough hits, and a person enough travel."""
        if track.class_id != PERSON_ID:
            return track.hits >= self.config.confirm_hits
        travel = self.config.person_confirm_travel_m
        return track.hits >= self.config.person_confirm_hits and (travel <= 0.0 or track.moved_m >= travel)

    def _duplicate(self, point: tuple[float, float], det: Detection, tracks: list[_Track]) -> bool:
        """A second detection of an object a track already follows: within ``duplicate_m`` of a
        confirmed track of the same group (furniture or person) that a detection of this scan updated."""
        person = det.class_id == PERSON_ID
        return any(
            t.state == "confirmed"
            and t.misses == 0
            and (t.class_id == PERSON_ID) == person
            and math.hypot(t.x - point[0], t.y - point[1]) < self.config.duplicate_m
            for t in tracks
        )

    def _alive(self, track: _Track, stamp_ns: int, still: bool) -> bool:
        if track.state == "tentative":
            return track.misses < self.config.tentative_misses
        timeout = self.config.still_delete_after_s if still else self.config.delete_after_s
        return (stamp_ns - track.last_hit_ns) / _NS_PER_S <= timeout

    @staticmethod
    def _middle_pose(robot: _Robot, message: Detections) -> Odometry | None:
        """The robot's pose at the middle scan, where the boxes were seen: the pose of that scan when
        its detections came, else interpolated between the poses of the scans around it (the
        detector skipped a tensor); None when no pose is known from before it (the first message
        after a reset or a start), since the newest scan's pose would misplace every box by what the
        robot moved in one scan, in a fast turn enough to start a second track on one desk
        (docs/tracking.md, "Placement")."""
        middle = message.pose_stamp_ns
        assert middle is not None
        known = robot.poses.get(middle)
        if known is not None:
            return known
        before = max((t for t in robot.poses if t < middle), default=None)
        after = min((t for t in robot.poses if t > middle), default=None)
        if before is None or after is None:
            return None
        a, b = robot.poses[before], robot.poses[after]
        f = (middle - before) / (after - before)
        turn = wrap_angle(b.yaw_rad - a.yaw_rad)
        return Odometry(
            x_m=a.x_m + f * (b.x_m - a.x_m),
            y_m=a.y_m + f * (b.y_m - a.y_m),
            yaw_rad=a.yaw_rad + f * turn,
            frame_id=b.frame_id,
            stamp_ns=middle,
        )

    @staticmethod
    def _placed(detections: list[Detection], pose: Odometry | None) -> list[tuple[float, float]]:
        if pose is None:
            return [(d.x_m, d.y_m) for d in detections]
        c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
        return [(pose.x_m + c * d.x_m - s * d.y_m, pose.y_m + s * d.x_m + c * d.y_m) for d in detections]

    def _assign(
        self, tracks: list[_Track], detections: list[Detection], points: list[tuple[float, float]]
    ) -> tuple[list[tuple[int, int]], list[int]]:
        if not tracks or not detections:
            return [], list(range(len(detections)))
        predicted = np.array([(t.x, t.y) for t in tracks])
        measured = np.array(points)
        distance = np.hypot(
            predicted[:, None, 0] - measured[None, :, 0], predicted[:, None, 1] - measured[None, :, 1]
        )
        track_class = np.array([t.class_id for t in tracks])
        det_class = np.array([d.class_id for d in detections])
        cost = distance + self.config.class_penalty_m * (track_class[:, None] != det_class[None, :])
        if self.config.person_coast_penalty_m:
            lost = np.array([t.misses > 0 for t in tracks]) & (track_class == PERSON_ID)
            cost += self.config.person_coast_penalty_m * lost[:, None]
        gated = distance > self.config.gate_m
        cost[gated] = 1e6  # never chosen over leaving both unmatched, filtered below
        rows, cols = linear_sum_assignment(cost)
        matches = [(int(r), int(c)) for r, c in zip(rows, cols, strict=True) if not gated[r, c]]
        taken = {c for _, c in matches}
        return matches, [d for d in range(len(detections)) if d not in taken]

    def _person_show_s(self, track: _Track) -> float:
        """How long a coasting person track stays in the message after its last hit: the shorter of
        ``person_show_coast_s`` and ``person_show_coast_share`` of its age at that hit."""
        seen_s = (track.last_hit_ns - track.first_stamp_ns) / _NS_PER_S
        return min(self.config.person_show_coast_s, self.config.person_show_coast_share * seen_s)

    def _message(self, message: Detections, robot: _Robot, pose: Odometry | None) -> Tracks:
        if pose is None:
            c, s, ox, oy = 1.0, 0.0, 0.0, 0.0
        else:
            c, s, ox, oy = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad), pose.x_m, pose.y_m
        stamp = message.scan_stamp_ns
        tracks = []
        for t in robot.tracks:
            since_hit_s = (stamp - t.last_hit_ns) / _NS_PER_S
            if since_hit_s > self.config.delete_after_s:
                continue  # dormant: still furniture kept to take its id back when seen again, not shown
            if t.class_id == PERSON_ID and since_hit_s > self._person_show_s(t):
                continue
            dx, dy = t.x - ox, t.y - oy
            class_id = t.class_id
            tracks.append(
                Track(
                    track_id=t.track_id,
                    class_id=class_id,
                    class_name=CLASS_NAMES[class_id],
                    score=min(1.0, max(0.0, t.score)),
                    x_m=c * dx + s * dy,
                    y_m=-s * dx + c * dy,
                    odom_x_m=None if pose is None else t.x,
                    odom_y_m=None if pose is None else t.y,
                    vx_mps=t.vx,
                    vy_mps=t.vy,
                    age_s=(stamp - t.first_stamp_ns) / _NS_PER_S,
                    hits=t.hits,
                    misses=t.misses,
                    state=t.state,
                )
            )
        return Tracks(
            robot_id=message.robot_id,
            seq=message.seq,
            stamp_ns=self.wall_clock_ns(),
            scan_stamp_ns=stamp,
            frame="laser" if pose is None else "odom",
            tracks=tracks,
        )
