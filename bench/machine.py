"""The machine a benchmark ran on, recorded next to its figures so that runs can be compared honestly."""

from __future__ import annotations

import os
import platform
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Final

ISA_FLAGS: Final[tuple[str, ...]] = ("avx2", "avx512f", "avx512_vnni", "avx_vnni", "amx_int8")


@dataclass
class MachineInfo:
    """CPU, cores, versions and load: what a reader needs to judge whether two runs compare."""

    cpu_model: str
    isa_flags: list[str]
    logical_cpus: int
    usable_cpus: int
    platform: str
    python: str
    versions: dict[str, str]
    process_nice: int
    loadavg_start: list[float]
    loadavg_end: list[float] = field(default_factory=list)


def _cpuinfo() -> tuple[str, list[str]]:
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return platform.processor() or "?", []
    model, flags = "?", set()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "model name" and model == "?":
            model = value.strip()
        elif key.strip() == "flags" and not flags:
            flags = set(value.split())
    return model, [flag for flag in ISA_FLAGS if flag in flags]


def _version(distribution: str) -> str:
    """The installed version, read from package metadata (importing torch just to ask would cost seconds)."""
    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return "not installed"


def machine_info() -> MachineInfo:
    cpu_model, isa = _cpuinfo()
    return MachineInfo(
        cpu_model=cpu_model,
        isa_flags=isa,
        logical_cpus=os.cpu_count() or 1,
        usable_cpus=len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1,
        platform=platform.platform(),
        python=platform.python_version(),
        versions={m: _version(m) for m in ("numpy", "onnxruntime", "eclipse-zenoh", "torch", "ultralytics")},
        process_nice=os.nice(0),
        loadavg_start=[round(x, 2) for x in os.getloadavg()],
    )
