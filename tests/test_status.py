"""``triscan status``: rates in and out, drops and the detector's latency, read from running services."""

from __future__ import annotations

import subprocess
import threading
import time

import numpy as np
import pytest

from bench.harness import start_loopback_service
from common.keys import ALL_DETECTIONS, scan_key
from common.messages import Scan, encode_message
from common.transport import ZenohSettings, open_session, wait_for_subscriber
from services.launcher import free_tcp_ports
from services.status import Flow, ServiceStatus, collect_status, flow_of, format_status
from tests.support.waiting import wait_for

RATE_HZ = 20.0


def test_flow_is_the_counters_difference_over_the_time_between_two_samples() -> None:
    first = {"stamp_ns": 0, "received": 10, "processed": 8, "dropped_stale": 1, "rejected": {}}
    last = {
        "stamp_ns": 2_000_000_000,
        "received": 50,
        "processed": 44,
        "dropped_stale": 3,
        "rejected": {"x": 2},
    }
    assert flow_of("detector", first, last) == Flow(in_per_s=20.0, out_per_s=18.0, dropped=5)
    assert flow_of(
        "simulator", {"stamp_ns": 0, "published": 0}, {"stamp_ns": 10**9, "published": 10}
    ) == Flow(None, 10.0, 0)
    assert flow_of("detector", last, last) == Flow(None, None, 5)  # one sample: no rate
    assert flow_of("someone_else", first, last) is None
    line = format_status(
        [
            ServiceStatus(
                "detector",
                "42",
                alive=True,
                counters={**last, "latency_ms": {"p50": 12.5, "p99": 30.0, "frames": 20}},
                flow=Flow(20.0, 18.0, 5),
            )
        ]
    )
    assert "in 20.0/s out 18.0/s dropped 5 latency p50 12.5 ms p99 30.0 ms | " in line


def _scan(seq: int) -> Scan:
    ranges = np.full(360, 2.0, dtype=np.float32)
    ranges[40:60] = 1.0  # something in front, so the rasters differ from an empty room
    return Scan(
        robot_id="statusbot",
        seq=seq,
        stamp_ns=time.time_ns(),
        angle_min=0.0,
        angle_increment=float(np.deg2rad(1.0)),
        range_min=0.12,
        range_max=3.5,
        ranges=ranges,
    )


@pytest.mark.slow
@pytest.mark.integration
def test_status_shows_the_rates_drops_and_latency_of_running_services() -> None:
    test_port, encoder_port, detector_port = free_tcp_ports(3)
    children = [
        start_loopback_service(
            "services.encoder", encoder_port, [test_port, detector_port], stdout=subprocess.DEVNULL
        ),
        start_loopback_service(
            "services.detector",
            detector_port,
            [test_port, encoder_port],
            "--threads",
            "1",
            "--workers",
            "1",
            "--detectors",
            "1",  # one process: the rates are this one's, not a sibling's without robots
            stdout=subprocess.DEVNULL,
        ),
    ]
    stop = threading.Event()
    detections: list[bytes] = []
    try:
        with open_session(ZenohSettings.loopback(test_port)) as session:
            session.declare_subscriber(ALL_DETECTIONS, lambda s: detections.append(s.payload.to_bytes()))
            wait_for_subscriber(session, scan_key("statusbot"), timeout_s=60)
            publisher = session.declare_publisher(scan_key("statusbot"))

            def publish() -> None:
                seq = 0
                while not stop.wait(1.0 / RATE_HZ):
                    publisher.put(encode_message(_scan(seq)))
                    seq += 1

            feeder = threading.Thread(target=publish, daemon=True)
            feeder.start()
            assert wait_for(lambda: len(detections) >= 5, 60), "the pipeline never answered"
            statuses = collect_status(ZenohSettings.loopback(None, [encoder_port, detector_port]), wait_s=3.5)
            stop.set()
            feeder.join()
    finally:
        stop.set()
        for child in children:
            child.terminate()
        for child in children:
            child.wait(20)
    by_service = {s.service: s for s in statuses}
    assert set(by_service) == {"encoder", "detector"}, statuses
    for name in ("encoder", "detector"):
        flow = by_service[name].flow
        assert flow is not None and flow.in_per_s and flow.out_per_s, (name, flow)
        assert 0 < flow.in_per_s < 2 * RATE_HZ and flow.dropped >= 0
    latency = by_service["detector"].counters["latency_ms"]
    assert latency["frames"] > 0 and 0 < latency["p50"] <= latency["p99"]
    text = format_status(statuses)
    assert "/s out " in text and "latency p50 " in text
