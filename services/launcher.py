"""``triscan up``: the whole simulation loop as five separate processes on this machine.

simulator → encoder → detector → tracker → visualizer, each its own Python process talking Zenoh peer to peer
over loopback: every child listens on its own 127.0.0.1 port and is given every other child's port
(and the launcher's) as explicit ``--connect`` endpoints, with multicast scouting off, so nothing
depends on the local network or an external router. The launcher is one more peer: it watches the
children's liveliness tokens (``triscan/@health/<service>/<pid>``), restarts a child that dies (with a
clear log line and a cap on restarts), and stops them all on Ctrl-C or after ``--duration``. Its own
session takes the user's Zenoh flags, so other apps (``examples/subscribe_detections.py``, ROS 2
bridges) join through it. Every ``SUMMARY_PERIOD_S`` and at the end it logs what the loop found, per
robot and class, against the simulator's truth (:mod:`services.run_summary`); the services' own
periodic counters then go to the debug log (``--verbose``), their final ones stay.

With ``--replay BAG...`` the scans come from recorded bags (``python -m services.bag_replay``) instead
of the simulator. A bag is finite, so the replay is started last, once the encoder, detector and
visualizer hold their health tokens (no scan of a short bag is lost to a detector still loading its
model), and it is never restarted: it would play the bag again from its first, older stamps, which the
encoder refuses as reordered. When the replay exits 0 (the bag played through, no ``--loop``) the run
ends: the launcher waits until no detections have arrived for ``DRAIN_QUIET_S`` (so the last scans'
detections reach the recording), stops the services and returns 0. A replay that exits otherwise
ends the run with 1.
"""

from __future__ import annotations

import logging
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from common.inference import OnnxDetector, model_class_names, model_facts
from common.keys import (
    ALL_DETECTIONS,
    ALL_HEALTH,
    ALL_TENSORS,
    ALL_TRUTH,
    DETECTIONS,
    SCAN,
    parse_health_key,
    parse_key,
    wildcard_key,
)
from common.messages import Detections, GroundTruth, Message, MessageError, StackedTensor, decode_message
from common.model_spec import default_model_path
from common.transport import ZenohSettings, open_session, payload_bytes
from services.bag_replay import SERVICE as REPLAY
from services.bag_replay import ReplayConfig, replay_robots
from services.detector.batch_cap import detector_model_and_batch
from services.run_summary import RunSummary
from services.runtime import (
    EXIT_WITH_PARENT_ENV,
    PERIODIC_SUMMARY_ENV,
    SUMMARY_PERIOD_S,
    USAGE_EXIT,
    default_of,
)
from services.simulator.defaults import ROBOTS, SIM_PEOPLE, SIM_SEED
from services.simulator.sensors import DEFAULT_PROFILE, check_sensor
from services.tracker import RULE_FLAGS, given_rules, rule_flags

log = logging.getLogger(__name__)

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"  # where other apps on this machine join the loop
SERVICES = ("simulator", "encoder", "detector", "tracker", "visualizer")
MODULES = {REPLAY: "services.bag_replay"}  # a child's module, where it is not services.<name>
STOP_GRACE_S = 5.0
READY_TIMEOUT_S = 60.0
RESTART_WINDOW_S = 60.0
DRAIN_QUIET_S = 1.0  # after a replay ends: stop once no detections arrived for this long
DRAIN_MAX_S = 10.0
REPLAY_WAIT_S = 30.0  # the replay's --wait for the encoder's subscription (it starts when all are up)


