"""``python -m services.ros2_bridge``: ROS 2 LaserScans (over Zenoh) in, triscan detections back to ROS 2.

Subscribes to a robot's ``scan`` topic as a ROS 2 node on rmw_zenoh would (or behind
zenoh-bridge-ros2dds, ``--style ros2dds``), publishes triscan ``Scan``s on ``triscan/<robot>/scan``
(each robot's announced, :func:`services.runtime.announce_source`), and turns the detector's
``triscan/<robot>/detections`` into ``vision_msgs/Detection3DArray`` and
``visualization_msgs/MarkerArray`` on ``<namespace>/triscan/{detections,markers}``, the tracker's
``triscan/<robot>/tracks`` into the same two types on ``<namespace>/triscan/{tracks,track_markers}``.
In rmw_zenoh style it declares the ROS graph tokens, so ``ros2 topic list`` shows its topics. Base
install plus ``rosbags`` (``pip install triscan[ros2]``). The rules live in :mod:`services.ros2_bridge.core`.
"""

from __future__ import annotations

import argparse
import logging
import threading
from typing import Any

from common.keys import ALL_DETECTIONS, ALL_TRACKS, SCAN
from common.transport import ZenohSettings, payload_bytes, settings_from_args
from services.ros2_bridge.core import BridgeConfig, BridgeCore, Outgoing
from services.ros2_bridge.rmw_zenoh import STYLES
from services.ros2_bridge.ros_types import DISTROS
from services.runtime import (
    ServiceRuntime,
    add_service_arguments,
    announce_source,
    configure_logging,
    default_of,
    exit_code_of,
    exit_process,
    service_parser,
    stop_event_on_signals,
)

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

SERVICE = "ros2_bridge"


def _attachment_bytes(sample: Any) -> bytes | None:
    attachment = sample.attachment
    return None if attachment is None else attachment.to_bytes()


def run(
    settings: ZenohSettings, stop: threading.Event, config: BridgeConfig, *, duration_s: float = 0.0
) -> BridgeCore:
    """Serve until ``stop`` is set (or ``duration_s`` passes); returns the core with its counters."""
    core = BridgeCore(config)
    lock = threading.Lock()  # the core is not thread-safe; Zenoh may call back from several threads
    with ServiceRuntime(SERVICE, settings, stop, duration_s=duration_s) as runtime:
        session = runtime.session
        zid = str(session.info.zid())
        publishers: dict[str, Any] = {}
        tokens: dict[str, Any] = {}
        sources: dict[str, Any] = {}  # robot id → its scans' source token

        def publish(samples: list[Outgoing]) -> None:
            for sample in samples:
                with lock:
                    publisher = publishers.get(sample.key)
                    if publisher is None:
                        publisher = publishers[sample.key] = runtime.keep(
                            session.declare_publisher(sample.key)
                        )
                publisher.put(sample.payload, attachment=sample.attachment)

        def announce_robots() -> None:
            """Each robot's scans are announced from the moment the bridge knows it, so the detector
            process that serves it subscribes to them; its first scans, which follow at once, are
            answered once every detector process has seen the token (docs/services.md)."""
            with lock:
                robot_ids = [robot_id for robot_id in core.robot_ids if robot_id not in sources]
            for robot_id in robot_ids:
                sources[robot_id] = runtime.keep(announce_source(session, robot_id, SCAN))
            declare_graph()

        def declare_graph() -> None:
            if config.style != "rmw_zenoh":
                return
            with lock:
                wanted = core.liveliness_tokens(zid)
            for key in wanted:
                if key not in tokens:
                    tokens[key] = runtime.keep(session.liveliness().declare_token(key))

        def on_scan(sample: Any) -> None:
            with lock:
                robots = len(core.robot_ids)
                out = core.handle_scan(str(sample.key_expr), payload_bytes(sample), _attachment_bytes(sample))
                new_robot = len(core.robot_ids) != robots
            if new_robot:
                announce_robots()
            if out is not None:
                publish([out])

        def on_odometry(sample: Any) -> None:
            with lock:
                robots = len(core.robot_ids)
                core.handle_odometry(str(sample.key_expr), payload_bytes(sample), _attachment_bytes(sample))
                new_robot = len(core.robot_ids) != robots
            if new_robot:
                announce_robots()

        def on_detections(key: str, payload: bytes) -> None:
            with lock:
                out = core.handle_detections(key, payload)
            publish(out)

        def on_tracks(key: str, payload: bytes) -> None:
            with lock:
                out = core.handle_tracks(key, payload)
            publish(out)

        def counters() -> dict[str, object]:
            with lock:
                return core.counters.to_dict()

        declare_graph()
        runtime.subscribe_samples(core.scan_subscription_key, on_scan)
        if core.odom_subscription_key is not None:
            runtime.subscribe_samples(core.odom_subscription_key, on_odometry)
        runtime.subscribe(ALL_DETECTIONS, on_detections)
        runtime.subscribe(ALL_TRACKS, on_tracks)
        log.info(
            "ros2 bridge ready (%s, %s): %s ⇄ triscan",
            config.style,
            config.distro,
            core.scan_subscription_key,
        )
        runtime.serve(counters)
    return core


def build_config(args: argparse.Namespace) -> BridgeConfig:
    namespace = None if args.namespace == "*" else args.namespace
    return BridgeConfig(
        style=args.style,
        domain=args.domain,
        scan_topic=args.scan_topic,
        odom_topic=None if args.odom_topic == "none" else args.odom_topic,
        namespace=namespace,
        robot=args.robot,
        distro=args.ros_distro,
    )


def main(argv: list[str] | None = None) -> int:
    parser = service_parser("services.ros2_bridge", __doc__.splitlines()[0])
    parser.add_argument(
        "--style", choices=STYLES, default=default_of(BridgeConfig, "style"), help="how ROS 2 reaches Zenoh"
    )
    parser.add_argument(
        "--domain",
        type=int,
        default=default_of(BridgeConfig, "domain"),
        help="ROS_DOMAIN_ID of the robot (rmw_zenoh style)",
    )
    parser.add_argument(
        "--scan-topic", default=default_of(BridgeConfig, "scan_topic"), help="LaserScan topic, relative"
    )
    parser.add_argument(
        "--odom-topic",
        default=default_of(BridgeConfig, "odom_topic"),
        help="nav_msgs/Odometry topic, relative, whose pose each scan carries ('none': no odometry)",
    )
    parser.add_argument(
        "--namespace",
        default=default_of(BridgeConfig, "namespace"),
        help="ROS namespace of the robot (its last segment is the robot id), or '*' for every "
        "one-segment namespace (default: the root namespace, which needs --robot)",
    )
    parser.add_argument(
        "--robot", default=None, help="triscan robot id (default: the namespace's last segment)"
    )
    parser.add_argument(
        "--ros-distro",
        choices=DISTROS,
        default=default_of(BridgeConfig, "distro"),
        help="type hashes and message layouts to publish",
    )
    add_service_arguments(parser)
    args = parser.parse_args(argv)
    configure_logging(args.verbose)
    try:
        config = build_config(args)
    except ValueError as exc:
        parser.error(str(exc))
    run(settings_from_args(args), stop_event_on_signals(), config, duration_s=args.duration)
    return 0


if __name__ == "__main__":
    exit_process(exit_code_of(main))
