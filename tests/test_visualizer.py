"""Tests for the visualizer: real Rerun recordings read back from disk, real Zenoh, no mocks.

What a person sees in the viewer is only as good as what is in the recording, so every test reads the
``.rrd`` back with ``rerun.chunk.RrdReader`` and checks entity paths, component kinds and counts.
"""

from __future__ import annotations

import json
import math
import queue
import signal
import subprocess
import sys
import time
import uuid
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

rr = pytest.importorskip("rerun")
from rerun.chunk import RrdReader  # noqa: E402

from common.keys import (  # noqa: E402
    detections_key,
    health_key,
    scan_key,
    stats_key,
    tensor_key,
    tracks_key,
    truth_key,
)
from common.messages import (  # noqa: E402
    TENSOR_SHAPE,
    Detection,
    Detections,
    GroundTruth,
    Odometry,
    Scan,
    StackedTensor,
    StageTimings,
    Track,
    Tracks,
    TruthObject,
    encode_message,
)
from common.model_spec import CLASS_COLOURS, CLASS_NAMES  # noqa: E402
from common.transport import ZenohSettings, open_session, payload_bytes  # noqa: E402
from services.tracker.core import track_colour  # noqa: E402
from services.visualizer.core import (  # noqa: E402
    TIMING_NAMES,
    TRAIL_LENGTH,
    RerunVisualizer,
    RobotPaths,
    blueprint,
    sector_outline,
    world_to_sensor,
)

ROOT = Path(__file__).resolve().parents[1]
DEG = math.pi / 180.0
BEAMS = 360
INVALID_BEAMS = (5, 6, 7, 200)  # inf, NaN, below range_min, above range_max

# --------------------------------------------------------------------------------------------------
# Hand-made messages
# --------------------------------------------------------------------------------------------------


def make_scan(robot_id: str, seq: int) -> Scan:
    ranges = np.full(BEAMS, 1.5, dtype=np.float32)
    ranges[5], ranges[6], ranges[7], ranges[200] = np.inf, np.nan, 0.05, 3.9
    return Scan(
        robot_id=robot_id,
        seq=seq,
        stamp_ns=1_700_000_000_000_000_000 + seq * 100_000_000,
        angle_min=0.0,
        angle_increment=DEG,
        range_min=0.12,
        range_max=3.5,
        ranges=ranges,
    )


def make_tensor(robot_id: str, seq: int) -> StackedTensor:
    tensor = np.zeros(TENSOR_SHAPE, dtype=np.uint8)
    tensor[23, :360, :] = 255
    return StackedTensor(
        robot_id=robot_id,
        seq=seq,
        stamp_ns=1_700_000_000_000_000_000 + seq * 100_000_000,
        tensor=tensor,
        padding="zero",
        scan_seqs=(seq - 2, seq - 1, seq),
        scan_stamps_ns=(1, 2, 3),
    )


def make_detection(class_id: int, score: float, bearing_deg: float) -> Detection:
    return Detection(
        class_id=class_id,
        class_name=CLASS_NAMES[class_id],
        score=score,
        box_px=(bearing_deg + 0.5 - 5, 18.0, bearing_deg + 0.5 + 5, 30.0),
        bearing_deg=bearing_deg,
        bearing_min_deg=bearing_deg - 5,
        bearing_max_deg=bearing_deg + 5,
        range_min_m=18 * 4 / 63,
        range_max_m=30 * 4 / 63,
        x_m=1.5 * math.cos(math.radians(bearing_deg)),
        y_m=1.5 * math.sin(math.radians(bearing_deg)),
    )


def make_detections(robot_id: str, seq: int) -> Detections:
    return Detections(
        robot_id=robot_id,
        seq=seq,
        stamp_ns=1_700_000_000_000_000_000 + seq * 100_000_000 + 30_000_000,
        detections=[make_detection(0, 0.91, 30.0), make_detection(2, 0.74, 120.0)],
        timings=StageTimings(encode_ms=0.4, inference_ms=12.5, nms_ms=0.3),
        model_id="test-model",
        scan_stamp_ns=1_700_000_000_000_000_000 + seq * 100_000_000,
    )


