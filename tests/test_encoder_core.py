"""The encoder's stream rules: per-robot FIFOs, first scans, gaps, restarts, reordering, silence."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest

from common.encoding import ScanError, ScanStacker, encode_scan
from common.messages import LIT_PIXELS_VERSION, Odometry, Scan, StackedTensor, decode_message, encode_message
from services.encoder.core import EncoderCore
from services.sim_bag import recorded_scans

DEG = math.radians(1.0)


class FakeClock:
    """A settable monotonic clock (a real value, not a mock of any project part)."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def scan(robot_id: str, seq: int, stamp_ns: int | None = None, distance: float = 1.0) -> Scan:
    ranges = np.full(360, distance, dtype=np.float32)
    ranges[seq % 360] = 0.5  # every scan differs, so tensors show which scans they hold
    return Scan(
        robot_id=robot_id,
        seq=seq,
        stamp_ns=stamp_ns if stamp_ns is not None else 1_000_000 + seq * 100_000_000,
        angle_min=0.0,
        angle_increment=DEG,
        range_min=0.12,
        range_max=3.5,
        ranges=ranges,
    )


def expected_tensor(*scans: Scan) -> np.ndarray:
    stacker = ScanStacker("zero")
    out = None
    for s in scans:
        out = stacker.push_scan(s.ranges, s.angle_min, s.angle_increment, s.range_min, s.range_max)
    assert out is not None
    return out


def test_first_two_scans_give_no_tensor_then_one_per_scan() -> None:
    core = EncoderCore("zero")
    scans = [scan("r1", i) for i in range(5)]
    out = [core.push(s) for s in scans]
    assert out[0] is None and out[1] is None
    for t in range(2, 5):
        tensor = out[t]
        assert isinstance(tensor, StackedTensor)
        assert tensor.seq == t and tensor.scan_seqs == (t - 2, t - 1, t)
        assert tensor.scan_stamps_ns == tuple(scans[i].stamp_ns for i in (t - 2, t - 1, t))
        np.testing.assert_array_equal(tensor.tensor, expected_tensor(*scans[t - 2 : t + 1]))
        assert tensor.encode_ms >= 0.0
    assert core.counters.warming_up == 2 and core.counters.published == 3


def test_robots_never_share_a_fifo() -> None:
    core = EncoderCore("zero")
    a = [scan("a", i, distance=1.0) for i in range(3)]
    b = [scan("b", i, distance=2.5) for i in range(3)]
    outputs = [core.push(s) for pair in zip(a, b, strict=True) for s in pair]  # interleaved a0 b0 a1 b1 …
    ta, tb = outputs[4], outputs[5]
    assert ta is not None and tb is not None and ta.robot_id == "a" and tb.robot_id == "b"
    np.testing.assert_array_equal(ta.tensor, expected_tensor(*a))
    np.testing.assert_array_equal(tb.tensor, expected_tensor(*b))


def test_gap_restarts_the_fifo_so_no_tensor_spans_it() -> None:
    core = EncoderCore("zero")
    for i in range(3):
        core.push(scan("r", i))
    assert core.push(scan("r", 5)) is None  # scans 3 and 4 were lost
    assert core.push(scan("r", 6)) is None
    tensor = core.push(scan("r", 7))
    assert tensor is not None and tensor.scan_seqs == (5, 6, 7)
    assert core.counters.gaps == 1


def test_out_of_order_and_duplicates_are_dropped_and_counted() -> None:
    core = EncoderCore("zero")
    for i in range(4):
        core.push(scan("r", i))
    assert core.push(scan("r", 2)) is None  # late
    assert core.push(scan("r", 3)) is None  # duplicate
    assert core.counters.rejected["out_of_order"] == 2
    tensor = core.push(scan("r", 4))  # the stream goes on as if nothing happened
    assert tensor is not None and tensor.scan_seqs == (2, 3, 4)


