"""``triscan status``: which services are alive and what their counters say, from any machine.

Liveliness tokens (``triscan/@health/<service>/<pid>``) say who is up; the JSON counters each service
publishes once a second on ``triscan/@stats/<service>/<pid>`` say what it did: messages received and
processed, rejections by reason, tensors dropped as stale, robots tracked.
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


@dataclass
class ServiceStatus:
    service: str
    instance: str
    alive: bool = False
    counters: dict[str, Any] = field(default_factory=dict)


def collect_status(settings: ZenohSettings, wait_s: float = 2.5 * STATS_PERIOD_S) -> list[ServiceStatus]:
    """Listen for ``wait_s`` and return every service seen, alive or only reporting."""
    found: dict[tuple[str, str], ServiceStatus] = {}
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
        counters = {k: v for k, v in status.counters.items() if k not in {"service", "pid", "stamp_ns"}}
        text = " ".join(f"{k}={v}" for k, v in _flatten(counters))
        lines.append(
            f"{status.service:10s} {status.instance:>8s} {'up' if status.alive else 'DOWN':4s} {text}"
        )
    return "\n".join(lines)


def _flatten(values: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    out: list[tuple[str, Any]] = []
    for key, value in sorted(values.items()):
        if isinstance(value, dict):
            out += _flatten(value, f"{prefix}{key}.")
        else:
            out.append((f"{prefix}{key}", value))
    return out
