"""``triscan train``: YOLOv8n (or the lighter ``p``) from Ultralytics' yaml with the paper's recipe, offline.

The recipe (:mod:`training.recipe`, ``training/recipes/default.toml``): imgsz 384 with rectangular
batches, no mosaic/mixup/cutmix/copy-paste (they would cut scans apart), flips, AdamW with a cosine
schedule, early stopping on validation fitness. Ultralytics keeps ``best.pt`` by validation fitness;
on top of that a callback watches for the collapse the paper saw after its best epoch and stops the
run when val mAP@0.5 falls far below its best, so a diverged run cannot waste hours. Training resumes
from ``last.pt``.
"""

from __future__ import annotations

import gzip
import json
import logging
import os
import platform
import shlex
import shutil
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from training.architectures import (
    DEFAULT_ACTIVATION,
    DEFAULT_ARCH,
    DEFAULT_DFL_BINS,
    check_activation,
    check_arch,
    check_dfl_bins,
    model_yaml,
    network_name,
    network_of_checkpoint,
    parse_network_name,
)
from training.offline import configure_offline
from training.recipe import SHIPPED_RECIPE, load_recipe

log = logging.getLogger(__name__)

# A run "diverged" when val mAP@0.5 stays below this share of its best for this many epochs in a row.
DIVERGENCE_RATIO = 0.5
DIVERGENCE_EPOCHS = 2
DIVERGENCE_MIN_BEST = 0.3  # only judge runs that have learnt something

_SHIPPED = load_recipe(SHIPPED_RECIPE).train


@dataclass(frozen=True)
class TrainConfig:
    """Arguments of one training run; stored next to its weights so the run can be repeated."""

    data: Path  # data.yaml written by `triscan dataset`
    out: Path  # run directory: weights/best.pt, weights/last.pt, results.csv, train_summary.json
    epochs: int = _SHIPPED.epochs
    batch: int = _SHIPPED.batch
    patience: int = _SHIPPED.patience
    workers: int = _SHIPPED.workers
    device: str = ""  # "" picks the first GPU when there is one, else the CPU
    seed: int = _SHIPPED.seed
    fraction: float = _SHIPPED.fraction  # share of the training images used per epoch (Ultralytics')
    arch: str = DEFAULT_ARCH  # training.architectures: n (the paper's YOLOv8n) or p (pico)
    activation: str = DEFAULT_ACTIVATION  # silu (YOLOv8's) or relu (cheaper in INT8)
    init: Path | None = None  # weights to start from (fine-tuning a shipped .pt), else random
    dfl_bins: int = DEFAULT_DFL_BINS  # the box branch's DFL bins (training.architectures)
    recipe: Path = SHIPPED_RECIPE  # its [train.ultralytics] arguments are this run's
    amp: bool | None = None  # mixed precision: None uses it on a GPU (Ultralytics' check needs its hub)
    plots: bool = True  # Ultralytics' training plots (they need polars)
    cache: bool = False  # hold the decoded training images in RAM (worth it where cores are many)
    lr0: float | None = None  # the peak learning rate; None: the recipe's (a fine-tune may want less)

    def __post_init__(self) -> None:
        check_arch(self.arch)
        check_activation(self.activation)
        check_dfl_bins(self.dfl_bins)

    @property
    def network(self) -> str:
        """The network this run trains, as its files are named (``yolov8p-relu-dfl8``)."""
        return network_name(self.arch, self.activation, self.dfl_bins)

    def network_yaml(self) -> str:
        return model_yaml(self.arch, self.out.resolve(), self.activation, self.dfl_bins)


