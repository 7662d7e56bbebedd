"""``triscan replay``: bags of all three formats, written here with rosbags' writers, replayed over Zenoh.

Each bag holds two LaserScan topics and a topic of another type; the test replays one scan topic over
loopback Zenoh to a subscriber session and checks that every scan arrives, in order, with its ranges,
stamp and frame, at roughly the recorded pace (a loose lower bound only: slow machines must pass).
"""

from __future__ import annotations

import itertools
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Rosbag1Writer
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Rosbag2Writer
from rosbags.typesys import Stores, get_typestore

from common.keys import SCAN, wildcard_key
from common.messages import Scan, decode_message
from common.transport import ZenohSettings, open_session, payload_bytes
from services.bag_replay import ReplayConfig, ReplayError, replay, robot_id_of_topic, run_replay
from services.cli import main as cli_main
from services.launcher import free_tcp_ports
from services.ros2_bridge.ros_types import LASER_SCAN
from tests.support.waiting import wait_for

SCANS = 8
PERIOD_NS = 50_000_000
T0_NS = 1_700_000_000_000_000_000
FORMATS = ("bag", "db3", "mcap")


def _ranges(i: int) -> np.ndarray:
    return (np.linspace(0.3, 3.3, 360) + 0.01 * i).astype(np.float32)


def _scan_message(store: Any, i: int, frame_id: str) -> object:
    t = store.types
    header_fields: dict[str, Any] = {
        "stamp": t["builtin_interfaces/msg/Time"](
            sec=(T0_NS + i * PERIOD_NS) // 10**9, nanosec=(T0_NS + i * PERIOD_NS) % 10**9
        ),
        "frame_id": frame_id,
    }
    if "seq" in {name for name, _ in store.fielddefs["std_msgs/msg/Header"][1]}:
        header_fields["seq"] = i  # ROS 1 headers carry one
    return t[LASER_SCAN](
        header=t["std_msgs/msg/Header"](**header_fields),
        angle_min=0.0, angle_max=2 * np.pi * 359 / 360, angle_increment=2 * np.pi / 360, time_increment=0.0,
        scan_time=0.1, range_min=0.12, range_max=3.5, ranges=_ranges(i), intensities=np.zeros(0, np.float32),
    )  # fmt: skip


def _write_drive(writer: Any, store: Any, serialize: Callable[[Any, str], Any]) -> None:
    """The same drive in any bag format: two robots' scans and a chatter topic, PERIOD_NS apart."""
    conns = {
        topic: writer.add_connection(topic, LASER_SCAN, typestore=store)
        for topic in ("/robot1/scan", "/robot2/scan")
    }
    chatter = writer.add_connection("/chatter", "std_msgs/msg/String", typestore=store)
    hello = serialize(store.types["std_msgs/msg/String"](data="hi"), "std_msgs/msg/String")
    for i in range(SCANS):
        for topic, conn in conns.items():
            writer.write(
                conn, T0_NS + i * PERIOD_NS, serialize(_scan_message(store, i, topic[1:7]), LASER_SCAN)
            )
        writer.write(chatter, T0_NS + i * PERIOD_NS, hello)


def write_bag(directory: Path, fmt: str) -> Path:
    """A bag with /robot1/scan, /robot2/scan (SCANS each, PERIOD_NS apart) and a /chatter String."""
    if fmt == "bag":
        store = get_typestore(Stores.ROS1_NOETIC)
        path = directory / "drive.bag"
        with Rosbag1Writer(path) as writer:
            _write_drive(writer, store, store.serialize_ros1)
        return path
    store = get_typestore(Stores.ROS2_JAZZY)
    plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
    path = directory / f"drive_{fmt}"
    with Rosbag2Writer(path, version=9, storage_plugin=plugin) as writer:
        _write_drive(writer, store, store.serialize_cdr)
    (file,) = path.glob(f"*.{fmt}")
    return file  # the storage file itself, as a user would name it


