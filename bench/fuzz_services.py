"""Fuzz the running encoder, detector and ROS 2 bridge with malformed payloads over real Zenoh.

The services must survive everything (no crash), process every good message, and count every bad one
under a reason. This process publishes, on the real keys:

* a **good stream**: one robot's consecutive real scans; each must come back as detections;
* **bad payloads** on scan and tensor keys of other robots: random bytes, truncated msgpack of real
  messages, wrong types, wrong shapes and dtypes, NaN/inf in every numeric field, arrays far beyond the
  limits, lit-pixel tensors whose counts, bytes or indices lie, payloads over the 4 MiB cap, unknown
  kinds and schema versions, payloads whose robot id differs from the key's, and keys that are not
  valid robot ids;
* **bad ROS 2 payloads** on the ROS 2 bridge's scan key (rmw_zenoh style, ``0/rosfuzz/scan/<type>/
  <hash>``): bytes that are not CDR, truncated CDR, trailing bytes, a wrong type hash, a missing or
  malformed rmw_zenoh attachment, absurd and lying beam counts, NaN/inf/zero angles, too many beams
  for a turn, bad range limits and stamps, bad frame ids; and valid-by-design ones (a Humble hash, a
  big-endian scan, a 1,440-beam sensor, a blind scan), which the bridge forwards to the encoder;
* a **good ROS 2 robot** (``rosgood``): the same real scans as LaserScans with a proper attachment; each
  must come back, through bridge, encoder and detector, as detections.

What the services should count is worked out here as the payloads are sent: scan payloads go through
a local :class:`EncoderCore` (the encoder's own rules, including its stream rules: a valid scan that
repeats a seq is rejected as out of order), tensor payloads through the message decoder, ROS payloads
through a local :class:`BridgeCore` (whose forwarded scans then go through the local encoder too). A
few "bad" inputs are valid by design (a scan full of NaN is a blind sensor, not an error). At the end
the services' own JSON counters (``triscan/@stats``), published by the separate processes, must equal
those expectations reason by reason (the bridge's ``rejected_scans`` and ``scans_published`` too),
every good scan must have come back as detections (or, at most as many as the detector counted as
``dropped_stale``, been replaced in its mailbox by its robot's next scan, which is the detector's design
when a process of the chain stalls for a scan period on a loaded machine), and all three processes
must still be alive. Puts
use Zenoh's blocking congestion control, so nothing is lost on the way and any difference is the
services'.

    python -m bench.fuzz_services --bad 10000
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import logging
import math
import random
import struct
import subprocess
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import zenoh

from bench.harness import start_loopback_service
from bench.report import write_report
from common.encoding import HIT
from common.keys import ALL_STATS, DETECTIONS, TENSOR, parse_key, scan_key, tensor_key, wildcard_key
from common.messages import (
    LIT_PIXELS_VERSION,
    MAX_PAYLOAD_BYTES,
    Detections,
    MessageError,
    Scan,
    StackedTensor,
    decode_message,
    encode_message,
)
from common.transport import ZenohSettings, open_session, payload_bytes, wait_for_subscriber
from services.encoder.core import EncoderCore, EncoderCounters
from services.launcher import free_tcp_ports, stop_processes
from services.ros2_bridge.core import DEFAULT_SCAN_TOPIC, BridgeConfig, BridgeCore
from services.ros2_bridge.rmw_zenoh import GID_SIZE, data_key, encode_attachment, qualified_topic
from services.ros2_bridge.ros_types import LASER_SCAN, TYPE_HASH_NOT_SUPPORTED, dds_type_name, ros_types
from services.runtime import announce_source
from services.sim_bag import T0_NS, laser_scan_message, recorded_scans

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

GOOD_ROBOT = "good"
FUZZ_ROBOT = "fuzz"  # the key (and, where not mutated, the payload) robot of every fuzz payload
ROS_GOOD_ROBOT = "rosgood"  # ROS namespaces /rosgood and /rosfuzz: the bridge names robots after them
ROS_FUZZ_ROBOT = "rosfuzz"
BRIDGE_ARGS = ("--namespace", "*")  # every one-segment namespace, rmw_zenoh style: BRIDGE_CONFIG
BRIDGE_CONFIG = BridgeConfig(style="rmw_zenoh", namespace=None)
REJECTED_FIELD = {"encoder": "rejected", "detector": "rejected", "ros2_bridge": "rejected_scans"}
RosSample = tuple[str, bytes, bytes | None]  # key, CDR payload, rmw_zenoh attachment


@dataclass
class FuzzReport:
    bad_sent: int = 0
    bad_sent_by_kind: dict[str, int] = field(default_factory=dict)
    valid_by_design: int = 0  # "fuzz" that decodes fine (NaN ranges, foreign but valid scans)
    good_scans: int = 0
    good_answered: int = 0
    ros_bad_sent: int = 0
    ros_bad_sent_by_kind: dict[str, int] = field(default_factory=dict)
    ros_good_scans: int = 0
    ros_good_answered: int = 0
    bridge_scans_published: dict[str, int] = field(default_factory=dict)  # expected, counted
    detector_dropped_stale: int = 0  # tensors replaced by a newer one of their robot: a good scan lost
    expected_rejected: dict[str, int] = field(default_factory=dict)  # per service
    counted_rejected: dict[str, int] = field(default_factory=dict)
    rejected_by_reason: dict[str, dict[str, int]] = field(default_factory=dict)
    expected_by_reason: dict[str, dict[str, int]] = field(default_factory=dict)
    alive_at_end: dict[str, bool] = field(default_factory=dict)
    passed: bool = False


def _raw(message: Any) -> dict[str, Any]:
    return msgpack.unpackb(encode_message(message))


def _pack(body: Any) -> bytes:
    return msgpack.packb(body, use_bin_type=True)


def mutations(scan: Scan, tensor: StackedTensor, rng: random.Random) -> list[tuple[str, Callable[[], bytes]]]:
    """Named makers of malformed payloads, each derived from a real message."""
    scan_raw, tensor_raw = _raw(scan), _raw(tensor)
    good_scan, good_tensor = encode_message(scan), encode_message(tensor)

    def with_field(raw: dict[str, Any], key: str, value: Any) -> Callable[[], bytes]:
        return lambda: _pack({**raw, key: value})

    def array(dtype: str, shape: list[int], data: bytes) -> dict[str, Any]:
        return {"dtype": dtype, "shape": shape, "data": data}

    def lit(**changes: Any) -> Callable[[], bytes]:
        """The tensor's lit-pixel map (``fuzz_tensor`` travels as one) with ``changes``."""
        return with_field(tensor_raw, "tensor", {**tensor_raw["tensor"], **changes})

    def lit_indices(change: Callable[[np.ndarray], None]) -> Callable[[], bytes]:
        indices = np.frombuffer(tensor_raw["tensor"]["lit"], dtype="<u2").copy()
        change(indices)
        return lit(lit=indices.tobytes())

    def outside(indices: np.ndarray) -> None:
        indices[-1] = 0xFFFF

    def unsorted(indices: np.ndarray) -> None:
        indices[:2] = indices[1::-1]

    def repeated(indices: np.ndarray) -> None:
        indices[1] = indices[0]

    nan_ranges = np.full(360, np.nan, dtype="<f4").tobytes()
    blind_seq = iter(range(1, 1 << 62))

    def blind_scan() -> bytes:
        """Valid by design: a blind sensor (all NaN) with fresh seqs, so the stream stays alive and
        counts nothing (a repeated seq would be rejected as out of order, and a robot that only sends
        rejects is forgotten after its silence timeout, which would make counts depend on timing)."""
        seq = next(blind_seq)
        return _pack({**scan_raw, "seq": seq, "stamp_ns": seq, "ranges": array("<f4", [360], nan_ranges)})

    return [
        ("random_bytes", lambda: rng.randbytes(rng.randint(0, 2048))),
        ("empty", lambda: b""),
        ("truncated_scan", lambda: good_scan[: rng.randint(1, len(good_scan) - 1)]),
        ("truncated_tensor", lambda: good_tensor[: rng.randint(1, len(good_tensor) - 1)]),
        ("not_a_map", lambda: _pack([1, 2, 3])),
        ("wrong_kind", with_field(scan_raw, "kind", "detections")),
        ("unknown_kind", with_field(scan_raw, "kind", "teleport")),
        ("schema_version", with_field(scan_raw, "schema_version", 99)),
        ("seq_wrong_type", with_field(scan_raw, "seq", "forty-two")),
        ("seq_negative", with_field(scan_raw, "seq", -1)),
        ("stamp_float", with_field(scan_raw, "stamp_ns", 1.5)),
        ("angle_nan", with_field(scan_raw, "angle_increment", math.nan)),
        ("angle_inf", with_field(scan_raw, "angle_min", math.inf)),
        ("range_max_nan", with_field(scan_raw, "range_max", math.nan)),
        ("ranges_all_nan", blind_scan),
        ("ranges_wrong_dtype", with_field(scan_raw, "ranges", array("<f8", [360], bytes(360 * 8)))),
        ("ranges_shape_lies", with_field(scan_raw, "ranges", array("<f4", [720], bytes(360 * 4)))),
        ("ranges_2d", with_field(scan_raw, "ranges", array("<f4", [18, 20], bytes(360 * 4)))),
        ("ranges_huge", with_field(scan_raw, "ranges", array("<f4", [100_000], bytes(400_000)))),
        ("ranges_not_array", with_field(scan_raw, "ranges", "lots")),
        ("over_4_mib", lambda: _pack({**scan_raw, "frame_id": "x" * (MAX_PAYLOAD_BYTES + 10)})),
        ("robot_id_mismatch", with_field(scan_raw, "robot_id", "someone_else")),
        ("robot_id_invalid", with_field(scan_raw, "robot_id", "../../etc")),
        ("missing_field", lambda: _pack({k: v for k, v in scan_raw.items() if k != "angle_min"})),
        ("extra_field", with_field(scan_raw, "extra", 1)),
        (
            "tensor_wrong_shape",
            with_field(tensor_raw, "tensor", array("|u1", [64, 360, 3], bytes(64 * 360 * 3))),
        ),
        (
            "tensor_float",
            with_field(tensor_raw, "tensor", array("<f4", [64, 384, 3], bytes(64 * 384 * 3 * 4))),
        ),
        ("tensor_bad_padding", with_field(tensor_raw, "padding", "mirror")),
        ("tensor_seqs_inconsistent", with_field(tensor_raw, "scan_seqs", [1, 2, 3])),
        ("tensor_encode_ms_nan", with_field(tensor_raw, "encode_ms", math.nan)),
        ("tensor_lit_under_version_2", with_field(tensor_raw, "schema_version", 2)),
        ("tensor_lit_extra_key", lit(data=b"")),
        ("tensor_lit_counts_huge", lit(counts=[1 << 40, 0, 0])),
        ("tensor_lit_counts_short", lit(counts=[360, 360])),
        ("tensor_lit_bytes_short", lit(lit=tensor_raw["tensor"]["lit"][:-2])),
        ("tensor_lit_index_outside", lit_indices(outside)),
        ("tensor_lit_unsorted", lit_indices(unsorted)),
        ("tensor_lit_repeated", lit_indices(repeated)),
    ]


