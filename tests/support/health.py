"""What the services' health tokens say, for tests of real processes (pids come from here, not logs)."""

from __future__ import annotations

from typing import Any

from common.keys import parse_health_key, service_health_key


def service_pids(session: Any, service: str, timeout_s: float = 2.0) -> set[int]:
    """Pids of the live instances of ``service``, read from their health tokens (not from logs)."""
    pids = set()
    for reply in session.liveliness().get(service_health_key(service), timeout=timeout_s):
        if reply.ok is not None:
            pids.add(int(parse_health_key(str(reply.ok.key_expr))[1]))
    return pids