def network_choices(
    arch: str, init: Path | None, activation: str | None, dfl_bins: int | None
) -> tuple[str, int]:
    """The activation and DFL bins a run trains: those asked for, else those of the ``init`` checkpoint
    when it is one of ``arch`` (a fine-tune of the shipped 12-bin pico stays a 12-bin pico without
    naming its bins), else the defaults. Asking for others than the checkpoint's is a deliberate
    change of network (:func:`initial_model`), never a silent one."""
    found_activation, found_bins = DEFAULT_ACTIVATION, DEFAULT_DFL_BINS
    if init is not None and init.is_file() and (activation is None or dfl_bins is None):
        found_arch, checkpoint_activation, checkpoint_bins = parse_network_name(network_of_checkpoint(init))
        if found_arch == arch:  # another architecture is refused by initial_model, with its reason
            found_activation, found_bins = checkpoint_activation, checkpoint_bins
    return (
        activation if activation is not None else found_activation,
        dfl_bins if dfl_bins is not None else found_bins,
    )


def pick_device(requested: str) -> str:
    if requested:
        return requested
    import torch

    return "0" if torch.cuda.is_available() else "cpu"


def initial_model(config: TrainConfig) -> Any:
    """The Ultralytics model a new run starts from: ``config``'s network with random weights, or the
    weights of ``config.init`` to fine-tune them on new rooms (same classes, same recipe).

    A checkpoint of another architecture than ``arch`` is refused rather than silently trained as what
    it is: the run directory, the card and the exported files would be named after a network the
    weights are not. One of the same architecture with another activation or DFL bin count starts the
    requested network from its weights (e.g. a ReLU pico from a trained SiLU pico): every tensor whose
    shape agrees carries over; a box branch with fewer bins is cut from the trained one
    (:mod:`training.box_branch`), one with more starts afresh.
    """
    from ultralytics import YOLO

    if config.init is None:
        # Architecture only: no pretrained weights exist offline.
        return YOLO(config.network_yaml())
    if not config.init.is_file():
        raise FileNotFoundError(
            f"{config.init} not found: pass an Ultralytics checkpoint (.pt) to start from"
        )
    expected = config.network
    found = network_of_checkpoint(config.init)
    if found == expected:
        return YOLO(str(config.init))
    found_arch, _, found_bins = parse_network_name(found)
    if found_arch != config.arch:
        raise ValueError(
            f"{config.init} holds a {found} network, not {expected}: pass the --arch it was trained with"
        )
    # Same layers, another activation: activations hold no weights, so every tensor carries over and
    # the run starts from the trained features rather than from scratch (SiLU and ReLU agree away
    # from zero). Other DFL bins change only the box branch's widths: Ultralytics copies the tensors
    # whose shapes agree (its ``intersect_dicts``), so the backbone, neck and class branch carry over;
    # fewer bins get the trained branch cut to size first. The network is the requested one, built
    # from its own YAML, and named after it: Ultralytics' trainer builds the network from the loaded
    # model's YAML dict and copies its weights in, so swapping in the requested network's YAML
    # (keeping the class count) is the whole change.
    from ultralytics.nn.tasks import yaml_model_load

    log.info("starting a %s network from the weights of %s (%s)", expected, config.init, found)
    model = YOLO(str(config.init))
    network: Any = model.model  # the loaded DetectionModel (Ultralytics types it loosely)
    spec = yaml_model_load(config.network_yaml())
    spec["nc"] = network.yaml["nc"]
    if config.dfl_bins < found_bins:
        model.model = _with_narrowed_box_branch(network, spec)
        log.info(
            "the box branch has %d DFL bins here, %d there: cut from the trained one (training.box_branch)",
            config.dfl_bins,
            found_bins,
        )
        return model
    if config.dfl_bins > found_bins:
        log.info(
            "the box branch has %d DFL bins here, %d there: it starts from random weights",
            config.dfl_bins,
            found_bins,
        )
    network.yaml = spec
    return model


def _with_narrowed_box_branch(network: Any, spec: dict[str, Any]) -> Any:
    """The network of ``spec`` holding every tensor of the trained ``network``, its box branch cut to the
    fewer bins of ``spec``. Ultralytics' trainer then copies all of it, every shape agreeing."""
    from ultralytics.nn.tasks import DetectionModel

    from training.box_branch import narrow_box_branch

    trained: Any = network.float()
    narrowed: Any = DetectionModel(spec, nc=spec["nc"], verbose=False)
    narrowed.load(trained, verbose=False)  # every tensor whose shape agrees: all but the box branch
    narrow_box_branch(trained.model[-1], narrowed.model[-1])
    narrowed.names = dict(trained.names)
    narrowed.args = getattr(trained, "args", {})
    return narrowed