def make_truth(robot_id: str, seq: int) -> GroundTruth:
    def box(class_id: int, visible: bool) -> TruthObject:
        return TruthObject(
            class_id=class_id,
            class_name=CLASS_NAMES[class_id],
            corners_xy=np.array([[1.0, 0.0], [1.4, 0.0], [1.4, 0.6], [1.0, 0.6]], dtype=np.float32),
            center_xy=(1.2, 0.3),
            yaw_rad=0.0,
            visible=visible,
            box_px=(0.0, 15.0, 30.0, 25.0) if visible else None,
        )

    return GroundTruth(
        robot_id=robot_id,
        seq=seq,
        stamp_ns=1_700_000_000_000_000_000 + seq * 100_000_000,
        scenario_id=3,
        robot_pose=(0.1, -0.2, 1.0),
        lidar_pose=(0.07, -0.2, 1.0),
        objects=[box(1, True), box(3, False)],
    )


def frame_samples(robot_id: str, seq: int) -> list[tuple[str, bytes]]:
    """One frame of every topic as (key, payload), exactly as the services publish them."""
    return [
        (scan_key(robot_id), encode_message(make_scan(robot_id, seq))),
        (tensor_key(robot_id), encode_message(make_tensor(robot_id, seq))),
        (detections_key(robot_id), encode_message(make_detections(robot_id, seq))),
        (truth_key(robot_id), encode_message(make_truth(robot_id, seq))),
    ]


# --------------------------------------------------------------------------------------------------
# Reading recordings back
# --------------------------------------------------------------------------------------------------


def read_components(path: Path) -> dict[str, dict[str, list[int]]]:
    """entity path → component (e.g. ``Points2D:positions``) → instance count of each logged row."""
    out: dict[str, dict[str, list[int]]] = defaultdict(lambda: defaultdict(list))
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            metadata = batch.schema.field(name).metadata or {}
            if metadata.get(b"rerun:kind") != b"data":
                continue
            out[chunk.entity_path][name].extend(len(row) for row in batch.column(name).to_pylist())
    return out