def tensor_rejection(payload: bytes, key_robot: str) -> str | None:
    """The reason the detector should count for this tensor payload, or None if it is valid."""
    try:
        message = decode_message(payload, StackedTensor)
    except MessageError as exc:
        return exc.reason
    if message.robot_id != key_robot:
        return "robot_id_mismatch"
    return None


def bad_payloads(
    count: int, scan: Scan, tensor: StackedTensor, seed: int
) -> Iterator[tuple[str, str, str, bytes]]:
    """(mutation name, topic, key robot id, payload), round-robin over mutations, seeded."""
    rng = random.Random(seed)
    makers = mutations(scan, tensor, rng)
    for i in range(count):
        name, make = makers[i % len(makers)]
        topic = "tensor" if name.startswith("tensor") or name == "truncated_tensor" else "scan"
        yield name, topic, FUZZ_ROBOT, make()


def ros_scan_key(robot: str, type_hash: str | None = None) -> str:
    """The rmw_zenoh key a ROS 2 node in namespace ``/<robot>`` publishes its LaserScans on."""
    c = BRIDGE_CONFIG
    fq_topic = qualified_topic(f"/{robot}", DEFAULT_SCAN_TOPIC)
    type_hash = type_hash or ros_types(c.distro).type_hash(LASER_SCAN)
    return data_key(c.style, c.domain, fq_topic, dds_type_name(LASER_SCAN), type_hash)


