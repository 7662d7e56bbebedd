"""The encoder's pure core: one three-scan FIFO per robot, and the rules for broken streams.

A tensor must show three consecutive scans of one sensor, or the network sees motion that never
happened. So, per robot (robots never share a FIFO):

* **First two scans** of a stream: rasterised and held, no tensor yet (Algorithm 1 needs three).
* **Next scan** (``seq == last + 1``): pushed; a tensor of the last three goes out.
* **Gap** (``seq > last + 1``, scans were lost): the FIFO restarts from this scan, so no tensor ever
  spans the hole; the next tensor comes two scans later.
* **Out of order or duplicate** (``seq <= last`` with a stamp no newer than the last one): dropped and
  counted; Zenoh over TCP keeps order, so this is a misbehaving publisher or a replay.
* **Publisher restart** (``seq <= last`` with a newer stamp: the simulator or driver came back and
  counts from 0 again): the FIFO restarts, so old and new frames never mix in one tensor.
* **Clock jump** (a later ``seq`` with an older stamp): the FIFO restarts too, so the stamps inside a
  tensor never run backwards.
* **Odometry**: a scan's ``odom`` (the robot's pose) goes into the tensor of which it is the newest
  scan; a non-finite pose is refused and counted (``odom_not_finite``) and the scan goes on without
  it, so a diverged odometry filter never costs a detection.
* **Odometry jump** (the pose moved more than :data:`common.messages.ODOM_JUMP_M` or turned more
  than :data:`common.messages.ODOM_JUMP_RAD` since the last stacked scan's, or its frame changed: a
  relocalisation, a robot carried off, a simulated robot put into a new world): the FIFO restarts
  (``odom_jumps``), since scans on both sides show two places, not one motion, and the network reads
  them as things that moved.
* **Silence**: a robot not heard from for ``forget_after_s`` is forgotten (its FIFO freed), so a fleet
  that changes over time does not leak memory; if it speaks again it starts a fresh stream.
* **Stacking period**: a model is trained on scans a set time apart (``stack_period_s``, from its
  metadata), since how far things move between the stacked scans is the cue it reads. From a faster
  sensor only every k-th scan is stacked, k = round(period / the sensor's measured scan interval)
  (every 4th of a 40 Hz sensor for a 0.1 s model, which also cuts its cost by 4), and "consecutive"
  above means consecutive among those; a slower sensor is stacked as it comes, and that is logged once.
* **Raster yaw**: a model may see its scans turned (``raster_yaw_deg``, from its metadata;
  :mod:`common.encoding`); every tensor is encoded with it and says so, so a detector whose model has
  another yaw refuses it.
"""

from __future__ import annotations

import logging
import statistics
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

from common.encoding import InvalidRule, Padding, ReadsScans, ScanError, ScanStacker
from common.keys import parse_key
from common.messages import LIT_PIXELS_VERSION, MessageError, Odometry, Scan, StackedTensor, decode_message

log = logging.getLogger(__name__)

DEFAULT_FORGET_AFTER_S = 10.0
DEFAULT_MAX_ROBOTS = 1024  # bounds memory: ~200 kB of FIFO per robot


@dataclass
class EncoderCounters:
    """What the encoder did with every payload it received; published as its stats."""

    received: int = 0
    published: int = 0
    warming_up: int = 0  # scans held without a tensor: the first two of a stream
    gaps: int = 0
    restarts: int = 0
    between_stacked: int = 0  # scans of a faster sensor left out to stack at the model's period
    forgotten_robots: int = 0
    odom_not_finite: int = 0
    odom_jumps: int = 0
    rejected: Counter[str] = field(default_factory=Counter)  # reason → count

    def to_dict(self) -> dict[str, object]:
        return {
            "received": self.received,
            "published": self.published,
            "warming_up": self.warming_up,
            "gaps": self.gaps,
            "restarts": self.restarts,
            "between_stacked": self.between_stacked,
            "forgotten_robots": self.forgotten_robots,
            "odom_not_finite": self.odom_not_finite,
            "odom_jumps": self.odom_jumps,
            "rejected": dict(self.rejected),
        }


class StacksScans(ReadsScans, Protocol):
    """A model's reading of scans and the period it stacks them at (:class:`common.inference.OnnxDetector`,
    :class:`common.model_meta.ModelFacts`)."""

    @property
    def stack_period_s(self) -> float | None: ...


INTERVALS_KEPT = 9  # scan intervals the sensor's period is measured over (their median)


