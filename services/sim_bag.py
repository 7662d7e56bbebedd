"""A ROS 2 bag of real simulated LiDAR scans (``triscan sim-bag``): data for ``triscan replay``,
``triscan up --replay`` and benchmarks. Needs the sim and ros2 extras.

No robot recording ships with triscan, and a bag of made-up ranges would show the detector nothing. This
writes what a ROS 2 robot with an LDS-01 would have recorded while driving through one of the
simulator's rooms: one ``sensor_msgs/msg/LaserScan`` topic (default ``/scan``), the simulator's scans
at its rate, header stamps and log times counted from ``T0_NS``, written by rosbags' own MCAP writer
(not by triscan's reader code, so a replay test checks one against the other).

    triscan sim-bag --scans 150 --out runs/sim_drive      # prints the .mcap file it wrote
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Final

import msgpack

from common.messages import Scan, decode_message, encode_message
from services.simulator.defaults import SCAN_RATE_HZ, SIM_SEED

T0_NS: Final[int] = 1_700_000_000_000_000_000  # a plausible wall-clock start (2023-11-14)
DEFAULT_TOPIC: Final[str] = "/scan"
RECORDED_SCANS_ENV: Final[str] = "TRISCAN_RECORDED_SCANS"  # a folder of recorded scans (no PyBullet needed)


def recorded_scans(count: int, seed: int = SIM_SEED, rate_hz: float = SCAN_RATE_HZ) -> list[Scan]:
    """``count`` consecutive scans of one simulated robot, stamped at its tick times from 0.

    For bags, benchmarks and replays that need real scans up front, so their timed loops simulate nothing.
    With ``$TRISCAN_RECORDED_SCANS`` naming a folder (every caller: the benches, ``triscan sim-bag``),
    the scans are read from the file there for these arguments and this simulator's code when it exists,
    and written there when they are simulated: a fleet server without PyBullet (it has the base
    dependencies only) runs the benches on scans recorded on another machine of the same checkout.
    """
    folder = os.environ.get(RECORDED_SCANS_ENV)
    cached = None
    if folder:  # the digest reads the simulator's source: only when a recording may be reused
        cached = Path(folder) / f"scans_seed{seed}_n{count}_{rate_hz:g}hz_sim{_simulator_digest()}.msgpack"
    if cached is not None and cached.is_file():
        return [decode_message(payload, Scan) for payload in msgpack.unpackb(cached.read_bytes())]
    from services.simulator.fleet import SimulatedFleet  # PyBullet: only when scans are recorded

    period_ns = round(1e9 / rate_hz)
    with SimulatedFleet(1, seed=seed, rate_hz=rate_hz) as fleet:
        scans = [fleet.step(tick * period_ns)[0][0] for tick in range(count)]
    if cached is not None:
        cached.parent.mkdir(parents=True, exist_ok=True)
        partial = cached.with_suffix(f".{os.getpid()}.part")  # a reader never sees half a file
        partial.write_bytes(msgpack.packb([encode_message(scan) for scan in scans], use_bin_type=True))
        os.replace(partial, cached)
    return scans


def _simulator_digest() -> str:
    """A short digest of the simulator's source: scans recorded by other simulator code are not reused."""
    digest = hashlib.blake2b(digest_size=4)
    for source in sorted((Path(__file__).parent / "simulator").glob("*.py")):
        digest.update(source.read_bytes())
    return digest.hexdigest()


def laser_scan_message(scan: Scan, stamp_ns: int) -> Any:
    """The rosbags (Jazzy) LaserScan a ROS driver would publish for ``scan``, stamped ``stamp_ns``."""
    from services.ros2_bridge.ros_types import LASER_SCAN, ros_types  # rosbags: the ros2 extra

    types = ros_types("jazzy").store.types
    beams = scan.ranges.shape[0]
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    return types[LASER_SCAN](
        header=types["std_msgs/msg/Header"](
            stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=scan.frame_id
        ),
        angle_min=scan.angle_min, angle_max=scan.angle_min + scan.angle_increment * max(beams - 1, 0),
        angle_increment=scan.angle_increment, time_increment=0.0, scan_time=0.0, range_min=scan.range_min,
        range_max=scan.range_max, ranges=scan.ranges.astype("<f4"), intensities=scan.ranges[:0].astype("<f4"),
    )  # fmt: skip


def write_scan_bag(directory: Path, scans: Sequence[Scan], *, topic: str = DEFAULT_TOPIC) -> Path:
    """Write ``scans`` (stamped from 0, as :func:`recorded_scans` makes them) as a ROS 2
    MCAP bag in ``directory`` (which must not exist); returns the ``.mcap`` file."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from services.ros2_bridge.ros_types import LASER_SCAN, ros_types

    store = ros_types("jazzy").store
    with Writer(directory, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        connection = writer.add_connection(topic, LASER_SCAN, typestore=store)
        for scan in scans:
            stamp_ns = T0_NS + scan.stamp_ns
            message = laser_scan_message(scan, stamp_ns)
            writer.write(connection, stamp_ns, bytes(store.serialize_cdr(message, LASER_SCAN)))
    (mcap,) = directory.glob("*.mcap")
    return mcap


def write_sim_bag(
    directory: Path,
    scans: int,
    *,
    seed: int = SIM_SEED,
    rate_hz: float = SCAN_RATE_HZ,
    topic: str = DEFAULT_TOPIC,
) -> Path:
    """Simulate ``scans`` consecutive scans of one robot and write them as a bag; returns the ``.mcap``."""
    return write_scan_bag(directory, recorded_scans(scans, seed=seed, rate_hz=rate_hz), topic=topic)
