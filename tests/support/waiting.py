"""Polling with a deadline, for tests that wait on other processes (never a timing assertion)."""

from __future__ import annotations

import time
from collections.abc import Callable


def wait_for(condition: Callable[[], object], timeout: float, poll_s: float = 0.05) -> bool:
    """True as soon as ``condition()`` is truthy, False if ``timeout`` seconds pass first."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(poll_s)
    return bool(condition())