@pytest.mark.parametrize("fmt", FORMATS)
def test_replay_publishes_every_scan_in_order_at_recorded_pace(tmp_path: Path, fmt: str) -> None:
    bag = write_bag(tmp_path, fmt)
    test_port, replay_port = free_tcp_ports(2)
    received: queue.Queue[tuple[float, bytes]] = queue.Queue()
    config = ReplayConfig(bags=(bag,), topics=("/robot1/scan",), robot="r1", speed=2.0, progress=False)
    with open_session(ZenohSettings.loopback(test_port)) as session:
        subscriber = session.declare_subscriber(
            wildcard_key(SCAN), lambda s: received.put((time.monotonic(), payload_bytes(s)))
        )
        summary = run_replay(ZenohSettings.loopback(replay_port, [test_port]), config, wait_s=30)
        arrivals = []
        for _ in range(SCANS):
            arrivals.append(received.get(timeout=10))
        # The replay's session has closed, and its link with it: whatever it sent was delivered first.
        assert wait_for(lambda: not list(session.info.peers_zid()), 10)
        subscriber.undeclare()
    assert received.empty(), "more scans than the topic holds: another topic leaked in"
    scans = [decode_message(payload, Scan) for _, payload in arrivals]
    assert summary.published == SCANS and summary.robots == {"/robot1/scan": "r1"} and not summary.rejected
    assert [s.robot_id for s in scans] == ["r1"] * SCANS
    assert [s.seq for s in scans] == list(range(SCANS))
    assert [s.stamp_ns for s in scans] == [T0_NS + i * PERIOD_NS for i in range(SCANS)]
    assert all(s.frame_id == "robot1" for s in scans)
    for i, scan in enumerate(scans):
        np.testing.assert_array_equal(scan.ranges, _ranges(i))
    recorded_s = (SCANS - 1) * PERIOD_NS / 1e9 / config.speed
    assert arrivals[-1][0] - arrivals[0][0] >= 0.5 * recorded_s  # paced, not dumped (loose on purpose)


def test_replay_of_all_topics_names_robots_after_topics_and_loops_with_rising_stamps(tmp_path: Path) -> None:
    bag = write_bag(tmp_path, "mcap")
    out: list[tuple[str, Scan]] = []
    stop = threading.Event()

    def publish(key: str, payload: bytes) -> None:
        out.append((key, decode_message(payload, Scan)))
        if len(out) == 4 * SCANS:  # two topics, two passes
            stop.set()

    summary = replay(ReplayConfig(bags=(bag,), speed=50.0, loop=True, progress=False), publish, stop=stop)
    assert summary.robots == {"/robot1/scan": "robot1_scan", "/robot2/scan": "robot2_scan"}
    for robot in ("robot1_scan", "robot2_scan"):
        mine = [scan for key, scan in out if key == f"triscan/{robot}/scan"]
        assert [s.seq for s in mine] == list(range(2 * SCANS))
        stamps = [s.stamp_ns for s in mine]
        assert all(b > a for a, b in itertools.pairwise(stamps))
    assert robot_id_of_topic("/front/laser scan") == "front_laser_scan"


def test_replay_refuses_what_it_cannot_do(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = write_bag(tmp_path, "bag")
    with pytest.raises(ReplayError, match="pick one with --topic"):
        replay(ReplayConfig(bags=(bag,), robot="r1", progress=False), lambda k, p: None)
    with pytest.raises(ReplayError, match="no LaserScan topic"):
        replay(ReplayConfig(bags=(bag,), topics=("/chatter",), progress=False), lambda k, p: None)
    assert cli_main(["replay", str(bag), "--robot", "r1", "--no-multicast", "--wait", "0"]) == 2


def _stamp(store: Any, ns: int) -> Any:
    return store.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def _header(store: Any, ns: int, frame_id: str) -> Any:
    fields: dict[str, Any] = {"stamp": _stamp(store, ns), "frame_id": frame_id}
    if "seq" in {name for name, _ in store.fielddefs["std_msgs/msg/Header"][1]}:
        fields["seq"] = 0
    return store.types["std_msgs/msg/Header"](**fields)


def _pose_parts(store: Any, i: int) -> tuple[float, float, Any]:
    """The robot's pose at tick i: driving along x, turning slowly; tick 3 is NaN (a diverged filter)."""
    x = float("nan") if i == 3 else 0.1 * i
    yaw = 0.05 * i
    quaternion = store.types["geometry_msgs/msg/Quaternion"](
        x=0.0, y=0.0, z=np.sin(yaw / 2), w=np.cos(yaw / 2)
    )
    return x, yaw, quaternion


def _odom_message(store: Any, i: int, ns: int) -> Any:
    t = store.types
    x, _, quaternion = _pose_parts(store, i)
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=x, y=0.5, z=0.0), orientation=quaternion
    )
    twist = t["geometry_msgs/msg/Twist"](
        linear=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
        angular=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
    )
    return t["nav_msgs/msg/Odometry"](
        header=_header(store, ns, "odom"),
        child_frame_id="base_link",
        pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
    )


