"""``triscan replay BAG...``: the LaserScans of recorded ROS bags, as triscan Scans, at recorded pace.

A robot's recorded drives are the cheapest test data there is; replaying them through the encoder and
detector shows what triscan would have seen, with no ROS install. rosbags' ``AnyReader`` reads all
three formats through one interface: ROS 1 ``.bag`` files, and ROS 2 ``.db3`` (SQLite) and ``.mcap``
recordings (a file or its directory).

* **Topics**: every ``sensor_msgs/LaserScan`` topic of the bags, or those named with ``--topic``.
* **Robots**: one topic replays as ``--robot`` (default ``replay``); several topics each become their
  own robot, named after the topic (``/robot1/scan`` → ``robot1_scan``), so their FIFOs never mix.
* **Scans**: seq counts from 0 per robot in replay order; stamp_ns is the header stamp; frame_id is
  kept. With ``--loop`` each pass shifts the stamps by the bag's length, so they keep increasing and
  the encoder sees one continuous stream. LaserScans the bridge would refuse are counted by reason and
  skipped (the same rules as :mod:`services.ros2_bridge.laser_scan`).
* **Odometry**: each scan carries the robot's newest pose from ``nav_msgs/Odometry`` on ``/odom``, or,
  without it, from ``/tf`` (odom → base_link), when the bags hold either; ``--odom-topic`` names
  another topic (of either type), ``--odom-topic none`` replays without. Poses refused (NaN, stale)
  are counted under ``odometry`` in the stats (:mod:`services.ros2_bridge.odometry`).
* **Pace**: messages go out at their recorded (bag) times divided by ``--speed``.
* **As a service** (``python -m services.bag_replay``, which ``triscan up --replay`` starts instead of
  the simulator): it holds the health token ``triscan/@health/replay/<pid>`` while it plays and
  publishes its counters (``published``, ``passes``, ``robots``, ``rejected``) on
  ``triscan/@stats/replay/<pid>``, so ``triscan status`` and the launcher see it like any service. It
  announces each robot's scans (:func:`services.runtime.announce_source`), so the detector processes
  sharing a fleet each subscribe to their own robots'. It exits 0 at the end of a bag played without
  ``--loop``: a finished replay is not a crash.

rosbags is imported only when a bag is opened, so the launcher can import this module (for
:class:`ReplayConfig`) on an install without the ``ros2`` extra.
"""

from __future__ import annotations

import argparse
import logging
import re
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

from common.keys import SCAN, scan_key, validate_robot_id
from common.messages import Scan, encode_message
from common.transport import ZenohSettings, add_zenoh_arguments, settings_from_args
from services.ros2_bridge.laser_scan import ScanRejectedError, fields_of_message, to_triscan_scan
from services.ros2_bridge.odometry import (
    ODOMETRY,
    TF_MESSAGE,
    OdometryPairing,
    odometry_of_message,
    odometry_of_tf,
)
from services.runtime import (
    ServiceRuntime,
    announce_lead_s,
    announce_source,
    configure_logging,
    default_of,
    exit_code_of,
    exit_process,
    service_parser,
    stop_event_on_signals,
)

log = logging.getLogger(__name__)

SERVICE: Final[str] = "replay"  # its health token and stats name
DEFAULT_ROBOT: Final[str] = "replay"
DEFAULT_WAIT_S: Final[float] = 10.0
ODOM_AUTO: Final[str] = "auto"  # /odom (nav_msgs/Odometry) if the bags have it, else /tf, else none
ODOM_NONE: Final[str] = "none"
_ODOM_DEFAULTS: Final[tuple[tuple[str, str], ...]] = (("/odom", ODOMETRY), ("/tf", TF_MESSAGE))
_NOT_IN_ID: Final[re.Pattern[str]] = re.compile(r"[^A-Za-z0-9_-]+")


class ReplayError(ValueError):
    """A replay that cannot start (no scans in the bags, unknown topic, ambiguous robot)."""


@dataclass(frozen=True)
class ReplayConfig:
    bags: tuple[Path, ...]
    topics: tuple[str, ...] = ()  # empty: every LaserScan topic
    robot: str | None = None
    speed: float = 1.0
    loop: bool = False
    progress: bool = True
    odom_topic: str = ODOM_AUTO

    def __post_init__(self) -> None:
        if not self.bags:
            raise ReplayError("no bag given")
        if not self.speed > 0.0:
            raise ReplayError(f"speed must be > 0, got {self.speed}")


