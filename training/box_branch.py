"""A trained Detect head's box branch cut down to fewer DFL bins, so a lighter head starts trained.

The box branch of Ultralytics' YOLOv8 Detect head is, at each stride, ``Conv(x, c2, 3) → Conv(c2, c2,
3) → Conv2d(c2, 4 · bins, 1)`` with ``c2 = max(16, P3 channels / 4, 4 · bins)``: for the pico network
its width follows the bin count alone (64 channels at 16 bins, 48 at 12, 32 at 8). A network with fewer
bins therefore cannot take the trained branch's tensors as they are, and a branch started from random
weights took the grafted 8-bin pico 27 epochs to reach what it reached (README, "Eight DFL bins").

Cut instead, as network slimming prunes channels (Liu et al., 2017): each hidden conv keeps the
``c2`` output channels whose batch-norm scale ``|γ|`` is largest (a channel with a small ``γ`` adds
little after the norm), the next conv reads only those, and the last conv keeps, for each of the four
box edges, its first ``bins`` distribution logits: the DFL then reads an edge as the expectation over
the nearer ``bins`` strides, which is where an edge of a box seen from that anchor lies unless the box
is wider than ``2 · (bins − 1)`` strides (the coarser strides' anchors cover those). Where every dropped
channel is silent, the cut branch gives the trained logits exactly
(``tests/test_box_branch.py``); elsewhere it is a warm start that fine-tuning repairs.
"""

from __future__ import annotations

from typing import Any

EDGES = 4  # a YOLOv8 box is four distances: left, top, right, bottom


def kept_channels(batch_norm: Any, count: int) -> Any:
    """Indices (``torch.long``, ascending) of the ``count`` channels with the largest ``|γ|``."""
    import torch

    scale = batch_norm.weight.detach().abs()
    if not 0 < count <= scale.numel():
        raise ValueError(f"cannot keep {count} of {scale.numel()} channels")
    return torch.sort(torch.topk(scale, count).indices).values


def bin_rows(source_bins: int, target_bins: int) -> Any:
    """Rows of a ``4 · source_bins`` logit conv that hold each edge's first ``target_bins`` bins."""
    import torch

    if not 0 < target_bins <= source_bins:
        raise ValueError(f"cannot cut {source_bins} DFL bins to {target_bins}")
    return torch.cat([edge * source_bins + torch.arange(target_bins) for edge in range(EDGES)])


def _copy_conv_block(source: Any, target: Any, rows: Any, columns: Any) -> None:
    """An Ultralytics ``Conv`` (conv without bias, then batch norm): output ``rows``, input ``columns``."""
    target.conv.weight.copy_(source.conv.weight[rows][:, columns])
    for name in ("weight", "bias", "running_mean", "running_var"):
        getattr(target.bn, name).copy_(getattr(source.bn, name)[rows])
    target.bn.num_batches_tracked.copy_(source.bn.num_batches_tracked)


def narrow_box_branch(source_head: Any, target_head: Any) -> None:
    """Fill ``target_head``'s box branch (``cv2``) from ``source_head``'s, which has as many bins or more.

    Both are Ultralytics ``Detect`` modules over the same neck (same strides and input widths); only
    ``cv2`` is written, in place. Raises ``ValueError`` for heads that do not fit that description.
    """
    import torch

    source_bins, target_bins = int(source_head.reg_max), int(target_head.reg_max)
    if len(source_head.cv2) != len(target_head.cv2):
        raise ValueError(
            f"{len(source_head.cv2)} strides in the source head, {len(target_head.cv2)} in the target"
        )
    rows = bin_rows(source_bins, target_bins)
    with torch.no_grad():
        for source, target in zip(source_head.cv2, target_head.cv2, strict=True):
            first, second, logits = source
            first_t, second_t, logits_t = target
            if first.conv.in_channels != first_t.conv.in_channels:
                raise ValueError(
                    f"box branch reads {first.conv.in_channels} channels in the source, "
                    f"{first_t.conv.in_channels} in the target: not the same neck"
                )
            everything = torch.arange(first.conv.in_channels)
            hidden = kept_channels(first.bn, first_t.conv.out_channels)
            _copy_conv_block(first, first_t, hidden, everything)
            hidden_next = kept_channels(second.bn, second_t.conv.out_channels)
            _copy_conv_block(second, second_t, hidden_next, hidden)
            logits_t.weight.copy_(logits.weight[rows][:, hidden_next])
            logits_t.bias.copy_(logits.bias[rows])