def _tf_message(store: Any, i: int, ns: int) -> Any:
    t = store.types
    x, _, quaternion = _pose_parts(store, i)

    def transform(parent: str, child: str, tx: float) -> Any:
        return t["geometry_msgs/msg/TransformStamped"](
            header=_header(store, ns, parent),
            child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=tx, y=0.5, z=0.0), rotation=quaternion
            ),
        )

    # Another frame pair first: only odom → base_link is the robot's pose.
    return t["tf2_msgs/msg/TFMessage"](
        transforms=[transform("base_link", "laser", 9.0), transform("odom", "base_link", x)]
    )


@pytest.mark.parametrize(("fmt", "source"), [("bag", "/odom"), ("mcap", "/odom"), ("mcap", "/tf")])
def test_replay_pairs_each_scan_with_the_newest_pose_and_refuses_nan(
    tmp_path: Path, fmt: str, source: str
) -> None:
    if fmt == "bag":
        store, serialize = get_typestore(Stores.ROS1_NOETIC), None
        path = tmp_path / "odom.bag"
        writer: Any = Rosbag1Writer(path)
    else:
        store, serialize = get_typestore(Stores.ROS2_JAZZY), None
        path = tmp_path / "odom_mcap"
        writer = Rosbag2Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    serialize = store.serialize_ros1 if fmt == "bag" else store.serialize_cdr
    msgtype = "nav_msgs/msg/Odometry" if source == "/odom" else "tf2_msgs/msg/TFMessage"
    make = _odom_message if source == "/odom" else _tf_message
    with writer:
        scans = writer.add_connection("/scan", LASER_SCAN, typestore=store)
        poses = writer.add_connection(source, msgtype, typestore=store)
        for i in range(SCANS):
            ns = T0_NS + i * PERIOD_NS
            writer.write(
                poses, ns - 1_000_000, serialize(make(store, i, ns - 1_000_000), msgtype)
            )  # 1 ms before
            writer.write(scans, ns, serialize(_scan_message(store, i, "laser"), LASER_SCAN))
    out: list[Scan] = []
    summary = replay(
        ReplayConfig(bags=(path,), speed=100.0, progress=False),
        lambda key, payload: out.append(decode_message(payload, Scan)),
    )
    assert summary.odom_topic == source and summary.published == SCANS
    assert summary.odometry.counters() == {"attached": SCANS, "refused": {"not_finite": 1}}
    for i, scan in enumerate(out):
        assert scan.odom is not None and scan.odom.frame_id == "odom"
        expected = i - 1 if i == 3 else i  # the NaN pose is refused: the scan keeps the one before
        assert scan.odom.x_m == pytest.approx(0.1 * expected) and scan.odom.y_m == pytest.approx(0.5)
        assert scan.odom.yaw_rad == pytest.approx(0.05 * expected)
        assert scan.odom.stamp_ns == T0_NS + expected * PERIOD_NS - 1_000_000
    plain = replay(
        ReplayConfig(bags=(path,), speed=100.0, progress=False, odom_topic="none"), lambda k, p: None
    )
    assert plain.odom_topic is None and plain.odometry.attached == 0
    with pytest.raises(ReplayError, match="no nav_msgs/Odometry"):
        replay(ReplayConfig(bags=(path,), progress=False, odom_topic="/scan"), lambda k, p: None)
