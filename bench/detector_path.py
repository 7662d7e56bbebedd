"""The detector's own work per frame at full load, without Zenoh: what each stage around the network costs.

``bench.fleet_bound`` compares the fleet a detector holds with the network alone on every core, and
its CPU split shows the detector spending more per scan than its network. This bench takes Zenoh,
the encoder and the scan sources out of that picture: in one process, the detector's default
workers (one single-threaded ONNX Runtime session per core, one Python thread each, as
``InferencePipeline`` runs them) process recorded frames back to back, ``--batch`` frames a call (1 by
default), stage by stage, each stage adding one piece of the detector's path to the one before:

* ``network``: ``session.run`` on prepared model inputs (the bound's own work);
* ``model_input``: + the uint8 → float32 model input (``to_model_input``, into one batch array);
* ``postprocess``: + decode, NMS, clipping, snapping and the seam merge (``OnnxDetector._boxes_many``);
* ``detections``: + the wire ``Detection`` objects and the ``Detections`` message with its timings
  (``DetectorCore.detect_many``);
* ``payload``: + decoding and validating the tensor payload as it arrives and encoding the
  ``Detections`` payload that leaves (``DetectorCore.decode`` … ``encode_message``): all the detector
  does per frame except Zenoh's receive and send.

Every round runs each stage for ``--seconds``, the order rotated from round to round; the process's
CPU time over a stage's frames gives its CPU per frame, and the median over rounds of the difference
between a stage and the one before is what that piece costs at full load. A last pass times each
piece alone on one thread, back to back and right after a ``session.run`` of another frame: what the
network's use of the caches does to the Python after it. ``bench.hot_path`` times the services'
Python one frame at a time, back to back and paced at 10 Hz.

    python -m bench.detector_path --out bench/results/detector_path.json
"""

from __future__ import annotations

import argparse
import itertools
import logging
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import numpy as np

from bench.harness import add_detector_model_argument, recorded_scans
from bench.machine import MachineInfo, machine_info
from bench.report import write_report
from common.encoding import to_model_input
from common.inference import (
    OnnxDetector,
    check_batch,
    detections_from_boxes,
    detector_model_and_batch,
    postprocess,
)
from common.messages import StackedTensor, decode_message, encode_message
from common.model_spec import INPUT_SHAPE
from services.detector.core import DetectorCore, default_workers
from services.encoder.core import EncoderCore

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

DEFAULT_OUT: Final[Path] = Path(__file__).resolve().parent / "results" / "detector_path.json"
SCANS: Final[int] = 60  # recorded scans: 58 distinct tensors, cycled through
STAGES: Final[tuple[str, ...]] = ("network", "model_input", "postprocess", "detections", "payload")

Call = Callable[[int], object]  # call index → one call of a stage's work, on ``batch`` frames


@dataclass
class StageRun:
    """One stage in one round: frames over all workers, per second and per CPU second."""

    stage: str
    round: int
    frames: int
    frames_per_s: float
    cpu_ms_per_frame: float


@dataclass
class DetectorPathReport:
    model: str
    workers: int
    batch: int
    seconds_per_stage: float
    rounds: int
    runs: list[StageRun] = field(default_factory=list)
    # Medians over rounds, per stage.
    frames_per_s: dict[str, float] = field(default_factory=dict)
    cpu_ms_per_frame: dict[str, float] = field(default_factory=dict)
    # Median over rounds of (stage − the stage before) CPU per frame: what each piece adds, in ms.
    added_cpu_ms_per_frame: dict[str, float] = field(default_factory=dict)
    # The whole path's CPU per frame over the network's, and its frames/s as a share of the network's.
    path_over_network_cpu: float = 0.0
    path_share_of_network_frames_per_s: float = 0.0
    # p50 µs of each piece alone on one thread: "back_to_back" (caches hot, as bench.hot_path's warm
    # figure) and "after_session_run" (each call right after a session.run of another frame, as in
    # the detector).
    piece_p50_us: dict[str, dict[str, float]] = field(default_factory=dict)
    machine: MachineInfo = field(default_factory=machine_info)


