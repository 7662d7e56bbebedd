"""``triscan status``: which services are alive and what their counters say, from any machine.

Liveliness tokens (``triscan/@health/<service>/<pid>``) say who is up; the JSON counters each service
publishes once a second on ``triscan/@stats/<service>/<pid>`` say what it did: messages received and
processed, rejections by reason, tensors dropped as stale, robots tracked. Two samples of a service's
counters heard during the wait give its rates (messages a second in and out), and the detector
publishes the scan-to-detection latency of its last second's frames.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from common.keys import ALL_HEALTH, ALL_STATS, parse_health_key, parse_stats_key
from common.transport import ZenohSettings, open_session
from services.runtime import STATS_PERIOD_S

# Which counters of each service are its messages in and out, and which count messages lost (dropped
# or refused): the names each service publishes in its stats.
FLOW_COUNTERS: dict[str, tuple[str | None, str | None, tuple[str, ...]]] = {
    "simulator": (None, "published", ("skipped_ticks",)),
    "replay": (None, "published", ("rejected",)),
    "encoder": ("received", "published", ("rejected",)),
    "detector": ("received", "processed", ("dropped_stale", "rejected")),
    "visualizer": ("received", "processed", ("rejected",)),
    "ros2_bridge": ("scans_received", "scans_published", ("rejected_scans",)),
}


@dataclass
class Flow:
    """A service's traffic over the wait: messages a second in and out (None: not measured), and the
    messages it dropped or refused so far."""

    in_per_s: float | None
    out_per_s: float | None
    dropped: int


@dataclass
class ServiceStatus:
    service: str
    instance: str
    alive: bool = False
    counters: dict[str, Any] = field(default_factory=dict)
    flow: Flow | None = None


def flow_of(service: str, first: dict[str, Any], last: dict[str, Any]) -> Flow | None:
    """The rates between two stats samples of one service (``stamp_ns`` apart) and its drops so far;
    None for a service whose counters this module does not know."""
    if service not in FLOW_COUNTERS:
        return None
    in_key, out_key, lost_keys = FLOW_COUNTERS[service]
    elapsed_s = (last.get("stamp_ns", 0) - first.get("stamp_ns", 0)) / 1e9

    def rate(key: str | None) -> float | None:
        if key is None or elapsed_s <= 0 or key not in last or key not in first:
            return None
        return (_total(last[key]) - _total(first[key])) / elapsed_s

    return Flow(rate(in_key), rate(out_key), sum(_total(last.get(key, 0)) for key in lost_keys))


def _total(value: Any) -> int:
    """A counter, or the sum of one counted by reason (``rejected``)."""
    if isinstance(value, dict):
        return sum(_total(v) for v in value.values())
    return int(value) if isinstance(value, int | float) else 0


def collect_status(settings: ZenohSettings, wait_s: float = 2.5 * STATS_PERIOD_S) -> list[ServiceStatus]:
    """Listen for ``wait_s`` and return every service seen, alive or only reporting."""
    found: dict[tuple[str, str], ServiceStatus] = {}
    first: dict[tuple[str, str], dict[str, Any]] = {}  # the earliest counters heard of each instance
    lock = threading.Lock()

    def on_stats(sample: Any) -> None:
        try:
            service, instance = parse_stats_key(str(sample.key_expr))
            counters = json.loads(sample.payload.to_bytes())
        except ValueError:
            return
        if not isinstance(counters, dict):
            return
        with lock:
            status = found.setdefault((service, instance), ServiceStatus(service, instance))
            status.counters = counters
            first.setdefault((service, instance), counters)

    def on_health(sample: Any) -> None:
        try:
            service, instance = parse_health_key(str(sample.key_expr))
        except ValueError:
            return
        with lock:
            status = found.setdefault((service, instance), ServiceStatus(service, instance))
            status.alive = sample.kind == zenoh.SampleKind.PUT

    import zenoh

    # Subscribers, not one-off queries: peers found through gossip connect during the wait, and
    # a subscriber with history hears their tokens whenever they arrive.
    with open_session(settings) as session:
        stats_sub = session.declare_subscriber(ALL_STATS, on_stats)
        health_sub = session.liveliness().declare_subscriber(ALL_HEALTH, on_health, history=True)
        time.sleep(wait_s)
        stats_sub.undeclare()
        health_sub.undeclare()
    for key, status in found.items():
        if key in first:
            status.flow = flow_of(status.service, first[key], status.counters)
    return sorted(found.values(), key=lambda s: (s.service, s.instance))


def format_status(statuses: list[ServiceStatus]) -> str:
    """One line per service: alive, and its counters flattened (``rejected.not_msgpack=3``)."""
    if not statuses:
        return (
            "no triscan services found: point --connect at the address one listens on (triscan up's "
            "--listen), or --discover to scout the LAN"
        )
    lines = []
    for status in statuses:
        counters = {
            k: v for k, v in status.counters.items() if k not in {"service", "pid", "stamp_ns", "latency_ms"}
        }
        text = " ".join(f"{k}={v}" for k, v in _flatten(counters))
        lines.append(
            f"{status.service:10s} {status.instance:>8s} {'up' if status.alive else 'DOWN':4s} "
            f"{_flow_text(status)}{text}"
        )
    return "\n".join(lines)


def _flow_text(status: ServiceStatus) -> str:
    """``in 10.0/s out 9.8/s dropped 2 latency p50 12.1 ms p99 30.2 ms | ``, or what of it is known."""
    parts = []
    if status.flow is not None:
        for label, rate in (("in", status.flow.in_per_s), ("out", status.flow.out_per_s)):
            if rate is not None:
                parts.append(f"{label} {rate:.1f}/s")
        parts.append(f"dropped {status.flow.dropped}")
    latency = status.counters.get("latency_ms")
    if isinstance(latency, dict):
        parts.append(f"latency p50 {latency.get('p50')} ms p99 {latency.get('p99')} ms")
    return " ".join(parts) + " | " if parts else ""


def _flatten(values: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    out: list[tuple[str, Any]] = []
    for key, value in sorted(values.items()):
        if isinstance(value, dict):
            out += _flatten(value, f"{prefix}{key}.")
        else:
            out.append((f"{prefix}{key}", value))
    return out
