"""The detector's batch cap: which model file and how many robots' tensors per model call, picked by
itself when the user says neither (``--batch``), by timing the model on the machine it runs on."""

from __future__ import annotations

import logging
import threading

import pytest

from common.inference import OnnxDetector
from common.model_spec import SHIPPED_BATCH_MODEL, SHIPPED_MODEL
from services.detector import __main__ as detector_main
from services.detector.batch_cap import (
    AUTO_BATCH,
    batch_cap_within,
    detector_model_and_batch,
    timed_batch_cap,
)


def test_the_detector_picks_its_model_and_batch_by_itself() -> None:
    assert detector_model_and_batch(None, None) == (SHIPPED_BATCH_MODEL, AUTO_BATCH)
    assert detector_model_and_batch(SHIPPED_MODEL, None) == (SHIPPED_MODEL, 1)  # a fixed model: batch 1
    assert detector_model_and_batch(None, 1) == (SHIPPED_MODEL, 1)
    assert detector_model_and_batch(None, 8) == (SHIPPED_BATCH_MODEL, 8)
    with pytest.raises(ValueError, match="free batch axis"):
        detector_model_and_batch(SHIPPED_MODEL, 4)
    with pytest.raises(ValueError, match="--batch must be >= 1"):
        detector_model_and_batch(None, 0)


@pytest.mark.parametrize(
    ("call_ms", "budget_ms", "cap"),
    [
        ({1: 2.0, 2: 4.0, 4: 8.0, 8: 16.0}, 10.0, 4),
        ({1: 2.0, 2: 4.0, 4: 8.0, 8: 16.0}, 16.0, 8),  # a call exactly on the budget fits
        ({1: 2.0, 2: 4.0, 4: 8.0, 8: 16.0}, 1.0, 1),  # nothing fits: a lone frame is still served
        ({8: 5.0, 1: 2.0, 4: 40.0, 2: 3.0}, 30.0, 2),  # sizes in any order; a slow 4 stops the climb
    ],
)
def test_the_batch_cap_is_the_largest_size_whose_call_and_every_smaller_one_fit(
    call_ms: dict[int, float], budget_ms: float, cap: int
) -> None:
    assert batch_cap_within(call_ms, budget_ms) == cap


def test_the_detector_times_its_model_calls_per_batch_size() -> None:
    detector = OnnxDetector(SHIPPED_BATCH_MODEL, intra_op_threads=1)
    call_ms = detector.call_ms_by_batch([1, 2, 4])
    assert list(call_ms) == [1, 2, 4] and all(ms > 0 for ms in call_ms.values())
    # The sizes tried are the powers of two up to the largest; the budget alone decides the cap.
    cap, timed = timed_batch_cap(detector, largest=6, budget_ms=1e9)
    assert cap == 4 and list(timed) == [1, 2, 4]
    assert timed_batch_cap(detector, largest=8, budget_ms=0.0)[0] == 1
    with pytest.raises(ValueError, match="largest must be >= 1"):
        timed_batch_cap(detector, largest=0)
    with pytest.raises(ValueError, match="fixed at batch 1"):
        OnnxDetector(SHIPPED_MODEL, intra_op_threads=1).call_ms_by_batch([1, 2])


@pytest.mark.parametrize(("flags", "timed"), [((), True), (("--batch", "3"), False)], ids=["auto", "given"])
def test_the_detector_service_times_its_cap_only_when_no_batch_is_given(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, flags: tuple[str, ...], timed: bool
) -> None:
    """``main`` wires the real model and timing; only the Zenoh serving loop is replaced, to read what
    it would have been given."""
    served: dict[str, object] = {}
    monkeypatch.setattr(detector_main, "run", lambda *args, **kwargs: served.update(kwargs))
    monkeypatch.setattr(detector_main, "configure_logging", lambda verbose: None)
    monkeypatch.setattr(detector_main, "stop_event_on_signals", threading.Event)  # pytest keeps its handlers
    with caplog.at_level(logging.INFO, logger=detector_main.log.name):
        assert detector_main.main(["--workers", "1", *flags]) == 0
    batch = served["batch"]
    logged = [r.getMessage() for r in caplog.records if r.getMessage().startswith("batch cap")]
    if timed:
        assert batch in {1, 2, 4, 8} and isinstance(batch, int) and batch <= AUTO_BATCH
        assert logged and logged[0].startswith(f"batch cap {batch}: model calls of 1/2/4/8 frames took")
    else:
        assert batch == 3 and not logged
