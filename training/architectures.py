"""The network family: YOLOv8 at the paper's scale ``n`` and a lighter ``p`` ("pico").

The 64×384 three-channel scan image is sparse and small, and YOLOv8n has more channels than it needs:
``p`` is the same graph from Ultralytics' own ``yolov8.yaml`` at half the width (depth 0.33, width
0.125, 0.9 M parameters against 3.0 M). Nothing is hand-written: the architecture file is
Ultralytics' with one scale entry added, so the ``p`` model trains, exports and decodes exactly like
``n``.

Each scale can also be built with ReLU instead of YOLOv8's SiLU (Ultralytics' own ``activation`` key
in the model YAML). SiLU is ``x·sigmoid(x)``: two more nodes after every conv, which ONNX Runtime runs
as a lookup and a multiply in INT8 (a quarter of the pico INT8 graph's node time) while ReLU folds
into the conv itself; docs/benchmarks.md (activation_speed) has what each costs.

The Detect head's box branch can also be built with fewer DFL bins (Ultralytics' ``reg_max`` key, 16 by
default). Its convs are ``max(16, P3 channels / 4, 4 · bins)`` wide at every stride, whatever the
network's width: 64 channels at 16 bins, four times the pico's own stride-8 stage, and so the largest
single cost of the pico network. 8 bins halve that branch; a box edge may then lie at most 7 strides
from its anchor (56 px at stride 8, 224 px at stride 32, where the 384-px-wide image's largest objects
go), and the edge within that range is still the bins' continuous expectation, not rounded to one.
12 bins are the middle ground (48 channels, 11 strides: 88 px at stride 8).
docs/benchmarks.md (activation_speed) has what each costs.
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
DFL_BINS: tuple[int, ...] = (16, 12, 8)  # the box branch's distribution bins per edge (Ultralytics' reg_max)
DEFAULT_DFL_BINS = 16  # Ultralytics' and the paper's


def model_name(arch: str) -> str:
    """``yolov8n``, ``yolov8p``: the name model ids and files carry (``triscan-yolov8p-zero.onnx``)."""
    check_arch(arch)
    return f"yolov8{arch}"


def network_name(arch: str, activation: str = DEFAULT_ACTIVATION, dfl_bins: int = DEFAULT_DFL_BINS) -> str:
    """``yolov8p``, ``yolov8p-relu``, ``yolov8p-relu-dfl8``: the architecture with a non-default
    activation and DFL bin count, as checkpoints, model YAMLs and exported files are named
    (:func:`network_of_checkpoint` reads it back)."""
    check_activation(activation)
    parts = [model_name(arch)]
    if activation != DEFAULT_ACTIVATION:
        parts.append(activation)
    if tag := dfl_bins_tag(dfl_bins):
        parts.append(tag)
    return "-".join(parts)


def dfl_bins_tag(dfl_bins: int) -> str:
    """``dfl8``: how a name marks a non-default DFL bin count (empty for Ultralytics' 16)."""
    check_dfl_bins(dfl_bins)
    return "" if dfl_bins == DEFAULT_DFL_BINS else f"dfl{dfl_bins}"


def parse_network_name(name: str) -> tuple[Arch, Activation, int]:
    """The inverse of :func:`network_name`: ``yolov8p-relu-dfl8`` → ``("p", "relu", 8)``."""
    stem, *rest = name.split("-")
    arch = stem.removeprefix("yolov8")
    activation, dfl_bins = DEFAULT_ACTIVATION, DEFAULT_DFL_BINS
    if rest and rest[0] in ACTIVATIONS:
        activation = rest.pop(0)
    bins_by_tag = {dfl_bins_tag(bins): bins for bins in DFL_BINS if bins != DEFAULT_DFL_BINS}
    if rest and rest[0] in bins_by_tag:
        dfl_bins = bins_by_tag[rest.pop(0)]
    if (
        not stem.startswith("yolov8")
        or arch not in ARCHS
        or rest
        or name != network_name(arch, activation, dfl_bins)
    ):
        raise ValueError(f"{name!r} is not a triscan network name (yolov8<arch>[-<activation>][-dfl<bins>])")
    return check_arch(arch), check_activation(activation), dfl_bins


def check_arch(arch: str) -> Arch:
    if arch not in ARCHS:
        raise ValueError(f"arch must be one of {ARCHS}, got {arch!r}")
    return arch  # type: ignore[return-value]


def check_activation(activation: str) -> Activation:
    if activation not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {ACTIVATIONS}, got {activation!r}")
    return activation  # type: ignore[return-value]


def check_dfl_bins(dfl_bins: int) -> int:
    if dfl_bins not in DFL_BINS:
        raise ValueError(f"DFL bins must be one of {DFL_BINS}, got {dfl_bins!r}")
    return dfl_bins


def model_yaml(
    arch: str, directory: Path, activation: str = DEFAULT_ACTIVATION, dfl_bins: int = DEFAULT_DFL_BINS
) -> str:
    """What to hand ``YOLO()`` for a new model of ``arch``.

    Ultralytics' own scales with its own activation (``n``, SiLU) are named directly
    (``yolov8n.yaml``). Anything else is written to ``directory``: Ultralytics' ``yolov8.yaml`` whose
    ``scales`` hold that scale alone, which Ultralytics then picks (it reads a scale letter from the
    file name only for n/s/m/l/x, and otherwise takes the first scale listed), plus the ``activation``
    key for ReLU and the ``reg_max`` key for other DFL bins. The file is named after the network
    (``yolov8p.yaml``, ``yolov8p-relu-dfl8.yaml``), and so are the checkpoint and the exported files
    (:func:`network_of_checkpoint`).
    """
    check_arch(arch)
    check_activation(activation)
    check_dfl_bins(dfl_bins)
    if arch not in EXTRA_SCALES and activation == DEFAULT_ACTIVATION and dfl_bins == DEFAULT_DFL_BINS:
        return f"{model_name(arch)}.yaml"
    import ultralytics
    from ultralytics.utils import YAML

    base = Path(ultralytics.__file__).parent / "cfg" / "models" / "v8" / "yolov8.yaml"
    spec = YAML.load(base)
    spec["scales"] = {arch: list(EXTRA_SCALES.get(arch) or spec["scales"][arch])}
    if activation != DEFAULT_ACTIVATION:
        spec["activation"] = _ACTIVATION_EXPRESSIONS[activation]
    if dfl_bins != DEFAULT_DFL_BINS:
        spec["reg_max"] = dfl_bins
    directory.mkdir(parents=True, exist_ok=True)
    target = directory / f"{network_name(arch, activation, dfl_bins)}.yaml"
    YAML.save(target, spec)
    return str(target)


def network_of_checkpoint(weights: Path) -> str:
    """``yolov8n``, ``yolov8p``, ``yolov8p-relu-dfl8``: the network an Ultralytics checkpoint was built from
    (its model YAML's file name, which :func:`model_yaml` names after the architecture)."""
    import torch

    checkpoint = torch.load(weights, map_location="cpu", weights_only=False)
    model = checkpoint.get("ema") or checkpoint.get("model")
    yaml_file = getattr(model, "yaml", {}).get("yaml_file") if model is not None else None
    if not yaml_file:
        raise ValueError(f"{weights}: no model YAML recorded, pass the file name (--name)")
    return Path(yaml_file).stem
