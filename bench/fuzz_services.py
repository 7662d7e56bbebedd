"""Fuzz the running encoder and detector with malformed payloads over real Zenoh, interleaved with good ones.

The services must survive everything (no crash), process every good message, and count every bad one
under a reason. This process publishes, on the real keys:

* a **good stream**: one robot's consecutive real scans; each must come back as detections;
* **bad payloads** on scan and tensor keys of other robots: random bytes, truncated msgpack of real
  messages, wrong types, wrong shapes and dtypes, NaN/inf in every numeric field, arrays far beyond the
  limits, payloads over the 4 MiB cap, unknown kinds and schema versions, payloads whose robot id
  differs from the key's, and keys that are not valid robot ids.

What the services should count is worked out here as the payloads are sent: scan payloads go through
a local :class:`EncoderCore` (the encoder's own rules, including its stream rules: a valid scan that
repeats a seq is rejected as out of order), tensor payloads through the message decoder. A few "bad"
inputs are valid by design (a scan full of NaN is a blind sensor, not an error). At the end the
services' own JSON counters (``triscan/@stats``), published by the separate processes, must equal
those expectations reason by reason, every good scan must have come back as detections, and both
processes must still be alive. Puts use Zenoh's blocking congestion control, so nothing is lost on
the way and any difference is the services'.

    python -m bench.fuzz_services --bad 10000
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import random
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

from bench.harness import recorded_scans, start_loopback_service
from bench.report import write_report
from common.keys import ALL_STATS, DETECTIONS, scan_key, tensor_key, wildcard_key
from common.messages import (
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

log = logging.getLogger("bench.fuzz_services")

GOOD_ROBOT = "good"
FUZZ_ROBOT = "fuzz"  # the key (and, where not mutated, the payload) robot of every fuzz payload


@dataclass
class FuzzReport:
    bad_sent: int = 0
    bad_sent_by_kind: dict[str, int] = field(default_factory=dict)
    valid_by_design: int = 0  # "fuzz" that decodes fine (NaN ranges, foreign but valid scans)
    good_scans: int = 0
    good_answered: int = 0
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


def run(bad: int, good_every: int, seed: int) -> FuzzReport:
    report = FuzzReport()
    fuzz_port, encoder_port, detector_port = free_tcp_ports(3)
    children = _start_services(fuzz_port, encoder_port, detector_port)
    scans = recorded_scans(40, seed=3)
    tensor = _fuzz_tensor()
    answered: set[int] = set()
    stats: dict[str, dict[str, Any]] = {}
    lock = threading.Lock()

    def on_detections(sample: Any) -> None:
        message = decode_message(payload_bytes(sample), Detections)
        if message.robot_id == GOOD_ROBOT:
            with lock:
                answered.add(message.seq)

    def on_stats(sample: Any) -> None:
        body = json.loads(payload_bytes(sample))
        with lock:
            stats[body["service"]] = body

    expected_encoder = EncoderCore("zero")  # the encoder's rules, applied to exactly what is sent
    expected_detector: Counter[str] = Counter()
    block = {"congestion_control": zenoh.CongestionControl.BLOCK}
    try:
        with open_session(ZenohSettings.loopback(fuzz_port)) as session:
            subs = [
                session.declare_subscriber(wildcard_key(DETECTIONS), on_detections),
                session.declare_subscriber(ALL_STATS, on_stats),
            ]
            wait_for_subscriber(session, scan_key(GOOD_ROBOT), 60)
            wait_for_subscriber(session, tensor_key(GOOD_ROBOT), 60)
            good_pub = session.declare_publisher(scan_key(GOOD_ROBOT), **block)
            good_seq = 0

            def send_good() -> None:
                nonlocal good_seq
                scan = scans[good_seq % len(scans)].model_copy(
                    update={"robot_id": GOOD_ROBOT, "seq": good_seq, "stamp_ns": time.time_ns()}
                )
                good_pub.put(encode_message(scan))
                if counting:
                    expected_encoder.push(scan)
                good_seq += 1

            counting = False

            # Prime: the good robot's detections prove every link is up before the fuzz starts.
            _prime(send_good, answered)
            with lock:
                answered.clear()
            first_counted_seq = good_seq
            counting = True
            # The local core must know the good stream's recent history, as the service does.
            _replay_good_history(expected_encoder, scans, good_seq)
            sent_by_kind = _send_bad_payloads(
                session,
                bad_payloads(bad, scans[0].model_copy(update={"robot_id": FUZZ_ROBOT}), tensor, seed),
                expected_encoder,
                expected_detector,
                report,
                send_good,
                good_every,
                block,
            )
            # Bad keys: not a robot id at all (the services must refuse the key, not the payload).
            _send_bad_keys(session, scans[0], max(1, bad // 100), expected_encoder, sent_by_kind, block)
            last_good = good_seq
            for _ in range(3):  # a few more, so the last fuzz cannot hide the last good tensor
                send_good()
                time.sleep(0.1)
            time.sleep(3.0)  # let counters of the last second arrive
            for sub in subs:
                sub.undeclare()
        report.alive_at_end = {name: p.poll() is None for name, p in children.items()}
    finally:
        stop_processes(children, grace_s=30)
    good_range = range(first_counted_seq + 2, last_good)  # tensors exist from the third scan on
    _judge(report, sent_by_kind, good_range, answered, expected_encoder, expected_detector, stats)
    return report


def _start_services(
    fuzz_port: int, encoder_port: int, detector_port: int
) -> dict[str, subprocess.Popen[bytes]]:
    """The encoder and the detector under test, each connected to this process."""
    quiet = {"stderr": subprocess.DEVNULL}  # thousands of rejections are logged; we read the counters
    return {
        "encoder": start_loopback_service(
            "services.encoder", encoder_port, [fuzz_port, detector_port], **quiet
        ),
        "detector": start_loopback_service(
            "services.detector", detector_port, [fuzz_port, encoder_port], **quiet
        ),
    }


def _fuzz_tensor() -> StackedTensor:
    """A valid tensor message of the fuzz robot: the base the tensor mutations start from."""
    return StackedTensor(
        robot_id=FUZZ_ROBOT, seq=2, stamp_ns=1, tensor=np.zeros((64, 384, 3), np.uint8), padding="zero",
        scan_seqs=(0, 1, 2), scan_stamps_ns=(1, 1, 1),
    )  # fmt: skip


def _prime(send_good: Callable[[], None], answered: set[int]) -> None:
    """Send good scans until the first detections come back (at most 60 s)."""
    deadline = time.monotonic() + 60
    while not answered:
        if time.monotonic() > deadline:
            raise TimeoutError("the pipeline never answered the good robot")
        send_good()
        time.sleep(0.1)


def _replay_good_history(expected_encoder: EncoderCore, scans: list[Scan], good_seq: int) -> None:
    """Push the good stream's last scans through the local core, then zero its counters."""
    for seq in range(max(0, good_seq - 3), good_seq):
        expected_encoder.push(
            scans[seq % len(scans)].model_copy(update={"robot_id": GOOD_ROBOT, "seq": seq, "stamp_ns": 0})
        )
    expected_encoder.counters = EncoderCounters()