def recipe(config: TrainConfig, device: str) -> dict[str, Any]:
    """Ultralytics ``train`` arguments: the recipe file's fixed ones plus this run's sizes."""
    fixed = load_recipe(config.recipe).train.ultralytics
    lr0 = fixed["lr0"] if config.lr0 is None else config.lr0
    return {
        **fixed,
        "lr0": lr0,
        "data": str(config.data),
        "epochs": config.epochs,
        "batch": config.batch,
        "patience": config.patience,
        "workers": config.workers,
        "device": device,
        "seed": config.seed,
        "fraction": config.fraction,
        # Ultralytics trains a loaded model from its yaml, discarding the weights, when this is False.
        "pretrained": config.init is not None,
        # Warm-up runs biases at 0.1, a rate meant for SGD from random weights; with AdamW it walks a
        # fine-tune's trained biases far off in the first hundred steps, so a fine-tune keeps lr0.
        **({"warmup_bias_lr": lr0} if config.init is not None else {}),
        # AMP is a GPU feature; on the CPU it only triggers a download check.
        "amp": config.amp if config.amp is not None else device != "cpu",
        "cache": "ram" if config.cache else False,
        "project": str(config.out.parent.resolve()),
        "name": config.out.name,
        "exist_ok": True,
        "plots": config.plots,
        "verbose": True,
    }


class DivergenceWatch:
    """Stops training once val mAP@0.5 has collapsed, as the paper's run did after its epoch 13."""

    def __init__(self) -> None:
        self.best = 0.0
        self.best_epoch = -1
        self.low_epochs = 0
        self.diverged = False

    def __call__(self, trainer: Any) -> None:
        map50 = float(trainer.metrics.get("metrics/mAP50(B)", 0.0))
        if map50 > self.best:
            self.best, self.best_epoch, self.low_epochs = map50, int(trainer.epoch), 0
            return
        if self.best >= DIVERGENCE_MIN_BEST and map50 < DIVERGENCE_RATIO * self.best:
            self.low_epochs += 1
            if self.low_epochs >= DIVERGENCE_EPOCHS:
                log.warning(
                    "val mAP@0.5 %.3f < %.0f%% of best %.3f (epoch %d) for %d epochs: stopping",
                    map50,
                    DIVERGENCE_RATIO * 100,
                    self.best,
                    self.best_epoch + 1,
                    self.low_epochs,
                )
                self.diverged = True
                trainer.stop = True
        else:
            self.low_epochs = 0


class StopAfterEpoch:
    """Ends this invocation after a given epoch, or before an epoch that would end past a time budget,
    while keeping the run's schedule (``--epochs``).

    A CPU run of 30 epochs takes days, and a rented accelerator comes in slices of minutes; stopping at
    epoch N and resuming later follows the same cosine learning-rate curve as one uninterrupted run,
    so two runs stopped at the same epoch compare fairly. Ultralytics strips the optimizer from
    ``last.pt`` when a run ends, which would make it impossible to resume: the full checkpoint is kept
    aside here and put back by :meth:`restore_last`.
    """

    def __init__(self, epoch: int | None = None, seconds: float | None = None) -> None:
        if epoch is not None and epoch < 1:
            raise ValueError(f"stop_after must be >= 1 epoch, got {epoch}")
        if seconds is not None and seconds <= 0:
            raise ValueError(f"the time budget must be positive, got {seconds} s")
        self.epoch = epoch
        self.seconds = seconds
        self.started = time.monotonic()
        self.epoch_ended = self.started
        self.kept: tuple[Path, Path] | None = None

    def _reached(self, epoch: int) -> bool:
        now = time.monotonic()
        longest_epoch, self.epoch_ended = now - self.epoch_ended, now
        if self.epoch is not None and epoch + 1 >= self.epoch:
            return True
        # Stop when the next epoch, as long as this one, would end past the budget.
        return self.seconds is not None and now - self.started + longest_epoch > self.seconds

    def __call__(self, trainer: Any) -> None:
        if self.kept is not None or not self._reached(int(trainer.epoch)):
            return
        log.info("epoch %d reached: stopping this invocation (resume to continue)", int(trainer.epoch) + 1)
        trainer.stop = True
        last = Path(trainer.last)
        if last.is_file():
            kept = last.with_name("last_resumable.pt")
            shutil.copyfile(last, kept)
            self.kept = (kept, last)

    def restore_last(self) -> None:
        """Put the resumable checkpoint (optimizer included) back as ``last.pt``."""
        if self.kept is not None:
            kept, last = self.kept
            kept.replace(last)