class DetectorPath:
    """The recorded frames in every form a stage starts from, and each stage's call per worker."""

    def __init__(self, model: Path, workers: int, batch: int) -> None:
        self.detectors = [OnnxDetector(model, intra_op_threads=1) for _ in range(workers)]
        self.core = DetectorCore(self.detectors[0])
        check_batch(batch, self.core.detector.batched, model)
        self.batch = batch
        encoder = EncoderCore(self.core.detector.padding, invalid=self.core.detector.invalid)
        tensors = [t for scan in recorded_scans(SCANS) if (t := encoder.push(scan)) is not None]
        self.payloads = [encode_message(t) for t in tensors]
        self.tensors: list[StackedTensor] = [decode_message(p, StackedTensor) for p in self.payloads]
        for detector in self.detectors:
            detector.warmup(batch)

    def call(self, stage: str, worker: int) -> Call:
        """``stage``'s work on ``batch`` frames, the ``i``-th call of ``worker``."""
        detector, core, batch = self.detectors[worker], self.core, self.batch
        count = len(self.tensors)
        offset = worker * 7  # workers start at different frames, as robots' scans differ

        def picks(i: int) -> list[int]:
            return [(i * batch + k + offset) % count for k in range(batch)]

        # The network's input, converted once per call pattern beforehand: only session.run is timed.
        inputs = [
            np.concatenate([to_model_input(self.tensors[k].tensor) for k in picks(i)]) for i in range(count)
        ]

        def network(i: int) -> object:
            return detector._run(inputs[i % count])

        def with_model_input(i: int) -> object:
            frames = np.empty((batch, *INPUT_SHAPE[1:]), np.float32)
            for j, k in enumerate(picks(i)):
                to_model_input(self.tensors[k].tensor, frames[j : j + 1])
            return detector._run(frames)

        def with_postprocess(i: int) -> object:
            return detector._boxes_many([self.tensors[k].tensor for k in picks(i)])

        def with_detections(i: int) -> object:
            return core.detect_many([self.tensors[k] for k in picks(i)], detector)

        def with_payload(i: int) -> object:
            tensors = []
            for k in picks(i):
                tensor = core.decode(self.payloads[k], self.tensors[k].robot_id)
                if tensor is None:
                    raise RuntimeError(f"recorded tensor {k} was rejected: {core.counters.rejected}")
                tensors.append(tensor)
            return [encode_message(message) for message in core.detect_many(tensors, detector)]

        calls: dict[str, Call] = {
            "network": network,
            "model_input": with_model_input,
            "postprocess": with_postprocess,
            "detections": with_detections,
            "payload": with_payload,
        }
        return calls[stage]

    def piece_p50_us(self, calls: int) -> dict[str, dict[str, float]]:
        """Each piece of the path alone on one thread: p50 µs back to back and right after a
        ``session.run`` of another frame (untimed), which is how the detector runs it."""
        detector, core, count = self.detectors[0], self.core, len(self.tensors)
        inputs = [to_model_input(t.tensor) for t in self.tensors]
        outputs = [detector._run(model_input)[0] for model_input in inputs]
        settings = {
            "conf_threshold": detector.conf_threshold,
            "iou_threshold": detector.iou_threshold,
            "max_detections": detector.max_detections,
            "padding": detector.padding,
            "num_classes": detector.num_classes,
            "box_grid": detector.box_grid,
        }
        boxes = [postprocess(output, **settings) for output in outputs]
        messages = [core.detect_many([tensor], detector)[0] for tensor in self.tensors]
        pieces: dict[str, Call] = {
            "model_input": lambda k: to_model_input(self.tensors[k].tensor),
            "postprocess": lambda k: postprocess(outputs[k], **settings),
            "detections": lambda k: detections_from_boxes(*boxes[k]),
            "payload_decode": lambda k: core.decode(self.payloads[k], self.tensors[k].robot_id),
            "payload_encode": lambda k: encode_message(messages[k]),
        }
        result: dict[str, dict[str, float]] = {"back_to_back": {}, "after_session_run": {}}
        for regime, after_run in (("back_to_back", False), ("after_session_run", True)):
            for name, piece in pieces.items():
                times = []
                for i in range(calls):
                    k = i % count
                    if after_run:
                        detector._run(inputs[(k + 3) % count])
                    started = time.perf_counter_ns()
                    piece(k)
                    times.append((time.perf_counter_ns() - started) / 1e3)
                result[regime][name] = round(float(np.median(times)), 1)
            log.info("pieces, %s: p50 µs %s", regime, result[regime])
        return result


