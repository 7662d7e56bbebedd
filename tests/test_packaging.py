"""triscan installs anywhere: the wheel holds the code packages and the shipped models, and a non-editable
install answers a tensor with its default model from any directory, the repository nowhere on sys.path."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import threading
import tomllib
import zipfile
from pathlib import Path
from typing import Any

import pytest

from common.model_spec import (
    MODEL_ENV,
    MODELS_DIR,
    MODELS_PACKAGE,
    SHIPPED_BATCH_MODEL,
    SHIPPED_MODEL,
    file_model_id,
)

ROOT = Path(__file__).resolve().parents[1]
ROBOT = "wheel"


def _setuptools() -> dict[str, Any]:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def _package_dir(name: str) -> Path:
    """Where a listed package's code is in the repository (``package-dir`` renames the models)."""
    top, _, rest = name.partition(".")
    base = ROOT / _setuptools()["package-dir"].get(top, top)
    return base.joinpath(*rest.split(".")) if rest else base


def test_the_package_list_is_every_package_directory_and_the_models() -> None:
    """pyproject.toml lists its packages by hand (find cannot install models/ under another name): the
    list is every package directory below the listed top-level names, and models/ is triscan_models."""
    from setuptools import find_packages

    config = _setuptools()
    listed = set(config["packages"])
    assert config["package-dir"] == {MODELS_PACKAGE: "models"} and MODELS_PACKAGE in listed
    for name in listed:
        assert (_package_dir(name) / "__init__.py").is_file(), name
    code = {name.split(".")[0] for name in listed} - {MODELS_PACKAGE}
    found = find_packages(str(ROOT), include=[pattern for top in code for pattern in (top, f"{top}.*")])
    assert set(found) == listed - {MODELS_PACKAGE}


def _copy_sources(into: Path) -> Path:
    """The files a wheel is built from, copied: building in the checkout would leave build/ there, and
    setuptools would reuse whatever an older build left in it."""
    into.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, into / name)
    tops = {name.split(".")[0] for name in _setuptools()["packages"]}
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.pt")
    for top in tops:
        source = _package_dir(top)
        shutil.copytree(source, into / source.relative_to(ROOT), ignore=ignore)
    return into


def _installed_environment(site: Path) -> dict[str, str]:
    """The installed copy alone on PYTHONPATH, and no model named: the default must come from it."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", MODEL_ENV)}
    env["PYTHONPATH"] = str(site)
    return env


@pytest.mark.slow
def test_a_wheel_installed_elsewhere_answers_a_tensor_with_its_default_model(tmp_path: Path) -> None:
    from common.keys import TENSOR, detections_key, tensor_key
    from common.messages import Detections, StackedTensor, decode_message, encode_message
    from common.transport import ZenohSettings, open_session, payload_bytes, wait_for_subscriber
    from services.launcher import free_tcp_ports
    from services.runtime import announce_source
    from tests.support.health import service_pids
    from tests.support.waiting import wait_for
    from training.evaluate import fresh_samples

    source = _copy_sources(tmp_path / "source")
    dist = tmp_path / "dist"
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    build = [*pip, "wheel", str(source), "-w", str(dist), "--no-deps", "--no-build-isolation"]
    subprocess.run(build, check=True, cwd=tmp_path)
    (wheel,) = dist.glob("triscan-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for model in (SHIPPED_MODEL, SHIPPED_BATCH_MODEL, SHIPPED_MODEL.parent / "MODEL_CARD.json"):
        assert f"{MODELS_PACKAGE}/{model.relative_to(MODELS_DIR).as_posix()}" in names, model
    assert not [n for n in names if n.endswith(".pt") or n.startswith("models/")]

    site = tmp_path / "site"
    subprocess.run([*pip, "install", "--no-deps", "--target", str(site), str(wheel)], check=True)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = _installed_environment(site)

    def python(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, *args], cwd=elsewhere, env=env, capture_output=True, text=True, timeout=120
        )

    where = python(
        "-c",
        "import common, services, common.model_spec as m\n"
        "print(common.__file__, services.__file__, m.MODELS_DIR, m.default_model_path(), sep='\\n')",
    )
    assert where.returncode == 0, where.stderr
    paths = [Path(line) for line in where.stdout.split()]
    assert len(paths) == 4 and all(path.is_relative_to(site) for path in paths), paths
    assert paths[2] == site / MODELS_PACKAGE and paths[3].is_file()
    helped = python("-m", "services.detector", "--help")
    assert helped.returncode == 0 and "--from-scans" in helped.stdout, helped.stderr

    sample = next(s for s in fresh_samples(1000, 1, 15, "zero", 15) if len(s.boxes))
    message = StackedTensor(
        robot_id=ROBOT, seq=2, stamp_ns=3, tensor=sample.tensor, padding="zero",
        scan_seqs=(0, 1, 2), scan_stamps_ns=(1, 2, 3),
    )  # fmt: skip
    (port,) = free_tcp_ports(1)
    detector = subprocess.Popen(
        [
            *(sys.executable, "-m", "services.detector", "--detectors", "1"),
            *ZenohSettings.loopback(port).to_cli(),
        ],
        cwd=elsewhere,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    answers: list[Detections] = []
    lock = threading.Lock()

    def collect(zenoh_sample: Any) -> None:
        with lock:
            answers.append(decode_message(payload_bytes(zenoh_sample), Detections))

    try:
        with open_session(ZenohSettings.loopback(None, [port])) as session:
            session.declare_subscriber(detections_key(ROBOT), collect)
            announced = announce_source(session, ROBOT, TENSOR)  # the detector subscribes to announced robots
            wait_for_subscriber(session, tensor_key(ROBOT))
            # serving, not merely subscribed: its health token comes once it has settled its robots
            assert wait_for(lambda: bool(service_pids(session, "detector")), 60), "the detector never came up"
            session.put(tensor_key(ROBOT), encode_message(message))
            assert wait_for(lambda: bool(answers), 60), "no detections came back"
            announced.undeclare()
    finally:
        detector.terminate()
        log, _ = detector.communicate(timeout=30)
    assert len(answers) == 1, log.decode(errors="replace")[-3000:]
    answer = answers[0]
    assert answer.seq == 2 and answer.detections
    # the default's file or its -batch variant, as the detector's batch setting picks
    assert answer.model_id in {file_model_id(SHIPPED_MODEL), file_model_id(SHIPPED_BATCH_MODEL)}
