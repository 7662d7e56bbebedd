"""One slice of a training run on a borrowed accelerator host: unpack a packed set, train, hand back files.

Such a host starts bare and is lent by the minute: it gets the repository, Ultralytics' wheels and a
set packed by :mod:`training.dataset_pack`, and it must return a checkpoint that resumes anywhere (on
the CPU machines too, with ``triscan train --resume --resume-from``). So this unpacks the set with
every core, trains with a time budget (:class:`training.train.StopAfterEpoch` stops before an epoch
that would end past it and keeps ``last.pt`` resumable), and copies ``last.pt``, ``best.pt``, the
curve and the summary flat into ``--out``.

``python -m training.remote_train --pack FILE --out DIR --minutes M [--resume-from last.pt] …``
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import time
from pathlib import Path

from training.dataset_pack import unpack
from training.train import TrainConfig, train

log = logging.getLogger(__name__)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m training.remote_train", allow_abbrev=False)
    parser.add_argument("--pack", type=Path, required=True, help="a set packed by training.dataset_pack")
    parser.add_argument("--out", type=Path, required=True, help="where last.pt, best.pt and the curve go")
    parser.add_argument("--minutes", type=float, required=True, help="time budget for training")
    parser.add_argument("--work", type=Path, default=Path("/tmp/triscan-remote"), help="scratch directory")
    parser.add_argument("--run-name", default="run", help="the run directory's name (Ultralytics' name)")
    parser.add_argument("--resume-from", type=Path, help="a resumable last.pt to continue")
    parser.add_argument("--epochs", type=int, required=True)
    parser.add_argument("--batch", type=int, required=True)
    parser.add_argument("--patience", type=int, required=True)
    parser.add_argument("--arch", required=True)
    parser.add_argument("--activation", required=True)
    parser.add_argument("--dfl-bins", type=int, required=True)
    parser.add_argument("--init", type=Path, help="weights to start a new run from")
    parser.add_argument("--unpack-workers", type=int, default=1, help="processes writing the PNGs")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    started = time.monotonic()
    cores = os.cpu_count() or 1
    data = args.work / "data"
    if not (data / "data.yaml").is_file():
        log.info("unpacking %s into %s", args.pack, data)
        log.info("unpacked %d images", unpack(args.pack, data, workers=args.unpack_workers))
    budget_s = args.minutes * 60.0 - (time.monotonic() - started)
    config = TrainConfig(
        data=data / "data.yaml",
        out=args.work / args.run_name,
        epochs=args.epochs,
        batch=args.batch,
        patience=args.patience,
        workers=min(cores, 16),
        arch=args.arch,
        activation=args.activation,
        dfl_bins=args.dfl_bins,
        init=args.init,
        amp=False,
        plots=False,
        cache=True,
    )
    try:
        train(
            config, resume=args.resume_from is not None, resume_from=args.resume_from, stop_after_s=budget_s
        )
    finally:
        args.out.mkdir(parents=True, exist_ok=True)
        for name in ("weights/last.pt", "weights/best.pt", "results.csv", "train_summary.json", "args.yaml"):
            source = config.out / name
            if source.is_file():
                shutil.copyfile(source, args.out / Path(name).name)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
