"""A model's raster yaw from data set to detections: recorded by the data set, written into the model by
export, read by the detector, refused where it differs; detections come back in the laser frame."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from common.inference import OnnxDetector, model_facts
from common.model_meta import metadata_entries
from common.model_spec import FURNITURE_CLASSES, META_RASTER_YAW, SHIPPED_MODEL
from common.postprocess import detections_from_boxes
from services.cli import main as cli_main
from tests.test_inference import constant_model, known_output
from training.dataset import DatasetConfig, _data_yaml
from training.onnx_export import dataset_raster_yaw, resolve_raster_yaw
from training.onnx_model import ExportError


def test_the_metadata_carries_a_yaw_only_when_there_is_one(tmp_path: Path) -> None:
    common = {"padding": "zero", "invalid": "sentinel", "box_grid": "none", "classes": FURNITURE_CLASSES}
    assert META_RASTER_YAW not in metadata_entries(**common)  # the paper's raster: as every model so far
    assert metadata_entries(**common, raster_yaw_deg=-180.0)[META_RASTER_YAW] == "180.0"
    turned = constant_model(
        tmp_path / "t.onnx", known_output(), metadata=metadata_entries(**common, raster_yaw_deg=180)
    )
    assert model_facts(turned).raster_yaw_deg == 180.0
    assert OnnxDetector(turned, providers=["CPUExecutionProvider"]).raster_yaw_deg == 180.0
    assert OnnxDetector(SHIPPED_MODEL, providers=["CPUExecutionProvider"]).raster_yaw_deg == 0.0
    for bad in ("nan", "inf", "ahead"):
        broken = constant_model(tmp_path / f"{bad}.onnx", known_output(), metadata={META_RASTER_YAW: bad})
        with pytest.raises(ValueError, match=f"declares an invalid triscan.raster_yaw_deg '{bad}'"):
            model_facts(broken)


def test_detections_keep_raster_boxes_and_give_laser_frame_bearings() -> None:
    import numpy as np

    boxes = np.array([[178.0, 30.0, 183.0, 34.0]], np.float32)  # columns 178–182 of a 180°-turned raster
    (plain,) = detections_from_boxes(boxes - [180.0, 0, 180.0, 0], np.array([0.9]), np.array([1]))
    (turned,) = detections_from_boxes(boxes, np.array([0.9]), np.array([1]), raster_yaw_deg=180.0)
    assert turned.box_px == (178.0, 30.0, 183.0, 34.0)
    assert (turned.bearing_min_deg, turned.bearing_deg, turned.bearing_max_deg) == (-2.5, 0.0, 2.5)
    assert turned.model_dump(exclude={"box_px"}) == plain.model_dump(exclude={"box_px"})
    assert turned.x_m > 0 and turned.y_m == pytest.approx(0.0)


def test_a_data_set_records_its_yaw_and_export_takes_it_from_there(tmp_path: Path) -> None:
    paper = DatasetConfig(out=tmp_path)
    assert "raster_yaw_deg" not in paper.summary_fields() and "raster yaw" not in _data_yaml(paper)
    turned = DatasetConfig(out=tmp_path, raster_yaw_deg=-180)
    assert turned.raster_yaw_deg == 180.0 and turned.summary_fields()["raster_yaw_deg"] == 180.0
    with pytest.raises(ValueError, match="raster yaw must be finite"):
        DatasetConfig(out=tmp_path, raster_yaw_deg=math.inf)
    with_summary, yaml_only = tmp_path / "a", tmp_path / "b"
    with_summary.mkdir(), yaml_only.mkdir()
    (with_summary / "summary.json").write_text(json.dumps({"config": turned.summary_fields()}))
    (yaml_only / "data.yaml").write_text(_data_yaml(turned))
    assert dataset_raster_yaw(with_summary) == dataset_raster_yaw(yaml_only) == 180.0
    assert dataset_raster_yaw(tmp_path / "none") == 0.0
    assert resolve_raster_yaw(None, with_summary) == resolve_raster_yaw(540.0, with_summary) == 180.0
    assert resolve_raster_yaw(None, None) == 0.0 and resolve_raster_yaw(90.0, None) == 90.0
    with pytest.raises(ExportError, match="raster yaw 0 requested but the data set"):
        resolve_raster_yaw(0.0, with_summary)


def test_eval_refuses_a_data_set_turned_otherwise_than_the_model(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    data = tmp_path / "set"
    data.mkdir()
    (data / "summary.json").write_text(json.dumps({"config": {"raster_yaw_deg": 180.0}}))
    code = cli_main(
        ["eval", "--model", str(SHIPPED_MODEL), "--data", str(data), "--out", str(tmp_path / "o")]
    )
    errors = [r for r in caplog.records if r.levelname == "ERROR"]
    assert code == 2 and len(errors) == 1 and errors[0].exc_info is None
    assert "turns its scans by a raster yaw of 180 deg" in errors[0].getMessage()
    assert errors[0].getMessage().endswith("by 0 deg")


def test_the_map_picture_turns_a_turned_sets_hits_back() -> None:
    import numpy as np

    from training.map_picture import decode_hits

    tensor = np.zeros((64, 384, 3), np.uint8)
    tensor[31, 180, :] = 255  # column 180 of a raster turned by 180°: straight ahead, about 2 m
    for points in decode_hits(tensor, (1.0, 2.0, 0.0), raster_yaw_deg=180.0):
        (x, y), *_ = points
        assert x == pytest.approx(1.0 + 31.5 * 4 / 63) and y == pytest.approx(2.0)  # ahead of the LiDAR