def run_stage(path: DetectorPath, stage: str, seconds: float) -> tuple[int, float, float]:
    """Frames, wall seconds and process CPU seconds of every worker running ``stage`` at once."""
    workers = len(path.detectors)
    counts = [0] * workers
    errors: list[BaseException] = []
    go, stop = threading.Barrier(workers + 1), threading.Event()

    def serve(worker: int) -> None:
        call = path.call(stage, worker)
        go.wait()
        done = 0
        try:
            while not stop.is_set():
                call(done)
                done += 1
        except BaseException as exc:  # re-raised in the bench's thread below
            errors.append(exc)
            stop.set()
        counts[worker] = done

    threads = [threading.Thread(target=serve, args=(w,), name=f"{stage}-{w}") for w in range(workers)]
    for thread in threads:
        thread.start()
    go.wait()
    wall0, cpu0 = time.perf_counter(), time.process_time()
    stop.wait(seconds)
    stop.set()
    for thread in threads:
        thread.join()
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    if errors:
        raise errors[0]
    return sum(counts) * path.batch, wall, cpu


def run(
    model: Path,
    workers: int,
    batch: int,
    seconds: float,
    rounds: int,
    piece_calls: int,
    stages: tuple[str, ...] = STAGES,
) -> DetectorPathReport:
    path = DetectorPath(model, workers, batch)
    report = DetectorPathReport(model.name, workers, batch, seconds, rounds)
    for round_index in range(rounds):
        shift = round_index % len(stages)
        for stage in stages[shift:] + stages[:shift]:  # rotated: no stage always follows the same one
            frames, wall, cpu = run_stage(path, stage, seconds)
            if frames == 0:
                raise RuntimeError(f"stage {stage} finished no frame in {seconds} s")
            report.runs.append(
                StageRun(stage, round_index, frames, round(frames / wall, 1), round(cpu / frames * 1e3, 4))
            )
            log.info(
                "round %d %-12s %7.1f frames/s, %.3f ms CPU a frame",
                round_index,
                stage,
                frames / wall,
                cpu / frames * 1e3,
            )
    summarise(report, stages)
    if piece_calls:
        report.piece_p50_us = path.piece_p50_us(piece_calls)
    return report


def summarise(report: DetectorPathReport, stages: tuple[str, ...]) -> None:
    def per_round(stage: str, metric: str) -> np.ndarray:
        runs = sorted((r for r in report.runs if r.stage == stage), key=lambda r: r.round)
        return np.array([getattr(r, metric) for r in runs], dtype=np.float64)

    for stage in stages:
        report.frames_per_s[stage] = round(float(np.median(per_round(stage, "frames_per_s"))), 1)
        report.cpu_ms_per_frame[stage] = round(float(np.median(per_round(stage, "cpu_ms_per_frame"))), 3)
    for before, stage in itertools.pairwise(stages):
        added = per_round(stage, "cpu_ms_per_frame") - per_round(before, "cpu_ms_per_frame")
        report.added_cpu_ms_per_frame[stage] = round(float(np.median(added)), 3)
    first, last = stages[0], stages[-1]
    report.path_over_network_cpu = round(
        float(np.median(per_round(last, "cpu_ms_per_frame") / per_round(first, "cpu_ms_per_frame"))), 3
    )
    report.path_share_of_network_frames_per_s = round(
        float(np.median(per_round(last, "frames_per_s") / per_round(first, "frames_per_s"))), 3
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_detector_model_argument(parser)
    parser.add_argument(
        "--workers", type=int, default=None, help="inference threads (default: the detector's, one per core)"
    )
    parser.add_argument(
        "--batch", type=int, default=1, help="frames per model call (above 1: a -batch model)"
    )
    parser.add_argument("--seconds", type=float, default=5.0, help="seconds per stage per round")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument(
        "--piece-calls",
        type=int,
        default=600,
        help="calls per piece per regime in the one-thread pass (0: skip)",
    )
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    model, _ = detector_model_and_batch(args.model, None)  # the file the detector would load
    report = run(
        model,
        args.workers or default_workers(os.cpu_count()),
        args.batch,
        args.seconds,
        args.rounds,
        args.piece_calls,
    )
    write_report(report, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
