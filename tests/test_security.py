"""Secure mode over real Zenoh sessions on loopback: mutual TLS keeps strangers out, the ACL keeps roles apart

Certificates come from ``security/make_certs.sh`` into a temporary directory, configs from
``security.zenoh_config``; every check is a real publication that does or does not reach a subscriber.
A denial can only be shown by waiting, so each negative check waits a bounded time (about a second).
"""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from common.keys import SCAN, TENSOR, shard_key, shard_members_key, topic_sources_key
from common.messages import Detection, Detections, Message, Scan, StageTimings, decode_message, encode_message
from security.zenoh_config import common_name, main, secure_config
from services.runtime import announce_source

zenoh = pytest.importorskip("zenoh")

if shutil.which("openssl") is None:
    pytest.skip(
        "openssl is not installed: security/make_certs.sh cannot make certificates", allow_module_level=True
    )

ROOT = Path(__file__).resolve().parents[1]
MAKE_CERTS = ROOT / "security" / "make_certs.sh"
ROBOTS = ("r1", "r2")
MODELS: dict[str, type[Message]] = {"scan": Scan, "detections": Detections}
MATCH_WAIT_S = 3.0  # a publisher that has a reachable subscriber sees it well within this
ARRIVE_WAIT_S = 1.0  # how long a publication is given to arrive before it counts as refused


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("certs")
    subprocess.run(
        [str(MAKE_CERTS), "--force", str(out), *ROBOTS], check=True, capture_output=True, text=True
    )
    return out


def zenoh_config(config: dict[str, Any]) -> Any:
    result = zenoh.Config()
    for key, value in config.items():
        result.insert_json5(key, json.dumps(value))
    return result


class Inbox:
    """Samples a subscriber received, decoded, with a bounded wait for the next one."""

    def __init__(self) -> None:
        self.samples: list[tuple[str, Any]] = []
        self._cond = threading.Condition()

    def __call__(self, sample: Any) -> None:
        with self._cond:
            key = str(sample.key_expr)
            model = MODELS[key.rsplit("/", 1)[-1]]
            self.samples.append((key, decode_message(sample.payload.to_bytes(), model)))
            self._cond.notify_all()

    def wait_for(self, count: int, timeout_s: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: len(self.samples) >= count, timeout_s)


class Mesh:
    """Secured sessions on loopback, all closed at the end (a callback subscriber otherwise hangs exit)."""

    def __init__(self, certs: Path, stack: ExitStack, port: int) -> None:
        self.certs = certs
        self.stack = stack
        self.port = port

    def open(self, config: dict[str, Any]) -> Any:
        session = zenoh.open(zenoh_config(config))
        self.stack.callback(session.close)
        return session

    def secure(
        self, identity: str, *, listen: bool = False, edit: Callable[[dict[str, Any]], None] | None = None
    ) -> Any:
        endpoint = f"tls/127.0.0.1:{self.port}"
        config = secure_config(
            self.certs, identity, listen=[endpoint] if listen else [], connect=[] if listen else [endpoint]
        )
        if edit is not None:
            edit(config)
        return self.open(config)

    def subscribe(self, session: Any, key: str) -> Inbox:
        inbox = Inbox()
        subscriber = session.declare_subscriber(key, inbox)
        self.stack.callback(subscriber.undeclare)
        return inbox


@pytest.fixture
def mesh(certs: Path, free_port: Callable[[], int]) -> Iterator[Mesh]:
    with ExitStack() as stack:
        yield Mesh(certs, stack, free_port())


def scan(robot_id: str) -> bytes:
    ranges = np.linspace(0.2, 3.0, 360, dtype=np.float32)
    return encode_message(
        Scan(
            robot_id=robot_id,
            seq=1,
            stamp_ns=1,
            angle_min=0.0,
            angle_increment=float(np.deg2rad(1.0)),
            range_min=0.12,
            range_max=3.5,
            ranges=ranges,
        )
    )


def detections(robot_id: str, model_id: str = "yolov8n-triscan") -> bytes:
    detection = Detection(
        class_id=0,
        class_name="chair",
        score=0.9,
        box_px=(1.0, 1.0, 5.0, 5.0),
        bearing_deg=10.0,
        bearing_min_deg=5.0,
        bearing_max_deg=15.0,
        range_min_m=0.5,
        range_max_m=0.9,
        x_m=0.7,
        y_m=0.1,
    )
    timings = StageTimings(encode_ms=0.1, inference_ms=1.0, nms_ms=0.1)
    message = Detections(
        robot_id=robot_id, seq=1, stamp_ns=2, detections=[detection], timings=timings, model_id=model_id,
        scan_stamp_ns=1,
    )  # fmt: skip
    return encode_message(message)


