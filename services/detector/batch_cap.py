"""How many robots' tensors the detector runs in one model call (``--batch``), and which model file.

A lone robot is served at batch 1 (same outputs, same speed); several waiting robots share one model
call, which on a CPU costs less per frame, and a worker waits a few milliseconds for the robots it
serves to fill its batch (``--gather-ms``, :class:`services.detector.core.LatestPerRobot`). Without
``--batch`` the detector picks its cap on the machine it runs on, by timing its model at start
(:func:`timed_batch_cap`): a heavier network, or a slower computer, gets a smaller cap without a
tuning table. The launcher and the benches resolve the model and cap the same way
(:func:`detector_model_and_batch`), so they start the encoder to match and refuse a ``--batch`` the
model cannot run before any process starts.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Final

from common.inference import OnnxDetector, model_facts
from common.model_spec import MODELS_DIR, SHIPPED_BATCH_MODEL, default_model_path

AUTO_BATCH: Final[int] = 8
"""The largest batch cap the detector picks by itself when none is given and its model takes batches
(:func:`timed_batch_cap` keeps the largest power of two up to this whose model call fits
:data:`AUTO_BATCH_CALL_BUDGET_MS`). Past a fleet's knee a larger batch keeps more scans answered."""

AUTO_BATCH_CALL_BUDGET_MS: Final[float] = 30.0
"""The longest model call :func:`timed_batch_cap` accepts. A frame that just misses a call waits for it
and rides the next: two calls, 60 ms, leave 40 of the fleet's 100 ms p99 for transport, encoding and
the mailbox."""


def check_batch(batch: int, takes_batches: bool, model_path: Path | str) -> None:
    """Refuse a batch size the model cannot run, before any frame is lost to it (``--batch``)."""
    if batch < 1:
        raise ValueError(f"--batch must be >= 1, got {batch}")
    if batch > 1 and not takes_batches:
        raise ValueError(
            f"--batch {batch} needs a model with a free batch axis; {model_path} is fixed at batch 1 "
            f"(its -batch variant, e.g. {SHIPPED_BATCH_MODEL.relative_to(MODELS_DIR.parent)}, is the same "
            "network)"
        )


def batch_cap_within(call_ms: Mapping[int, float], budget_ms: float) -> int:
    """The largest batch size whose call, and every smaller size's, took at most ``budget_ms``; 1 when
    none did (a lone frame is served whatever it costs)."""
    cap = 1
    for size in sorted(call_ms):
        if call_ms[size] > budget_ms:
            break
        cap = size
    return cap


def detector_model_and_batch(model: Path | None, batch: int | None) -> tuple[Path, int]:
    """The model and batch cap a detector runs when the user may have chosen neither.

    ``batch`` None picks by itself: the shipped ``-batch`` model (or ``model``) with :data:`AUTO_BATCH`
    when the model takes batches (the largest cap: the detector then keeps what its own timing allows,
    :func:`timed_batch_cap`), batch 1 when it does not. An explicit ``batch`` is checked against
    the model (:func:`check_batch`); with ``batch`` 1 and no model, the fixed batch-1 file is used.
    """
    if batch is None:
        path = model or default_model_path(batched=True)
        return path, AUTO_BATCH if model_facts(path).takes_batches else 1
    path = model or default_model_path(batched=batch > 1)
    check_batch(batch, batch == 1 or model_facts(path).takes_batches, path)
    return path, batch


def timed_batch_cap(
    detector: OnnxDetector, largest: int = AUTO_BATCH, budget_ms: float = AUTO_BATCH_CALL_BUDGET_MS
) -> tuple[int, dict[int, float]]:
    """The batch cap a detector picks by itself on this machine: the largest power of two up to
    ``largest`` whose model call fits ``budget_ms`` (:func:`batch_cap_within`), and the call times it
    measured."""
    if largest < 1:
        raise ValueError(f"largest must be >= 1, got {largest}")
    sizes = [1 << k for k in range(largest.bit_length())]  # 1, 2, 4, … up to largest
    call_ms = detector.call_ms_by_batch(sizes)
    return batch_cap_within(call_ms, budget_ms), call_ms