def with_beam_count(cdr: bytes, count: int) -> bytes:
    """A little-endian LaserScan CDR whose ranges count says ``count`` (the ranges stay as they are)."""
    body = 4  # after the encapsulation header: sec, nanosec, frame_id length + bytes, pad, 7 floats
    (name_len,) = struct.unpack_from("<I", cdr, body + 8)
    out = bytearray(cdr)
    struct.pack_into("<I", out, body + ((12 + name_len + 3) & ~3) + 28, count)
    return bytes(out)


class RosScans:
    """rmw_zenoh samples of one ROS 2 node: CDR LaserScans of real scans, fresh stamps, own attachments.

    Stamps rise by 100 ms per message, so the scans the bridge forwards form one stream, or, with
    ``falling_stamps``, fall: then each forwarded scan is the next seq with an older stamp, which the
    encoder takes as a clock jump and restarts its FIFO on (counted as a restart, not a rejection). The
    fuzz node uses that, so its valid-by-design scans never become tensors: a burst of them would
    keep the detector from the good robots' 10 Hz, and the fuzz would measure capacity, not robustness.
    """

    def __init__(self, robot: str, *, falling_stamps: bool = False) -> None:
        self.key = ros_scan_key(robot)
        self.store = ros_types(BRIDGE_CONFIG.distro).store
        step_ns = -100_000_000 if falling_stamps else 100_000_000
        self._stamps = itertools.count(T0_NS + (10**15 if falling_stamps else 0), step_ns)
        self._sequence = itertools.count()
        self._gid = bytes(range(GID_SIZE))

    def attachment(self) -> bytes:
        return encode_attachment(next(self._sequence), time.time_ns(), self._gid)

    def message(self, scan: Scan, **fields: Any) -> Any:
        return dataclasses.replace(laser_scan_message(scan, next(self._stamps)), **fields)

    def cdr(self, message: Any, *, little_endian: bool = True) -> bytes:
        return bytes(self.store.serialize_cdr(message, LASER_SCAN, little_endian=little_endian))

    def sample(self, scan: Scan) -> RosSample:
        return self.key, self.cdr(self.message(scan)), self.attachment()