@dataclass(frozen=True)
class UpConfig:
    """Everything ``triscan up`` starts; ``service_args`` are extra flags per service."""

    robots: int = ROBOTS
    rate_hz: float | None = None  # None: the sensor's own rate
    sensor: str = DEFAULT_PROFILE
    people: int = SIM_PEOPLE
    duration_s: float = 0.0  # 0: until Ctrl-C
    headless: bool = False
    rrd_path: Path | None = None  # headless recording (default: runs/triscan-<time>.rrd)
    viewer: str = "spawn"  # spawn | web | none, when not headless
    model: Path | None = None
    # The detector's --batch (None: it times its own cap, services.detector.batch_cap.timed_batch_cap).
    batch: int | None = None
    # The detector's --detectors (None: one process per core, services.detector.core.default_processes).
    detectors: int | None = None
    motion_confirm: bool = True  # the detector's motion confirmation (--no-motion-confirm: off)
    # The tracker rules of services.tracker.RULE_FLAGS, by their TrackerConfig field names (None: the
    # tracker's defaults, services.tracker.core).
    person_confirm_travel_m: float | None = None
    person_confirm_hits: int | None = None
    person_coast_penalty_m: float | None = None
    person_resume_s: float | None = None
    person_show_coast_s: float | None = None
    person_show_coast_share: float | None = None
    seed: int = SIM_SEED
    max_restarts: int = 5  # per service within RESTART_WINDOW_S, then the launcher gives up
    settings: ZenohSettings = field(default_factory=lambda: ZenohSettings(listen=(DEFAULT_LISTEN,)))
    verbose: bool = False
    replay: ReplayConfig | None = None  # bags replayed instead of the simulator
    snapshot_dir: Path | None = None  # the newest frame's pictures, redrawn every few seconds

    def __post_init__(self) -> None:
        """Refuse what a child would refuse, before any process starts (a child that exits on its
        arguments is not restarted, but the others would already be running)."""
        if self.robots < 1:
            raise ValueError(f"--robots must be >= 1, got {self.robots}")
        if self.rate_hz is not None and not (self.rate_hz > 0.0 and math.isfinite(self.rate_hz)):
            raise ValueError(f"--rate must be a positive number of scans per second, got {self.rate_hz:g}")
        if self.people < 0:
            raise ValueError(f"--people must be >= 0, got {self.people}")
        check_sensor(self.sensor)
        if not (self.duration_s >= 0.0 and math.isfinite(self.duration_s)):
            raise ValueError(f"--duration must be >= 0 seconds (0: until Ctrl-C), got {self.duration_s:g}")
        if self.max_restarts < 0:
            raise ValueError(f"--max-restarts must be >= 0, got {self.max_restarts}")
        if self.batch is not None and self.batch < 1:
            raise ValueError(f"--batch must be >= 1, got {self.batch}")
        if self.tracker_rules:
            from services.tracker.core import TrackerConfig

            TrackerConfig(**self.tracker_rules)  # type: ignore[arg-type]  # its ValueError names the rule
        if self.snapshot_dir is not None and self.replay is not None:
            raise ValueError("--snapshot draws the simulator's worlds and truth: it cannot go with --replay")

    @property
    def tracker_rules(self) -> dict[str, float]:
        """The tracker rules given (:func:`services.tracker.given_rules`)."""
        return given_rules(**{field: getattr(self, field) for field in RULE_FLAGS})

    @property
    def services(self) -> tuple[str, ...]:
        """The children, scan source first: the simulator, or the replay of ``replay``'s bags."""
        source = "simulator" if self.replay is None else REPLAY
        return (source, *SERVICES[1:])


def free_tcp_ports(count: int) -> list[int]:
    """Distinct ports free on 127.0.0.1 right now (held open together so none is handed out twice)."""
    sockets = []
    try:
        for _ in range(count):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind(("127.0.0.1", 0))
            sockets.append(s)
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


def stop_processes(processes: Mapping[str, subprocess.Popen[bytes]], grace_s: float) -> None:
    """SIGTERM every process, then wait for all of them together; kill those still alive after ``grace_s``.

    Signalling all first lets them shut down in parallel (each closes its Zenoh session), so the whole
    stop takes one grace period, not one per process.
    """
    for process in processes.values():
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + grace_s
    for name, process in processes.items():
        try:
            process.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            log.warning("%s (pid %d) did not stop in %.0f s: killing it", name, process.pid, grace_s)
            process.kill()
            process.wait()


def _endpoint_port(endpoint: str) -> int | None:
    host_port = endpoint.split("/", 1)[-1]
    try:
        return int(host_port.rsplit(":", 1)[1].split("#", 1)[0])
    except (IndexError, ValueError):
        return None