def image_sizes(path: Path, entity: str) -> list[tuple[int, int, int]]:
    """(width, height, bytes per pixel) of every image logged at ``entity``."""
    sizes = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path != entity:
            continue
        batch = chunk.to_record_batch()
        for (fmt,), (buffer,) in zip(
            batch.column("Image:format").to_pylist(), batch.column("Image:buffer").to_pylist(), strict=True
        ):
            sizes.append((fmt["width"], fmt["height"], len(buffer) // (fmt["width"] * fmt["height"])))
    return sizes


def timelines_of(path: Path, entity: str) -> set[str]:
    return {
        t for chunk in RrdReader(path).stream() if chunk.entity_path == entity for t in chunk.timeline_names
    }


def new_recording(path: Path) -> rr.RecordingStream:
    rec = rr.RecordingStream("triscan_visualizer_test", recording_id=uuid.uuid4())
    rec.save(path)
    return rec


def close(rec: rr.RecordingStream) -> None:
    rec.flush()
    rec.disconnect()


# --------------------------------------------------------------------------------------------------
# Core
# --------------------------------------------------------------------------------------------------


def test_core_logs_every_view(tmp_path: Path) -> None:
    path = tmp_path / "core.rrd"
    rec = new_recording(path)
    viz = RerunVisualizer(rec, ["r1"])
    for seq in (10, 11):
        for key, payload in frame_samples("r1", seq):
            assert viz.handle(key, payload), key
    close(rec)

    assert viz.stats().accepted == {"scan": 2, "tensor": 2, "detections": 2, "truth": 2}
    assert viz.stats().rejected == {}
    got = read_components(path)
    p = RobotPaths("r1")
    entity = "/" + p.scan
    assert got[entity]["Points2D:positions"] == [BEAMS - len(INVALID_BEAMS)] * 2
    assert got["/" + p.raster]["Image:buffer"] == [1, 1]  # one 64×384×3 blob per frame
    assert image_sizes(path, "/" + p.raster) == [(384, 64, len(b"RGB"))] * 2
    assert got["/" + p.raster_detections]["Boxes2D:half_sizes"] == [2, 2]
    assert got["/" + p.raster_detections]["Boxes2D:labels"] == [2, 2]
    assert got["/" + p.raster_truth]["Boxes2D:half_sizes"] == [1, 1]  # only the visible object
    assert got["/" + p.map_detections]["Points2D:positions"] == [2, 2]
    assert got["/" + p.map_detection_extents]["LineStrips2D:strips"] == [2, 2]
    assert got["/" + p.map_truth]["LineStrips2D:strips"] == [2, 2]  # visible and unseen alike
    for name in TIMING_NAMES:
        assert got["/" + p.timing(name)]["Scalars:scalars"] == [1, 1]
    # Static display transforms put the metric view forward-up without touching the logged numbers.
    assert "Transform3D:mat3x3" in got["/" + p.scan]
    assert "Transform3D:mat3x3" in got["/" + p.map]
    assert {"seq", "stamp"} <= timelines_of(path, entity)
    assert len(RrdReader(path).blueprints()) == 1
    RrdReader(path).store()  # the footer (manifest) was written: the file is complete


def test_detection_labels_carry_class_and_score_and_colours_come_from_one_context(tmp_path: Path) -> None:
    path = tmp_path / "labels.rrd"
    rec = new_recording(path)
    RerunVisualizer(rec, send_blueprints=False).log_message(make_detections("r1", 3))
    close(rec)
    context = None
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        if chunk.entity_path == "/" and "AnnotationContext:context" in batch.schema.names:
            context = batch.column("AnnotationContext:context").to_pylist()[0][0]
        if chunk.entity_path == "/" + RobotPaths("r1").raster_detections:
            labels = batch.column("Boxes2D:labels").to_pylist()[0]
            class_ids = batch.column("Boxes2D:class_ids").to_pylist()[0]
            assert "Boxes2D:colors" not in batch.schema.names  # no per-call colours
            break
    else:
        pytest.fail("no raster detections logged")
    assert labels == ["chair 0.91", "desk 0.74"]
    assert class_ids == [0, 2]
    assert context is not None, "the class AnnotationContext must be logged, static, at the root"
    infos = {entry["class_id"]: entry["class_description"]["info"] for entry in context}
    assert [infos[i]["label"] for i in range(len(CLASS_NAMES))] == list(CLASS_NAMES)
    colours = [infos[i]["color"] for i in range(len(CLASS_NAMES))]
    expected = [(r << 24) | (g << 16) | (b << 8) | 0xFF for r, g, b in CLASS_COLOURS]
    assert colours == expected


def _tracks_of(robot_id: str, seq: int, pose: tuple[float, float, float] | None) -> Tracks:
    """A still chair at world (2, 1) and a walker moving +y, seen from a robot at ``pose``."""
    world = {1_700_000_000_007: (2.0, 1.0, "confirmed"), 1_700_000_000_008: (0.5, 0.1 * seq, "coasting")}
    x0, y0, yaw = pose or (0.0, 0.0, 0.0)
    c, s = math.cos(yaw), math.sin(yaw)
    tracks = [
        Track(
            track_id=track_id,
            class_id=0,
            class_name=CLASS_NAMES[0],
            score=0.8,
            x_m=c * (x - x0) + s * (y - y0),
            y_m=-s * (x - x0) + c * (y - y0),
            odom_x_m=None if pose is None else x,
            odom_y_m=None if pose is None else y,
            vx_mps=0.0,
            vy_mps=0.0 if track_id % 2 else 1.0,
            age_s=1.0,
            hits=5,
            misses=0,
            state=state,
        )
        for track_id, (x, y, state) in world.items()
    ]
    tentative = tracks[0].model_copy(update={"track_id": 3, "state": "tentative"})
    return Tracks(
        robot_id=robot_id, seq=seq, stamp_ns=1, scan_stamp_ns=1_700_000_000_000_000_000 + seq * 100_000_000,
        frame="laser" if pose is None else "odom", tracks=[*tracks, tentative],
    )  # fmt: skip


def _rows_of(path: Path, entity: str, column: str) -> list[Any]:
    return [
        row
        for chunk in RrdReader(path).stream()
        if chunk.entity_path == entity
        for row in chunk.to_record_batch().column(column).to_pylist()
    ]


def test_tracks_get_a_colour_from_their_id_and_a_trail_that_stays_put_in_the_odometry_frame(
    tmp_path: Path,
) -> None:
    path = tmp_path / "tracks.rrd"
    rec = new_recording(path)
    viz = RerunVisualizer(rec, send_blueprints=False)
    frames = TRAIL_LENGTH + 5
    for seq in range(frames):
        pose = (0.2 * seq, -0.1 * seq, 0.05 * seq)  # the robot drives and turns
        detections = Detections(
            **make_detections("r1", seq).model_dump(exclude={"schema_version", "odom"}),
            odom=Odometry(x_m=pose[0], y_m=pose[1], yaw_rad=pose[2], stamp_ns=1),
        )
        assert viz.handle(detections_key("r1"), encode_message(detections))
        assert viz.handle(tracks_key("r1"), encode_message(_tracks_of("r1", seq, pose)))
    # a robot whose detections carried no pose: its tracks in the laser frame, trails as they came
    for seq in range(3):
        assert viz.handle(tracks_key("r2"), encode_message(_tracks_of("r2", seq, None)))
    close(rec)
    assert viz.stats().accepted["tracks"] == frames + 3
    p = RobotPaths("r1")
    labels = _rows_of(path, "/" + p.map_tracks, "Points2D:labels")
    assert labels[0] == ["#1700000000007 chair", "#1700000000008 chair"]  # tentative tracks are not drawn
    colours = _rows_of(path, "/" + p.map_tracks, "Points2D:colors")
    expected = [
        (r << 24) | (g << 16) | (b << 8) | 0xFF
        for r, g, b in map(track_colour, (1_700_000_000_007, 1_700_000_000_008))
    ]
    assert all(row == expected for row in colours)
    strips = _rows_of(path, "/" + p.map_track_trails, "LineStrips2D:strips")
    assert [len(row[0]) for row in strips] == [min(k + 1, TRAIL_LENGTH) for k in range(frames)]
    last_pose = (0.2 * (frames - 1), -0.1 * (frames - 1), 0.05 * (frames - 1))
    chair, walker = (np.array(strip) for strip in strips[-1])
    # the still chair's whole trail is one point in the last scan's laser frame, where the chair is now
    assert np.allclose(chair, world_to_sensor(np.array([[2.0, 1.0]]), last_pose), atol=1e-5)
    walked = np.linalg.norm(walker[-1] - walker[0])
    assert walked == pytest.approx(0.1 * (TRAIL_LENGTH - 1), abs=1e-4)  # the walker's own path only
    r2 = _rows_of(path, "/" + RobotPaths("r2").map_track_trails, "LineStrips2D:strips")
    assert [len(row[0]) for row in r2] == [1, 2, 3]


def test_bad_payloads_are_counted_by_reason_and_never_raise(tmp_path: Path) -> None:
    rec = new_recording(tmp_path / "bad.rrd")
    viz = RerunVisualizer(rec, send_blueprints=False)
    scan = encode_message(make_scan("r1", 1))
    bad: list[tuple[str, Any]] = [
        (scan_key("r1"), b"\xc1 not msgpack"),
        (scan_key("r1"), encode_message(make_tensor("r1", 5))),  # a tensor on the scan key
        (scan_key("r1"), scan[:-7]),  # truncated
        (scan_key("r2"), scan),  # r1's payload on r2's key
        ("triscan/r1/unknown", scan),
        ("elsewhere/r1/scan", scan),
        (scan_key("r1"), "not bytes"),
    ]
    for key, payload in bad:
        assert viz.handle(key, payload) is False
    assert viz.handle(scan_key("r1"), scan) is True  # and it keeps serving
    close(rec)
    stats = viz.stats()
    assert sum(stats.rejected.values()) == len(bad)
    assert stats.rejected["bad_key"] == 2
    assert stats.rejected["robot_id_mismatch"] == 1
    assert stats.rejected["wrong_kind"] == 1
    assert stats.rejected["not_bytes"] == 1
    assert stats.accepted == {"scan": 1}
    assert stats.robots == ("r1",)


def test_truth_corners_are_moved_into_the_sensor_frame() -> None:
    # A sensor at (1, 2) facing +y (yaw 90°): a world point 1 m further along +y is 1 m ahead (x),
    # a world point 1 m along −x is 1 m to its left (y).
    pose = (1.0, 2.0, math.pi / 2)
    got = world_to_sensor(np.array([[1.0, 3.0], [0.0, 2.0]]), pose)
    np.testing.assert_allclose(got, [[1.0, 0.0], [0.0, 1.0]], atol=1e-12)


def test_detection_extent_follows_the_arc_across_the_seam() -> None:
    det = make_detection(1, 0.5, 180.0).model_copy(
        update={"bearing_min_deg": 175.0, "bearing_max_deg": -175.0}
    )
    outline = sector_outline(det)
    bearings = np.degrees(np.arctan2(outline[:, 1], outline[:, 0]))
    assert np.all(np.abs(np.abs(bearings) - 180.0) <= 5.0 + 1e-9)  # the 10° arc behind, not the 350° one
    np.testing.assert_allclose(outline[0], outline[-1])  # closed


def test_blueprint_has_a_tab_per_robot() -> None:
    assert isinstance(blueprint([]), rr.blueprint.Blueprint)
    assert isinstance(blueprint(["a"]), rr.blueprint.Blueprint)
    two = blueprint(["b", "a", "b"])
    tabs = two.root_container
    assert isinstance(tabs, rr.blueprint.Tabs)
    assert [c.name for c in tabs.contents] == ["a", "b"]


# --------------------------------------------------------------------------------------------------
# The service, end to end over Zenoh
# --------------------------------------------------------------------------------------------------


def start_service(port: int, rrd: Path, duration_s: float) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.visualizer",
            "--save",
            str(rrd),
            "--duration",
            str(duration_s),
            "--listen",
            f"tcp/127.0.0.1:{port}",
            "--no-multicast",
        ],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def wait_for_health(session: Any, proc: subprocess.Popen[str], timeout_s: float = 20.0) -> None:
    """The service's liveliness token appears once its subscribers are declared."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()[0]
        replies = session.liveliness().get(health_key("visualizer", str(proc.pid)), timeout=1.0)
        if any(reply.ok is not None for reply in replies):
            return
        time.sleep(0.2)
    proc.kill()
    pytest.fail("visualizer never announced itself:\n" + proc.communicate()[0])


def wait_for_processed(
    session: Any, proc: subprocess.Popen[str], count: int, timeout_s: float = 60.0
) -> None:
    """Block until the visualizer's own counters (``triscan/@stats/visualizer/<pid>``) say it has
    processed ``count`` messages: what it logged is then in the recording, whatever the machine's load."""
    processed = queue.Queue[int]()

    def on_stats(sample: Any) -> None:
        processed.put(int(json.loads(payload_bytes(sample)).get("processed", 0)))

    subscriber = session.declare_subscriber(stats_key("visualizer", str(proc.pid)), on_stats)
    try:
        deadline = time.monotonic() + timeout_s
        while (remaining := deadline - time.monotonic()) > 0:
            try:
                if processed.get(timeout=remaining) >= count:
                    return
            except queue.Empty:
                break
        pytest.fail(f"the visualizer did not process {count} messages within {timeout_s:.0f} s")
    finally:
        subscriber.undeclare()


def publish_frames(session: Any, robot_ids: list[str]) -> None:
    """Every frame, blocking: a put's default congestion control drops a sample when the link is busy,
    and a burst of 73 KB tensors on a loaded machine is exactly that (the test counts every message)."""
    import zenoh

    for seq in (2, 3):
        for robot_id in robot_ids:
            for key, payload in frame_samples(robot_id, seq):
                session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)


