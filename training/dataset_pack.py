"""A ``triscan dataset`` set as one compact file, to carry it to a training host and unpack it there.

A set is tens of thousands of small PNGs; most of each image is dark. Packed, an image is the list of
its lit pixels (flat column-major index) and a 3-bit mask of the scans that lit each, delta-coded and
compressed with the label lines and the set's metadata files. Unpacking writes the same PNGs
(:func:`training.png.write_rgb_png`), label files, ``data.yaml``, ``summary.json`` and the JSON-lines
files, so a training run on the unpacked set sees exactly the set that was packed.

``python -m training.dataset_pack pack DATASET FILE`` and ``… unpack FILE DIR [--workers N]``.
"""

from __future__ import annotations

import argparse
import io
import logging
import lzma
import multiprocessing
from pathlib import Path

import numpy as np

from common.encoding import IMAGE_WIDTH, RANGE_ROWS, STACK_DEPTH
from training.png import read_tensor_png, write_rgb_png

log = logging.getLogger(__name__)

FORMAT = "triscan-dataset-pack-1"
METADATA_FILES = ("data.yaml", "summary.json", "scenarios.jsonl", "samples.jsonl")
HIT = 255


def encode_image(tensor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lit pixels of a uint8[64, 384, 3] tensor: (flat column-major indices, per-pixel channel bits)."""
    lit = tensor != 0
    if np.any(tensor[lit] != HIT):
        raise ValueError("a packed tensor's pixels must be 0 or 255")
    bits = (lit * (1 << np.arange(STACK_DEPTH))).sum(axis=2).astype(np.uint8)  # [64, 384]
    flat = bits.T.reshape(-1)  # column-major: a column's few lit rows sit together
    index = np.flatnonzero(flat)
    return index.astype(np.uint16), flat[index]


def decode_image(index: np.ndarray, bits: np.ndarray) -> np.ndarray:
    """The tensor back from :func:`encode_image`'s arrays."""
    flat = np.zeros(RANGE_ROWS * IMAGE_WIDTH, dtype=np.uint8)
    flat[index.astype(np.int64)] = bits
    plane = flat.reshape(IMAGE_WIDTH, RANGE_ROWS).T
    channels = [((plane >> c) & 1) * HIT for c in range(STACK_DEPTH)]
    return np.stack(channels, axis=-1).astype(np.uint8)


def pack(dataset: Path, out: Path) -> dict[str, int]:
    """Pack every image and label of ``dataset`` (a ``triscan dataset`` directory) into ``out``."""
    images = sorted((dataset / "images").glob("*/*.png"))
    if not images:
        raise FileNotFoundError(f"{dataset}/images holds no PNGs: is it a `triscan dataset` output?")
    names, counts, indices, bits, labels = [], [], [], [], []
    for path in images:
        index, mask = encode_image(read_tensor_png(path))
        names.append(f"{path.parent.name}/{path.stem}")
        counts.append(len(index))
        # Deltas of a sorted index fit a byte mostly and compress far better than the index itself.
        indices.append(np.diff(index, prepend=np.uint16(0)).astype(np.uint16))
        bits.append(mask)
        label = dataset / "labels" / path.parent.name / f"{path.stem}.txt"
        labels.append(label.read_text() if label.is_file() else "")
    buffer = io.BytesIO()
    np.savez(
        buffer,
        format=np.array(FORMAT),
        names=np.array(names),
        counts=np.array(counts, dtype=np.int32),
        deltas=np.concatenate(indices),
        bits=np.concatenate(bits),
        labels=np.array(labels),
        metadata_names=np.array([n for n in METADATA_FILES if (dataset / n).is_file()]),
        metadata=np.array([(dataset / n).read_text() for n in METADATA_FILES if (dataset / n).is_file()]),
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(lzma.compress(buffer.getvalue(), preset=6))
    log.info("packed %d images of %s into %s (%.1f MB)", len(names), dataset, out, out.stat().st_size / 1e6)
    return {"images": len(names), "bytes": out.stat().st_size}


def _write_share(task: tuple[Path, list[str], list[np.ndarray], list[np.ndarray], list[str]]) -> int:
    out, names, deltas, bits, labels = task
    for done, (name, delta, mask, label) in enumerate(zip(names, deltas, bits, labels, strict=True)):
        if done and done % 10_000 == 0:
            log.info("%d of %d images written", done, len(names))
        split, stem = name.split("/")
        index = np.cumsum(delta, dtype=np.int64)
        write_rgb_png(out / "images" / split / f"{stem}.png", decode_image(index, mask))
        (out / "labels" / split / f"{stem}.txt").write_text(label)
    return len(names)


def unpack(packed: Path, out: Path, workers: int = 1) -> int:
    """Write the set packed in ``packed`` under ``out``; returns the number of images."""
    with np.load(io.BytesIO(lzma.decompress(packed.read_bytes()))) as data:
        if str(data["format"]) != FORMAT:
            raise ValueError(f"{packed} is not a {FORMAT} file")
        # Each lookup in an NpzFile reads its array anew: read every array once.
        names = [str(n) for n in data["names"]]
        counts, all_deltas, all_bits = data["counts"], data["deltas"], data["bits"]
        ends = np.cumsum(counts)
        starts = ends - counts
        deltas = [all_deltas[a:b] for a, b in zip(starts, ends, strict=True)]
        bits = [all_bits[a:b] for a, b in zip(starts, ends, strict=True)]
        labels = [str(t) for t in data["labels"]]
        for name, text in zip(data["metadata_names"], data["metadata"], strict=True):
            out.mkdir(parents=True, exist_ok=True)
            (out / str(name)).write_text(str(text))
    for split in {n.split("/")[0] for n in names}:
        (out / "images" / split).mkdir(parents=True, exist_ok=True)
        (out / "labels" / split).mkdir(parents=True, exist_ok=True)
    shares = [
        (out, names[i::workers], deltas[i::workers], bits[i::workers], labels[i::workers])
        for i in range(workers)
    ]
    if workers == 1:
        return _write_share(shares[0])
    with multiprocessing.get_context("spawn").Pool(workers) as pool:
        return sum(pool.map(_write_share, shares))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m training.dataset_pack", allow_abbrev=False)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("pack", help="pack a data set directory into one file")
    p.add_argument("dataset", type=Path)
    p.add_argument("file", type=Path)
    u = sub.add_parser("unpack", help="write a packed data set back as a directory")
    u.add_argument("file", type=Path)
    u.add_argument("dir", type=Path)
    u.add_argument("--workers", type=int, default=1)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.command == "pack":
        pack(args.dataset, args.file)
    else:
        log.info("unpacked %d images into %s", unpack(args.file, args.dir, args.workers), args.dir)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
