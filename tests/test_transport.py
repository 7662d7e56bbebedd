"""Zenoh settings: flags, config files and ``$ZENOH_CONFIG`` reach a real ``zenoh.Config`` the same way."""

from __future__ import annotations

import argparse
import json
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import pytest

from common.keys import health_key, parse_health_key
from common.transport import (
    ZenohSettings,
    add_zenoh_arguments,
    open_session,
    settings_from_args,
)
from services.launcher import free_tcp_ports
from tests.support.waiting import wait_for


def parse(*argv: str) -> ZenohSettings:
    parser = argparse.ArgumentParser()
    add_zenoh_arguments(parser)
    return settings_from_args(parser.parse_args(list(argv)))


def config_value(settings: ZenohSettings, key: str) -> object:
    return json.loads(settings.to_config().get_json(key))


def test_flags_reach_the_zenoh_config() -> None:
    settings = parse(
        "--mode", "client", "-e", "tcp/10.0.0.2:7447", "-l", "tcp/0.0.0.0:7448", "--no-multicast"
    )
    assert config_value(settings, "mode") == "client"
    assert config_value(settings, "connect/endpoints") == ["tcp/10.0.0.2:7447"]
    assert config_value(settings, "listen/endpoints") == ["tcp/0.0.0.0:7448"]
    assert config_value(settings, "scouting/multicast/enabled") is False


def test_to_cli_round_trips_through_the_flags(tmp_path: Path) -> None:
    config_file = tmp_path / "z.json5"
    config_file.write_text("{}")
    original = ZenohSettings(
        mode="peer",
        connect=("tcp/127.0.0.1:1", "tcp/127.0.0.1:2"),
        listen=("tcp/127.0.0.1:3",),
        multicast_scouting=False,
        config_file=config_file,
    )
    assert parse(*original.to_cli()) == original


def test_config_file_and_env_are_read_and_flags_override_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    config_file = tmp_path / "zenoh.json5"
    config_file.write_text('{ mode: "client", connect: { endpoints: ["tcp/192.168.7.7:7447"] } }')
    assert config_value(parse("--zenoh-config", str(config_file)), "mode") == "client"
    monkeypatch.setenv("ZENOH_CONFIG", str(config_file))
    from_env = parse()
    assert config_value(from_env, "connect/endpoints") == ["tcp/192.168.7.7:7447"]
    assert config_value(parse("--mode", "peer"), "mode") == "peer"  # the flag wins over the file
    monkeypatch.setenv("ZENOH_CONFIG", str(tmp_path / "missing.json5"))
    with pytest.raises(FileNotFoundError, match=r"missing\.json5"):
        parse().to_config()


def test_bad_mode_is_refused() -> None:
    with pytest.raises(ValueError, match="mode"):
        ZenohSettings(mode="satellite")


def test_health_keys_round_trip_and_reject_others() -> None:
    assert parse_health_key(health_key("detector", "123")) == ("detector", "123")
    for key in ("triscan/robot0/scan", "triscan/@health/detector", "triscan/@health/a/b/c"):
        with pytest.raises(ValueError):
            parse_health_key(key)


def test_two_loopback_sessions_exchange_a_sample() -> None:
    (port,) = free_tcp_ports(1)
    got: list[bytes] = []
    with (
        open_session(ZenohSettings.loopback(port)) as a,
        open_session(ZenohSettings.loopback(None, [port])) as b,
    ):
        sub = a.declare_subscriber("triscan/t/scan", lambda s: got.append(s.payload.to_bytes()))
        publisher = b.declare_publisher("triscan/t/scan")
        deadline = time.monotonic() + 10
        while not publisher.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.02)
        publisher.put(b"hello")
        while not got and time.monotonic() < deadline:
            time.sleep(0.02)
        sub.undeclare()
    assert got == [b"hello"]