def test_publisher_restart_never_mixes_old_and_new_frames() -> None:
    core = EncoderCore("zero")
    for i in range(50, 53):
        core.push(scan("r", i, stamp_ns=i * 100))
    # The simulator restarted: seq counts from 0 again, stamps are newer.
    assert core.push(scan("r", 0, stamp_ns=10_000)) is None
    assert core.push(scan("r", 1, stamp_ns=10_100)) is None
    tensor = core.push(scan("r", 2, stamp_ns=10_200))
    assert tensor is not None and tensor.scan_seqs == (0, 1, 2)
    assert core.counters.restarts == 1


def test_silent_robot_is_forgotten_and_starts_fresh() -> None:
    clock = FakeClock()
    core = EncoderCore("zero", forget_after_s=5.0, clock=clock)
    for i in range(3):
        core.push(scan("quiet", i))
    clock.now = 3.0
    core.push(scan("busy", 0))
    clock.now = 6.0
    assert core.forget_silent() == ["quiet"]
    assert core.robot_ids == ["busy"]
    assert core.push(scan("quiet", 3)) is None  # a fresh stream: two more scans before a tensor
    assert core.counters.forgotten_robots == 1


def test_bad_payloads_are_counted_by_reason_and_lose_nothing_else() -> None:
    core = EncoderCore("zero")
    good = [encode_message(scan("r", i)) for i in range(3)]
    assert core.handle_payload(good[0], "r") is None
    assert core.handle_payload(b"\x00garbage", "r") is None
    assert core.handle_payload(good[1], "r") is None
    assert core.handle_payload(good[2], "someone_else") is None  # key and payload disagree
    tensor = core.handle_payload(good[2], "r")
    assert tensor is not None and tensor.scan_seqs == (0, 1, 2)
    assert sum(core.counters.rejected.values()) == 2
    assert core.counters.rejected["robot_id_mismatch"] == 1
    assert core.counters.received == 5
    assert decode_message(encode_message(tensor), StackedTensor).scan_seqs == (0, 1, 2)


def test_unencodable_scan_is_rejected_and_treated_as_a_gap() -> None:
    core = EncoderCore("zero")
    core.push(scan("r", 0))
    core.push(scan("r", 1))
    with pytest.raises(ScanError):
        encode_scan(np.ones(360, np.float32), float("nan"), DEG, 0.12, 3.5)
    bad = scan("r", 2).model_copy(update={"angle_min": float("nan")})
    assert core.push(bad) is None
    assert core.counters.rejected["bad_scan"] == 1
    assert core.push(scan("r", 3)) is None  # restarts after the hole at seq 2
    assert core.counters.gaps == 1


def test_robot_limit_bounds_memory() -> None:
    clock = FakeClock()
    core = EncoderCore("zero", max_robots=2, clock=clock)
    core.push(scan("a", 0))
    core.push(scan("b", 0))
    assert core.push(scan("c", 0)) is None
    assert core.counters.rejected["too_many_robots"] == 1
    clock.now = 100.0  # a and b went silent: room for c
    core.push(scan("c", 1))
    assert core.robot_ids == ["c"]


def test_clock_jump_back_restarts_the_fifo() -> None:
    core = EncoderCore("zero")
    for i in range(3):
        core.push(scan("r", i, stamp_ns=1_000 + i))
    assert core.push(scan("r", 3, stamp_ns=500)) is None  # next seq, older stamp: the clock jumped back
    assert core.push(scan("r", 4, stamp_ns=501)) is None
    tensor = core.push(scan("r", 5, stamp_ns=502))
    assert tensor is not None and tensor.scan_stamps_ns == (500, 501, 502)
    assert core.counters.restarts == 1


def test_tensors_carry_the_invalid_rule_they_were_made_with() -> None:
    from common.encoding import SENTINEL_ROW

    scans = [scan("r1", seq, distance=np.inf) for seq in range(3)]  # blind but for one 0.5 m return
    sentinel, empty = EncoderCore("zero"), EncoderCore("zero", invalid="empty")
    a = next(t for s in scans if (t := sentinel.push(s)) is not None)
    b = next(t for s in scans if (t := empty.push(s)) is not None)
    assert (a.invalid, b.invalid) == ("sentinel", "empty")
    assert a.tensor[SENTINEL_ROW, :360].sum() > 0 and not b.tensor[SENTINEL_ROW].any()
    assert b.tensor.any()  # the valid 0.5 m returns are drawn under both rules
    with pytest.raises(ScanError, match="invalid must be one of"):
        EncoderCore("zero", invalid="drop")  # type: ignore[arg-type]


