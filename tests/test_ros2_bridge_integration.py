"""The ROS 2 bridge against a ROS 2 client nobody here wrote: zenoh-ros2-sdk, over loopback Zenoh.

zenoh-ros2-sdk publishes LaserScans exactly as a ROS 2 node on rmw_zenoh does (its own key
expression, its own RIHS01 hash computation from ``.msg`` text, its own attachment, its own CDR via
rosbags) and subscribes to the bridge's Detection3DArray and MarkerArray the same way, so a wrong
key, hash, attachment or byte anywhere in the bridge shows up as silence or a decode error here.
Between them run the real bridge, encoder, detector and tracker processes with the shipped model, on real
simulated scans. Nothing is downloaded: the SDK reads every ``.msg`` from a local directory built
from rosbags' definitions and the repository's vision_msgs (the SDK would otherwise ``git clone`` the
message repositories on first use, which needs the network).
"""

from __future__ import annotations

import json
import queue
import subprocess
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from bench.harness import start_loopback_service
from common.keys import service_stats_key
from common.model_spec import CLASS_NAMES
from common.transport import payload_bytes
from services.launcher import free_tcp_ports, stop_processes
from services.ros2_bridge.ros_messages import CUBE, DELETEALL, TEXT_VIEW_FACING
from services.ros2_bridge.ros_types import (
    DETECTION3D_ARRAY,
    LASER_SCAN,
    MARKER_ARRAY,
    VISION_MSGS,
    ros_types,
    vision_msgs_definition,
)
from tests.support.scan_replay import replay_scans
from tests.support.waiting import wait_for

pytestmark = [pytest.mark.slow, pytest.mark.integration]
sdk = pytest.importorskip("zenoh_ros2_sdk")

ROBOT = "robot1"
SCANS = 14
PERIOD_NS = 100_000_000


def write_message_directory(root: Path) -> Path:
    """``<pkg>/msg/<Type>.msg`` for every type the test's topics use, as zenoh-ros2-sdk looks them up."""
    store = ros_types("jazzy").store
    todo = [LASER_SCAN, MARKER_ARRAY, *(f"vision_msgs/msg/{name}" for name in VISION_MSGS)]
    done: set[str] = set()
    while todo:
        typename = todo.pop()
        if typename in done:
            continue
        done.add(typename)
        package, _, name = typename.split("/")
        if package == "vision_msgs":
            text = vision_msgs_definition(name)  # the repository's upstream copy, as the bridge uses
        else:
            text = store.gendefhash(typename, {}, ros_version=2)[0]
        path = root / package / "msg" / f"{name}.msg"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        for _, desc in store.fielddefs[typename][1]:
            nested = desc[1] if desc[0] == 2 else desc[1][0][1] if desc[0] in (3, 4) else None
            if isinstance(nested, str):
                todo.append(nested)
    return root


@pytest.fixture
def sdk_session(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[int, list[int]]]:
    """Ports (bridge, [encoder, detector, tracker]) and a zenoh-ros2-sdk set up offline; closed afterwards."""
    from zenoh_ros2_sdk import message_registry

    monkeypatch.setenv("ZENOH_CONFIG_OVERRIDE", 'listen/endpoints=["tcp/127.0.0.1:0"]')
    monkeypatch.setenv("ROS_DOMAIN_ID", "0")
    monkeypatch.setattr(message_registry, "_registry", None)  # the SDK's registry is a process global
    message_registry.get_registry(str(write_message_directory(tmp_path / "msgs")))
    bridge_port, encoder_port, detector_port, tracker_port = free_tcp_ports(4)
    try:
        yield bridge_port, [encoder_port, detector_port, tracker_port]
    finally:
        session = sdk.ZenohSession._instance
        if session is not None:
            session.close()


def stamp_of(message: Any) -> int:
    return message.header.stamp.sec * 1_000_000_000 + message.header.stamp.nanosec


def next_answer(answers: queue.Queue[Any], not_before_ns: int, stamp: Callable[[Any], int]) -> Any:
    """The next message stamped ``not_before_ns`` or later, skipping older ones (answers to priming)."""
    while True:
        message = answers.get(timeout=30)
        if stamp(message) >= not_before_ns:
            return message