@dataclass
class ReplaySummary:
    published: int = 0
    passes: int = 0
    robots: dict[str, str] = field(default_factory=dict)  # topic → robot id
    rejected: Counter[str] = field(default_factory=Counter)
    odometry: OdometryPairing = field(default_factory=OdometryPairing)
    odom_topic: str | None = None


def robot_id_of_topic(topic: str) -> str:
    """``/robot1/scan`` → ``robot1_scan``: a robot id that names the topic it came from."""
    return validate_robot_id(_NOT_IN_ID.sub("_", topic.strip("/")).strip("_") or DEFAULT_ROBOT)


def robots_for(topics: Sequence[str], robot: str | None) -> dict[str, str]:
    if len(topics) == 1:
        return {topics[0]: validate_robot_id(robot or DEFAULT_ROBOT)}
    if robot is not None:
        raise ReplayError(
            f"--robot names one robot, the bags have {len(topics)} scan topics: pick one with --topic"
        )
    robots = {topic: robot_id_of_topic(topic) for topic in topics}
    if len(set(robots.values())) != len(robots):
        raise ReplayError(f"scan topics {sorted(topics)} map to the same robot id; pick one with --topic")
    return robots


BAG_ADVICE: Final[str] = "give ROS 1 .bag files, or one ROS 2 bag (its folder, with metadata.yaml)"


@contextmanager
def _open_reader(bags: Sequence[Path]) -> Iterator[Any]:
    """rosbags' reader of ``bags``, open; a path that is no bag is a ReplayError saying what is."""
    try:
        from rosbags.highlevel import AnyReader, AnyReaderError

        from services.ros2_bridge.ros_types import ros_types
    except ImportError as exc:
        raise ReplayError(f"replaying bags needs rosbags: pip install 'triscan[ros2]' ({exc})") from None
    missing = [str(bag) for bag in bags if not bag.exists()]
    if missing:
        raise FileNotFoundError(f"no such file or folder: {', '.join(missing)}: {BAG_ADVICE}")
    names = ", ".join(map(str, bags))
    try:
        reader = AnyReader(list(bags), default_typestore=ros_types("jazzy").store)
        reader.open()
    except (AnyReaderError, OSError) as exc:
        raise ReplayError(f"cannot read {names} as a bag ({exc}): {BAG_ADVICE}") from None
    try:
        yield reader
    finally:
        reader.close()


def scan_connections(reader: Any, topics: Sequence[str]) -> list[Any]:
    """The LaserScan connections of an open reader, restricted to ``topics`` if any are named."""
    from services.ros2_bridge.ros_types import LASER_SCAN

    scans = [c for c in reader.connections if c.msgtype == LASER_SCAN]
    if topics:
        known = {c.topic for c in scans}
        missing = [t for t in topics if t not in known]
        if missing:
            raise ReplayError(
                f"no LaserScan topic {missing} in the bags; they have {sorted(known) or 'none'}"
            )
        scans = [c for c in scans if c.topic in topics]
    if not scans:
        raise ReplayError("the bags hold no sensor_msgs/LaserScan topic")
    return scans


def odom_connection(reader: Any, odom_topic: str) -> Any | None:
    """The connection the poses come from (see :data:`ODOM_AUTO`), or None to replay without them."""
    if odom_topic == ODOM_NONE:
        return None
    usable = [c for c in reader.connections if c.msgtype in (ODOMETRY, TF_MESSAGE)]
    if odom_topic != ODOM_AUTO:
        named = [c for c in usable if c.topic == odom_topic]
        if not named:
            raise ReplayError(
                f"no nav_msgs/Odometry or tf2_msgs/TFMessage topic {odom_topic!r} in the bags; they have "
                f"{sorted({c.topic for c in usable}) or 'none'}"
            )
        return named[0]
    for topic, msgtype in _ODOM_DEFAULTS:
        for connection in usable:
            if connection.topic == topic and connection.msgtype == msgtype:
                return connection
    return None


