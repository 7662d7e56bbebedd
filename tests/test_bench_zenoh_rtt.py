"""The CPU-per-message arithmetic of ``bench.zenoh_rtt``, on windows written by hand (no processes)."""

from __future__ import annotations

import pytest

from bench.zenoh_rtt import CpuWindows


def test_each_end_pays_its_window_less_its_idle_rate_and_the_sender_less_its_pacing() -> None:
    windows = CpuWindows(
        idle_s=2.0, idle_near_s=0.02, idle_far_s=0.04,  # Zenoh's timers: 10 and 20 ms of CPU a second
        pacing_s=5.0, pacing_near_s=0.15,  # the paced loop sending nothing: 150 ms, 50 of them timers
        window_s=5.0, near_s=0.65, far_s=0.60, received=2_500,
    )  # fmt: skip
    per_message = windows.ms_per_message()
    # Sender: 650 ms − 50 ms of timers − 100 ms of pacing = 500 ms over 2,500 messages.
    assert per_message["sender"] == pytest.approx(0.2)
    # Receiver: 600 ms − 100 ms of timers = 500 ms; it paces nothing.
    assert per_message["receiver"] == pytest.approx(0.2)
    assert per_message["sender_pacing"] == pytest.approx(0.04)


def test_a_window_quieter_than_idle_prices_nothing_rather_than_a_negative_cost() -> None:
    windows = CpuWindows(
        idle_s=1.0, idle_near_s=0.1, idle_far_s=0.1, pacing_s=1.0, pacing_near_s=0.05,
        window_s=1.0, near_s=0.05, far_s=0.05, received=0,
    )  # fmt: skip
    assert windows.ms_per_message() == {"sender": 0.0, "receiver": 0.0, "sender_pacing": 0.0}
