"""The fuzz run at CI size: malformed payloads over real Zenoh into real encoder and detector processes."""

from __future__ import annotations

import pytest

from bench.fuzz_services import run

pytestmark = [pytest.mark.slow, pytest.mark.integration]


def test_services_survive_fuzz_count_every_bad_payload_and_answer_every_good_scan() -> None:
    report = run(bad=600, good_every=30, seed=1)  # 20 rounds of the 30 mutation kinds (+ bad keys)
    assert all(report.alive_at_end.values()), report.alive_at_end
    assert report.good_scans >= 15 and report.good_answered == report.good_scans
    assert report.counted_rejected == report.expected_rejected, report.rejected_by_reason
    assert report.expected_rejected["encoder"] > 400 and report.expected_rejected["detector"] > 80
    assert report.passed