def validation_dataset(args: Any, data: dict[str, Any], img_path: str, batch: int | None, stride: int) -> Any:
    """A validation set of the images as they are: 64×384, rectangular batches with no letterbox pad.

    Stock Ultralytics builds rectangular validation batches with half a stride of padding, so our
    64-row images are validated letterboxed to 96 rows with grey bands the network never sees in
    training or at run time. That understated val mAP@0.5 by half (0.47 against 0.96 at epoch 2 of the
    first run) and so steered best-checkpoint selection, early stopping and the divergence watch by a
    distorted figure. Pad 0 validates exactly the tensor the detector gets.
    """
    from ultralytics.data.dataset import YOLODataset
    from ultralytics.utils import colorstr

    return YOLODataset(
        img_path=img_path,
        imgsz=args.imgsz,
        batch_size=batch,
        augment=False,
        hyp=args,
        rect=True,
        cache=args.cache or None,
        single_cls=args.single_cls or False,
        stride=stride,
        pad=0.0,
        prefix=colorstr("val: "),
        task=args.task,
        classes=args.classes,
        data=data,
        fraction=1.0,
    )


def triscan_trainer() -> type:
    """Ultralytics' detection trainer with :func:`validation_dataset` for validation."""
    from ultralytics.models.yolo.detect import DetectionTrainer
    from ultralytics.utils.torch_utils import unwrap_model

    class TriscanTrainer(DetectionTrainer):
        def read_results_csv(self) -> dict[str, list[float]]:
            """The curve so far, as Ultralytics stores it in each checkpoint, read with the standard
            library: Ultralytics reads it with polars, which a training host may not have."""
            import csv

            try:
                with open(self.csv, newline="") as handle:
                    rows = list(csv.DictReader(handle))
            except OSError:
                return {}
            return {key.strip(): [float(row[key]) for row in rows] for key in (rows[0] if rows else {})}

        def build_dataset(self, img_path: str, mode: str = "train", batch: int | None = None) -> Any:
            if mode == "train":
                return super().build_dataset(img_path, mode, batch)
            stride = max(int(unwrap_model(self.model).stride.max()), 32)
            return validation_dataset(self.args, self.data, img_path, batch, stride)

    return TriscanTrainer


def use_all_cores(trainer: Any) -> None:
    """Ultralytics leaves one core free for its loaders (``torch.set_num_threads(cpu_count - 1)``).

    On a 2-core machine that halves training speed, while PNG decoding of 1.5 kB sparse images costs
    almost nothing: give torch every core once the device is chosen.
    """
    if trainer.device.type == "cpu":
        import torch

        torch.set_num_threads(os.cpu_count() or 1)


def _add_callbacks(
    model: Any,
    watch: DivergenceWatch,
    stopper: StopAfterEpoch | None,
    on_epoch_end: Callable[[], None] | None = None,
) -> None:
    model.add_callback("on_fit_epoch_end", watch)
    model.add_callback("on_train_start", use_all_cores)
    if stopper is not None:
        model.add_callback("on_fit_epoch_end", stopper)
    if on_epoch_end is not None:
        model.add_callback("on_fit_epoch_end", lambda trainer: on_epoch_end())