def test_zenoh_ros2_sdk_node_gets_detections_and_markers_back(sdk_session: tuple[int, list[int]]) -> None:
    bridge_port, (encoder_port, detector_port, tracker_port) = sdk_session
    scans = [r.scan for r in replay_scans(ROBOT, SCANS)]
    quiet = {"stdout": subprocess.PIPE, "stderr": subprocess.STDOUT}
    children = {
        "bridge": start_loopback_service(
            "services.ros2_bridge",
            bridge_port,
            [encoder_port, detector_port, tracker_port],
            "--namespace",
            f"/{ROBOT}",
            **quiet,
        ),
        "encoder": start_loopback_service("services.encoder", encoder_port, [detector_port], **quiet),
        "detector": start_loopback_service("services.detector", detector_port, [], "--threads", "1", **quiet),
        "tracker": start_loopback_service("services.tracker", tracker_port, [detector_port], **quiet),
    }
    arrays: queue.Queue[Any] = queue.Queue()
    markers: queue.Queue[Any] = queue.Queue()
    tracks: queue.Queue[Any] = queue.Queue()
    stats: list[dict[str, Any]] = []
    endpoints: list[Any] = []
    try:
        common = {"router_port": bridge_port, "domain_id": 0, "namespace": f"/{ROBOT}"}
        endpoints += [
            sdk.ROS2Subscriber(f"/{ROBOT}/triscan/detections", DETECTION3D_ARRAY, arrays.put, **common),
            sdk.ROS2Subscriber(f"/{ROBOT}/triscan/markers", MARKER_ARRAY, markers.put, **common),
            sdk.ROS2Subscriber(f"/{ROBOT}/triscan/tracks", DETECTION3D_ARRAY, tracks.put, **common),
        ]
        lidar = sdk.ROS2Publisher(f"/{ROBOT}/scan", LASER_SCAN, node_name="lidar", **common)
        endpoints.append(lidar)
        session = sdk.ZenohSession.get_instance()
        endpoints.append(
            session.session.declare_subscriber(
                service_stats_key("ros2_bridge"), lambda s: stats.append(json.loads(payload_bytes(s)))
            )
        )
        types = session.store.types

        def publish(index: int, stamp_ns: int) -> None:
            scan = scans[index % len(scans)]
            sec, nanosec = divmod(stamp_ns, 1_000_000_000)
            lidar.publish(
                header=types["std_msgs/msg/Header"](
                    stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
                    frame_id=scan.frame_id,
                ),
                angle_min=scan.angle_min,
                angle_max=scan.angle_min + scan.angle_increment * (len(scan.ranges) - 1),
                angle_increment=scan.angle_increment,
                time_increment=0.0,
                scan_time=0.1,
                range_min=scan.range_min,
                range_max=scan.range_max,
                ranges=scan.ranges.copy(),
                intensities=scan.ranges[:0].copy(),
            )

        # Prime: peers that start together may connect on Zenoh's retry; scans before that are lost.
        stamp = 1_700_000_000_000_000_000
        deadline = time.monotonic() + 90
        while arrays.empty():
            assert time.monotonic() < deadline, "no Detection3DArray ever came back"
            publish(0, stamp)
            stamp += PERIOD_NS
            time.sleep(0.1)
        # Lockstep: each scan's detections come back, stamped with that scan, before the next scan.
        # Answers to priming scans still in flight carry earlier stamps than any lockstep scan's.
        lockstep_from = stamp
        got_arrays, got_markers = [], []
        for index in range(SCANS):
            publish(index, stamp)
            array = next_answer(arrays, lockstep_from, stamp_of)
            marker = next_answer(markers, lockstep_from, lambda m: stamp_of(m.markers[0]))
            got_arrays.append((stamp, array))
            got_markers.append((stamp, marker))
            stamp += PERIOD_NS
        # The tracks of the last lockstep scan, and every tracks array since lockstep began.
        got_tracks: list[Any] = []
        while not got_tracks or stamp_of(got_tracks[-1]) < stamp - PERIOD_NS:
            got_tracks.append(next_answer(tracks, lockstep_from, stamp_of))
        topics = dict(sdk.get_topic_names_and_types(domain_id=0, router_port=bridge_port, timeout=2.0))
        assert wait_for(lambda: bool(stats), 10)
    finally:
        for endpoint in endpoints:
            (endpoint.close if hasattr(endpoint, "close") else endpoint.undeclare)()
        stop_processes(children, grace_s=30)
    logs = {name: p.stdout.read().decode(errors="replace") for name, p in children.items()}  # type: ignore[union-attr]
    assert all(p.returncode == 0 for p in children.values()), {n: log[-2000:] for n, log in logs.items()}
    assert [stamp_of(a) for _, a in got_arrays] == [s for s, _ in got_arrays]
    assert [stamp_of(m.markers[0]) for _, m in got_markers] == [s for s, _ in got_markers]
    total = 0
    for (_, array), (_, marker_array) in zip(got_arrays, got_markers, strict=True):
        assert array.header.frame_id == scans[0].frame_id
        ms = marker_array.markers
        assert ms[0].action == DELETEALL and len(ms) == 1 + 2 * len(array.detections)
        assert [m.type for m in ms[1:]] == [CUBE, TEXT_VIEW_FACING] * len(array.detections)
        for detection in array.detections:
            hypothesis = detection.results[0].hypothesis
            assert hypothesis.class_id in CLASS_NAMES and 0.0 < hypothesis.score <= 1.0
            assert detection.bbox.size.x > 0 and detection.bbox.size.y > 0
        total += len(array.detections)
    assert total > 0, "the shipped model saw nothing in 14 real scans"
    assert topics.get(f"/{ROBOT}/triscan/detections") == [DETECTION3D_ARRAY]
    assert topics.get(f"/{ROBOT}/triscan/markers") == [MARKER_ARRAY]
    assert topics.get(f"/{ROBOT}/triscan/tracks") == [DETECTION3D_ARRAY]
    assert topics.get(f"/{ROBOT}/triscan/track_markers") == [MARKER_ARRAY]
    # The same scans over and over: the same objects keep the same track ids from array to array.
    seen = Counter(d.id for array in got_tracks for d in array.detections)
    assert seen and all(track_id.isdigit() for track_id in seen)
    assert max(seen.values()) >= SCANS // 2, seen
    assert {a.header.frame_id for a in got_tracks} == {scans[0].frame_id}  # no odometry: laser frame
    assert stats[-1]["rejected_scans"] == {} and stats[-1]["rejected_detections"] == {}
    assert stats[-1]["rejected_tracks"] == {}
