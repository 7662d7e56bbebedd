"""Each formula of README "The encoding" against pixels computed by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from common.encoding import (
    IMAGE_WIDTH,
    R_MAX_M,
    SENTINEL_ROW,
    ScanError,
    ScanStacker,
    angle_columns,
    bearing_to_pixel_x,
    check_raster_yaw,
    encode_scan,
    pad_raster,
    pixel_x_to_bearing_deg,
    pixel_y_to_range_m,
    polar_to_xy,
    range_rows,
    range_to_pixel_y,
    raster_to_laser_bearing_deg,
    scan_points_xy,
    stack_rasters,
    to_model_input,
    wrap_bearing_deg,
)

DEG = math.pi / 180.0


def one_beam(bearing_deg: float, rho: float, range_min: float = 0.12, range_max: float = 3.5) -> np.ndarray:
    return encode_scan(np.array([rho]), bearing_deg * DEG, DEG, range_min, range_max)


def lit_pixels(raster: np.ndarray) -> list[tuple[int, int]]:
    return [(int(r), int(c)) for r, c in zip(*np.nonzero(raster), strict=True)]


@pytest.mark.parametrize(
    ("bearing_deg", "column"),
    [
        (0.0, 0),
        (0.49, 0),
        (0.5, 1),
        (1.0, 1),
        (179.5, 180),
        (359.0, 359),
        (359.49, 359),
        (359.5, 0),
        (360.0, 0),
        (-0.4, 0),
        (-0.5, 0),
        (-0.6, 359),
        (-90.0, 270),
        (721.0, 1),
    ],
)
def test_angle_column_rounds_half_up_and_wraps(bearing_deg: float, column: int) -> None:
    assert angle_columns(np.array([bearing_deg * DEG]))[0] == column
    assert lit_pixels(one_beam(bearing_deg, 1.0)) == [(15, column)]  # 1.0 m · 63 / 4 = 15.75 → row 15


@pytest.mark.parametrize(
    ("rho", "row"),
    [(0.0, 0), (0.0634, 0), (0.0635, 1), (1.0, 15), (2.0, 31), (3.5, 55), (3.99, 62), (4.0, 63), (9.0, 63)],
)
def test_range_row_floors_and_clips(rho: float, row: int) -> None:
    # 0.0635 m · 63 / 4 = 1.000125 → 1; 3.5 · 15.75 = 55.125 → 55; 3.99 · 15.75 = 62.84 → 62
    assert range_rows(np.array([rho]))[0] == row
    assert lit_pixels(one_beam(10.0, rho, range_min=0.0, range_max=10.0)) == [(row, 10)]


@pytest.mark.parametrize("bad", [math.inf, -math.inf, math.nan, 0.05, 3.6, -1.0])
def test_invalid_returns_become_the_sentinel_row(bad: float) -> None:
    raster = one_beam(42.0, bad)
    assert lit_pixels(raster) == [(SENTINEL_ROW, 42)]
    assert SENTINEL_ROW == 63 and R_MAX_M == 4.0


def test_full_scan_lights_one_pixel_per_beam() -> None:
    ranges = np.full(360, 2.0, dtype=np.float32)
    ranges[::2] = np.inf
    raster = encode_scan(ranges, 0.0, DEG, 0.12, 3.5)
    assert raster.shape == (64, 360) and raster.dtype == np.uint8
    assert set(np.unique(raster)) == {0, 255}
    assert np.all(raster[SENTINEL_ROW, ::2] == 255) and np.all(raster[31, 1::2] == 255)
    assert np.count_nonzero(raster) == 360


def test_denser_and_narrower_sensors_bin_by_their_own_angles() -> None:
    # 720 beams, 0.5° apart: two beams per column except where rounding half up shares them out.
    dense = encode_scan(np.full(720, 1.0), 0.0, 0.5 * DEG, 0.1, 10.0)
    assert np.count_nonzero(dense) == 360
    # A 180° sensor facing forward (−90°…+89°): only columns 270–359 and 0–89 are lit.
    narrow = encode_scan(np.full(180, 1.0), -90 * DEG, DEG, 0.1, 10.0)
    lit_columns = set(np.nonzero(narrow)[1].tolist())
    assert lit_columns == set(range(0, 90)) | set(range(270, 360))
    # A clockwise sensor (negative increment) lands its beams at the mirrored columns.
    clockwise = encode_scan(np.array([1.0, 1.0, 1.0]), 0.0, -DEG, 0.1, 10.0)
    assert set(np.nonzero(clockwise)[1].tolist()) == {0, 359, 358}


def test_zero_padding_leaves_columns_360_to_383_empty() -> None:
    raster = np.zeros((64, 360), dtype=np.uint8)
    raster[5, 3] = raster[7, 359] = 255
    padded = pad_raster(raster, "zero")
    assert padded.shape == (64, IMAGE_WIDTH)
    assert np.array_equal(padded[:, :360], raster)
    assert not padded[:, 360:].any()


def test_wrap_padding_repeats_columns_0_to_23() -> None:
    raster = np.zeros((64, 360), dtype=np.uint8)
    raster[5, 3] = raster[9, 23] = raster[11, 24] = 255
    padded = pad_raster(raster, "wrap")
    assert lit_pixels(padded[:, 360:]) == [(5, 3), (9, 23)]  # column 24 is not repeated
    assert padded[5, 363] == 255 and padded[9, 383] == 255


def test_unknown_padding_is_refused() -> None:
    with pytest.raises(ScanError, match="padding"):
        pad_raster(np.zeros((64, 360), np.uint8), "mirror")  # type: ignore[arg-type]
    with pytest.raises(ScanError, match="padding"):
        ScanStacker("mirror")  # type: ignore[arg-type]


def test_stack_puts_oldest_scan_in_channel_0() -> None:
    frames = [pad_raster(one_beam(b, 1.0)) for b in (10.0, 20.0, 30.0)]
    tensor = stack_rasters(*frames)
    assert tensor.shape == (64, 384, 3) and tensor.dtype == np.uint8
    assert lit_pixels(tensor[:, :, 0]) == [(15, 10)]
    assert lit_pixels(tensor[:, :, 1]) == [(15, 20)]
    assert lit_pixels(tensor[:, :, 2]) == [(15, 30)]


def test_stacker_fifo_keeps_the_last_three_in_order() -> None:
    stacker = ScanStacker()
    outputs = [stacker.push_scan(np.array([1.0]), b * DEG, DEG, 0.12, 3.5) for b in (10, 20, 30, 40)]
    assert outputs[0] is None and outputs[1] is None
    assert [lit_pixels(outputs[2][:, :, c])[0][1] for c in range(3)] == [10, 20, 30]
    assert [lit_pixels(outputs[3][:, :, c])[0][1] for c in range(3)] == [20, 30, 40]
    stacker.reset()
    assert len(stacker) == 0 and not stacker.ready


@pytest.mark.parametrize("padding", ["zero", "wrap"])
@pytest.mark.parametrize("invalid", ["sentinel", "empty"])
def test_stacker_equals_the_reference_raster_path(padding: str, invalid: str) -> None:
    """The stacker's lit-pixel FIFO gives exactly Algorithm 1's rasters, padded and stacked."""
    rng = np.random.default_rng(7)
    stacker = ScanStacker(padding, invalid)  # type: ignore[arg-type]
    rasters = []
    for beams in (360, 720, 1081, 250, 360):  # denser, narrower, seam-crossing sensors in one stream
        ranges = rng.uniform(0.0, 5.0, beams)
        ranges[rng.random(beams) < 0.1] = rng.choice([np.nan, np.inf, 0.01, 9.0])
        angle_min, increment = rng.uniform(-np.pi, np.pi), rng.choice([-1.0, 1.0]) * 2 * np.pi / beams
        tensor = stacker.push_scan(ranges, angle_min, increment, 0.12, 3.5)
        rasters.append(pad_raster(encode_scan(ranges, angle_min, increment, 0.12, 3.5, invalid), padding))
        if len(rasters) >= 3:
            assert tensor is not None and np.array_equal(tensor, stack_rasters(*rasters[-3:]))
        else:
            assert tensor is None


def test_stacker_keeps_its_fifo_when_a_scan_is_bad() -> None:
    stacker = ScanStacker()
    stacker.push_scan(np.array([1.0]), 0.0, DEG, 0.12, 3.5)
    with pytest.raises(ScanError):
        stacker.push_scan(np.array([]), 0.0, DEG, 0.12, 3.5)
    assert len(stacker) == 1


@pytest.mark.parametrize(
    ("ranges", "angle_min", "increment", "rmin", "rmax", "message"),
    [
        (np.array([]), 0.0, DEG, 0.1, 3.5, "empty"),
        (np.ones((2, 3)), 0.0, DEG, 0.1, 3.5, "one-dimensional"),
        (np.array(["a", "b"]), 0.0, DEG, 0.1, 3.5, "numeric"),
        (np.ones(3), math.nan, DEG, 0.1, 3.5, "angle_min"),
        (np.ones(3), 0.0, 0.0, 0.1, 3.5, "non-zero"),
        (np.ones(3), 0.0, math.inf, 0.1, 3.5, "angle_increment"),
        (np.ones(3), 0.0, DEG, 3.5, 0.1, "range_min < range_max"),
        (np.ones(3), 0.0, DEG, -1.0, 3.5, "range_min < range_max"),
    ],
)
def test_bad_scans_raise_a_clear_error(ranges, angle_min, increment, rmin, rmax, message) -> None:
    with pytest.raises(ScanError, match=message):
        encode_scan(ranges, angle_min, increment, rmin, rmax)


def test_pixel_mapping_inverts_the_encoding() -> None:
    assert bearing_to_pixel_x(10.0) == 10.5  # column 10 is centred on 10°
    assert pixel_x_to_bearing_deg(10.5) == 10.0
    assert range_to_pixel_y(4.0) == pytest.approx(63.0)
    assert pixel_y_to_range_m(15.75) == pytest.approx(1.0)
    # A beam's pixel contains the continuous coordinates of its bearing and range.
    raster = one_beam(123.3, 2.2)
    ((row, col),) = lit_pixels(raster)
    assert col <= bearing_to_pixel_x(123.3) < col + 1 and row <= range_to_pixel_y(2.2) < row + 1


def test_bearings_wrap_to_plus_minus_180_and_map_to_rep103_xy() -> None:
    assert np.allclose(
        wrap_bearing_deg([0.0, 180.0, 190.0, 359.0, -180.0, 540.0]), [0.0, 180.0, -170.0, -1.0, 180.0, 180.0]
    )
    xy = polar_to_xy([0.0, 90.0, 180.0], [1.0, 2.0, 3.0])
    assert np.allclose(xy, [[1.0, 0.0], [0.0, 2.0], [-3.0, 0.0]])  # x forward, y left


def test_scan_points_leave_invalid_beams_out() -> None:
    points = scan_points_xy(np.array([1.0, np.inf, np.nan, 2.0]), 0.0, 90 * DEG, 0.12, 3.5)
    assert np.allclose(points, [[1.0, 0.0], [0.0, -2.0]])


def test_model_input_keeps_channel_order_and_scales() -> None:
    tensor = np.zeros((64, 384, 3), dtype=np.uint8)
    tensor[1, 2, 0] = 255
    tensor[3, 4, 2] = 51
    model_input = to_model_input(tensor)
    assert model_input.shape == (1, 3, 64, 384) and model_input.dtype == np.float32
    assert model_input[0, 0, 1, 2] == 1.0 and model_input[0, 2, 3, 4] == pytest.approx(0.2)
    with pytest.raises(ScanError):
        to_model_input(np.zeros((64, 360, 3), dtype=np.uint8))


def test_model_input_is_contiguous_and_bit_identical_to_the_training_conversion() -> None:
    # Every byte value in every channel, so a rounding difference anywhere would show.
    tensor = np.random.default_rng(3).integers(0, 256, (64, 384, 3), dtype=np.uint8)
    tensor[0, :256, 1] = np.arange(256, dtype=np.uint8)
    model_input = to_model_input(tensor)
    training = tensor.transpose(2, 0, 1)[None].astype(np.float32) / np.float32(255.0)
    assert model_input.flags.c_contiguous
    assert model_input.tobytes() == np.ascontiguousarray(training).tobytes()


def test_model_input_writes_into_a_batch_slot() -> None:
    frames = [np.full((64, 384, 3), value, dtype=np.uint8) for value in (0, 51, 255)]
    batch = np.full((3, 3, 64, 384), -1.0, np.float32)
    for index, frame in enumerate(frames):
        slot = batch[index : index + 1]
        assert to_model_input(frame, slot) is slot
    assert [float(batch[i].min()) for i in range(3)] == [0.0, pytest.approx(0.2), 1.0]
    assert batch.tobytes() == np.concatenate([to_model_input(f) for f in frames]).tobytes()
    with pytest.raises(ValueError, match="C-contiguous float32"):
        to_model_input(frames[0], np.zeros((1, 64, 384, 3), np.float32))
    with pytest.raises(ValueError, match="C-contiguous float32"):
        to_model_input(frames[0], np.zeros((1, 3, 64, 768), np.float32)[..., ::2])


def test_invalid_rule_empty_leaves_invalid_beams_dark() -> None:
    from common.encoding import SENTINEL_ROW

    ranges = np.array([1.0, np.inf, np.nan, 0.05, 9.0, 2.0])
    sentinel = encode_scan(ranges, 0.0, math.radians(1.0), 0.12, 3.5)
    empty = encode_scan(ranges, 0.0, math.radians(1.0), 0.12, 3.5, invalid="empty")
    assert sentinel[SENTINEL_ROW, 1:5].tolist() == [255] * 4
    assert empty[SENTINEL_ROW].sum() == 0 and np.count_nonzero(empty) == 2
    assert np.array_equal(empty[:, [0, 5]], sentinel[:, [0, 5]])
    with pytest.raises(ScanError, match="invalid must be one of"):
        encode_scan(ranges, 0.0, 0.01, 0.12, 3.5, invalid="drop")  # type: ignore[arg-type]
    with pytest.raises(ScanError, match="invalid must be one of"):
        ScanStacker("zero", "drop")  # type: ignore[arg-type]
    stacker = ScanStacker("zero", "empty")
    for _ in range(3):
        tensor = stacker.push_scan(ranges, 0.0, math.radians(1.0), 0.12, 3.5)
    assert tensor is not None and tensor[SENTINEL_ROW].sum() == 0


# --- raster yaw ----------------------------------------------------------------------------------------


def test_a_raster_yaw_turns_every_beam_by_whole_columns_and_zero_is_the_papers_raster() -> None:
    rng = np.random.default_rng(3)
    ranges = rng.uniform(0.2, 3.4, 271)
    geometry = (math.radians(-135.0), DEG, 0.12, 3.5)  # a 270° sensor, one beam per degree
    plain = encode_scan(ranges, *geometry)
    assert np.array_equal(encode_scan(ranges, *geometry, raster_yaw_deg=0.0), plain)
    turned = encode_scan(ranges, *geometry, raster_yaw_deg=180.0)
    assert np.array_equal(turned, np.roll(plain, 180, axis=1))
    # The 90 columns a 270° sensor never sees lie around column 0 after the turn: behind the robot.
    dark = np.flatnonzero(~turned.any(axis=0))
    assert set(dark) == set(range(316, 360)) | set(range(0, 45))
    # Taken mod 360: −180 and 540 are the same turn; a non-integer yaw rounds in the turned frame.
    assert np.array_equal(encode_scan(ranges, *geometry, raster_yaw_deg=-180.0), turned)
    assert np.array_equal(encode_scan(ranges, *geometry, raster_yaw_deg=540.0), turned)
    assert lit_pixels(encode_scan(np.array([1.0]), 10.3 * DEG, DEG, 0.12, 3.5, raster_yaw_deg=0.4)) == [
        (15, 11)
    ]


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, "ahead"])
def test_a_raster_yaw_must_be_a_finite_number(bad: object) -> None:
    with pytest.raises(ScanError, match="raster yaw"):
        check_raster_yaw(bad)  # type: ignore[arg-type]
    with pytest.raises(ScanError, match="raster yaw"):
        ScanStacker(raster_yaw_deg=bad)  # type: ignore[arg-type]


def test_raster_yaw_is_taken_mod_360_and_bearings_turn_back() -> None:
    assert [check_raster_yaw(v) for v in (0, 180, -90, 720.5, -1e-20)] == [0.0, 180.0, 270.0, 0.5, 0.0]
    assert ScanStacker(raster_yaw_deg=-180).raster_yaw_deg == 180.0
    # Column 180 of a raster turned by 180° is bearing 0 of the laser, forward.
    raster_bearing = pixel_x_to_bearing_deg(180.5)
    assert float(wrap_bearing_deg(raster_to_laser_bearing_deg(raster_bearing, 180.0))) == 0.0
    assert float(raster_to_laser_bearing_deg(raster_bearing, 0.0)) == raster_bearing


def test_the_stacker_turns_every_scan_by_its_yaw() -> None:
    ranges = np.linspace(0.3, 3.0, 360)
    plain, turned = ScanStacker(), ScanStacker(raster_yaw_deg=180.0)
    for k in range(3):
        a = plain.push_scan(np.roll(ranges, k), 0.0, DEG, 0.12, 3.5)
        b = turned.push_scan(np.roll(ranges, k), 0.0, DEG, 0.12, 3.5)
    assert a is not None and b is not None
    expected = np.roll(a[:, :360], 180, axis=1)
    assert np.array_equal(b[:, :360], expected) and not b[:, 360:].any()
