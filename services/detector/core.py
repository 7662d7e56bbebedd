"""The detector's core: newest tensor per robot in, ``Detections`` out, with no network in sight.

A detector that queues frames falls further behind with every frame it cannot keep up with, and its
detections describe a world that is gone. :class:`LatestPerRobot` holds at most one pending tensor
per robot: a newer one replaces the waiting one (counted as dropped), and robots are served in turn,
so one chatty robot cannot starve the others. :class:`InferencePipeline` is the whole detector minus
Zenoh: samples go in through :meth:`InferencePipeline.handle_sample` (the Zenoh callback only
forwards), inference threads drain the mailbox, and every result leaves through a ``publish``
callback. Inference itself is :class:`common.inference.OnnxDetector`, the code ``triscan eval``
measures.
"""

from __future__ import annotations

import ctypes
import logging
import math
import os
import sys
import threading
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Generic, NamedTuple, TypeVar

import numpy as np

from common.inference import OnnxDetector
from common.keys import parse_key
from common.messages import (
    Detection,
    Detections,
    MessageError,
    Odometry,
    StackedTensor,
    StageTimings,
    decode_message,
)
from services.detector.batch_cap import check_batch
from services.encoder.core import DEFAULT_FORGET_AFTER_S, EncoderCore

log = logging.getLogger(__name__)

T = TypeVar("T")


class Arrival(NamedTuple):
    """When a tensor was accepted (``perf_counter_ns``) and how long decoding it took."""

    accepted_ns: int
    decode_ms: float


class Pending(NamedTuple):
    """A tensor waiting in the mailbox, with its arrival."""

    tensor: StackedTensor
    arrival: Arrival


DEFAULT_GATHER_MS = 10.0
"""How long a tensor may wait for other robots' to fill its batch (``--gather-ms``). A model call on
several frames costs less per frame, and on a many-core fleet server each process's lone inference
thread is what its busiest shard runs out of first; 10 ms of the 100 ms scan period lets the batches
fill (``bench.fleet_bound`` compares). A robot served alone never waits."""
GATHER_WINDOW_S = 1.0  # robots heard from this recently may send a frame a gathering worker waits for
TAKE_TIMEOUT_S = 0.5  # how often an idle inference thread looks at the stop flag
# Inference threads are named <prefix><N> in the OS (``name_os_thread``), which the benches read.
INFERENCE_THREAD_PREFIX = "inference-"


