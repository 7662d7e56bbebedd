"""Property-based tests of the encoder and the encoder service's stream rules (hypothesis).

Whatever a sensor sends — any beam count, any field of view, NaN, inf, negative or huge ranges — the
raster is well formed and every beam is accounted for; and whatever order scans arrive in, the
encoder never raises and never emits a tensor whose scans are not three consecutive ones in time order.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from common.encoding import (
    ANGLE_COLUMNS,
    RANGE_ROWS,
    ScanError,
    ScanStacker,
    angle_columns,
    beam_bearings_rad,
    encode_scan,
)
from common.messages import Scan
from services.encoder.core import EncoderCore

range_values = st.one_of(
    st.floats(min_value=-10.0, max_value=100.0, allow_nan=False, width=32),
    st.just(float("nan")),
    st.just(float("inf")),
    st.just(float("-inf")),
)


@st.composite
def scans(draw: st.DrawFn) -> tuple[np.ndarray, float, float, float, float]:
    beams = draw(st.integers(min_value=1, max_value=1440))
    fov = draw(st.floats(min_value=0.1, max_value=2 * math.pi))
    increment = fov / beams * draw(st.sampled_from([1.0, -1.0]))
    angle_min = draw(st.floats(min_value=-4 * math.pi, max_value=4 * math.pi))
    range_min = draw(st.floats(min_value=0.0, max_value=1.0))
    range_max = range_min + draw(st.floats(min_value=0.1, max_value=30.0))
    ranges = np.array(draw(st.lists(range_values, min_size=beams, max_size=beams)), dtype=np.float32)
    return ranges, angle_min, increment, range_min, range_max


@settings(max_examples=200, deadline=None)
@given(scans())
def test_any_scan_gives_a_binary_raster_with_one_hit_per_beam_column(scan: tuple) -> None:
    ranges, angle_min, increment, range_min, range_max = scan
    raster = encode_scan(ranges, angle_min, increment, range_min, range_max)
    assert raster.shape == (RANGE_ROWS, ANGLE_COLUMNS) and raster.dtype == np.uint8
    assert set(np.unique(raster).tolist()) <= {0, 255}
    # Every beam marks exactly one pixel in its own column (invalid returns in the sentinel row):
    # the hit columns are exactly the beams' columns, with at least one hit each.
    columns = np.unique(angle_columns(beam_bearings_rad(angle_min, increment, ranges.size)))
    hit_columns = np.flatnonzero(raster.any(axis=0))
    np.testing.assert_array_equal(hit_columns, columns)
    assert np.count_nonzero(raster) <= ranges.size


@pytest.mark.filterwarnings("error::RuntimeWarning")  # no overflow or invalid cast on the way either
@settings(max_examples=300, deadline=None)
@given(
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(allow_nan=True, allow_infinity=True),
    st.floats(allow_nan=True, allow_infinity=True),
)
def test_nonsensical_sensor_parameters_raise_scan_error_or_encode(
    angle_min: float, increment: float, range_max: float
) -> None:
    stacker = ScanStacker("zero")
    try:
        stacker.push_scan(np.ones(360, np.float32), angle_min, increment, 0.1, range_max)
    except ScanError:
        assert len(stacker) == 0  # a refused scan leaves the FIFO untouched
    else:
        assert len(stacker) == 1


def make_scan(seq: int, stamp: int) -> Scan:
    return Scan(
        robot_id="r",
        seq=seq,
        stamp_ns=stamp,
        angle_min=0.0,
        angle_increment=math.radians(1.0),
        range_min=0.12,
        range_max=3.5,
        ranges=np.full(360, 1.0 + (seq % 7) / 10, dtype=np.float32),
    )


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 30), st.integers(0, 30)), min_size=1, max_size=60))
def test_any_arrival_order_yields_only_consecutive_time_ordered_tensors(arrivals: list) -> None:
    core = EncoderCore("zero")
    for seq, stamp in arrivals:
        tensor = core.push(make_scan(seq, stamp))
        if tensor is not None:
            a, b, c = tensor.scan_seqs
            assert (b, c) == (a + 1, a + 2) and c == seq
            s0, s1, s2 = tensor.scan_stamps_ns
            assert s0 <= s1 <= s2  # never backwards (a clock jump restarts the FIFO)
    counted = core.counters
    assert counted.received == len(arrivals)
    assert counted.published + counted.warming_up + sum(counted.rejected.values()) == len(arrivals)