def replay(
    config: ReplayConfig,
    publish: Callable[[str, bytes], None],
    *,
    stop: threading.Event | None = None,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], object] = time.sleep,
    summary: ReplaySummary | None = None,
) -> ReplaySummary:
    """Publish the bags' scans through ``publish(key, payload)`` at recorded pace; returns what it did.

    ``summary``, if given, is filled in as the replay goes (for a caller that reports progress).
    """
    summary = ReplaySummary() if summary is None else summary
    stop = stop or threading.Event()
    with _open_reader(config.bags) as reader:
        connections = scan_connections(reader, config.topics)
        summary.robots = robots_for(sorted({c.topic for c in connections}), config.robot)
        odom = odom_connection(reader, config.odom_topic)
        if odom is not None:
            summary.odom_topic = odom.topic
            connections = [*connections, odom]
            log.info("odometry from %s (%s)", odom.topic, odom.msgtype)
        next_seq = dict.fromkeys(summary.robots.values(), 0)
        span_ns = reader.end_time - reader.start_time + 1
        total = sum(c.msgcount for c in connections if c.topic != summary.odom_topic)
        bar = _progress(None if config.loop else total, config.progress)
        try:
            while not stop.is_set():
                for scan in _one_pass(reader, connections, summary, next_seq, config, clock, sleep, stop,
                                      stamp_offset_ns=summary.passes * span_ns):  # fmt: skip
                    publish(scan_key(scan.robot_id), encode_message(scan))
                    summary.published += 1
                    bar.update(1)
                summary.passes += 1
                if not config.loop:
                    break
        finally:
            bar.close()
    if summary.rejected:
        log.warning("skipped LaserScans by reason: %s", dict(summary.rejected))
    return summary


def _one_pass(
    reader: Any,
    connections: list[Any],
    summary: ReplaySummary,
    next_seq: dict[str, int],
    config: ReplayConfig,
    clock: Callable[[], float],
    sleep: Callable[[float], object],
    stop: threading.Event,
    *,
    stamp_offset_ns: int,
) -> Iterator[Scan]:
    started = clock()
    first_ns: int | None = None
    for connection, log_time_ns, raw in reader.messages(connections=connections):
        if stop.is_set():
            return
        first_ns = log_time_ns if first_ns is None else first_ns
        delay = started + (log_time_ns - first_ns) / 1e9 / config.speed - clock()
        if delay > 0:
            sleep(delay)
        if connection.topic == summary.odom_topic:
            _update_odometry(summary.odometry, reader.deserialize(raw, connection.msgtype), stamp_offset_ns)
            continue
        robot_id = summary.robots[connection.topic]
        try:
            scan = to_triscan_scan(fields_of_message(reader.deserialize(raw, connection.msgtype)), robot_id,
                                   next_seq[robot_id])  # fmt: skip
        except ScanRejectedError as exc:
            summary.rejected[exc.reason] += 1
            log.debug("%s at %d: %s", connection.topic, log_time_ns, exc)
            continue
        if stamp_offset_ns:
            scan = scan.model_copy(update={"stamp_ns": scan.stamp_ns + stamp_offset_ns})
        next_seq[robot_id] += 1
        yield summary.odometry.attach(scan)


def _update_odometry(pairing: OdometryPairing, message: Any, stamp_offset_ns: int) -> None:
    pose = odometry_of_tf(message) if hasattr(message, "transforms") else odometry_of_message(message)
    if pose is None:  # a /tf message about other frames
        return
    if stamp_offset_ns:
        pose = pose.model_copy(update={"stamp_ns": pose.stamp_ns + stamp_offset_ns})
    pairing.update(pose)


class _NoBar:
    def update(self, n: int) -> None:
        pass

    def close(self) -> None:
        pass


def _progress(total: int | None, enabled: bool) -> Any:
    if not enabled:
        return _NoBar()
    from tqdm import tqdm

    return tqdm(total=total, unit="scan", desc="replay")


def replay_robots(config: ReplayConfig) -> dict[str, str]:
    """Open the bags and map each replayed topic to its robot id; ReplayError if the replay cannot start.

    ``triscan up --replay`` calls this before starting anything, so a wrong bag or topic is an error
    message, not a service that dies on start.
    """
    with _open_reader(config.bags) as reader:
        topics = sorted({c.topic for c in scan_connections(reader, config.topics)})
    return robots_for(topics, config.robot)