def seed_last_checkpoint(resume_from: Path, last: Path) -> None:
    """Copy a saved resumable checkpoint to ``last``, gunzipping a ``.gz`` one.

    A resumable YOLOv8n checkpoint is about 30 MB, most of it AdamW's two moments per weight, over
    what a repository should track per file; gzipped it is about 27 MB (``gzip -c last.pt >
    training/checkpoints/<run>_last.pt.gz``), and resuming from it needs no other step. A run
    directory without ``results.csv`` gets the curve the checkpoint carries (Ultralytics stores it
    as ``train_results``): Ultralytics would otherwise start the file afresh at the resumed epoch,
    and the run's curve would lose every epoch before it.
    """
    if not resume_from.is_file():
        raise FileNotFoundError(f"{resume_from} not found: no checkpoint to resume from")
    last.parent.mkdir(parents=True, exist_ok=True)
    if resume_from.suffix == ".gz":
        with gzip.open(resume_from, "rb") as src, last.open("wb") as dst:
            shutil.copyfileobj(src, dst)
    else:
        shutil.copyfile(resume_from, last)
    results_csv = last.parent.parent / "results.csv"
    if not results_csv.exists():
        import torch

        curve = torch.load(last, map_location="cpu", weights_only=False).get("train_results") or {}
        if curve:
            columns = list(curve)
            rows = zip(*(curve[c] for c in columns), strict=True)
            results_csv.write_text(
                ",".join(columns) + "\n" + "".join(",".join(f"{v:.6g}" for v in r) + "\n" for r in rows)
            )


def train(
    config: TrainConfig,
    *,
    resume: bool = False,
    resume_from: Path | None = None,
    stop_after: int | None = None,
    stop_after_s: float | None = None,
    on_epoch_end: Callable[[], None] | None = None,
) -> dict[str, Any]:
    """Train (or resume) one run and write ``train_summary.json`` beside its weights.

    ``resume_from`` seeds ``OUT/weights/last.pt`` from a saved checkpoint (e.g. the one committed in
    ``training/checkpoints/``) when the run directory has none, so a run can continue on another
    machine. The data set and run directory are taken from ``config``, not from the paths stored in
    the checkpoint. ``stop_after`` ends this invocation once that epoch (1-based) is done.
    """
    if not config.data.is_file():
        raise FileNotFoundError(f"{config.data} not found: pass the data.yaml written by `triscan dataset`")
    configure_offline()
    from ultralytics import YOLO

    device = pick_device(config.device)
    last = config.out / "weights" / "last.pt"
    watch = DivergenceWatch()
    stopper = (
        StopAfterEpoch(stop_after, stop_after_s)
        if stop_after is not None or stop_after_s is not None
        else None
    )
    started = time.perf_counter()
    if resume and resume_from is not None and not last.is_file():
        seed_last_checkpoint(resume_from, last)
    if resume and last.is_file():
        log.info("resuming from %s", last)
        model = YOLO(str(last))
        _add_callbacks(model, watch, stopper, on_epoch_end)
        model.train(
            trainer=triscan_trainer(),
            resume=True,
            data=str(config.data),
            save_dir=str(config.out.resolve()),
            device=device,
            workers=config.workers,
        )
    else:
        if resume:
            log.info("no %s yet: starting a new run", last)
        model = initial_model(config)
        _add_callbacks(model, watch, stopper, on_epoch_end)
        model.train(trainer=triscan_trainer(), **recipe(config, device))
    if stopper is not None:
        stopper.restore_last()
    elapsed = time.perf_counter() - started
    trainer = model.trainer
    summary = {
        "config": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(config).items()},
        "command": shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "device": device,
        "hardware": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "epochs_run": int(trainer.epoch) + 1,
        "best_epoch_map50": watch.best_epoch + 1,
        "best_map50": watch.best,
        "diverged": watch.diverged,
        "best_fitness": float(trainer.best_fitness or 0.0),
        "wall_time_s_this_invocation": elapsed,
        "best_weights": str(trainer.best),
    }
    (config.out / "train_summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    log.info("training done: %s", summary)
    return summary