@dataclass
class _Stream:
    stacker: ScanStacker
    seqs: list[int] = field(default_factory=list)  # of the scans in the FIFO, oldest first
    stamps_ns: list[int] = field(default_factory=list)
    last_seen_s: float = 0.0
    last_stamp_ns: int | None = None  # of the last scan received, stacked or not
    intervals_ns: deque[int] = field(default_factory=lambda: deque(maxlen=INTERVALS_KEPT))
    slow_sensor_logged: bool = False
    odom: Odometry | None = None  # the pose of the last stacked scan, if it had a finite one

    def restart(self) -> None:
        self.stacker.reset()
        self.seqs.clear()
        self.stamps_ns.clear()
        self.odom = None

    def stride(self, stamp_ns: int, period_s: float | None) -> int:
        """Every how many scans of this robot's sensor to stack, learning its interval from ``stamp_ns``."""
        if self.last_stamp_ns is not None and stamp_ns > self.last_stamp_ns:
            self.intervals_ns.append(stamp_ns - self.last_stamp_ns)
        self.last_stamp_ns = stamp_ns
        if period_s is None or not self.intervals_ns:
            return 1
        interval_s = statistics.median(self.intervals_ns) / 1e9
        return max(1, round(period_s / interval_s))


class EncoderCore:
    """Scans in, stacked tensors out; see the module docstring for the stream rules.

    :meth:`handle_sample`, :meth:`handle_payload`, :meth:`forget_silent` and :meth:`snapshot` may be
    called from several threads (Zenoh callbacks, the service's housekeeping); :meth:`push` is for one.
    """

    def __init__(
        self,
        padding: Padding = "zero",
        *,
        invalid: InvalidRule = "sentinel",
        forget_after_s: float = DEFAULT_FORGET_AFTER_S,
        max_robots: int = DEFAULT_MAX_ROBOTS,
        clock: Callable[[], float] = time.monotonic,
        stack_period_s: float | None = None,
        raster_yaw_deg: float = 0.0,
    ) -> None:
        # Validates the names and the yaw early, with the encoder's own message.
        self.raster_yaw_deg = ScanStacker(padding, invalid, raster_yaw_deg).raster_yaw_deg
        if stack_period_s is not None and not stack_period_s > 0.0:
            raise ValueError(f"stack_period_s must be positive or None, got {stack_period_s}")
        self.padding: Padding = padding
        self.invalid: InvalidRule = invalid
        self.stack_period_s = stack_period_s  # None: stack consecutive scans, whatever their rate
        self.forget_after_s = forget_after_s
        self.max_robots = max_robots
        self.clock = clock
        self.counters = EncoderCounters()
        self._streams: dict[str, _Stream] = {}
        self._lock = threading.RLock()

    @classmethod
    def for_model(cls, model: StacksScans, **settings: Any) -> EncoderCore:
        """An encoder whose tensors ``model`` reads as it was trained: its padding, invalid rule, raster
        yaw and stacking period; ``settings`` are the other keyword arguments."""
        return cls(
            model.padding,
            invalid=model.invalid,
            stack_period_s=model.stack_period_s,
            raster_yaw_deg=model.raster_yaw_deg,
            **settings,
        )

    @property
    def robot_ids(self) -> list[str]:
        return list(self._streams)

    def handle_sample(self, key: str, payload: bytes) -> StackedTensor | None:
        """One Zenoh sample on a scan key: the key names the robot, the payload must agree."""
        with self._lock:
            try:
                robot_id, _ = parse_key(key)
            except ValueError as exc:
                self.counters.received += 1
                self._reject("bad_key", str(exc))
                return None
            return self.handle_payload(payload, robot_id)

    def snapshot(self) -> dict[str, object]:
        """The counters and the number of robots tracked, for the service's stats."""
        with self._lock:
            return {**self.counters.to_dict(), "robots": len(self._streams)}

    def handle_payload(self, payload: bytes, key_robot_id: str | None = None) -> StackedTensor | None:
        """Decode and push one wire payload; a bad one is logged, counted by reason and dropped.

        ``key_robot_id`` is the robot named by the key it arrived on: a scan claiming another robot
        is refused, so one publisher cannot feed (or poison) another robot's FIFO. Thread-safe.
        """
        with self._lock:
            self.counters.received += 1
            try:
                scan = decode_message(payload, Scan)
            except MessageError as exc:
                self._reject(exc.reason, str(exc))
                return None
            if key_robot_id is not None and scan.robot_id != key_robot_id:
                self._reject(
                    "robot_id_mismatch", f"key says {key_robot_id!r}, payload says {scan.robot_id!r}"
                )
                return None
            return self._push(scan)

    def push(self, scan: Scan) -> StackedTensor | None:
        """Push an already-decoded scan (the ``--from-scans`` detector and tests call this)."""
        self.counters.received += 1
        return self._push(scan)

    def forget_silent(self) -> list[str]:
        """Drop the FIFOs of robots silent for longer than ``forget_after_s``; returns their ids."""
        with self._lock:
            now = self.clock()
            silent = [rid for rid, s in self._streams.items() if now - s.last_seen_s > self.forget_after_s]
            for robot_id in silent:
                del self._streams[robot_id]
                log.info("robot %s silent for %.0f s: forgotten", robot_id, self.forget_after_s)
            self.counters.forgotten_robots += len(silent)
            return silent

    def _log_slow_sensor(self, stream: _Stream, robot_id: str) -> None:
        """Say once per robot that its sensor scans slower than the model's trained period."""
        if self.stack_period_s is None or stream.slow_sensor_logged or len(stream.intervals_ns) < 3:
            return
        interval_s = statistics.median(stream.intervals_ns) / 1e9
        if interval_s > 1.25 * self.stack_period_s:
            stream.slow_sensor_logged = True
            log.warning(
                "%s scans every %.0f ms, the model was trained on scans %.0f ms apart: stacking them as "
                "they come (expect lower recall on moving things)",
                robot_id,
                interval_s * 1e3,
                self.stack_period_s * 1e3,
            )

    def _reject(self, reason: str, detail: str) -> None:
        self.counters.rejected[reason] += 1
        log.warning("scan rejected (%s): %s", reason, detail)

    def _stream_of(self, robot_id: str) -> _Stream | None:
        stream = self._streams.get(robot_id)
        if stream is None:
            if len(self._streams) >= self.max_robots:
                self.forget_silent()
            if len(self._streams) >= self.max_robots:
                self._reject("too_many_robots", f"{robot_id}: already tracking {self.max_robots} robots")
                return None
            stream = self._streams[robot_id] = _Stream(
                ScanStacker(self.padding, self.invalid, self.raster_yaw_deg)
            )
        return stream

    def _push(self, scan: Scan) -> StackedTensor | None:
        started = time.perf_counter_ns()
        stream = self._stream_of(scan.robot_id)
        if stream is None:
            return None
        if stream.seqs:
            last_seq, last_stamp = stream.seqs[-1], stream.stamps_ns[-1]
            if scan.seq <= last_seq and scan.stamp_ns <= last_stamp:
                self._reject("out_of_order", f"{scan.robot_id}: seq {scan.seq} after {last_seq}")
                return None
            if scan.seq <= last_seq:
                self.counters.restarts += 1
                log.info(
                    "%s: seq %d after %d with a newer stamp: publisher restarted",
                    scan.robot_id,
                    scan.seq,
                    last_seq,
                )
                stream.restart()
            elif scan.stamp_ns < last_stamp:
                # The next seq with an older stamp: the sender's clock jumped back. Frames on both
                # sides of the jump are not one motion; start over rather than mix them.
                self.counters.restarts += 1
                log.info(
                    "%s: seq %d stamped before seq %d: clock jumped, FIFO restarted",
                    scan.robot_id,
                    scan.seq,
                    last_seq,
                )
                stream.restart()
        stride = stream.stride(scan.stamp_ns, self.stack_period_s)
        if stream.seqs:
            last_seq = stream.seqs[-1]
            if last_seq < scan.seq < last_seq + stride:
                self.counters.between_stacked += 1
                stream.last_seen_s = self.clock()
                return None
            if scan.seq > last_seq + stride:
                self.counters.gaps += 1
                log.debug("%s: gap, seq %d after %d: FIFO restarted", scan.robot_id, scan.seq, last_seq)
                stream.restart()
        odom = scan.odom
        if odom is not None and not odom.finite:
            self.counters.odom_not_finite += 1
            log.warning("%s seq %d: non-finite odometry refused, scan kept", scan.robot_id, scan.seq)
            odom = None
        if odom is not None and stream.odom is not None and stream.seqs:
            broken = odom.break_from(stream.odom)
            if broken is not None:
                self.counters.odom_jumps += 1
                log.info("%s seq %d: %s, FIFO restarted", scan.robot_id, scan.seq, broken.replace("_", " "))
                stream.restart()
        self._log_slow_sensor(stream, scan.robot_id)
        try:
            tensor = stream.stacker.push_scan(
                scan.ranges, scan.angle_min, scan.angle_increment, scan.range_min, scan.range_max
            )
        except ScanError as exc:
            # The FIFO is unchanged, but the stream now has a hole: the next scan restarts it as a gap.
            self._reject("bad_scan", f"{scan.robot_id} seq {scan.seq}: {exc}")
            return None
        stream.last_seen_s = self.clock()
        stream.seqs = [*stream.seqs[-2:], scan.seq]
        stream.stamps_ns = [*stream.stamps_ns[-2:], scan.stamp_ns]
        stream.odom = odom  # a jump is judged between consecutive stacked scans, or not at all
        if tensor is None:
            self.counters.warming_up += 1
            return None
        self.counters.published += 1
        tensor.flags.writeable = False  # no one else holds it: the message keeps it without a copy
        return StackedTensor(
            schema_version=LIT_PIXELS_VERSION,  # travels as its lit pixels (common.messages)
            robot_id=scan.robot_id,
            seq=scan.seq,
            stamp_ns=scan.stamp_ns,
            tensor=tensor,
            padding=self.padding,
            invalid=self.invalid,
            raster_yaw_deg=self.raster_yaw_deg or None,  # absent for the paper's raster, as it always was
            scan_seqs=(stream.seqs[0], stream.seqs[1], stream.seqs[2]),
            scan_stamps_ns=(stream.stamps_ns[0], stream.stamps_ns[1], stream.stamps_ns[2]),
            encode_ms=(time.perf_counter_ns() - started) / 1e6,
            odom=odom,
        )
