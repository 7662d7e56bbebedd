"""The network family: YOLOv8 at the paper's scale ``n`` and a lighter ``p`` ("pico").

The 64×384 three-channel scan image is sparse and small, and YOLOv8n has more channels than it needs:
``p`` is the same graph from Ultralytics' own ``yolov8.yaml`` at half the width (depth 0.33, width
0.125, 0.9 M parameters against 3.0 M). Nothing is hand-written: the architecture file is
Ultralytics' with one scale entry added, so the ``p`` model trains, exports and decodes exactly like
``n``.

Each scale can also be built with ReLU instead of YOLOv8's SiLU (Ultralytics' own ``activation`` key
in the model YAML). SiLU is ``x·sigmoid(x)``: two more nodes after every conv, which ONNX Runtime runs
as a lookup and a multiply in INT8 (a quarter of the pico INT8 graph's node time) while ReLU folds
into the conv itself; ``python -m bench.activation_speed`` times both, untrained, in turns.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, get_args

Arch = Literal["n", "p"]
ARCHS: tuple[str, ...] = get_args(Arch)
DEFAULT_ARCH: Arch = "n"  # the paper's YOLOv8n
# Ultralytics' scale triple: depth multiple, width multiple, max channels.
EXTRA_SCALES: dict[str, tuple[float, float, int]] = {"p": (0.33, 0.125, 1024)}
Activation = Literal["silu", "relu"]
ACTIVATIONS: tuple[str, ...] = get_args(Activation)
DEFAULT_ACTIVATION: Activation = "silu"  # YOLOv8's own, the paper's
# What Ultralytics' YAML ``activation`` key takes (it evaluates the expression); SiLU is its default.
_ACTIVATION_EXPRESSIONS: dict[str, str] = {"relu": "nn.ReLU()"}


def model_name(arch: str) -> str:
    """``yolov8n``, ``yolov8p``: the name model ids and files carry (``triscan-yolov8p-zero.onnx``)."""
    check_arch(arch)
    return f"yolov8{arch}"


def network_name(arch: str, activation: str = DEFAULT_ACTIVATION) -> str:
    """``yolov8p``, ``yolov8p-relu``: the architecture with a non-default activation, as checkpoints,
    model YAMLs and exported files are named (:func:`network_of_checkpoint` reads it back)."""
    check_activation(activation)
    name = model_name(arch)
    return name if activation == DEFAULT_ACTIVATION else f"{name}-{activation}"


def parse_network_name(name: str) -> tuple[Arch, Activation]:
    """The inverse of :func:`network_name`: ``yolov8p-relu`` → ``("p", "relu")``."""
    stem, _, activation = name.partition("-")
    arch = stem.removeprefix("yolov8")
    if not stem.startswith("yolov8") or arch not in ARCHS or (activation and activation not in ACTIVATIONS):
        raise ValueError(f"{name!r} is not a triscan network name (yolov8<arch>[-<activation>])")
    return check_arch(arch), check_activation(activation or DEFAULT_ACTIVATION)


def check_arch(arch: str) -> Arch:
    if arch not in ARCHS:
        raise ValueError(f"arch must be one of {ARCHS}, got {arch!r}")
    return arch  # type: ignore[return-value]


def check_activation(activation: str) -> Activation:
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {ACTIVATIONS}, got {activation!r}")
    return activation  # type: ignore[return-value]


def model_yaml(arch: str, directory: Path, activation: str = DEFAULT_ACTIVATION) -> str:
    """What to hand ``YOLO()`` for a new model of ``arch``.

    Ultralytics' own scales with its own activation (``n``, SiLU) are named directly
    (``yolov8n.yaml``). Anything else is written to ``directory``: Ultralytics' ``yolov8.yaml`` whose
    ``scales`` hold that scale alone, which Ultralytics then picks (it reads a scale letter from the
    file name only for n/s/m/l/x, and otherwise takes the first scale listed), plus the ``activation``
    key for ReLU. The file is named after the network (``yolov8p.yaml``, ``yolov8p-relu.yaml``), and
    so are the checkpoint and the exported files (:func:`network_of_checkpoint`).
    """
    check_arch(arch)
    check_activation(activation)
    if arch not in EXTRA_SCALES and activation == DEFAULT_ACTIVATION:
        return f"{model_name(arch)}.yaml"
    import ultralytics
    from ultralytics.utils import YAML

    base = Path(ultralytics.__file__).parent / "cfg" / "models" / "v8" / "yolov8.yaml"
    spec = YAML.load(base)
    spec["scales"] = {arch: list(EXTRA_SCALES.get(arch) or spec["scales"][arch])}
    if activation != DEFAULT_ACTIVATION:
        spec["activation"] = _ACTIVATION_EXPRESSIONS[activation]
    directory.mkdir(parents=True, exist_ok=True)
    target = directory / f"{network_name(arch, activation)}.yaml"
    YAML.save(target, spec)
    return str(target)


def network_of_checkpoint(weights: Path) -> str:
    """``yolov8n``, ``yolov8p``, ``yolov8p-relu``: the network an Ultralytics checkpoint was built from
    (its model YAML's file name, which :func:`model_yaml` names after the architecture)."""
    import torch

    checkpoint = torch.load(weights, map_location="cpu", weights_only=False)
    model = checkpoint.get("ema") or checkpoint.get("model")
    yaml_file = getattr(model, "yaml", {}).get("yaml_file") if model is not None else None
    if not yaml_file:
        raise ValueError(f"{weights}: no model YAML recorded, pass the file name (--name)")
    return Path(yaml_file).stem