def service_commands(
    config: UpConfig, ports: dict[str, int], launcher_port: int | None
) -> dict[str, list[str]]:
    """The command line of each child: its service flags plus its loopback Zenoh wiring."""
    python = [sys.executable, "-m"]
    verbose = ["--verbose"] if config.verbose else []
    if config.headless:
        rrd = config.rrd_path or Path("runs") / f"triscan-{time.strftime('%Y%m%d-%H%M%S')}.rrd"
        sink = ["--save", str(rrd)]
    elif config.viewer == "web":
        sink = ["--serve-web"]
    elif config.viewer == "spawn":
        sink = ["--spawn"]
    else:
        sink = []
    model, _ = detector_model_and_batch(config.model, config.batch)  # a batch it cannot run fails here
    facts = model_facts(model)  # the encoder must match the model
    padding = facts.padding
    service_args = {
        REPLAY: [] if config.replay is None else replay_arguments(config.replay),
        "simulator": [
            *("--robots", str(config.robots), "--seed", str(config.seed)),
            *("--sensor", config.sensor, "--people", str(config.people)),
            *(("--rate", str(config.rate_hz)) if config.rate_hz is not None else ()),
            *("--padding", padding),
            *(("--raster-yaw", repr(facts.raster_yaw_deg)) if facts.raster_yaw_deg else ()),
        ],
        "encoder": facts.encoder_flags(),
        "detector": [
            *(("--model", str(config.model)) if config.model else ()),
            *(("--batch", str(config.batch)) if config.batch is not None else ()),
            *(("--detectors", str(config.detectors)) if config.detectors is not None else ()),
            *(() if config.motion_confirm else ("--no-motion-confirm",)),
        ],
        "tracker": rule_flags(config.tracker_rules),
        "visualizer": sink,
    }
    commands = {}
    for name in config.services:
        if name == "visualizer" and not sink:
            continue
        others = [port for other, port in ports.items() if other != name]
        if launcher_port is not None:
            others.append(launcher_port)
        zenoh = ZenohSettings(
            mode="peer",
            listen=(f"tcp/127.0.0.1:{ports[name]}",),
            connect=tuple(f"tcp/127.0.0.1:{port}" for port in others),
            multicast_scouting=False,
            config_file=config.settings.config_file,
        )
        module = MODULES.get(name, f"services.{name}")
        commands[name] = [*python, module, *service_args[name], *verbose, *zenoh.to_cli()]
    return commands


def replay_arguments(replay: ReplayConfig) -> list[str]:
    """``python -m services.bag_replay``'s flags for ``replay`` (no progress bar: the launcher logs)."""
    args = [
        *map(str, replay.bags),
        "--speed",
        str(replay.speed),
        "--wait",
        str(REPLAY_WAIT_S),
        "--no-progress",
    ]
    for topic in replay.topics:
        args += ["--topic", topic]
    if replay.robot is not None:
        args += ["--robot", replay.robot]
    if replay.loop:
        args.append("--loop")
    if replay.odom_topic != default_of(ReplayConfig, "odom_topic"):
        args += ["--odom-topic", replay.odom_topic]
    return args


@dataclass
class _Child:
    name: str
    command: list[str]
    process: subprocess.Popen[bytes] | None = None
    restarts: deque[float] = field(default_factory=deque)

    def start(self) -> None:
        # Own process group: a terminal's Ctrl-C reaches the launcher only, which then stops the
        # children in order instead of all of them racing each other down.
        self.process = subprocess.Popen(self.command, start_new_session=True, env=child_environment())
        log.info("started %s (pid %d)", self.name, self.process.pid)

    def exit_code(self) -> int | None:
        return None if self.process is None else self.process.poll()


class HealthBoard:
    """Which services currently hold a liveliness token, fed by a Zenoh liveliness subscriber."""

    def __init__(self) -> None:
        self._alive: dict[str, set[str]] = {}
        self._lock = threading.Lock()

    def on_sample(self, sample: Any) -> None:
        try:
            service, instance = parse_health_key(str(sample.key_expr))
        except ValueError:
            return
        import zenoh

        with self._lock:
            instances = self._alive.setdefault(service, set())
            if sample.kind == zenoh.SampleKind.PUT:
                instances.add(instance)
            else:
                instances.discard(instance)

    def alive(self) -> set[str]:
        with self._lock:
            return {service for service, instances in self._alive.items() if instances}