def run_replay(
    settings: ZenohSettings,
    config: ReplayConfig,
    *,
    wait_s: float = DEFAULT_WAIT_S,
    stop: threading.Event | None = None,
) -> ReplaySummary:
    """Replay as a service: wait up to ``wait_s`` for a subscriber of the first robot, then play.

    Runs in a :class:`ServiceRuntime` (health token, counters on ``triscan/@stats/replay/<pid>``);
    puts block rather than drop under congestion, so a bag replays whole or not at all.
    """
    import zenoh

    from common.transport import wait_for_subscriber

    robots = replay_robots(config)
    stop = stop or threading.Event()
    summary = ReplaySummary()
    with ServiceRuntime(SERVICE, settings, stop) as runtime:
        runtime.ready()  # it subscribes to nothing: up as soon as its session is
        for robot_id in robots.values():  # each detector process subscribes to the robots it serves
            runtime.keep(announce_source(runtime.session, robot_id, SCAN))
        try:
            wait_for_subscriber(runtime.session, scan_key(next(iter(robots.values()))), wait_s)
        except TimeoutError as exc:
            log.warning("%s: replaying anyway", exc)
        stop.wait(announce_lead_s(SCAN))  # the robots' owners take their scans from here on
        publishers: dict[str, Any] = {}

        def publish(key: str, payload: bytes) -> None:
            publisher = publishers.get(key)
            if publisher is None:
                publisher = publishers[key] = runtime.keep(
                    runtime.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
                )
            publisher.put(payload)
            runtime.publish_stats(summary_counters(summary))

        replay(config, publish, stop=stop, sleep=stop.wait, summary=summary)
        runtime.publish_stats(summary_counters(summary), force=True)
    return summary


def summary_counters(summary: ReplaySummary) -> dict[str, object]:
    """The replay's stats (``published`` is updated once a message has been put)."""
    return {
        "published": summary.published,
        "passes": summary.passes,
        "robots": len(summary.robots),
        "rejected": dict(summary.rejected),
        "odometry": summary.odometry.counters(),
    }


def add_replay_arguments(parser: argparse.ArgumentParser) -> None:
    """The replay's flags, shared by ``triscan replay`` and ``python -m services.bag_replay``."""
    parser.add_argument(
        "bags", nargs="+", type=Path, metavar="BAG", help="ROS 1 .bag files, or one ROS 2 bag"
    )
    parser.add_argument(
        "--topic", action="append", default=[], help="LaserScan topic to replay (default: all)"
    )
    parser.add_argument(
        "--robot", default=None, help=f"robot id of a single replayed topic (default: {DEFAULT_ROBOT})"
    )
    parser.add_argument(
        "--speed",
        type=float,
        default=default_of(ReplayConfig, "speed"),
        help="playback speed relative to the recording",
    )
    parser.add_argument("--loop", action="store_true", help="start over at the end, until stopped")
    parser.add_argument(
        "--odom-topic",
        default=ODOM_AUTO,
        help="nav_msgs/Odometry or tf2_msgs/TFMessage topic of the robot's pose "
        f"(default {ODOM_AUTO}: /odom, else /tf; {ODOM_NONE}: no odometry)",
    )
    parser.add_argument(
        "--wait", type=float, default=DEFAULT_WAIT_S, help="seconds to wait for a subscriber first"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_zenoh_arguments(parser)


def config_from_args(args: argparse.Namespace) -> ReplayConfig:
    return ReplayConfig(
        bags=tuple(args.bags),
        topics=tuple(args.topic),
        robot=args.robot,
        speed=args.speed,
        loop=args.loop,
        progress=not args.no_progress,
        odom_topic=args.odom_topic,
    )


def main(argv: list[str] | None = None) -> int:
    """``python -m services.bag_replay``: 0 at the end of the bag, 2 if the replay cannot start."""
    parser = service_parser("services.bag_replay", __doc__.splitlines()[0])
    add_replay_arguments(parser)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    args = parser.parse_args(argv)
    configure_logging(args.verbose)
    try:
        summary = run_replay(
            settings_from_args(args), config_from_args(args), wait_s=args.wait, stop=stop_event_on_signals()
        )
    except ReplayError as exc:
        log.error("%s", exc)
        return 2
    log.info(
        "published %d scans in %d pass(es) as %s; skipped %s",
        summary.published,
        summary.passes,
        ", ".join(sorted(summary.robots.values())),
        dict(summary.rejected) or "none",
    )
    return 0


if __name__ == "__main__":
    exit_process(exit_code_of(main))