def delivered(session: Any, key: str, payload: bytes, inbox: Inbox) -> bool:
    """Put ``payload`` on ``key`` once a subscriber matches; True when it reached ``inbox`` in time."""
    before = len(inbox.samples)
    publisher = session.declare_publisher(key)
    try:
        deadline = time.monotonic() + MATCH_WAIT_S
        while not publisher.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.02)
        publisher.put(payload)
        return inbox.wait_for(before + 1, ARRIVE_WAIT_S)
    finally:
        publisher.undeclare()


def _live_tokens(session: Any, pattern: str) -> list[str]:
    """The liveliness tokens ``session`` sees on ``pattern``, asked until some answer or the wait ends."""
    deadline = time.monotonic() + MATCH_WAIT_S
    tokens: list[str] = []
    while not tokens and time.monotonic() < deadline:
        replies = session.liveliness().get(pattern, timeout=1.0)
        tokens = [str(reply.ok.key_expr) for reply in replies if reply.ok]
    return tokens


def drop_access_control(config: dict[str, Any]) -> None:
    """A rogue writes its own config: it can always switch its own checks off."""
    del config["access_control"]


def test_make_certs_names_each_identity_and_keeps_keys_private(certs: Path) -> None:
    identities = ["detector", "encoder", "visualizer", "simulator", "app"] + [f"robot-{r}" for r in ROBOTS]
    for identity in identities:
        cn = common_name(identity)
        subject = subprocess.run(
            [
                "openssl",
                "x509",
                "-in",
                str(certs / f"{cn}.pem"),
                "-noout",
                "-subject",
                "-ext",
                "subjectAltName",
            ],
            check=True,
            capture_output=True,
            text=True,
        ).stdout
        assert f"CN = {cn}" in subject or f"CN={cn}" in subject
        assert "DNS:localhost" in subject and "IP Address:127.0.0.1" in subject
        assert stat.S_IMODE(os.stat(certs / f"{cn}.key").st_mode) == 0o600
    again = subprocess.run([str(MAKE_CERTS), str(certs)], capture_output=True, text=True)
    assert again.returncode != 0 and "--force" in again.stderr