def _stream(rate_hz: float, count: int) -> list[Scan]:
    period_ns = round(1e9 / rate_hz)
    return [
        scan("r", seq, stamp_ns=1_000_000_000 + seq * period_ns, distance=1.0 + 0.01 * seq)
        for seq in range(count)
    ]


def test_a_fast_sensor_is_stacked_at_the_models_period() -> None:
    """A 40 Hz stream for a model trained on scans 0.1 s apart: every 4th scan is stacked."""
    core = EncoderCore(stack_period_s=0.1)
    tensors = [t for s in _stream(40.0, 60) if (t := core.push(s)) is not None]
    assert tensors, "tensors come once the interval is learnt"
    for tensor in tensors:
        a, b, c = tensor.scan_seqs
        assert b - a == 4 and c - b == 4
        assert tensor.scan_stamps_ns[2] - tensor.scan_stamps_ns[1] == 4 * 25_000_000
    assert core.counters.between_stacked >= 40
    assert core.counters.gaps == 0
    # The tensor is made of exactly the picked scans.
    picked = {s.seq: s for s in _stream(40.0, 60)}
    last = tensors[-1]
    np.testing.assert_array_equal(last.tensor, expected_tensor(*(picked[q] for q in last.scan_seqs)))


def test_without_a_period_or_from_a_slow_sensor_scans_are_stacked_as_they_come(
    caplog: pytest.LogCaptureFixture,
) -> None:
    plain = EncoderCore()
    assert next(t.scan_seqs for s in _stream(40.0, 6) if (t := plain.push(s)) is not None) == (0, 1, 2)
    slow = EncoderCore(stack_period_s=0.1)
    with caplog.at_level("WARNING"):
        seqs = [t.scan_seqs for s in _stream(5.5, 12) if (t := slow.push(s)) is not None]
    assert seqs[0] == (0, 1, 2) and seqs[-1] == (9, 10, 11)
    assert sum("stacking them as they come" in r.message for r in caplog.records) == 1, "logged once"


def test_a_lost_scan_of_a_fast_sensor_is_a_gap_among_the_stacked_ones() -> None:
    core = EncoderCore(stack_period_s=0.1)
    stream = [s for s in _stream(40.0, 40) if s.seq != 21]
    tensors = [t for s in stream if (t := core.push(s)) is not None]
    assert core.counters.gaps == 0  # 21 was between stacked scans: nothing lost that mattered
    assert all(t.scan_seqs[1] - t.scan_seqs[0] == 4 for t in tensors)
    core = EncoderCore(stack_period_s=0.1)
    stack = [t.scan_seqs for s in _stream(40.0, 40) if (t := core.push(s)) is not None]
    lost = stack[-1][1]  # a scan that would be stacked
    core = EncoderCore(stack_period_s=0.1)
    for s in _stream(40.0, 40):
        if s.seq != lost:
            core.push(s)
    assert core.counters.gaps == 1


def with_odom(s: Scan, odom: Odometry) -> Scan:
    return Scan(**{**s.model_dump(exclude={"schema_version"}), "odom": odom})


def test_odometry_of_the_newest_scan_travels_into_the_tensor_and_a_nan_pose_is_refused_alone() -> None:
    core = EncoderCore("zero")
    poses = [Odometry(x_m=0.1 * i, y_m=0.0, yaw_rad=0.0, stamp_ns=i) for i in range(3)]
    out = [core.push(with_odom(scan("r1", i), poses[i])) for i in range(3)]
    tensor = out[2]
    assert tensor is not None and tensor.odom == poses[2]
    assert decode_message(encode_message(tensor), StackedTensor).odom == poses[2]
    nan_pose = Odometry(x_m=float("nan"), y_m=0.0, yaw_rad=0.0, stamp_ns=3)
    payload = encode_message(with_odom(scan("r1", 3), nan_pose))
    kept = core.handle_payload(payload, "r1")
    assert kept is not None and kept.odom is None and kept.seq == 3
    assert core.counters.odom_not_finite == 1 and not core.counters.rejected
    without = core.push(scan("r1", 4))
    assert without is not None and without.odom is None


