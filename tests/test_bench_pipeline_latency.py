"""The pipeline bench starts the encoder as the launcher does: tensors the detector's model accepts."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

import bench.pipeline_latency as pipeline_latency
from common.inference import model_facts
from common.model_spec import MODELS_DIR, SHIPPED_MODEL
from services.launcher import SERVICES, UpConfig, service_commands

PEOPLE_MODEL = MODELS_DIR / "yolov8p-relu-dfl12" / "triscan-yolov8p-relu-dfl12-zero-int8.onnx"


@pytest.mark.parametrize("model", [SHIPPED_MODEL, PEOPLE_MODEL], ids=["default", "raster-yaw-180"])
def test_the_bench_encoder_gets_the_launchers_flags_for_the_model(
    model: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    started: dict[str, tuple[Any, ...]] = {}

    def start(module: str, port: int, peers: list[int], *args: str) -> None:
        started[module] = args

    monkeypatch.setattr(pipeline_latency, "start_loopback_service", start)
    pipeline_latency._start_services(False, None, model, 1, 2, 3)
    flags = model_facts(model).encoder_flags()
    assert list(started["services.encoder"][: len(flags)]) == flags
    ports = {name: port for port, name in enumerate(SERVICES, start=1)}
    launched = service_commands(UpConfig(viewer="none", model=model), ports, None)["encoder"]
    assert all(flag in launched for flag in flags)
    if model == PEOPLE_MODEL:
        assert flags[flags.index("--raster-yaw") + 1] == "180.0"