def test_config_is_tls_only_and_loads_in_zenoh(
    certs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(ValueError, match="tls"):
        secure_config(certs, "detector", listen=["tcp/0.0.0.0:7447"])
    assert main(["--certs", str(certs), "--identity", "detector", "--listen", "tls/0.0.0.0:7447"]) == 0
    config = json.loads(capsys.readouterr().out)
    assert config["transport"]["link"]["protocols"] == ["tls"]
    assert config["transport"]["link"]["tls"]["enable_mtls"] is True
    assert config["scouting"]["multicast"]["enabled"] is False
    assert config["access_control"]["default_permission"] == "deny"
    path = tmp_path / "detector.json5"
    path.write_text(json.dumps(config))
    zenoh.Config.from_file(str(path))  # zenoh itself accepts every key


def test_session_without_client_certificate_is_refused(mesh: Mesh) -> None:
    listener = mesh.secure("visualizer", listen=True)
    trusted = mesh.subscribe(listener, "triscan/*/detections")
    endpoint = f"tls/127.0.0.1:{mesh.port}"

    plain_tcp = {"mode": "client", "connect": {"endpoints": [f"tcp/127.0.0.1:{mesh.port}"]}}
    no_cert = secure_config(mesh.certs, "app", connect=[endpoint], mode="client")
    drop_access_control(no_cert)
    tls = no_cert["transport"]["link"]["tls"]
    for key in ("connect_private_key", "connect_certificate", "listen_private_key", "listen_certificate"):
        del tls[key]
    tls["enable_mtls"] = False
    for config in (plain_tcp, no_cert):  # a client must reach its endpoint to open: it cannot
        config["scouting"] = {"multicast": {"enabled": False}}
        with pytest.raises(zenoh.ZError):
            mesh.open(config)

    # A peer without a certificate opens alone: it has no link, so it neither hears nor is heard.
    stranger = mesh.open({**no_cert, "mode": "peer"})
    assert list(stranger.info.peers_zid()) == []
    eavesdropper = mesh.subscribe(stranger, "triscan/**")
    assert not delivered(stranger, "triscan/r1/detections", detections("r1", "forged"), trusted)
    detector = mesh.secure("detector")
    assert delivered(detector, "triscan/r1/detections", detections("r1"), trusted)
    assert [message.model_id for _, message in eavesdropper.samples] == ["forged"]  # its own put, locally


def test_detector_detections_arrive(mesh: Mesh) -> None:
    inbox = mesh.subscribe(mesh.secure("visualizer", listen=True), "triscan/**")
    assert delivered(mesh.secure("detector"), "triscan/r1/detections", detections("r1"), inbox)
    key, message = inbox.samples[-1]
    assert key == "triscan/r1/detections" and isinstance(message, Detections) and message.robot_id == "r1"


def test_only_the_detector_may_put_detections(mesh: Mesh) -> None:
    inbox = mesh.subscribe(mesh.secure("visualizer", listen=True), "triscan/**")
    app = mesh.secure("app")
    assert not delivered(app, "triscan/r1/detections", detections("r1", "forged"), inbox)
    rogue = mesh.secure("app", edit=drop_access_control)  # the receiver's ingress check is what stops it
    assert not delivered(rogue, "triscan/r1/detections", detections("r1", "forged"), inbox)
    detector = mesh.secure("detector")
    assert not delivered(detector, "triscan/r1/scan", scan("r1"), inbox)
    assert inbox.samples == []


def test_only_the_robot_may_put_its_scans(mesh: Mesh) -> None:
    inbox = mesh.subscribe(mesh.secure("encoder", listen=True), "triscan/*/scan")
    assert delivered(mesh.secure("robot-r1"), "triscan/r1/scan", scan("r1"), inbox)
    robot_r2 = mesh.secure("robot-r2")
    assert not delivered(robot_r2, "triscan/r1/scan", scan("r1"), inbox)
    assert delivered(robot_r2, "triscan/r2/scan", scan("r2"), inbox)
    assert [key for key, _ in inbox.samples] == ["triscan/r1/scan", "triscan/r2/scan"]
    assert all(isinstance(message, Scan) for _, message in inbox.samples)


def test_a_client_cannot_launder_detections_through_a_peer(mesh: Mesh) -> None:
    """A peer routes for its clients; its own ingress check still sees the client's certificate."""
    detector = mesh.secure("detector", listen=True)
    inbox = mesh.subscribe(mesh.secure("visualizer"), "triscan/*/detections")
    rogue = mesh.secure(
        "app", edit=lambda config: (drop_access_control(config), config.update(mode="client"))
    )
    assert not delivered(rogue, "triscan/r1/detections", detections("r1", "forged"), inbox)
    assert delivered(detector, "triscan/r1/detections", detections("r1"), inbox)
    assert [message.model_id for _, message in inbox.samples] == ["yolov8n-triscan"]


def test_health_tokens_and_stats_still_flow(mesh: Mesh) -> None:
    """The ACL leaves the launcher's liveliness watch and the stats plane working for every member."""
    watcher = mesh.secure("app", listen=True)
    detector = mesh.secure("detector")
    token = detector.liveliness().declare_token("triscan/@health/detector/1")
    mesh.stack.callback(token.undeclare)
    stats: list[bytes] = []
    arrived = threading.Event()

    def on_stats(sample: Any) -> None:
        stats.append(sample.payload.to_bytes())
        arrived.set()

    subscriber = watcher.declare_subscriber("triscan/@stats/**", on_stats)
    mesh.stack.callback(subscriber.undeclare)
    alive = _live_tokens(watcher, "triscan/@health/**")
    assert alive == ["triscan/@health/detector/1"]
    publisher = detector.declare_publisher("triscan/@stats/detector/1")
    mesh.stack.callback(publisher.undeclare)
    deadline = time.monotonic() + MATCH_WAIT_S
    while not publisher.matching_status.matching and time.monotonic() < deadline:
        time.sleep(0.02)
    publisher.put(b"{}")
    assert arrived.wait(ARRIVE_WAIT_S) and stats == [b"{}"]


def test_shard_tokens_flow_so_detector_processes_can_share_a_fleet(mesh: Mesh) -> None:
    """Detector processes on other hosts see each other's shard tokens through the ACL."""
    watcher = mesh.secure("detector", listen=True)
    other = mesh.secure("detector")
    token = other.liveliness().declare_token(shard_key("detector", "a1f3"))
    mesh.stack.callback(token.undeclare)
    members = _live_tokens(watcher, shard_members_key("detector"))
    assert members == [shard_key("detector", "a1f3")]


def test_tensor_source_tokens_flow_so_detectors_know_which_robots_to_subscribe_to(mesh: Mesh) -> None:
    """An encoder's announcement of a robot's tensors reaches a detector on another host through the ACL."""
    watcher = mesh.secure("detector", listen=True)
    encoder = mesh.secure("encoder")
    token = announce_source(encoder, "r1", TENSOR)
    mesh.stack.callback(token.undeclare)
    sources = _live_tokens(watcher, topic_sources_key(TENSOR))
    assert sources == [f"triscan/@sources/tensor/r1/{encoder.zid()}"]


@pytest.mark.parametrize("publisher", ["robot-r1", "simulator"])
def test_scan_source_tokens_flow_so_detectors_know_which_robots_scans_to_subscribe_to(
    mesh: Mesh, publisher: str
) -> None:
    """A robot's (or the simulator's) announcement of its scans reaches a ``--from-scans`` detector on
    another host through the ACL."""
    watcher = mesh.secure("detector", listen=True)
    robot = mesh.secure(publisher)
    token = announce_source(robot, "r1", SCAN)
    mesh.stack.callback(token.undeclare)
    sources = _live_tokens(watcher, topic_sources_key(SCAN))
    assert sources == [f"triscan/@sources/scan/r1/{robot.zid()}"]
