"""How every benchmark reports: JSON to stdout and to a file, and the same latency summary."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np


def latency_quantiles_ms(values_ms: Sequence[float] | np.ndarray) -> dict[str, float]:
    """p50, p95, p99 and max of latencies in milliseconds, rounded to 10 µs."""
    values = np.asarray(values_ms, dtype=np.float64)
    summary = {f"p{q}": float(np.percentile(values, q)) for q in (50, 95, 99)}
    summary["max"] = float(values.max())
    return {k: round(v, 2) for k, v in summary.items()}


def write_report(report: Any, out: Path | None, *, echo: bool = True) -> str:
    """Serialise ``report`` (a dataclass or plain data) as JSON; print it and write it to ``out``."""
    data = dataclasses.asdict(report) if dataclasses.is_dataclass(report) else report
    text = json.dumps(data, indent=2, ensure_ascii=False)
    if echo:
        print(text)
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text + "\n")
    return text
