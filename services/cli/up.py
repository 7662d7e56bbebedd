"""``triscan up``: simulator (or bag replay), encoder, detector and visualizer as separate processes.

Its children need the sim and viz extras; the defaults of the simulator and replay flags are those of
:class:`services.launcher.UpConfig` and :class:`services.bag_replay.ReplayConfig`.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
from typing import Any

from common.moving_people import add_motion_argument
from common.transport import add_zenoh_arguments
from services.cli.command import Command
from services.runtime import default_of
from services.simulator.sensors import PROFILES
from services.tracker import add_tracker_arguments, rules_of

SIMULATOR_ONLY_FLAGS = {
    "robots": "--robots",
    "rate_hz": "--rate",
    "seed": "--seed",
    "people": "--people",
    "sensor": "--sensor",
}
REPLAY_ONLY_FLAGS = {
    "topic": "--topic",
    "robot": "--robot",
    "speed": "--speed",
    "loop": "--loop",
    "odom_topic": "--odom-topic",
}


def add_arguments(p: argparse.ArgumentParser) -> None:
    from services.bag_replay import ReplayConfig
    from services.launcher import UpConfig

    def up(name: str) -> Any:
        return default_of(UpConfig, name)

    # None: the default of UpConfig (simulator flags) or ReplayConfig (replay flags), so that a flag of
    # the other source can be refused rather than silently ignored.
    p.add_argument("--robots", type=int, default=None, help=f"simulated robots (default {up('robots')})")
    p.add_argument(
        "--rate", dest="rate_hz", type=float, default=None,
        help="scans per second per robot (default: the sensor's)",
    )  # fmt: skip
    p.add_argument(
        "--sensor", default=None, choices=list(PROFILES), metavar="NAME",
        help=f"the simulated LiDAR (default {up('sensor')}): one of {', '.join(PROFILES)}",
    )  # fmt: skip
    p.add_argument(
        "--people", type=int, default=None, metavar="N",
        help=f"people walking about each simulated room (default {up('people')}; 0: furniture only)",
    )  # fmt: skip
    p.add_argument(
        "--duration", type=float, default=up("duration_s"), help="stop after this many seconds (0: Ctrl-C)"
    )
    p.add_argument("--headless", action="store_true", help="no viewer: record an .rrd instead")
    p.add_argument(
        "--rrd", type=Path, default=None, help="--headless recording (default: runs/triscan-<time>.rrd)"
    )
    p.add_argument(
        "--viewer", choices=("spawn", "web", "none"), default=up("viewer"), help="viewer when not --headless"
    )
    p.add_argument("--model", type=Path, default=None, help="ONNX model (default: the shipped one)")
    p.add_argument(
        "--snapshot", type=Path, default=None, metavar="DIR",
        help="every few seconds, write each robot's newest frame as PNGs (raster with boxes, top-down map)",
    )  # fmt: skip
    p.add_argument(
        "--batch",
        type=int,
        default=None,
        help="detector: most robots per model call (default: it picks, 4 with the shipped -batch model)",
    )
    p.add_argument(
        "--detectors",
        type=int,
        default=None,
        help="detector processes sharing the robots (default: one per core)",
    )
    add_motion_argument(p)
    add_tracker_arguments(p)
    p.add_argument(
        "--seed", type=int, default=None, help=f"simulator seed (default {up('seed')}; training used 0)"
    )
    p.add_argument(
        "--max-restarts",
        type=int,
        default=up("max_restarts"),
        help="restarts of one service per minute before giving up",
    )
    replay = p.add_argument_group("replay (instead of the simulator; the run ends when the bag does)")
    replay.add_argument(
        "--replay",
        nargs="+",
        type=Path,
        default=None,
        metavar="BAG",
        help="ROS 1 .bag files or one ROS 2 bag",
    )
    replay.add_argument("--topic", action="append", default=None, help="LaserScan topic (default: all)")
    replay.add_argument("--robot", default=None, help="robot id of a single replayed topic (default: replay)")
    replay.add_argument(
        "--speed",
        type=float,
        default=None,
        help=f"playback speed (default {default_of(ReplayConfig, 'speed'):g})",
    )
    replay.add_argument("--loop", action="store_true", default=None, help="replay until stopped")
    replay.add_argument(
        "--odom-topic",
        default=None,
        help="Odometry or /tf topic of the robot's pose (default: /odom, else /tf; none: no odometry)",
    )
    add_zenoh_arguments(p)


def _given(args: argparse.Namespace, flags: dict[str, str]) -> dict[str, object]:
    """The flags of ``flags`` (attribute → flag) given on the command line, by attribute."""
    return {name: getattr(args, name) for name in flags if getattr(args, name) is not None}


def run(args: argparse.Namespace) -> int:
    from common.transport import settings_from_args
    from services.bag_replay import ReplayConfig
    from services.launcher import DEFAULT_LISTEN, UpConfig, up
    from services.runtime import stop_event_on_signals

    settings = settings_from_args(args)
    if not settings.listen and settings.config_file is None:
        settings = replace(settings, mode=settings.mode or "peer", listen=(DEFAULT_LISTEN,))
    simulator_flags, replay_flags = _given(args, SIMULATOR_ONLY_FLAGS), _given(args, REPLAY_ONLY_FLAGS)
    replay = None
    if args.replay is not None:
        if simulator_flags:
            raise ValueError(f"{', '.join(SIMULATOR_ONLY_FLAGS[k] for k in simulator_flags)}: simulator only")
        topics: list[str] = replay_flags.pop("topic", [])  # type: ignore[assignment]
        replay_flags["topics"] = tuple(topics)
        replay = ReplayConfig(bags=tuple(args.replay), progress=False, **replay_flags)  # type: ignore[arg-type]
    elif replay_flags:
        raise ValueError(f"{', '.join(REPLAY_ONLY_FLAGS[k] for k in replay_flags)}: needs --replay")
    config = UpConfig(
        duration_s=args.duration,
        headless=args.headless,
        rrd_path=args.rrd,
        viewer=args.viewer,
        model=args.model,
        batch=args.batch,
        detectors=args.detectors,
        motion_confirm=args.motion_confirm,
        max_restarts=args.max_restarts,
        settings=settings,
        verbose=args.verbose,
        replay=replay,
        snapshot_dir=args.snapshot,
        **simulator_flags,  # type: ignore[arg-type]
        **rules_of(args),  # type: ignore[arg-type]  # UpConfig names its tracker rules by their fields
    )
    return up(config, stop_event_on_signals())


COMMAND = Command(
    "up",
    "the full simulation loop: simulator, encoder, detector, tracker, visualizer as five processes",
    add_arguments,
    run,
    extras=("sim", "viz"),
)
