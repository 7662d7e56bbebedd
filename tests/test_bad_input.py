"""A bad input is one line saying what is wrong and what to do: no traceback, no process started.

Each case a new user meets in their first hour (a wrong ``--model``, a port in use, an endpoint
without its protocol, a file that is no bag, a negative rate) exits non-zero with its message, as
``triscan`` and as the ``python -m services.<name>`` a launcher or a robot runs.
"""

from __future__ import annotations

import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from common.transport import ZenohSettings, open_session
from services import launcher
from services.cli import main
from services.runtime import USAGE_EXIT

REPO = Path(__file__).resolve().parents[1]
ENDPOINT_WITHOUT_PROTOCOL = "127.0.0.1:7447"


def _service(module: str, *argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", module, *argv],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def _error_lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if " ERROR " in line or ": error: " in line]


@pytest.fixture
def not_a_model(tmp_path: Path) -> Path:
    path = tmp_path / "notes.onnx"
    path.write_text("these are not the weights you are looking for\n")
    return path


@pytest.fixture
def no_children(monkeypatch: pytest.MonkeyPatch) -> None:
    """``triscan up`` must refuse before it starts any process, and leave the test's signals alone."""

    def refuse(*args: object, **kwargs: object) -> None:
        raise AssertionError(f"a process was started: {args}")

    monkeypatch.setattr(launcher.subprocess, "Popen", refuse)
    monkeypatch.setattr("services.runtime.stop_event_on_signals", threading.Event)


@pytest.fixture
def held_port(free_port: Callable[[], int]) -> Iterator[int]:
    """A loopback port a Zenoh session listens on, as another ``triscan up`` would."""
    port = free_port()
    with open_session(ZenohSettings.loopback(port)):
        yield port


@pytest.mark.parametrize(
    ("model", "message"),
    [
        ("missing.onnx", "not found: give --model an existing .onnx file"),
        (None, "is not a loadable ONNX model"),
    ],
)
def test_detector_refuses_a_missing_or_broken_model_in_one_line(
    model: str | None, message: str, tmp_path: Path, not_a_model: Path
) -> None:
    path = tmp_path / model if model else not_a_model
    result = _service("services.detector", "--model", str(path))
    assert result.returncode == USAGE_EXIT
    assert "Traceback" not in result.stderr
    (line,) = _error_lines(result.stderr)
    assert str(path) in line and message in line


@pytest.mark.parametrize("model", ["missing.onnx", None])
def test_up_refuses_a_missing_or_broken_model_before_starting_anything(
    model: str | None,
    tmp_path: Path,
    not_a_model: Path,
    no_children: None,
    caplog: pytest.LogCaptureFixture,
    capsys: pytest.CaptureFixture[str],
) -> None:
    path = tmp_path / model if model else not_a_model
    assert main(["up", "--headless", "--model", str(path)]) == USAGE_EXIT
    (record,) = [r for r in caplog.records if r.levelname == "ERROR"]
    assert str(path) in record.getMessage() and record.exc_info is None
    assert "Traceback" not in capsys.readouterr().err


def test_a_service_on_a_port_in_use_says_so_in_one_line(held_port: int) -> None:
    result = _service("services.encoder", "--listen", f"tcp/127.0.0.1:{held_port}", "--duration", "5")
    assert result.returncode == USAGE_EXIT
    assert "Traceback" not in result.stderr and ".rs:" not in result.stderr
    (line,) = _error_lines(result.stderr)
    assert "Address already in use" in line and "pick another --listen" in line


def test_up_on_a_port_in_use_says_so_before_starting_anything(
    held_port: int, no_children: None, caplog: pytest.LogCaptureFixture
) -> None:
    assert main(["up", "--headless", "--listen", f"tcp/127.0.0.1:{held_port}"]) == USAGE_EXIT
    (record,) = [r for r in caplog.records if r.levelname == "ERROR"]
    assert "Address already in use" in record.getMessage() and ".rs:" not in record.getMessage()


@pytest.mark.parametrize("command", [["status"], ["up", "--headless"], ["replay", "x.bag"]])
def test_an_endpoint_without_its_protocol_is_one_error_naming_the_fix(
    command: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main([*command, "--connect", ENDPOINT_WITHOUT_PROTOCOL])
    assert exit_info.value.code == USAGE_EXIT
    err = capsys.readouterr().err
    assert len(err.splitlines()) <= 2 and "Json5" not in err
    (line,) = _error_lines(err)
    assert (
        line.startswith(f"triscan {command[0]}: error:") and f"write tcp/{ENDPOINT_WITHOUT_PROTOCOL}" in line
    )


def test_a_service_given_an_endpoint_without_its_protocol_names_itself_and_the_fix() -> None:
    result = _service("services.detector", "--from-scans", "--listen", ENDPOINT_WITHOUT_PROTOCOL)
    assert result.returncode == USAGE_EXIT
    assert result.stderr.splitlines()[0] == (
        f"python -m services.detector: error: argument --listen/-l: zenoh endpoint "
        f"'{ENDPOINT_WITHOUT_PROTOCOL}' has no <protocol>/ in front: write tcp/{ENDPOINT_WITHOUT_PROTOCOL}"
    )
    assert len(result.stderr.splitlines()) == 2


@pytest.mark.parametrize("what", ["recording.rrd", "a_folder", "missing.bag"])
def test_replay_of_something_that_is_no_bag_says_what_a_bag_is(
    what: str, tmp_path: Path, caplog: pytest.LogCaptureFixture, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("rosbags")
    path = tmp_path / what
    if what.endswith(".rrd"):
        path.write_bytes(b"RRF2")
    elif "." not in what:
        path.mkdir()
    assert main(["replay", str(path), "--wait", "0"]) == USAGE_EXIT
    (record,) = [r for r in caplog.records if r.levelname == "ERROR"]
    assert str(path) in record.getMessage() and "ROS 1 .bag files, or one ROS 2 bag" in record.getMessage()
    assert "Traceback" not in capsys.readouterr().err


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--rate", "-1"], "--rate must be a positive number"),
        (["--robots", "0"], "--robots must be >= 1"),
        (["--duration", "-5"], "--duration must be >= 0"),
        (["--batch", "0"], "--batch must be >= 1"),
    ],
)
def test_up_checks_every_flag_before_starting_anything(
    flags: list[str], message: str, no_children: None, caplog: pytest.LogCaptureFixture
) -> None:
    assert main(["up", "--headless", *flags]) == USAGE_EXIT
    (record,) = [r for r in caplog.records if r.levelname == "ERROR"]
    assert message in record.getMessage()


class _RefusingChild:
    """A child that exits with argparse's code as soon as it is started."""

    def __init__(self) -> None:
        self.name = "simulator"
        self.restarts: list[float] = []
        self.starts = 0

    def exit_code(self) -> int:
        return USAGE_EXIT

    def start(self) -> None:
        self.starts += 1


def test_a_child_that_refuses_its_arguments_is_reported_once_and_not_restarted(
    caplog: pytest.LogCaptureFixture,
) -> None:
    child = _RefusingChild()
    assert launcher._restart_dead({"simulator": child}, max_restarts=5) is False  # type: ignore[dict-item]
    assert child.starts == 0
    (record,) = [r for r in caplog.records if r.levelname == "ERROR"]
    assert "simulator exited with code 2" in record.getMessage() and "not restarting" in record.getMessage()