class LatestPerRobot(Generic[T]):
    """A mailbox with one slot per robot; ``take_many`` serves the robots waiting longest.

    Thread-safe: Zenoh callbacks ``put``, inference threads ``take_many`` and ``release``. A robot whose
    previous item is still being processed is not handed out again until ``release``, so with several
    inference workers one robot's detections still come out in order.
    """

    def __init__(self, gather_s: float = 0.0, clock: Callable[[], float] = time.monotonic) -> None:
        if not (gather_s >= 0 and math.isfinite(gather_s)):
            raise ValueError(f"gather_s must be a finite number >= 0, got {gather_s}")
        self.gather_s = gather_s
        self._slots: OrderedDict[str, T] = OrderedDict()
        self._put_at: dict[str, float] = {}  # when each waiting item arrived (gathering's deadline)
        self._heard_at: dict[str, float] = {}  # each robot's last put, for how many to gather
        self._busy: set[str] = set()
        self._cond = threading.Condition()
        self._closed = False
        self._gathering = False  # one worker gathers at a time: two would wait for the same items
        self._clock = clock
        self.dropped = 0

    def __len__(self) -> int:
        with self._cond:
            return len(self._slots)

    def put(self, robot_id: str, item: T) -> bool:
        """Store ``item`` as the robot's newest; True when it replaced one never taken (dropped)."""
        with self._cond:
            replaced = robot_id in self._slots
            self._slots[robot_id] = item  # keeps the robot's place in the queue if it had one
            if replaced:
                self.dropped += 1
            if not self.gather_s:
                self._cond.notify()
                return replaced
            now = self._clock()
            if not replaced:
                self._put_at[robot_id] = now
            self._heard_at[robot_id] = now
            self._cond.notify_all()  # a gathering worker waits for the batch's next item too
            return replaced

    def _first_ready(self) -> str | None:
        return next((robot_id for robot_id in self._slots if robot_id not in self._busy), None)

    def _ready(self) -> list[str]:
        """Robots with an item waiting and none being processed, longest-waiting first."""
        return [robot_id for robot_id in self._slots if robot_id not in self._busy]

    def take_many(self, limit: int, timeout: float | None = None) -> list[tuple[str, T]]:
        """Up to ``limit`` free robots' newest items, longest-waiting first; empty after ``timeout``
        or once closed.

        Waits for the first item. With :attr:`gather_s` 0 it takes whatever else is ready then, so a
        lone robot's frame is never held back and past a fleet's knee the batches fill by themselves.
        With :attr:`gather_s` > 0 it waits, at most until the oldest waiting item is that old, for as
        many items as robots it could still get (those heard from in the last
        :data:`GATHER_WINDOW_S`, up to ``limit``): one model call then serves several robots for less
        CPU per frame, and a robot alone is still served at once. A robot that has just gone silent
        still counts for that window, so takes wait the full ``gather_s`` until it drops out. One
        worker gathers at a time; the others wait until it has taken its batch. Each robot stays busy
        until :meth:`release`.
        """
        if limit < 1:
            raise ValueError(f"limit must be >= 1, got {limit}")
        with self._cond:
            self._cond.wait_for(
                lambda: self._closed or (not self._gathering and self._first_ready() is not None), timeout
            )
            if self._closed or self._gathering or self._first_ready() is None:
                return []  # closed, or the timeout passed with nothing this worker may take
            if self.gather_s:
                self._gathering = True
                try:
                    self._gather(limit, self.gather_s)
                finally:
                    self._gathering = False
                    self._cond.notify_all()  # the other workers may take what is left
                if self._closed:
                    return []
            ready = self._ready()[:limit]
            self._busy.update(ready)
            for robot_id in ready:
                self._put_at.pop(robot_id, None)  # kept only while gathering
            return [(robot_id, self._slots.pop(robot_id)) for robot_id in ready]

    def _gather(self, limit: int, gather_s: float) -> None:
        """Wait until ``limit`` items, or every robot that may still send one, are ready, or the
        oldest ready item is ``gather_s`` old (the caller holds the condition's lock; waiting
        releases it)."""
        now = self._clock()
        for robot_id in [r for r, heard in self._heard_at.items() if now - heard > GATHER_WINDOW_S]:
            del self._heard_at[robot_id]  # silent robots: no item to wait for
        target = min(limit, len(self._heard_at) - len(self._busy))
        ready = self._ready()
        if len(ready) >= target:
            return
        deadline = min(self._put_at[robot_id] for robot_id in ready) + gather_s
        self._cond.wait_for(
            lambda: self._closed or len(self._ready()) >= target, max(0.0, deadline - self._clock())
        )

    def release(self, robot_id: str) -> None:
        """The robot's last taken item is done: its next one may be taken."""
        with self._cond:
            self._busy.discard(robot_id)
            self._cond.notify_all()

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()


@dataclass
class DetectorCounters:
    """What the detector did with every tensor it received; published as its stats."""

    received: int = 0
    processed: int = 0
    inference_calls: int = 0  # processed ÷ this is the mean batch size (``--batch``)
    dropped_stale: int = 0  # replaced by a newer tensor of the same robot before inference
    # Another detector process serves the robot (services.shards): skipped before decoding, or, when
    # the robot moved while its tensor was in the model, its detections not published.
    not_ours: int = 0
    handed_over: int = 0
    rejected: Counter[str] = field(default_factory=Counter)  # reason → count

    def to_dict(self) -> dict[str, object]:
        return {
            "received": self.received,
            "processed": self.processed,
            "inference_calls": self.inference_calls,
            "dropped_stale": self.dropped_stale,
            "not_ours": self.not_ours,
            "handed_over": self.handed_over,
            "rejected": dict(self.rejected),
        }