def ros_mutations(scan: Scan, rng: random.Random) -> list[tuple[str, Callable[[], RosSample]]]:
    """Named makers of bad (and a few valid-by-design) ROS 2 samples for the bridge's scan key."""
    node = RosScans(ROS_FUZZ_ROBOT, falling_stamps=True)
    times = node.store.types["builtin_interfaces/msg/Time"]

    def good() -> bytes:
        return node.cdr(node.message(scan))

    def attached(make: Callable[[], bytes], key: str = node.key) -> Callable[[], RosSample]:
        """The sample of ``make()``'s payload with a proper attachment: only the payload (or key) is bad."""
        return lambda: (key, make(), node.attachment())

    def cdr_with(**fields: Any) -> Callable[[], RosSample]:
        return attached(lambda: node.cdr(node.message(scan, **fields)))

    def stamped(sec: int, nanosec: int) -> Callable[[], bytes]:
        def make() -> bytes:
            message = node.message(scan)
            header = dataclasses.replace(message.header, stamp=times(sec=sec, nanosec=nanosec))
            return node.cdr(dataclasses.replace(message, header=header))

        return make

    def with_frame_id(frame_id: str) -> bytes:
        message = node.message(scan)
        return node.cdr(
            dataclasses.replace(message, header=dataclasses.replace(message.header, frame_id=frame_id))
        )

    def frame_id_not_terminated() -> bytes:
        payload = bytearray(good())
        (name_len,) = struct.unpack_from("<I", payload, 4 + 8)
        payload[4 + 12 + name_len - 1] = ord("x")  # the NUL that ends frame_id
        return bytes(payload)

    def bad_gid_length() -> RosSample:
        attachment = bytearray(node.attachment())
        attachment[16] = GID_SIZE // 2
        return node.key, good(), bytes(attachment)

    ranges = scan.ranges.astype("<f4")
    fine = np.repeat(ranges, 4)  # a 1,440-beam sensor over the same turn
    return [
        ("ros_random_bytes", attached(lambda: rng.randbytes(rng.randint(0, 2048)))),
        ("ros_empty", attached(lambda: b"")),
        ("ros_msgpack_not_cdr", attached(lambda: encode_message(scan))),
        ("ros_truncated", attached(lambda: (g := good())[: rng.randint(0, len(g) - 1)])),
        ("ros_trailing_bytes", attached(lambda: good() + bytes(8))),
        ("ros_wrong_type_hash", attached(good, ros_scan_key(ROS_FUZZ_ROBOT, "RIHS01_" + "0" * 64))),
        ("ros_humble_hash", attached(good, ros_scan_key(ROS_FUZZ_ROBOT, TYPE_HASH_NOT_SUPPORTED))),
        ("ros_no_attachment", lambda: (node.key, good(), None)),
        ("ros_attachment_short", lambda: (node.key, good(), node.attachment()[:20])),
        ("ros_attachment_gid_length", bad_gid_length),
        ("ros_beams_absurd", attached(lambda: with_beam_count(good(), 0x7FFFFFFF))),
        ("ros_beams_lie", attached(lambda: with_beam_count(good(), ranges.size + 1))),
        ("ros_beams_zero", cdr_with(ranges=ranges[:0], angle_max=scan.angle_min)),
        ("ros_beams_1440", cdr_with(ranges=fine, angle_increment=scan.angle_increment / 4)),
        ("ros_beams_beyond_a_turn", cdr_with(ranges=np.tile(ranges, 2))),
        ("ros_angle_increment_nan", cdr_with(angle_increment=math.nan)),
        ("ros_angle_min_inf", cdr_with(angle_min=math.inf)),
        ("ros_angle_increment_zero", cdr_with(angle_increment=0.0)),
        ("ros_range_max_nan", cdr_with(range_max=math.nan)),
        ("ros_range_limits_swapped", cdr_with(range_min=5.0, range_max=1.0)),
        ("ros_stamp_nanosec_overflow", attached(stamped(1, 2_000_000_000))),
        ("ros_stamp_negative", attached(stamped(-5, 0))),
        ("ros_frame_id_empty", attached(lambda: with_frame_id(""))),
        ("ros_frame_id_not_terminated", attached(frame_id_not_terminated)),
        ("ros_ranges_all_nan", cdr_with(ranges=np.full_like(ranges, np.nan))),
        ("ros_big_endian", attached(lambda: node.cdr(node.message(scan), little_endian=False))),
    ]


