"""``triscan show``: the raster picture and the top-down map of one data-set sample.

The expectations are computed here from the data set's own files (PNG, YOLO lines, poses) with the
formulas of README "The encoding", not the module's helpers, so a wrong magnification, a mirrored bearing, a
wrong channel or a misplaced box makes a test fail.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

pytest.importorskip("pybullet")  # generating the tiny data set needs the simulator extra

from common.model_spec import CLASS_COLOURS
from services.cli import main as cli_main
from training.dataset import DatasetConfig, generate_dataset
from training.map_picture import MAP_BOTTOM_MARGIN, MAP_ORIGIN, MAP_PANEL_WIDTH, decode_hits
from training.picture_style import AXIS
from training.pictures import render_sample
from training.raster_picture import RASTER_ORIGIN

ROWS_PER_M = 63 / 4.0


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("pictures") / "ds"
    generate_dataset(DatasetConfig(out=out, scenarios=3, positions=2, seed=1, workers=1), progress=False)
    return out


def records(dataset: Path) -> list[dict]:
    return [json.loads(line) for line in (dataset / "samples.jsonl").read_text().splitlines()]


def yolo_boxes(dataset: Path, record: dict) -> list[tuple[int, float, float, float, float]]:
    """(class, x1, y1, x2, y2) in raster pixels, read straight from the label file."""
    split, name = Path(record["image"]).parts[1], Path(record["image"]).stem
    boxes = []
    for line in (dataset / "labels" / split / f"{name}.txt").read_text().splitlines():
        cls, xc, yc, w, h = line.split()
        xc, yc, w, h = float(xc) * 384, float(yc) * 64, float(w) * 384, float(h) * 64
        boxes.append((int(cls), xc - w / 2, yc - h / 2, xc + w / 2, yc + h / 2))
    return boxes


def richest_sample(dataset: Path) -> int:
    """Index of a sample with the most distinct labelled classes (ties: the first)."""
    counts = [len({b[0] for b in yolo_boxes(dataset, r)}) for r in records(dataset)]
    return int(np.argmax(counts))


def pixels(path: Path) -> np.ndarray:
    with Image.open(path) as image:
        assert image.mode == "RGB"
        return np.asarray(image)


def test_decode_hits_inverts_the_encoding_and_skips_sentinel_and_padding() -> None:
    tensor = np.zeros((64, 384, 3), dtype=np.uint8)
    tensor[10, 90, 1] = 255  # t-1: bearing 90° (left of the sensor), row 10
    tensor[0, 0, 0] = 255  # t-2: straight ahead, nearest row
    tensor[63, 45, 2] = 255  # sentinel row: "no return", not a point
    tensor[5, 370, 2] = 255  # padding column: a copy (wrap) or nothing (zero), never a beam of its own
    oldest, middle, newest = decode_hits(tensor, (1.0, 2.0, math.pi / 2))  # sensor facing +y
    rho = 10.5 / ROWS_PER_M
    np.testing.assert_allclose(middle, [[1.0 - rho, 2.0]], atol=1e-12)  # left of +y is -x
    np.testing.assert_allclose(oldest, [[1.0, 2.0 + 0.5 / ROWS_PER_M]], atol=1e-12)
    assert newest.shape == (0, 2)


def test_render_by_index_writes_both_pngs_named_after_the_sample(dataset: Path, tmp_path: Path) -> None:
    record = records(dataset)[1]
    name = Path(record["image"]).stem
    raster_png, map_png = render_sample(dataset, tmp_path / "new" / "dir", sample=None, index=1, scale=3)
    assert raster_png == tmp_path / "new" / "dir" / f"{name}_raster.png"
    assert map_png == tmp_path / "new" / "dir" / f"{name}_map.png"
    raster, top_down = pixels(raster_png), pixels(map_png)
    ox, oy = RASTER_ORIGIN
    assert raster.shape[1] >= ox + 384 * 3 and raster.shape[0] > oy + 64 * 3
    assert top_down.shape == (
        MAP_ORIGIN[1] + 660 + MAP_BOTTOM_MARGIN,
        MAP_ORIGIN[0] + 660 + MAP_PANEL_WIDTH,
        3,
    )


def test_scale_magnifies_the_raster(dataset: Path, tmp_path: Path) -> None:
    """The frame drawn round the raster sits exactly 384·scale × 64·scale pixels from its origin."""
    ox, oy = RASTER_ORIGIN
    for scale in (2, 3, 5):
        raster_png, _ = render_sample(dataset, tmp_path / f"s{scale}", sample=None, index=0, scale=scale)
        picture = pixels(raster_png)
        right = picture[oy : oy + 64 * scale, ox + 384 * scale]
        bottom = picture[oy + 64 * scale, ox : ox + 384 * scale]
        inside = picture[oy + 1 : oy + 64 * scale - 1, ox + 384 * scale - 2]
        frame = np.array(AXIS)
        assert np.all(right == frame) and np.all(bottom == frame)
        assert not np.all(inside == frame)  # the column just inside is raster, not frame


def test_render_by_name_path_or_stem_gives_the_same_pictures(dataset: Path, tmp_path: Path) -> None:
    record = records(dataset)[-1]
    image_rel = record["image"]
    by_path = render_sample(dataset, tmp_path / "a", sample=image_rel, index=0, scale=3)
    by_stem = render_sample(dataset, tmp_path / "b", sample=Path(image_rel).stem, index=0, scale=3)
    by_index = render_sample(dataset, tmp_path / "c", sample=None, index=len(records(dataset)) - 1, scale=3)
    assert by_path[0].name == f"{Path(image_rel).stem}_raster.png"
    for one, other, third in zip(by_path, by_stem, by_index, strict=True):
        assert one.read_bytes() == other.read_bytes() == third.read_bytes()  # also: deterministic


def test_raster_shows_each_lit_pixel_magnified_in_its_channel(dataset: Path, tmp_path: Path) -> None:
    index, scale = richest_sample(dataset), 4
    record = records(dataset)[index]
    tensor = pixels(dataset / record["image"])
    raster_png, _ = render_sample(dataset, tmp_path, sample=None, index=index, scale=scale)
    picture = pixels(raster_png)
    ox, oy = RASTER_ORIGIN
    shown = picture[oy : oy + 64 * scale, ox : ox + 384 * scale]
    # Leave out pixels near a box edge or tag: those are drawn over on purpose.
    near_box = np.zeros((64, 384), dtype=bool)
    for _, x1, y1, x2, y2 in yolo_boxes(dataset, record):
        near_box[max(int(y1) - 5, 0) : math.ceil(y2) + 1, max(int(x1) - 1, 0) : math.ceil(x2) + 1] = True
    rows, cols = np.nonzero(tensor.any(axis=-1) & ~near_box)
    assert len(rows) > 100
    centre = shown[rows * scale + scale // 2, cols * scale + scale // 2]
    lit = tensor[rows, cols] == 255
    assert np.all(centre[lit] == 255), "a lit channel is not shown at its magnified pixel"
    # An unlit raster pixel keeps its block's interior dark: the display dilation tints one screen
    # pixel round a lit block, never more, so the picture does not overstate where the hits are.
    dark_rows, dark_cols = np.nonzero(~tensor.any(axis=-1) & ~near_box)
    blocks = shown[: 64 * scale, : 384 * scale].reshape(64, scale, 384, scale, 3)
    interiors = blocks[dark_rows, 1 : scale - 1, dark_cols, 1 : scale - 1]
    assert not np.any(interiors == 255)


def test_raster_draws_each_label_box_in_its_class_colour(dataset: Path, tmp_path: Path) -> None:
    index, scale = richest_sample(dataset), 3
    record = records(dataset)[index]
    boxes = yolo_boxes(dataset, record)
    assert len({b[0] for b in boxes}) >= 3, "the tiny set should have a sample showing most classes"
    raster_png, _ = render_sample(dataset, tmp_path, sample=None, index=index, scale=scale)
    picture = pixels(raster_png)
    ox, oy = RASTER_ORIGIN
    for cls, x1, y1, x2, y2 in boxes:
        colour = np.array(CLASS_COLOURS[cls])
        left, right = ox + round(x1 * scale), ox + round(x2 * scale) - 1
        top, bottom = oy + round(y1 * scale), oy + round(y2 * scale) - 1
        edges = {
            "left": picture[top : bottom + 1, left],
            "right": picture[top : bottom + 1, right],
            "bottom": picture[bottom, left : right + 1],
        }
        for side, line in edges.items():
            match = np.all(line == colour, axis=-1).mean()
            assert match >= 0.5, f"class {cls} box: only {match:.0%} of its {side} edge has its colour"
        # Just outside the box (two pixels left of the left edge) is not the box colour.
        outside = picture[top + 2 : bottom - 1, left - 3]
        assert np.all(outside == colour, axis=-1).mean() < 0.5


def test_map_shows_hits_decoded_from_the_png_where_the_pose_puts_them(dataset: Path, tmp_path: Path) -> None:
    index = richest_sample(dataset)
    record = records(dataset)[index]
    tensor = pixels(dataset / record["image"])
    x, y, yaw = record["lidar_pose"]
    _, map_png = render_sample(dataset, tmp_path, sample=None, index=index, scale=3)
    picture = pixels(map_png)
    for channel in range(3):
        rows, cols = np.nonzero(tensor[:63, :360, channel])
        ranges = (rows + 0.5) / ROWS_PER_M
        keep = ranges > 0.4  # clear of the robot drawing
        theta = np.radians(cols[keep]) + yaw  # column a is bearing a°, counter-clockwise
        wx, wy = x + ranges[keep] * np.cos(theta), y + ranges[keep] * np.sin(theta)
        u = np.rint(MAP_ORIGIN[0] + (wx + 3.3) * 100).astype(int)
        v = np.rint(MAP_ORIGIN[1] + (3.3 - wy) * 100).astype(int)
        assert len(u) > 50
        at_hits = picture[v, u]
        hit_coloured = np.all((at_hits == 0) | (at_hits == 255), axis=-1) & (at_hits[:, channel] == 255)
        assert hit_coloured.mean() >= 0.9, f"channel {channel}: {hit_coloured.mean():.0%} of hits found"
        map_area = picture[MAP_ORIGIN[1] : MAP_ORIGIN[1] + 660, MAP_ORIGIN[0] : MAP_ORIGIN[0] + 660]
        assert (map_area[..., channel] == 255).mean() < 0.1  # the match above is not luck


def test_map_draws_the_robot_three_centimetres_ahead_of_the_lidar(dataset: Path, tmp_path: Path) -> None:
    record = records(dataset)[0]
    x, y, yaw = record["lidar_pose"]
    _, map_png = render_sample(dataset, tmp_path, sample=None, index=0, scale=3)
    picture = pixels(map_png)
    cx, cy = x + 0.03 * math.cos(yaw), y + 0.03 * math.sin(yaw)
    # Points on the outline (radius 0.105 m, 2 px wide): behind the centre and to either side.
    for along, across in ((-0.1, 0.0), (0.0, -0.1), (0.0, 0.1)):
        px = cx + along * math.cos(yaw) - across * math.sin(yaw)
        py = cy + along * math.sin(yaw) + across * math.cos(yaw)
        u, v = round(MAP_ORIGIN[0] + (px + 3.3) * 100), round(MAP_ORIGIN[1] + (3.3 - py) * 100)
        patch = picture[v - 1 : v + 2, u - 1 : u + 2].reshape(-1, 3)
        assert np.any(np.all(patch == 255, axis=-1)), "robot outline not where the pose puts it"


def test_cli_show_writes_the_pictures_and_reports_bad_input(dataset: Path, tmp_path: Path) -> None:
    assert cli_main(["show", "--dataset", str(dataset), "--index", "0", "--out", str(tmp_path / "ok")]) == 0
    assert len(list((tmp_path / "ok").glob("*.png"))) == 2
    assert (
        cli_main(["show", "--dataset", str(dataset), "--sample", "nope", "--out", str(tmp_path / "x")]) == 2
    )
    assert not (tmp_path / "x").exists(), "nothing is written for a sample that does not exist"


def test_unknown_sample_and_bad_index_are_value_errors(dataset: Path, tmp_path: Path) -> None:
    count = len(records(dataset))
    with pytest.raises(ValueError, match="s9999_p000_f002"):
        render_sample(dataset, tmp_path, sample="s9999_p000_f002", index=0, scale=3)
    with pytest.raises(ValueError, match="out of range"):
        render_sample(dataset, tmp_path, sample=None, index=count, scale=3)
    with pytest.raises(ValueError, match="out of range"):
        render_sample(dataset, tmp_path, sample=None, index=-1, scale=3)
    with pytest.raises(ValueError, match="scale"):
        render_sample(dataset, tmp_path, sample=None, index=0, scale=0)


def test_missing_files_are_named(dataset: Path, tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="does not exist"):
        render_sample(tmp_path / "nowhere", tmp_path / "out", sample=None, index=0, scale=3)
    for name in ("samples.jsonl", "scenarios.jsonl"):
        broken = tmp_path / f"no_{name}"
        shutil.copytree(dataset, broken)
        (broken / name).unlink()
        with pytest.raises(FileNotFoundError, match=name):
            render_sample(broken, tmp_path / "out", sample=None, index=0, scale=3)
    record = records(dataset)[0]
    broken = tmp_path / "no_files"
    shutil.copytree(dataset, broken)
    (broken / record["image"]).unlink()
    with pytest.raises(FileNotFoundError, match=Path(record["image"]).name):
        render_sample(broken, tmp_path / "out", sample=None, index=0, scale=3)
    other = records(dataset)[1]  # a sample whose image is still there: only its labels go missing
    label = Path(other["image"].replace("images/", "labels/", 1)).with_suffix(".txt")
    (broken / label).unlink()
    with pytest.raises(FileNotFoundError, match=label.name):
        render_sample(broken, tmp_path / "out", sample=label.stem, index=0, scale=3)


def test_the_models_boxes_are_dashed_in_their_class_colour_and_tagged_under(dataset: Path) -> None:
    import dataclasses

    from training.dataset_sample import load_sample
    from training.raster_picture import DetectedBox, draw_raster_picture

    scale = 3
    sample = dataclasses.replace(load_sample(dataset, index=0), boxes=())  # the model's box alone
    box = DetectedBox(1, 150.0, 20.0, 200.0, 40.0, 0.87)
    picture = np.asarray(draw_raster_picture(sample, scale, [box]).convert("RGB"))
    ox, oy = RASTER_ORIGIN
    left, right = ox + round(box.x1 * scale), ox + round(box.x2 * scale) - 1
    top, bottom = oy + round(box.y1 * scale), oy + round(box.y2 * scale) - 1
    colour = np.array(CLASS_COLOURS[box.class_id])
    for side, line in {"top": picture[top, left:right], "left": picture[top:bottom, left]}.items():
        share = np.all(line == colour, axis=-1).mean()
        assert 0.3 <= share <= 0.7, f"{side} edge {share:.0%} in colour: not dashed"
    under = picture[bottom + 2 : bottom + 15, left : left + 60]
    assert np.all(under == colour, axis=-1).any(), "no tag under the box"
    above = picture[top - 14 : top - 2, left : left + 60]
    assert not np.all(above == colour, axis=-1).any(), "a label-style tag above the model's box"


def test_show_with_a_model_draws_what_the_detector_finds(dataset: Path, tmp_path: Path) -> None:
    from common.model_spec import default_model_path
    from training.dataset_sample import load_sample
    from training.evaluate import box_iou
    from training.pictures import model_boxes

    index = richest_sample(dataset)
    sample = load_sample(dataset, index=index)
    found = model_boxes(default_model_path(), sample.tensor, sample.padding)
    labels = yolo_boxes(dataset, records(dataset)[index])
    assert found, "the shipped model finds nothing in a labelled sample"
    for box in found:
        same_class = np.array([b[1:] for b in labels if b[0] == box.class_id]).reshape(-1, 4)
        ious = box_iou(np.array([[box.x1, box.y1, box.x2, box.y2]]), same_class)
        assert ious.size and ious.max() > 0.5, f"a {box.class_id} box on no label of its class"
    argv = ["show", "--dataset", str(dataset), "--index", str(index)]
    assert cli_main([*argv, "--out", str(tmp_path / "plain")]) == 0
    assert cli_main([*argv, "--out", str(tmp_path / "model"), "--model", str(default_model_path())]) == 0
    name = Path(records(dataset)[index]["image"]).stem
    plain, with_model = (pixels(tmp_path / d / f"{name}_raster.png") for d in ("plain", "model"))
    assert plain.shape != with_model.shape or np.any(plain != with_model)