def test_zenoh_own_flag_names_are_accepted(tmp_path: Path) -> None:
    parser = argparse.ArgumentParser()
    add_zenoh_arguments(parser)
    config_file = tmp_path / "z.json5"
    config_file.write_text('{ mode: "peer" }')
    args = parser.parse_args(
        ["-c", str(config_file), "--cfg", "scouting/multicast/enabled:false", "--cfg", 'mode:"client"']
    )
    settings = settings_from_args(args)
    assert settings.config_file == config_file
    assert settings.cfg == (("scouting/multicast/enabled", "false"), ("mode", '"client"'))
    assert settings_from_args(parser.parse_args(settings.to_cli())) == settings  # survives a child's argv
    config = settings.to_config()
    assert json.loads(config.get_json("mode")) == "client"  # --cfg wins over the file
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    with pytest.raises(SystemExit):
        parser.parse_args(["--cfg", "no-colon"])
    with pytest.raises(ValueError, match="--cfg"):
        ZenohSettings(cfg=(("no/such/key", "1"),)).to_config()


def test_the_low_latency_transport_is_warned_about(caplog: pytest.LogCaptureFixture) -> None:
    """It drops messages larger than its batch (docs/benchmarks.md): whoever turns it on hears why."""
    with caplog.at_level("WARNING", logger="common.transport"):
        parse("--cfg", "transport/unicast/qos/enabled:false").to_config()
        assert not caplog.records
        parse(
            "--cfg", "transport/unicast/qos/enabled:false", "--cfg", "transport/unicast/lowlatency:true"
        ).to_config()
    (record,) = caplog.records
    assert "transport/unicast/lowlatency" in record.getMessage() and "73 KB" in record.getMessage()


def _two_sessions_meet(first: ZenohSettings, second: ZenohSettings, timeout_s: float) -> bool:
    """Whether a publication of one session reaches the other within ``timeout_s`` (a key of their own,
    so no other Zenoh peer on this host can answer for them)."""
    key = f"triscan/t{uuid.uuid4().hex[:12]}/scan"
    got: list[bytes] = []
    with open_session(first) as a, open_session(second) as b:
        a.declare_subscriber(key, lambda s: got.append(s.payload.to_bytes()))
        publisher = b.declare_publisher(key)
        wait_for(lambda: publisher.matching_status.matching, timeout_s)
        publisher.put(b"hello")
        wait_for(lambda: got, 1.0)
    return got == [b"hello"]


def test_sessions_not_pointed_at_each_other_never_meet_unless_asked_to_discover(
    free_port: Callable[[], int],
) -> None:
    """The accidental join: two peers on one host, each listening on its own port, neither told of the
    other. By default they stay apart; with --discover on both, multicast scouting joins them."""

    def alone(discover: bool = False) -> ZenohSettings:
        return ZenohSettings(
            mode="peer", listen=(f"tcp/127.0.0.1:{free_port()}",), multicast_scouting=discover
        )

    assert (
        parse().multicast_scouting is False and config_value(parse(), "scouting/multicast/enabled") is False
    )
    assert not _two_sessions_meet(alone(), alone(), timeout_s=3.0)
    assert not _two_sessions_meet(alone(), alone(discover=True), timeout_s=3.0)  # one scouting is not enough
    assert _two_sessions_meet(alone(discover=True), alone(discover=True), timeout_s=10.0)


def test_discover_is_a_flag_that_survives_a_childs_argv() -> None:
    settings = parse("--discover", "-e", "tcp/10.0.0.2:7447")
    assert (
        settings.multicast_scouting is True and config_value(settings, "scouting/multicast/enabled") is True
    )
    assert parse(*settings.to_cli()) == settings
    with pytest.raises(SystemExit):
        parse("--discover", "--no-multicast")
    with pytest.raises(ValueError, match=r"write tcp/10\.0\.0\.2:7447"):
        ZenohSettings(connect=("10.0.0.2:7447",))