def ros_bad_payloads(count: int, scan: Scan, seed: int) -> Iterator[tuple[str, RosSample]]:
    """(mutation name, ROS sample), round-robin over the ROS mutations, seeded."""
    rng = random.Random(seed + 1)
    makers = ros_mutations(scan, rng)
    for i in range(count):
        name, make = makers[i % len(makers)]
        yield name, make()


BLOCK: dict[str, Any] = {"congestion_control": zenoh.CongestionControl.BLOCK}  # nothing lost on the way
Children = dict[str, subprocess.Popen[bytes]]


def _start_services() -> tuple[int, Children]:
    """The three services as children wired to each other and to this process's port (returned)."""
    fuzz_port, encoder_port, detector_port, bridge_port = free_tcp_ports(4)
    quiet = {"stderr": subprocess.DEVNULL}  # thousands of rejections are logged; we read the counters
    children = {
        "encoder": start_loopback_service(
            "services.encoder", encoder_port, [fuzz_port, detector_port], **quiet
        ),
        # One detector process: with siblings, a payload for a robot another process owns is dropped
        # unread there, and the one process whose counters are read would not see it.
        "detector": start_loopback_service(
            "services.detector", detector_port, [fuzz_port, encoder_port], "--detectors", "1", **quiet
        ),
        "ros2_bridge": start_loopback_service(
            "services.ros2_bridge",
            bridge_port,
            [fuzz_port, encoder_port, detector_port],
            *BRIDGE_ARGS,
            **quiet,
        ),
    }
    return fuzz_port, children


def fuzz_tensor() -> StackedTensor:
    """A valid tensor of the fuzz robot: the real message the tensor mutations are derived from. Like
    the encoder's, it is version 3 with one lit pixel per beam per channel, so it travels as its lit
    pixels."""
    raster = np.zeros((64, 384, 3), np.uint8)
    raster[20, :360, :] = HIT
    return StackedTensor(
        schema_version=LIT_PIXELS_VERSION, robot_id=FUZZ_ROBOT, seq=2, stamp_ns=1, tensor=raster,
        padding="zero", scan_seqs=(0, 1, 2), scan_stamps_ns=(1, 1, 1),
    )  # fmt: skip