@pytest.mark.parametrize(
    ("jump", "frame"),
    [((1.5, 0.0, 0.0), "odom"), ((0.0, 0.0, math.radians(45.0)), "odom"), ((0.0, 0.0, 0.0), "map")],
    ids=["moved", "turned", "other_frame"],
)
def test_an_odometry_jump_restarts_the_fifo_so_no_tensor_shows_two_places(
    jump: tuple[float, float, float], frame: str
) -> None:
    """A robot put somewhere else between two scans: a tensor of scans from both places would show
    motion that never happened, so the stack starts over at the jump."""
    core = EncoderCore("zero")
    dx, dy, dyaw = jump

    def pose(i: int, after: bool) -> Odometry:
        moved = (dx, dy, dyaw, frame) if after else (0.0, 0.0, 0.0, "odom")
        return Odometry(
            x_m=0.1 * i + moved[0], y_m=moved[1], yaw_rad=0.05 * i + moved[2], frame_id=moved[3], stamp_ns=i
        )

    out = [core.push(with_odom(scan("r1", i), pose(i, after=i >= 4))) for i in range(8)]
    assert [t is not None for t in out] == [False, False, True, True, False, False, True, True]
    assert core.counters.odom_jumps == 1 and core.counters.gaps == 0 and core.counters.restarts == 0
    tensor = out[6]
    assert tensor is not None and tensor.scan_seqs == (4, 5, 6) and tensor.odom == pose(6, after=True)


def test_steady_motion_a_missing_pose_or_a_nan_one_is_no_jump() -> None:
    """0.1 m and 0.05 rad a scan is a robot driving; a scan without a pose, or with a refused one, is
    compared with nothing, and the next pose is compared with the last good one."""
    core = EncoderCore("zero")
    poses = [Odometry(x_m=0.1 * i, y_m=0.0, yaw_rad=0.05 * i, stamp_ns=i) for i in range(8)]
    nan_pose = Odometry(x_m=float("nan"), y_m=0.0, yaw_rad=0.0, stamp_ns=5)
    scans = [with_odom(scan("r1", i), poses[i]) for i in range(8)]
    scans[3] = scan("r1", 3)
    scans[5] = with_odom(scan("r1", 5), nan_pose)
    out = [core.push(s) for s in scans]
    assert all(t is not None for t in out[2:]) and core.counters.odom_jumps == 0


def test_tensors_travel_as_their_lit_pixels_and_decode_to_the_dense_raster() -> None:
    """What the encoder process publishes (``encode_message`` of the core's tensor) for simulated scans."""
    core = EncoderCore("zero")
    tensors = [t for s in recorded_scans(8, seed=11) if (t := core.push(s)) is not None]
    assert len(tensors) == 6
    for tensor in tensors:
        payload = encode_message(tensor)
        body = msgpack.unpackb(payload)
        assert (
            body["schema_version"] == LIT_PIXELS_VERSION and "lit" in body["tensor"] and len(payload) < 4096
        )
        decoded = decode_message(payload, StackedTensor)
        assert decoded == tensor and decoded.tensor.tobytes() == tensor.tensor.tobytes()


def test_tensors_are_encoded_with_the_models_raster_yaw_and_say_so() -> None:
    scans = [scan("r1", i) for i in range(3)]
    plain = EncoderCore("zero").push  # the paper's raster: the field stays absent on the wire
    *_, paper = [plain(s) for s in scans]
    assert paper is not None and paper.raster_yaw_deg is None
    core = EncoderCore("zero", raster_yaw_deg=-180.0)
    assert core.raster_yaw_deg == 180.0
    *_, turned = [core.push(s) for s in scans]
    assert turned is not None and turned.raster_yaw_deg == 180.0
    assert np.array_equal(turned.tensor[:, :360], np.roll(paper.tensor[:, :360], 180, axis=1))
    assert decode_message(encode_message(turned), StackedTensor) == turned
    with pytest.raises(ScanError, match="raster yaw"):
        EncoderCore("zero", raster_yaw_deg=math.nan)