LATENCY_WINDOW = 1000  # most frames a stats period's latency percentiles are taken over
POSE_HISTORY = 8  # newest scans' poses kept per robot: a tensor asks for its two older scans'


class DetectorCore:
    """Decodes tensor payloads and turns one tensor into one ``Detections`` message."""

    def __init__(self, detector: OnnxDetector) -> None:
        self.detector = detector
        self.counters = DetectorCounters()
        self._lock = threading.Lock()  # counters are bumped from Zenoh and inference threads
        self._latencies_ms: deque[float] = deque(maxlen=LATENCY_WINDOW)
        # Each robot's newest scans' odometry poses by scan seq, and when it was last heard from: a
        # tensor carries only its newest scan's pose, and motion confirmation asks whether the robot
        # stood still over all three (common.moving_people).
        self._poses: dict[str, OrderedDict[int, Odometry]] = {}
        self._heard_at: dict[str, float] = {}

    def take_latency(self) -> dict[str, float] | None:
        """Scan-to-detection latency (the newest scan's stamp to publication, wall clock) of the frames
        since the last call: p50, p99 and their count, for the stats; None when there were none."""
        with self._lock:
            latencies = np.array(self._latencies_ms)
            self._latencies_ms.clear()
        if not latencies.size:
            return None
        p50, p99 = np.percentile(latencies, (50, 99))
        return {"p50": round(float(p50), 2), "p99": round(float(p99), 2), "frames": int(latencies.size)}

    def reject(self, reason: str, detail: str) -> None:
        with self._lock:
            self.counters.rejected[reason] += 1
        log.warning("tensor rejected (%s): %s", reason, detail)

    def decode(self, payload: bytes, key_robot_id: str | None = None) -> StackedTensor | None:
        """A validated tensor, or None (logged and counted) for anything this model cannot take."""
        self.count_received()
        try:
            tensor = decode_message(payload, StackedTensor)
        except MessageError as exc:
            self.reject(exc.reason, str(exc))
            return None
        return self._checked(tensor, key_robot_id)

    def accept(self, tensor: StackedTensor, key_robot_id: str | None = None) -> StackedTensor | None:
        """Same as :meth:`decode` for a tensor built in this process (``--from-scans``)."""
        self.count_received()
        return self._checked(tensor, key_robot_id)

    def count_received(self) -> None:
        with self._lock:
            self.counters.received += 1

    def _remember_pose(self, tensor: StackedTensor) -> None:
        if tensor.odom is None or self.detector.motion_confirm is None:  # nothing will ask
            return
        with self._lock:
            poses = self._poses.setdefault(tensor.robot_id, OrderedDict())
            poses[tensor.scan_seqs[2]] = tensor.odom
            poses.move_to_end(tensor.scan_seqs[2])
            while len(poses) > POSE_HISTORY:
                poses.popitem(last=False)
            self._heard_at[tensor.robot_id] = time.monotonic()

    def sensor_still(self, tensor: StackedTensor) -> bool | None:
        """Whether the robot stood still over the tensor's three scans by odometry; None when a pose is
        unknown (no odometry, or an older scan's tensor never came)."""
        with self._lock:
            poses = self._poses.get(tensor.robot_id)
            older = [None if poses is None else poses.get(seq) for seq in tensor.scan_seqs[:2]]
        return self.detector.still_by_odometry([*older, tensor.odom])

    def forget_poses(self, older_than_s: float) -> None:
        """Drop the poses of robots not heard from for ``older_than_s``: fleets change."""
        cutoff = time.monotonic() - older_than_s
        with self._lock:
            for robot_id in [r for r, heard in self._heard_at.items() if heard < cutoff]:
                del self._heard_at[robot_id], self._poses[robot_id]

    def _checked(self, tensor: StackedTensor, key_robot_id: str | None) -> StackedTensor | None:
        """Checks that need the model or the key: robot id, and the encoding the model was trained on."""
        if key_robot_id is not None and tensor.robot_id != key_robot_id:
            self.reject("robot_id_mismatch", f"key says {key_robot_id!r}, payload says {tensor.robot_id!r}")
            return None
        for setting, reason in (("padding", "padding_mismatch"), ("invalid", "invalid_rule_mismatch")):
            made_with, trained_on = getattr(tensor, setting), getattr(self.detector, setting)
            if made_with != trained_on:
                self.reject(
                    reason,
                    f"{tensor.robot_id}: tensor made with {setting} {made_with!r}, model "
                    f"{self.detector.model_id} expects {trained_on!r}",
                )
                return None
        if tensor.yaw_deg != self.detector.raster_yaw_deg:
            self.reject(
                "raster_yaw_mismatch",
                f"{tensor.robot_id}: tensor made with raster yaw {tensor.yaw_deg:g} deg, model "
                f"{self.detector.model_id} expects {self.detector.raster_yaw_deg:g} deg",
            )
            return None
        self._remember_pose(tensor)
        return tensor

    def note_dropped(self) -> None:
        with self._lock:
            self.counters.dropped_stale += 1

    def note_not_ours(self) -> None:
        with self._lock:
            self.counters.not_ours += 1

    def note_handed_over(self) -> None:
        with self._lock:
            self.counters.handed_over += 1

    def detect_many(
        self,
        tensors: Sequence[StackedTensor],
        detector: OnnxDetector | None = None,
        *,
        arrivals: Sequence[Arrival] | None = None,
    ) -> list[Detections]:
        """Run the model on several robots' tensors (one call with a batch model); ``encode_ms`` adds the
        encoder's own time from each tensor. ``detector`` is a worker's own session of the same model
        (``--workers``); default: the core's. ``arrivals`` (one per tensor) fill the decode and queue
        timings."""
        if not tensors:
            return []
        started_ns = time.perf_counter_ns()
        model = detector or self.detector
        still = [self.sensor_still(tensor) for tensor in tensors] if model.motion_confirm else None
        results = model.detect_many([tensor.tensor for tensor in tensors], still)
        with self._lock:
            self.counters.processed += len(results)
            self.counters.inference_calls += 1 if model.batched else len(results)
        waits = arrivals or [Arrival(started_ns, 0.0)] * len(tensors)
        return [
            self._message(tensor, detections, timings, arrival, started_ns)
            for tensor, (detections, timings), arrival in zip(tensors, results, waits, strict=True)
        ]

    def _message(
        self,
        tensor: StackedTensor,
        detections: list[Detection],
        timings: StageTimings,
        arrival: Arrival,
        started_ns: int,
    ) -> Detections:
        stamp_ns = time.time_ns()
        with self._lock:
            self._latencies_ms.append((stamp_ns - tensor.scan_stamps_ns[2]) / 1e6)
        return Detections(
            robot_id=tensor.robot_id,
            seq=tensor.seq,
            stamp_ns=stamp_ns,
            detections=detections,
            timings=StageTimings(
                encode_ms=timings.encode_ms + tensor.encode_ms,
                inference_ms=timings.inference_ms,
                nms_ms=timings.nms_ms,
                decode_ms=arrival.decode_ms,
                queue_ms=max(0.0, (started_ns - arrival.accepted_ns) / 1e6),
            ),
            model_id=self.detector.model_id,
            scan_stamp_ns=tensor.scan_stamps_ns[2],
            pose_stamp_ns=tensor.scan_stamps_ns[1],  # the boxes are the middle scan's
            odom=tensor.odom,
        )