class Heard:
    """What the services publish back: the seqs answered for each good robot, each service's latest stats."""

    def __init__(self) -> None:
        self.answered: dict[str, set[int]] = {GOOD_ROBOT: set(), ROS_GOOD_ROBOT: set()}
        self.stats: dict[str, dict[str, Any]] = {}
        self._lock = threading.Lock()

    def on_detections(self, sample: Any) -> None:
        """Note a good robot's answered seq; the fuzz robots' answers are not judged."""
        message = decode_message(payload_bytes(sample), Detections)
        if message.robot_id in self.answered:
            with self._lock:
                self.answered[message.robot_id].add(message.seq)

    def on_stats(self, sample: Any) -> None:
        """Keep each service's latest counters: the last ones are judged."""
        body = json.loads(payload_bytes(sample))
        with self._lock:
            self.stats[body["service"]] = body

    def forget_answers(self) -> None:
        """Drop the answers so far, so only those to counted scans are judged."""
        with self._lock:
            for seqs in self.answered.values():
                seqs.clear()


@dataclass
class FuzzSession:
    """This process's side of a run: what it puts, and what each service should count for it.

    Scan payloads go through a local encoder core, tensor payloads through the message decoder, ROS
    samples through a local bridge core (whose forwarded scans feed the local encoder too).
    """

    session: Any  # zenoh.Session
    scans: list[Scan]
    good_pub: Any  # the good robot's scan publisher
    ros_good: RosScans
    fuzz_source: Any  # the fuzz robot's tensor source token: the detector subscribes to announced robots
    expected_encoder: EncoderCore = field(default_factory=lambda: EncoderCore("zero"))
    expected_detector: Counter[str] = field(default_factory=Counter)
    expected_bridge: BridgeCore = field(default_factory=lambda: BridgeCore(BRIDGE_CONFIG))
    ros_good_seqs: list[int] = field(default_factory=list)  # bridge seqs of the good ROS scans counted
    sent_by_kind: Counter[str] = field(default_factory=Counter)
    ros_sent_by_kind: Counter[str] = field(default_factory=Counter)
    valid_by_design: int = 0
    good_seq: int = 0
    counting: bool = False  # off while priming: the local cores count only what is judged

    @classmethod
    def ready(cls, session: Any, scans: list[Scan]) -> FuzzSession:
        """Wait until the services subscribe to the good keys and the fuzz robot's tensors, so the
        first put is not lost (the good robots' tensors come from the encoder, which announces them)."""
        ros_good = RosScans(ROS_GOOD_ROBOT)
        fuzz_source = announce_source(session, FUZZ_ROBOT, TENSOR)
        wait_for_subscriber(session, scan_key(GOOD_ROBOT), 60)
        wait_for_subscriber(session, tensor_key(FUZZ_ROBOT), 60)
        wait_for_subscriber(session, ros_good.key, 60)  # the bridge hears every ROS sample sent
        good_pub = session.declare_publisher(scan_key(GOOD_ROBOT), **BLOCK)
        return cls(session, scans, good_pub, ros_good, fuzz_source)

    def send_ros(self, sample: RosSample) -> Scan | None:
        """Put a ROS sample; returns the Scan the bridge should forward (the local core's)."""
        key, payload, attachment = sample
        self.session.put(key, payload, attachment=attachment, **BLOCK)
        out = self.expected_bridge.handle_scan(key, payload, attachment)
        if out is None:
            return None
        self.expected_encoder.handle_payload(out.payload, parse_key(out.key)[0])
        return decode_message(out.payload, Scan)

    def send_good(self) -> None:
        """The next real scan of both good robots: as a triscan Scan and as a ROS 2 LaserScan."""
        scan = self.scans[self.good_seq % len(self.scans)].model_copy(
            update={"robot_id": GOOD_ROBOT, "seq": self.good_seq, "stamp_ns": time.time_ns()}
        )
        self.good_pub.put(encode_message(scan))
        if self.counting:
            self.expected_encoder.push(scan)
        self.good_seq += 1
        forwarded = self.send_ros(self.ros_good.sample(scan))
        if self.counting and forwarded is not None:
            self.ros_good_seqs.append(forwarded.seq)

    def send_bad(self, name: str, topic: str, robot: str, payload: bytes) -> None:
        """Put a bad triscan payload, counting it as the encoder (scans) or the detector (tensors) should."""
        if topic == "scan":
            rejected_before = sum(self.expected_encoder.counters.rejected.values())
            self.expected_encoder.handle_payload(payload, robot)
            valid = sum(self.expected_encoder.counters.rejected.values()) == rejected_before
            self.session.put(scan_key(robot), payload, **BLOCK)
        else:
            reason = tensor_rejection(payload, robot)
            valid = reason is None
            if reason is not None:
                self.expected_detector[reason] += 1
            self.session.put(tensor_key(robot), payload, **BLOCK)
        self.valid_by_design += int(valid)
        self.sent_by_kind[name] += 1

    def send_ros_fuzz(self, name: str, sample: RosSample) -> None:
        """Put a bad ROS sample; one the bridge forwards is valid by design."""
        self.valid_by_design += int(self.send_ros(sample) is not None)
        self.ros_sent_by_kind[name] += 1