@pytest.mark.slow
@pytest.mark.integration
def test_service_records_two_robots_and_exits_after_duration(
    tmp_path: Path, free_port: Callable[[], int]
) -> None:
    port, rrd = free_port(), tmp_path / "e2e.rrd"
    proc = start_service(port, rrd, duration_s=20.0)  # ample on a loaded machine: the test waits on counters
    try:
        with open_session(ZenohSettings.loopback(None, [port])) as session:
            wait_for_health(session, proc)
            publish_frames(session, ["alpha", "beta"])
            session.put(scan_key("alpha"), b"garbage")
            wait_for_processed(session, proc, 2 * 2 * 4)  # 2 robots × 2 frames × 4 topics
            output, _ = proc.communicate(timeout=30)  # it stops by itself when --duration is over
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, output
    assert "rejected payload (not_msgpack" in output
    got = read_components(rrd)
    for robot_id in ("alpha", "beta"):
        p = RobotPaths(robot_id)
        assert got["/" + p.scan]["Points2D:positions"] == [BEAMS - len(INVALID_BEAMS)] * 2, output
        assert got["/" + p.raster]["Image:buffer"], output
        assert got["/" + p.raster_detections]["Boxes2D:half_sizes"] == [2, 2], output
        assert got["/" + p.map_truth]["LineStrips2D:strips"] == [2, 2], output
        assert got["/" + p.timing("inference_ms")]["Scalars:scalars"] == [1, 1], output
    assert RrdReader(rrd).blueprints(), output


@pytest.mark.slow
@pytest.mark.integration
def test_service_leaves_a_complete_recording_after_sigterm(
    tmp_path: Path, free_port: Callable[[], int]
) -> None:
    port, rrd = free_port(), tmp_path / "sigterm.rrd"
    proc = start_service(port, rrd, duration_s=120.0)
    try:
        with open_session(ZenohSettings.loopback(None, [port])) as session:
            wait_for_health(session, proc)
            publish_frames(session, ["gamma"])
            wait_for_processed(session, proc, 2 * 4)  # 2 frames × 4 topics
            proc.send_signal(signal.SIGTERM)
            output, _ = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, output
    RrdReader(rrd).store()  # footer written: the file is complete, not just a prefix
    got = read_components(rrd)
    assert got["/" + RobotPaths("gamma").scan]["Points2D:positions"] == [BEAMS - len(INVALID_BEAMS)] * 2, (
        output
    )
