"""Cutting a trained box branch to fewer DFL bins (``training.box_branch``, ``triscan train --dfl-bins
12 --init <16-bin .pt>``): the cut branch computes exactly what the trained one did where the dropped
channels are silent, and a fine-tune starts from it rather than from random weights."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("ultralytics")

from common.model_spec import PAPER_CHECKPOINT  # noqa: E402
from training.box_branch import EDGES, bin_rows, kept_channels, narrow_box_branch  # noqa: E402

PICO_NECK = (32, 64, 128)  # the pico's P3, P4, P5 widths: what the head's branches read


def _detect_head(bins: int, neck: tuple[int, ...] = PICO_NECK) -> Any:
    from ultralytics.nn.modules.head import Detect

    return Detect(nc=4, reg_max=bins, ch=neck).eval()


def _silence_all_but_the_strongest(head: Any, keep: int, generator: torch.Generator) -> None:
    """Give each hidden batch norm ``keep`` strong channels and zero the others' scale and shift, so
    the dropped channels output SiLU(0) = 0 and the cut branch must reproduce the logits exactly."""
    with torch.no_grad():
        for branch in head.cv2:
            for block in branch[:2]:
                bn = block.bn
                width = bn.weight.numel()
                strong = torch.randperm(width, generator=generator)[:keep]
                bn.weight.zero_()
                bn.bias.zero_()
                bn.weight[strong] = 1.0 + torch.rand(keep, generator=generator)
                bn.bias[strong] = torch.randn(keep, generator=generator) * 0.1
                bn.running_mean.copy_(torch.randn(width, generator=generator) * 0.1)
                bn.running_var.copy_(1.0 + torch.rand(width, generator=generator))


def test_bin_rows_keep_each_edges_nearest_bins() -> None:
    rows = bin_rows(16, 12).tolist()
    assert len(rows) == EDGES * 12
    assert rows[:12] == list(range(12)) and rows[12:24] == list(range(16, 28)) and rows[-1] == 3 * 16 + 11
    assert bin_rows(16, 16).tolist() == list(range(64))
    with pytest.raises(ValueError, match="cannot cut 8 DFL bins to 12"):
        bin_rows(8, 12)


def test_kept_channels_are_the_largest_batch_norm_scales_in_order() -> None:
    bn = torch.nn.BatchNorm2d(6)
    with torch.no_grad():
        bn.weight.copy_(torch.tensor([0.1, -3.0, 0.5, 2.0, -0.2, 1.0]))
    assert kept_channels(bn, 3).tolist() == [1, 3, 5]
    with pytest.raises(ValueError, match="cannot keep 7 of 6 channels"):
        kept_channels(bn, 7)


@pytest.mark.parametrize("bins", [12, 8])
def test_the_cut_branch_gives_the_trained_logits_where_dropped_channels_are_silent(bins: int) -> None:
    generator = torch.Generator().manual_seed(bins)
    source, target = _detect_head(16), _detect_head(bins)
    width = target.cv2[0][0].conv.out_channels
    assert width == 4 * bins < source.cv2[0][0].conv.out_channels == 64
    _silence_all_but_the_strongest(source, width, generator)
    narrow_box_branch(source, target)
    rows = bin_rows(16, bins)
    for level, channels in enumerate(PICO_NECK):
        features = torch.randn(2, channels, 8 >> level, 48 >> level, generator=generator)
        with torch.no_grad():
            expected = source.cv2[level](features)[:, rows]
            got = target.cv2[level](features)
        assert got.shape == expected.shape
        torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)


def test_a_head_over_another_neck_is_refused() -> None:
    with pytest.raises(ValueError, match="not the same neck"):
        narrow_box_branch(_detect_head(16), _detect_head(12, neck=(64, 128, 256)))


def test_a_fine_tune_to_fewer_bins_starts_from_the_cut_trained_branch(tmp_path: Path) -> None:
    """``initial_model`` with ``--dfl-bins 12 --init`` a trained 16-bin network (the paper's YOLOv8n, whose
    box branch is as wide as the pico's): the requested network, every other tensor the trained one's,
    the box branch the trained branch cut (not random weights)."""
    from training.offline import configure_offline
    from training.train import TrainConfig, initial_model

    configure_offline()
    model = initial_model(
        TrainConfig(
            data=tmp_path / "data.yaml", out=tmp_path / "run", arch="n", dfl_bins=12, init=PAPER_CHECKPOINT
        )
    )
    network = model.model
    source = torch.load(PAPER_CHECKPOINT, map_location="cpu", weights_only=False)
    source_network = (source.get("ema") or source["model"]).float()
    head, source_head = network.model[-1], source_network.model[-1]
    assert (head.reg_max, source_head.reg_max, network.yaml["reg_max"]) == (12, 16, 12)
    assert network.names == source_network.names
    tensors, source_tensors = network.state_dict(), source_network.state_dict()
    others = [k for k in source_tensors if not k.startswith(("model.22.cv2", "model.22.dfl"))]
    assert others and all(torch.equal(tensors[k], source_tensors[k]) for k in others)
    for branch, source_branch in zip(head.cv2, source_head.cv2, strict=True):
        hidden = kept_channels(source_branch[1].bn, 48)
        expected = source_branch[2].weight[bin_rows(16, 12)][:, hidden]
        assert torch.equal(branch[2].weight, expected)