def default_processes(cpus: int | None = None) -> int:
    """Detector processes sharing the fleet when the user gives none (``--detectors``): one per core.

    Each scan costs a detector process Python work (receiving, decoding, building and publishing the
    message) that holds the GIL, so one process tops out far below a many-core machine whatever its
    inference threads do; processes side by side, each serving its share of the robots
    (:mod:`services.shards`), do not share a GIL (``bench.fleet_bound --detectors`` compares counts).
    """
    return cpus or os.cpu_count() or 1


def default_workers(cpus: int | None = None, processes: int = 1) -> int:
    """Inference threads of one process when the user gives none: its share of the cores, each thread
    with a single-threaded session.

    ONNX Runtime splits one small 64×384 frame over several threads poorly: single-threaded sessions
    side by side, one per core, run more frames a second than one session spread over every core
    (``bench.fleet_bound`` measures both), so a detector holds more robots. A lone robot waits a
    little longer per frame (one core instead of all of them work on it), well inside its 100 ms
    period.
    """
    return max(1, (cpus or os.cpu_count() or 1) // processes)


def default_intra_op_threads(
    workers: int, from_scans: bool, cpus: int | None = None, processes: int = 1
) -> int | None:
    """ONNX Runtime threads per worker when the user gives none (``None``: every core).

    Several workers, and several processes (``--detectors``), share the cores. With ``--from-scans``
    the encoder's Zenoh callbacks run in this process too, and an ONNX Runtime thread on every core
    then competes with them for the CPU, which delays every scan's encoding (``bench.pipeline_latency
    --from-scans --threads N`` compares). So one core is left to the rest of the process.
    """
    cpus = cpus or os.cpu_count() or 1
    share = max(1, cpus // processes)
    if workers > 1 or processes > 1:
        return max(1, share // workers)
    if from_scans:
        return max(1, cpus - 1)
    return None


_PR_SET_NAME = 15  # linux/prctl.h


def name_os_thread(name: str) -> None:
    """Give the calling thread ``name`` in the OS, where Python 3.11 calls every thread "python".

    Then ``top -H``, ``ps -L`` and ``/proc/<pid>/task/*/comm`` tell the inference threads from
    Zenoh's (rx-0, tx-0, …), and ``bench.fleet_capacity`` splits the detector's CPU by thread. Linux
    keeps 15 bytes; elsewhere, or without libc's ``prctl``, nothing happens.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        ctypes.CDLL(None).prctl(_PR_SET_NAME, name.encode()[:15], 0, 0, 0)
    except (OSError, AttributeError):
        log.debug("could not name thread %s", name)


class InferencePipeline:
    """Samples in, ``Detections`` out through ``publish``: the mailbox and one thread per detector.

    One inference thread per detector in ``detectors`` (sessions of the same model): ONNX Runtime
    releases the GIL, so on a multi-core robot with many robots to serve, several single-threaded
    sessions in parallel beat one session spreading a batch-1 frame over all cores. Each thread takes
    up to ``batch`` robots' waiting tensors per model call (a batch model is needed for more than 1),
    waiting at most ``gather_ms`` for the robots it serves to fill it (:meth:`LatestPerRobot.take_many`;
    a lone robot never waits). With ``from_scans`` the samples are scans and an :class:`EncoderCore`
    in this process stacks them. ``owns`` says whether this process serves a robot at the moment
    (:mod:`services.shards`): it is asked when a sample arrives and again before its detections are
    published.
    """

    def __init__(
        self,
        detectors: Sequence[OnnxDetector],
        publish: Callable[[Detections], None],
        *,
        batch: int = 1,
        from_scans: bool = False,
        forget_after_s: float = DEFAULT_FORGET_AFTER_S,
        owns: Callable[[str], bool] | None = None,
        gather_ms: float = DEFAULT_GATHER_MS,
    ) -> None:
        if not detectors:
            raise ValueError("need at least one detector")
        check_batch(batch, all(d.batched for d in detectors), detectors[0].model_path)
        self.detectors = list(detectors)
        self.core = DetectorCore(self.detectors[0])
        self.encoder = (
            EncoderCore.for_model(self.core.detector, forget_after_s=forget_after_s) if from_scans else None
        )
        self.batch = batch
        self._forget_after_s = forget_after_s
        self._owns = owns or (lambda _robot_id: True)
        self._publish = publish
        self._mailbox: LatestPerRobot[Pending] = LatestPerRobot(gather_s=gather_ms / 1000)
        self._stop = threading.Event()
        self._workers: list[threading.Thread] = []

    def start(self) -> None:
        """Warm every batch size a worker may run (no first-frame stall), then start the workers."""
        for detector in self.detectors:
            detector.warmup(self.batch)
        self._workers = [
            threading.Thread(target=self._serve, args=(d,), name=f"{INFERENCE_THREAD_PREFIX}{i}", daemon=True)
            for i, d in enumerate(self.detectors)
        ]
        for worker in self._workers:
            worker.start()

    def stop(self, timeout_s: float = 10.0) -> None:
        self._stop.set()
        self._mailbox.close()
        for worker in self._workers:
            worker.join(timeout_s)

    def not_ours(self, key: str) -> bool:
        """True (and counted) for a sample of a robot another process serves: the Zenoh callback then
        never copies its payload out. A key that does not parse is left to :meth:`handle_sample`."""
        try:
            robot_id, _ = parse_key(key)
        except ValueError:
            return False
        if self._owns(robot_id):
            return False
        self.core.note_not_ours()
        return True

    def handle_sample(self, key: str, payload: bytes) -> None:
        """A tensor (or, ``from_scans``, a scan) sample from Zenoh; cheap, never blocks on inference."""
        started_ns = time.perf_counter_ns()
        try:
            robot_id, _ = parse_key(key)
        except ValueError as exc:
            self.core.reject("bad_key", str(exc))
            return
        if not self._owns(robot_id):  # another process's robot: not even decoded
            self.core.note_not_ours()
            return
        if self.encoder is not None:
            tensor = self.encoder.handle_payload(payload, robot_id)
            accepted = self.core.accept(tensor) if tensor is not None else None
        else:
            accepted = self.core.decode(payload, robot_id)
        if accepted is None:
            return
        accepted_ns = time.perf_counter_ns()
        pending = Pending(accepted, Arrival(accepted_ns, (accepted_ns - started_ns) / 1e6))
        if self._mailbox.put(accepted.robot_id, pending):
            self.core.note_dropped()

    def housekeeping(self) -> dict[str, object]:
        """The service's once-a-second chore: with ``from_scans`` forget the encoder's silent robots;
        return the counters for the stats, with the latency of the frames since the last call."""
        counters: dict[str, object] = self.core.counters.to_dict()
        counters["latency_ms"] = self.core.take_latency()
        self.core.forget_poses(self._forget_after_s)
        if self.encoder is not None:
            self.encoder.forget_silent()
            counters["encoder"] = self.encoder.snapshot()
        return counters

    def _serve(self, detector: OnnxDetector) -> None:
        name_os_thread(threading.current_thread().name)
        while not self._stop.is_set():
            try:
                taken = self._mailbox.take_many(self.batch, TAKE_TIMEOUT_S)
            except Exception:  # a thread that died here would leave its process alive and silent
                log.exception("inference worker: taking tensors from the mailbox failed; going on")
                self._stop.wait(TAKE_TIMEOUT_S)
                continue
            if not taken:
                continue
            try:
                try:
                    results = self.core.detect_many(
                        [pending.tensor for _, pending in taken],
                        detector,
                        arrivals=[pending.arrival for _, pending in taken],
                    )
                except Exception as exc:  # one failed model call must not end this worker
                    log.exception("inference failed for %s", [robot_id for robot_id, _ in taken])
                    for robot_id, pending in taken:
                        self.core.reject("inference_error", f"{robot_id} seq {pending.tensor.seq}: {exc}")
                    results = []
                for detections in results:
                    if self._owns(detections.robot_id):
                        self._publish(detections)
                    else:  # the robot moved to another process while its tensor was in the model
                        self.core.note_handed_over()
            finally:
                for robot_id, _ in taken:  # only now: a robot's next tensor must not overtake this one
                    self._mailbox.release(robot_id)