def _prime(fuzz: FuzzSession, heard: Heard) -> None:
    """Send good scans until both good robots are answered: every link is up before the fuzz starts."""
    deadline = time.monotonic() + 60
    while not all(heard.answered.values()):
        if time.monotonic() > deadline:
            raise TimeoutError(f"the pipeline never answered both good robots: {heard.answered}")
        fuzz.send_good()
        time.sleep(0.1)
    heard.forget_answers()


def _replay_good_history(fuzz: FuzzSession) -> None:
    """Start counting from zero, the local encoder knowing the good stream's recent history as the service."""
    fuzz.counting = True
    for seq in range(max(0, fuzz.good_seq - 3), fuzz.good_seq):
        fuzz.expected_encoder.push(
            fuzz.scans[seq % len(fuzz.scans)].model_copy(
                update={"robot_id": GOOD_ROBOT, "seq": seq, "stamp_ns": 0}
            )
        )
    fuzz.expected_encoder.counters = EncoderCounters()


def _send_bad_payloads(fuzz: FuzzSession, bad: int, ros_bad: int, good_every: int, seed: int) -> None:
    """The fuzz proper: each bad payload with a bad ROS sample beside it, a good scan every ``good_every``."""
    ros_fuzz = ros_bad_payloads(ros_bad, fuzz.scans[0].model_copy(update={"robot_id": ROS_FUZZ_ROBOT}), seed)
    fuzz_scan = fuzz.scans[0].model_copy(update={"robot_id": FUZZ_ROBOT})
    for i, (name, topic, robot, payload) in enumerate(bad_payloads(bad, fuzz_scan, fuzz_tensor(), seed)):
        fuzz.send_bad(name, topic, robot, payload)
        if (ros := next(ros_fuzz, None)) is not None:
            fuzz.send_ros_fuzz(*ros)
        if i % good_every == 0:
            fuzz.send_good()
            time.sleep(0.1)  # the good robot scans at 10 Hz; the fuzz floods in between
    for ros in ros_fuzz:  # those left when ros_bad > bad
        fuzz.send_ros_fuzz(*ros)


