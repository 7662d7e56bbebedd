"""The network family: YOLOv8 at the paper's scale ``n`` and a lighter ``p`` ("pico").

The 64×384 three-channel scan image is sparse and small, and YOLOv8n has more channels than it needs:
``p`` is the same graph from Ultralytics' own ``yolov8.yaml`` at half the width (depth 0.33, width
0.125, 0.9 M parameters against 3.0 M). Nothing is hand-written: the architecture file is
Ultralytics' with one scale entry added, so the ``p`` model trains, exports and decodes exactly like
``n``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, get_args

Arch = Literal["n", "p"]
ARCHS: tuple[str, ...] = get_args(Arch)
DEFAULT_ARCH: Arch = "n"  # the paper's YOLOv8n
# Ultralytics' scale triple: depth multiple, width multiple, max channels.
EXTRA_SCALES: dict[str, tuple[float, float, int]] = {"p": (0.33, 0.125, 1024)}


def model_name(arch: str) -> str:
    """``yolov8n``, ``yolov8p``: the name model ids and files carry (``triscan-yolov8p-zero.onnx``)."""
    check_arch(arch)
    return f"yolov8{arch}"


def check_arch(arch: str) -> Arch:
    if arch not in ARCHS:
        raise ValueError(f"arch must be one of {ARCHS}, got {arch!r}")
    return arch  # type: ignore[return-value]


def model_yaml(arch: str, directory: Path) -> str:
    """What to hand ``YOLO()`` for a new model of ``arch``.

    Ultralytics' own scales (``n``) are named directly (``yolov8n.yaml``). Another scale is written to
    ``directory/yolov8<arch>.yaml``: Ultralytics' ``yolov8.yaml`` whose ``scales`` hold that entry
    alone, which Ultralytics then picks (it reads a scale letter from the file name only for
    n/s/m/l/x, and otherwise takes the first scale listed).
    """
    check_arch(arch)
    if arch not in EXTRA_SCALES:
        return f"{model_name(arch)}.yaml"
    import ultralytics
    from ultralytics.utils import YAML

    base = Path(ultralytics.__file__).parent / "cfg" / "models" / "v8" / "yolov8.yaml"
    spec = YAML.load(base)
    spec["scales"] = {arch: list(EXTRA_SCALES[arch])}
    directory.mkdir(parents=True, exist_ok=True)
    target = directory / f"{model_name(arch)}.yaml"
    YAML.save(target, spec)
    return str(target)


def network_of_checkpoint(weights: Path) -> str:
    """``yolov8n`` or ``yolov8p``: the network an Ultralytics checkpoint was built from (its model YAML's
    file name, which :func:`model_yaml` names after the architecture)."""
    import torch

    checkpoint = torch.load(weights, map_location="cpu", weights_only=False)
    model = checkpoint.get("ema") or checkpoint.get("model")
    yaml_file = getattr(model, "yaml", {}).get("yaml_file") if model is not None else None
    if not yaml_file:
        raise ValueError(f"{weights}: no model YAML recorded, pass the file name (--name)")
    return Path(yaml_file).stem
