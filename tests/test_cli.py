"""The ``triscan`` command's shape: what it imports, how it refuses, how it names itself."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from services.cli import COMMANDS, command_parser, main, missing_extra
from services.cli.command import Command

REPO = Path(__file__).resolve().parents[1]
HEAVY = ("training", "torch", "ultralytics", "pybullet", "rerun", "rosbags")


def _python(code: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60, check=False
    )


@pytest.mark.parametrize("argv", [["--help"], ["status", "--help"], ["up", "--help"], []])
def test_triscan_and_its_help_load_no_offline_or_optional_module(argv: list[str]) -> None:
    """The robot's base install runs `triscan`: neither the training tools nor an extra's module."""
    code = (
        "import sys\nfrom services.cli import main\ntry:\n"
        f"    main({argv!r})\nexcept SystemExit:\n    pass\n"
        f"print(sorted({{m.split('.')[0] for m in sys.modules}} & {set(HEAVY)!r}))"
    )
    result = _python(code)
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[-1] == "[]"


def test_a_missing_extra_is_one_line_naming_it_and_exit_2(tmp_path: Path) -> None:
    result = _python(
        "import sys\nsys.modules['pybullet'] = None  # as on an install without the sim extra\n"
        "from services.cli import main\n"
        f"raise SystemExit(main(['sim-bag', '--scans', '1', '--out', {str(tmp_path / 'bag')!r}]))"
    )
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in result.stderr
    assert lines[0].endswith("triscan sim-bag needs the sim and ros2 extras: pip install 'triscan[sim,ros2]'")


def test_only_an_extras_module_is_reported_as_a_missing_extra() -> None:
    train = next(c for c in COMMANDS if c.name == "train")
    status = next(c for c in COMMANDS if c.name == "status")
    advice = missing_extra(train, ModuleNotFoundError("no torch", name="torch"))
    assert advice == "triscan train needs the train extra: pip install 'triscan[train]'"
    assert missing_extra(train, ModuleNotFoundError("bug", name="training.nothing")) is None
    assert missing_extra(status, ModuleNotFoundError("bug", name="torch")) is None


def _service_main(module: str) -> Callable[[list[str]], object]:
    import importlib

    return importlib.import_module(module).main  # type: ignore[no-any-return]


@pytest.mark.parametrize(
    ("prog", "run", "argv", "unknown"),
    [
        ("triscan status", main, ["status", "--wai", "1"], "--wai 1"),
        ("triscan eval", main, ["eval", "--model", "m.onnx", "--fresh", "1", "--fram", "3"], "--fram 3"),
        ("triscan up", main, ["up", "--head"], "--head"),
        ("python -m services.detector", "services.detector.__main__", ["--from-scan"], "--from-scan"),
        ("python -m services.encoder", "services.encoder.__main__", ["--pad", "zero"], "--pad zero"),
        (
            "python -m services.ros2_bridge",
            "services.ros2_bridge.__main__",
            ["--scan", "scan"],
            "--scan scan",
        ),
        ("python -m services.simulator", "services.simulator.__main__", ["--robot", "2"], "--robot 2"),
        (
            "python -m services.visualizer",
            "services.visualizer.__main__",
            ["--save", "x.rrd", "--dur", "1"],
            "--dur 1",
        ),
        ("python -m services.bag_replay", "services.bag_replay", ["b.mcap", "--spe", "2"], "--spe 2"),
    ],
)
def test_an_abbreviated_flag_is_refused_in_the_commands_own_name(
    prog: str, run: object, argv: list[str], unknown: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """`--from-scan` is not `--from-scans`: argparse would guess it; these parsers say no, as the
    command the user typed."""
    entry = run if callable(run) else _service_main(str(run))
    with pytest.raises(SystemExit) as exit_info:
        entry(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert f"usage: {prog} " in err and f"{prog}: error: unrecognized arguments: {unknown}" in err


def test_every_subcommand_parser_is_built_with_its_name_and_no_abbreviation() -> None:
    from services.cli import build_parser

    for command in COMMANDS:
        chosen = command_parser(build_parser(command), command.name)
        assert chosen.prog == f"triscan {command.name}" and chosen.allow_abbrev is False
    assert build_parser().allow_abbrev is False


def test_commands_have_distinct_names() -> None:
    names = [c.name for c in COMMANDS]
    assert len(set(names)) == len(names) and all(isinstance(c, Command) for c in COMMANDS)