def _send_bad_keys(fuzz: FuzzSession, bad: int) -> None:
    """Keys that are not a robot id at all: the services must refuse the key, not the payload."""
    for i in range(max(1, bad // 100)):
        fuzz.session.put(f"triscan/bad.id{i}/scan", encode_message(fuzz.scans[0]), **BLOCK)
        fuzz.expected_encoder.counters.rejected["bad_key"] += 1
        fuzz.sent_by_kind["bad_key"] += 1


def run(bad: int, good_every: int, seed: int, ros_bad: int | None = None) -> FuzzReport:
    """``bad`` triscan payloads and ``ros_bad`` (default ``bad // 2``) ROS payloads, interleaved."""
    ros_bad = bad // 2 if ros_bad is None else ros_bad
    fuzz_port, children = _start_services()
    scans = recorded_scans(40, seed=3)
    heard = Heard()
    try:
        with open_session(ZenohSettings.loopback(fuzz_port)) as session:
            subs = [
                session.declare_subscriber(wildcard_key(DETECTIONS), heard.on_detections),
                session.declare_subscriber(ALL_STATS, heard.on_stats),
            ]
            fuzz = FuzzSession.ready(session, scans)
            _prime(fuzz, heard)
            first_counted_seq = fuzz.good_seq
            _replay_good_history(fuzz)
            _send_bad_payloads(fuzz, bad, ros_bad, good_every, seed)
            _send_bad_keys(fuzz, bad)
            last_good, last_ros_good = fuzz.good_seq, len(fuzz.ros_good_seqs)
            for _ in range(3):  # a few more, so the last fuzz cannot hide the last good tensor
                fuzz.send_good()
                time.sleep(0.1)
            time.sleep(3.0)  # let counters of the last second arrive
            for sub in subs:
                sub.undeclare()
        alive_at_end = {name: p.poll() is None for name, p in children.items()}
    finally:
        stop_processes(children, grace_s=30)
    good_range = range(first_counted_seq + 2, last_good)  # tensors exist from the third scan on
    return _judge(fuzz, heard, alive_at_end, good_range, fuzz.ros_good_seqs[2:last_ros_good])


def _judge(
    fuzz: FuzzSession,
    heard: Heard,
    alive_at_end: dict[str, bool],
    good_range: range,
    ros_good_judged: list[int],
) -> FuzzReport:
    """The report: the services' counters against the expected ones, the good scans against the answers."""
    report = FuzzReport(valid_by_design=fuzz.valid_by_design, alive_at_end=alive_at_end)
    report.bad_sent = sum(fuzz.sent_by_kind.values())
    report.bad_sent_by_kind = dict(fuzz.sent_by_kind)
    report.good_scans = len(good_range)
    report.good_answered = sum(1 for s in good_range if s in heard.answered[GOOD_ROBOT])
    report.ros_bad_sent = sum(fuzz.ros_sent_by_kind.values())
    report.ros_bad_sent_by_kind = dict(fuzz.ros_sent_by_kind)
    report.ros_good_scans = len(ros_good_judged)
    report.ros_good_answered = sum(1 for s in ros_good_judged if s in heard.answered[ROS_GOOD_ROBOT])
    expected = {
        "encoder": dict(fuzz.expected_encoder.counters.rejected),
        "detector": dict(fuzz.expected_detector),
        "ros2_bridge": dict(fuzz.expected_bridge.counters.rejected_scans),
    }
    report.expected_by_reason = expected
    stats = heard.stats
    for service, rejected_field in REJECTED_FIELD.items():
        counted = stats.get(service, {}).get(rejected_field, {})
        report.rejected_by_reason[service] = counted
        report.counted_rejected[service] = sum(counted.values())
        report.expected_rejected[service] = sum(expected[service].values())
    bridge_stats = stats.get("ros2_bridge", {})
    report.detector_dropped_stale = stats.get("detector", {}).get("dropped_stale", -1)
    report.bridge_scans_published = {
        "expected": fuzz.expected_bridge.counters.scans_published,
        "counted": bridge_stats.get("scans_published", -1),
    }
    unanswered = report.good_scans - report.good_answered + report.ros_good_scans - report.ros_good_answered
    report.passed = (
        all(report.alive_at_end.values())
        and unanswered <= max(0, report.detector_dropped_stale)
        and all(report.rejected_by_reason[s] == expected[s] for s in expected)
        and report.bridge_scans_published["expected"] == report.bridge_scans_published["counted"]
        and bridge_stats.get("rejected_detections") == {}
    )
    if not report.passed:
        log.error("expected rejections %s, counted %s", expected, report.rejected_by_reason)
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bad", type=int, default=10_000, help="malformed payloads to send")
    parser.add_argument(
        "--ros-bad", type=int, default=None, help="malformed ROS payloads for the bridge (default: --bad / 2)"
    )
    parser.add_argument("--good-every", type=int, default=25, help="one good scan after this many bad")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("bench/results/fuzz_services.json"))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    report = run(args.bad, args.good_every, args.seed, args.ros_bad)
    write_report(report, args.out)
    return 0 if report.passed else 1


if __name__ == "__main__":
    raise SystemExit(main())