def _send_bad_payloads(
    session: Any,
    payloads: Iterator[tuple[str, str, str, bytes]],
    expected_encoder: EncoderCore,
    expected_detector: Counter[str],
    report: FuzzReport,
    send_good: Callable[[], None],
    good_every: int,
    block: dict[str, Any],
) -> Counter[str]:
    """Publish every bad payload, counting what each service should reject; a good scan now and then."""
    sent_by_kind: Counter[str] = Counter()
    for i, (name, topic, robot, payload) in enumerate(payloads):
        if topic == "scan":
            rejected_before = sum(expected_encoder.counters.rejected.values())
            expected_encoder.handle_payload(payload, robot)
            valid = sum(expected_encoder.counters.rejected.values()) == rejected_before
            session.put(scan_key(robot), payload, **block)
        else:
            reason = tensor_rejection(payload, robot)
            valid = reason is None
            if reason is not None:
                expected_detector[reason] += 1
            session.put(tensor_key(robot), payload, **block)
        report.valid_by_design += int(valid)
        sent_by_kind[name] += 1
        if i % good_every == 0:
            send_good()
            time.sleep(0.1)  # the good robot scans at 10 Hz; the fuzz floods in between
    return sent_by_kind


def _send_bad_keys(
    session: Any,
    scan: Scan,
    count: int,
    expected_encoder: EncoderCore,
    sent_by_kind: Counter[str],
    block: dict[str, Any],
) -> None:
    """Publish a valid scan on ``count`` keys that are not robot ids; the encoder must refuse each."""
    for i in range(count):
        session.put(f"triscan/bad.id{i}/scan", encode_message(scan), **block)
        expected_encoder.counters.rejected["bad_key"] += 1
        sent_by_kind["bad_key"] += 1


def _judge(
    report: FuzzReport,
    sent_by_kind: Counter[str],
    good_range: range,
    answered: set[int],
    expected_encoder: EncoderCore,
    expected_detector: Counter[str],
    stats: dict[str, dict[str, Any]],
) -> None:
    """Fill in the report's counts and whether the services counted exactly what was expected."""
    report.bad_sent = sum(sent_by_kind.values())
    report.bad_sent_by_kind = dict(sent_by_kind)
    report.good_scans = len(good_range)
    report.good_answered = sum(1 for s in good_range if s in answered)
    expected = {"encoder": dict(expected_encoder.counters.rejected), "detector": dict(expected_detector)}
    report.expected_by_reason = expected
    for service in ("encoder", "detector"):
        counted = stats.get(service, {}).get("rejected", {})
        report.rejected_by_reason[service] = counted
        report.counted_rejected[service] = sum(counted.values())
        report.expected_rejected[service] = sum(expected[service].values())
    report.passed = (
        all(report.alive_at_end.values())
        and report.good_answered == report.good_scans
        and all(report.rejected_by_reason[s] == expected[s] for s in expected)
    )
    if not report.passed:
        log.error("expected rejections %s, counted %s", expected, report.rejected_by_reason)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bad", type=int, default=10_000, help="malformed payloads to send")
    parser.add_argument("--good-every", type=int, default=25, help="one good scan after this many bad")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("bench/results/fuzz_services.json"))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    report = run(args.bad, args.good_every, args.seed)
    write_report(report, args.out)
    return 0 if report.passed else 1


if __name__ == "__main__":
    raise SystemExit(main())