class TrafficCounter:
    """Messages seen per topic, so the launcher can say what the loop did when it stops."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}
        self.robots: set[str] = set()
        self._lock = threading.Lock()

    def counter(self, topic: str) -> Any:
        def count(sample: Any) -> None:
            robot = parse_key(str(sample.key_expr))[0]
            with self._lock:
                self.counts[topic] = self.counts.get(topic, 0) + 1
                self.robots.add(robot)

        return count

    def count_of(self, topic: str) -> int:
        with self._lock:
            return self.counts.get(topic, 0)

    def summary(self) -> str:
        with self._lock:
            parts = [f"{count} {topic} messages" for topic, count in sorted(self.counts.items())]
            return f"seen: {', '.join(parts) or 'no messages'} from {len(self.robots)} robot(s)"


def up(config: UpConfig, stop: threading.Event) -> int:
    """Start, watch and stop the services; 0 on a clean stop (or a replay played through), 1 if a
    service kept dying, never came up, or the replay failed."""
    if config.detectors is not None and config.detectors < 1:
        raise ValueError(f"--detectors must be >= 1, got {config.detectors}")
    if config.replay is not None:
        robots = replay_robots(config.replay)  # a wrong bag or topic fails here, before anything starts
        log.info("replaying %s", ", ".join(f"{topic} as {robot}" for topic, robot in robots.items()))
    model, _ = detector_model_and_batch(config.model, config.batch)
    OnnxDetector(model, intra_op_threads=1)  # loaded as the detector will: a file it refuses fails here
    launcher_ports = [p for p in (_endpoint_port(e) for e in config.settings.listen) if p is not None]
    ports = dict(zip(config.services, free_tcp_ports(len(config.services)), strict=True))
    commands = service_commands(config, ports, launcher_ports[0] if launcher_ports else None)
    children = {name: _Child(name, command) for name, command in commands.items()}
    replay_child = children.get(REPLAY)
    restartable = {name: child for name, child in children.items() if child is not replay_child}
    health = HealthBoard()
    traffic = TrafficCounter()
    summary = RunSummary(model_class_names(config.model or default_model_path()))
    feeds: dict[str, tuple[type[Message], list[Callable[[Any], None]]]] = {
        ALL_TRUTH: (GroundTruth, [summary.update]),
        ALL_DETECTIONS: (Detections, [summary.update]),
    }
    snapshots = None
    if config.snapshot_dir is not None:
        from training.snapshots import SNAPSHOT_PERIOD_S, LiveFrames  # the sim extra, which up needs

        snapshots = LiveFrames(config.seed)
        log.info(
            "every %.0f s: each robot's newest frame as PNGs in %s", SNAPSHOT_PERIOD_S, config.snapshot_dir
        )
        feeds[ALL_TENSORS] = (StackedTensor, [])
        for _, consumers in feeds.values():
            consumers.append(snapshots.update)
    exit_code = 0
    with open_session(config.settings) as session:
        watcher = session.liveliness().declare_subscriber(ALL_HEALTH, health.on_sample, history=True)
        counters = [
            session.declare_subscriber(wildcard_key(topic), traffic.counter(topic))
            for topic in (SCAN, DETECTIONS)
        ]
        counters += [
            session.declare_subscriber(key, message_feeder(kind, consumers))
            for key, (kind, consumers) in feeds.items()
        ]
        for child in restartable.values():
            child.start()
        started = last_table = last_snapshot = time.monotonic()
        ready = False
        try:
            while not stop.wait(0.2):
                now = time.monotonic()
                if now - last_table >= SUMMARY_PERIOD_S:
                    log.info("%s", summary.table(now - started))
                    last_table = now
                if snapshots is not None and now - last_snapshot >= SNAPSHOT_PERIOD_S:
                    _write_snapshots(snapshots, config.snapshot_dir)
                    last_snapshot = now
                if not ready:
                    missing = set(children) - health.alive()
                    if replay_child is not None and replay_child.process is None and missing == {REPLAY}:
                        replay_child.start()  # the others are up: the bag's first scans are not lost
                    if not missing:
                        ready = True
                        log.info("all services up after %.1f s: %s", now - started, ", ".join(children))
                    elif now - started > READY_TIMEOUT_S:
                        log.error(
                            "services not up after %.0f s: %s", READY_TIMEOUT_S, ", ".join(sorted(missing))
                        )
                        exit_code = 1
                        break
                replay_code = None if replay_child is None else replay_child.exit_code()
                if replay_code is not None:
                    exit_code = _end_of_replay(replay_code, traffic)
                    break
                if not _restart_dead(restartable, config.max_restarts):
                    exit_code = 1
                    break
                if config.duration_s and now - started >= config.duration_s:
                    log.info("duration %.0f s reached: stopping", config.duration_s)
                    break
        finally:
            stop_processes({n: c.process for n, c in children.items() if c.process is not None}, STOP_GRACE_S)
            watcher.undeclare()
            for counter in counters:
                counter.undeclare()
    log.info("%s", summary.table(time.monotonic() - started))
    log.info("%s", traffic.summary())
    rrd = commands.get("visualizer", [])
    if "--save" in rrd:
        path = rrd[rrd.index("--save") + 1]
        log.info("recording: %s (view it with `rerun %s`)", path, path)
    return exit_code


def message_feeder(kind: type[Message], consumers: list[Callable[[Any], None]]) -> Callable[[Any], None]:
    """A Zenoh callback decoding ``kind`` messages once for all ``consumers``; a bad payload is left to
    the services, which count it."""

    def feed(sample: Any) -> None:
        try:
            message = decode_message(payload_bytes(sample), kind)
        except MessageError:
            return
        for consume in consumers:
            consume(message)

    return feed


def _write_snapshots(snapshots: Any, out_dir: Path | None) -> None:
    assert out_dir is not None  # snapshots exist only with a snapshot_dir
    written = snapshots.write(out_dir)
    if written:
        log.debug("snapshot: %s", ", ".join(map(str, written)))


def _end_of_replay(code: int, traffic: TrafficCounter) -> int:
    """The replay exited: drain the last detections if it played through (0), else report it (1)."""
    if code != 0:
        log.error("replay exited with code %d: a replay is not restarted, stopping", code)
        return 1
    log.info("replay finished: waiting for the last detections")
    deadline = time.monotonic() + DRAIN_MAX_S
    seen, quiet_since = traffic.count_of(DETECTIONS), time.monotonic()
    while time.monotonic() < deadline and time.monotonic() - quiet_since < DRAIN_QUIET_S:
        time.sleep(0.1)
        if (now_seen := traffic.count_of(DETECTIONS)) != seen:
            seen, quiet_since = now_seen, time.monotonic()
    return 0


def _restart_dead(children: dict[str, _Child], max_restarts: int) -> bool:
    """Restart children that exited; False once one has died more than ``max_restarts`` times lately."""
    now = time.monotonic()
    for child in children.values():
        code = child.exit_code()
        if code is None:
            continue
        while child.restarts and now - child.restarts[0] > RESTART_WINDOW_S:
            child.restarts.popleft()
        if len(child.restarts) >= max_restarts:
            log.error(
                "%s exited with code %d and has died %d times in %.0f s: giving up",
                child.name,
                code,
                len(child.restarts) + 1,
                RESTART_WINDOW_S,
            )
            return False
        if code == USAGE_EXIT:
            log.error(
                "%s exited with code %d: it refused its arguments or input (its message is above); "
                "not restarting it",
                child.name,
                code,
            )
            return False
        child.restarts.append(now)
        log.error(
            "%s exited with code %d: restarting (%d/%d)", child.name, code, len(child.restarts), max_restarts
        )
        child.start()
    return True


def child_environment() -> dict[str, str]:
    """The children import ``services``/``common`` from this checkout even when it is not installed."""
    env = dict(os.environ)
    env[EXIT_WITH_PARENT_ENV] = "1"  # a child whose launcher was killed -9 stops instead of lingering
    env[PERIODIC_SUMMARY_ENV] = "debug"  # the launcher's table replaces the services' periodic counters
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH", "")) if p)
    return env
