"""How ``triscan up`` wires its children (the running loop itself is tested in test_up.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from common.model_spec import SHIPPED_MODEL
from services.launcher import SERVICES, UpConfig, free_tcp_ports, service_commands
from services.tracker import RULE_FLAGS


def flag_values(command: list[str], flag: str) -> list[str]:
    return [command[i + 1] for i, arg in enumerate(command) if arg == flag]


def test_free_ports_are_distinct() -> None:
    ports = free_tcp_ports(8)
    assert len(set(ports)) == 8 and all(1024 <= p < 65536 for p in ports)


def test_every_child_listens_on_its_own_port_and_connects_to_all_others() -> None:
    ports = dict(zip(SERVICES, (7001, 7002, 7003, 7004, 7005), strict=True))
    commands = service_commands(UpConfig(headless=True, rrd_path=Path("x.rrd")), ports, 7447)
    assert set(commands) == set(SERVICES)
    for name, command in commands.items():
        assert command[1:3] == ["-m", f"services.{name}"]
        assert flag_values(command, "--listen") == [f"tcp/127.0.0.1:{ports[name]}"]
        expected = {f"tcp/127.0.0.1:{p}" for other, p in ports.items() if other != name} | {
            "tcp/127.0.0.1:7447"
        }
        assert set(flag_values(command, "--connect")) == expected
        assert "--no-multicast" in command and flag_values(command, "--mode") == ["peer"]
    assert flag_values(commands["visualizer"], "--save") == ["x.rrd"]
    assert flag_values(commands["simulator"], "--robots") == ["1"]


def test_viewer_choices() -> None:
    ports = dict(zip(SERVICES, (1, 2, 3, 4, 5), strict=True))
    assert "--serve-web" in service_commands(UpConfig(viewer="web"), ports, None)["visualizer"]
    assert "--spawn" in service_commands(UpConfig(viewer="spawn"), ports, None)["visualizer"]
    assert "visualizer" not in service_commands(UpConfig(viewer="none"), ports, None)


def test_encoder_padding_invalid_rule_and_raster_yaw_follow_the_model(tmp_path: Path) -> None:
    onnx = pytest.importorskip("onnx")
    model = onnx.load(str(SHIPPED_MODEL))
    for prop in model.metadata_props:
        if prop.key == "triscan.padding":
            prop.value = "wrap"
    model.metadata_props.add(key="triscan.invalid", value="empty")
    model.metadata_props.add(key="triscan.raster_yaw_deg", value="-180")
    wrap_model = tmp_path / "wrap.onnx"
    onnx.save(model, str(wrap_model))
    ports = dict(zip(SERVICES, (1, 2, 3, 4, 5), strict=True))
    commands = service_commands(UpConfig(model=wrap_model, viewer="none"), ports, None)
    assert flag_values(commands["encoder"], "--padding") == ["wrap"]
    assert flag_values(commands["encoder"], "--invalid") == ["empty"]
    assert flag_values(commands["encoder"], "--raster-yaw") == ["180.0"]  # mod 360
    assert flag_values(commands["simulator"], "--raster-yaw") == ["180.0"]  # its truth boxes too
    assert flag_values(commands["detector"], "--model") == [str(wrap_model)]
    default = service_commands(UpConfig(viewer="none"), ports, None)
    assert flag_values(default["encoder"], "--padding") == ["zero"]
    assert flag_values(default["encoder"], "--invalid") == ["sentinel"]  # a model that does not say
    assert (
        flag_values(default["encoder"], "--raster-yaw")
        == flag_values(default["simulator"], "--raster-yaw")
        == []
    )


def test_batch_reaches_the_detector_and_a_fixed_model_is_refused_before_anything_starts() -> None:
    import threading

    from services.launcher import up

    ports = dict(zip(SERVICES, (1, 2, 3, 4, 5), strict=True))
    assert flag_values(service_commands(UpConfig(viewer="none"), ports, None)["detector"], "--batch") == []
    batched = service_commands(UpConfig(viewer="none", batch=8), ports, None)["detector"]
    assert flag_values(batched, "--batch") == ["8"] and flag_values(batched, "--model") == []
    fixed = SHIPPED_MODEL
    with pytest.raises(ValueError, match="free batch axis"):
        up(UpConfig(viewer="none", batch=4, model=fixed), threading.Event())
    with pytest.raises(ValueError, match="--batch must be >= 1"):
        up(UpConfig(viewer="none", batch=0), threading.Event())


def test_detectors_reach_the_detector_and_zero_is_refused_before_anything_starts() -> None:
    import threading

    from services.launcher import up

    ports = {name: port for port, name in enumerate(SERVICES, start=1)}
    default = service_commands(UpConfig(viewer="none"), ports, None)["detector"]
    assert flag_values(default, "--detectors") == []  # the detector picks: one process per core
    three = service_commands(UpConfig(viewer="none", detectors=3), ports, None)["detector"]
    assert flag_values(three, "--detectors") == ["3"]
    with pytest.raises(ValueError, match="--detectors must be >= 1"):
        up(UpConfig(viewer="none", detectors=0), threading.Event())


def test_the_person_travel_rule_reaches_the_tracker_and_a_negative_one_is_refused(
    caplog: pytest.LogCaptureFixture,
) -> None:
    from services.cli import main as cli_main

    ports = {name: port for port, name in enumerate(SERVICES, start=1)}
    default = service_commands(UpConfig(viewer="none"), ports, None)["tracker"]
    assert flag_values(default, "--person-confirm-travel") == []  # the tracker's default: off
    travel = service_commands(UpConfig(viewer="none", person_confirm_travel_m=0.5), ports, None)["tracker"]
    assert flag_values(travel, "--person-confirm-travel") == ["0.5"]
    assert flag_values(default, "--person-resume") == []  # the tracker's default
    resume = service_commands(UpConfig(viewer="none", person_resume_s=0.0), ports, None)["tracker"]
    assert flag_values(resume, "--person-resume") == ["0.0"]
    shown = service_commands(UpConfig(viewer="none", person_show_coast_s=1.5), ports, None)["tracker"]
    assert flag_values(shown, "--person-show-coast") == ["1.5"] and not flag_values(
        default, "--person-show-coast"
    )
    hits = service_commands(UpConfig(viewer="none", person_confirm_hits=3), ports, None)["tracker"]
    assert flag_values(hits, "--person-confirm-hits") == ["3"]
    assert not flag_values(default, "--person-confirm-hits")
    share = service_commands(UpConfig(viewer="none", person_show_coast_share=0.5), ports, None)["tracker"]
    assert flag_values(share, "--person-show-coast-share") == ["0.5"]
    assert not flag_values(default, "--person-show-coast-share")
    penalty = service_commands(UpConfig(viewer="none", person_coast_penalty_m=0.0), ports, None)["tracker"]
    assert flag_values(penalty, "--person-coast-penalty") == ["0.0"]
    assert not flag_values(default, "--person-coast-penalty")
    assert not [flag for flag in RULE_FLAGS.values() if flag in default]  # every rule: the tracker's default
    with pytest.raises(ValueError, match="person confirm travel must be >= 0 metres, got -1"):
        UpConfig(person_confirm_travel_m=-1.0)
    assert cli_main(["up", "--person-confirm-travel", "-1", "--duration", "1"]) == 2  # before any start
    assert "person confirm travel must be >= 0 metres, got -1" in caplog.text
    assert cli_main(["up", "--person-resume", "nan", "--duration", "1"]) == 2
    assert "person resume must be finite and >= 0" in caplog.text
    assert cli_main(["up", "--person-coast-penalty", "nan", "--duration", "1"]) == 2
    assert "person coast penalty must be finite and >= 0 metres" in caplog.text
    assert cli_main(["up", "--person-confirm-hits", "0", "--duration", "1"]) == 2
    assert "person confirm hits must be a whole number >= 1, got 0" in caplog.text


def test_a_replay_replaces_the_simulator_and_gets_its_flags(tmp_path: Path) -> None:
    from services.bag_replay import ReplayConfig

    bags = (tmp_path / "a.bag", tmp_path / "b.bag")
    replay = ReplayConfig(bags=bags, topics=("/front/scan",), robot="r7", speed=2.5, loop=True)
    config = UpConfig(viewer="none", replay=replay)
    assert config.services == ("replay", "encoder", "detector", "tracker", "visualizer")
    ports = dict(zip(config.services, (1, 2, 3, 4, 5), strict=True))
    commands = service_commands(config, ports, None)
    assert set(commands) == {"replay", "encoder", "detector", "tracker"}
    command = commands["replay"]
    assert command[1:5] == ["-m", "services.bag_replay", str(bags[0]), str(bags[1])]
    assert flag_values(command, "--topic") == ["/front/scan"] and flag_values(command, "--robot") == ["r7"]
    assert flag_values(command, "--speed") == ["2.5"] and "--loop" in command and "--no-progress" in command
    assert flag_values(command, "--listen") == ["tcp/127.0.0.1:1"]
    assert "tcp/127.0.0.1:1" in flag_values(commands["encoder"], "--connect")
    assert flag_values(commands["encoder"], "--padding") == ["zero"]  # still the model's
    once = service_commands(UpConfig(viewer="none", replay=ReplayConfig(bags=bags[:1])), ports, None)
    assert "--loop" not in once["replay"] and flag_values(once["replay"], "--robot") == []


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--replay", "x.bag", "--robots", "2"], "--robots: simulator only"),
        (["--replay", "x.bag", "--rate", "5", "--seed", "3"], "--rate, --seed: simulator only"),
        (["--speed", "2"], "--speed: needs --replay"),
        (["--loop", "--topic", "/scan"], "--topic, --loop: needs --replay"),
    ],
)
def test_up_refuses_flags_of_the_other_scan_source(
    argv: list[str], message: str, caplog: pytest.LogCaptureFixture
) -> None:
    from services.cli import main

    assert main(["up", "--headless", *argv]) == 2
    assert message in caplog.text


def test_up_refuses_a_replay_that_cannot_start_before_starting_anything(tmp_path: Path) -> None:
    import threading

    from services.bag_replay import ReplayConfig
    from services.launcher import up

    with pytest.raises(FileNotFoundError, match="missing"):
        up(UpConfig(viewer="none", replay=ReplayConfig(bags=(tmp_path / "missing.mcap",))), threading.Event())
