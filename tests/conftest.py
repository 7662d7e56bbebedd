"""Fixtures every test of real processes and real Zenoh sessions shares.

Tests that talk over Zenoh use loopback TCP on ports that are free right now, with multicast
scouting off, and wait on conditions (``wait_for``), never on fixed sleeps before an exact count.
Markers: ``slow`` (more than a few seconds: processes, training, export) and ``integration`` (several
real processes talking over Zenoh); ``python -m pytest -m "not slow"`` is the quick edit loop.
"""

from __future__ import annotations

from collections.abc import Callable

import pytest

from services.launcher import free_tcp_ports


@pytest.fixture
def free_port() -> Callable[[], int]:
    """A function returning a TCP port free on 127.0.0.1 (call it once per listener)."""

    def next_port() -> int:
        return free_tcp_ports(1)[0]

    return next_port
