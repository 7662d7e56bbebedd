"""How every benchmark reports: JSON to stdout and to a file, and the same latency summary."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np


def latency_quantiles_ms(values_ms: Sequence[float] | np.ndarray) -> dict[str, float]:
    """p50, p95, p99 and max of latencies in milliseconds, rounded to 10 µs."""
    values = np.asarray(values_ms, dtype=np.float64)
    summary = {f"p{q}": float(np.percentile(values, q)) for q in (50, 95, 99)}
    summary["max"] = float(values.max())
    return {k: round(v, 2) for k, v in summary.items()}


_NOT_COUNTERS = frozenset({"pid", "stamp_ns"})  # numbers in a service's stats that name, not count


def summed_counters(bodies: Iterable[dict[str, Any]]) -> dict[str, Any]:
    """The counters of several processes of one service (``--detectors N``) as one: numbers summed,
    nested counters summed key by key, anything else (its pid and stamp, a member id) from the first
    process."""
    total: dict[str, Any] = {}
    for body in bodies:
        for key, value in body.items():
            if key in _NOT_COUNTERS and key in total:
                continue
            if key not in total:
                total[key] = summed_counters([value]) if isinstance(value, dict) else value
            elif isinstance(value, dict) and isinstance(total[key], dict):
                total[key] = summed_counters([total[key], value])
            elif isinstance(value, int | float) and isinstance(total[key], int | float):
                total[key] = total[key] + value
    return total


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
