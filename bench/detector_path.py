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

Two more stages are a lever measured, not taken: the ``postprocess`` stage with the class choice
and the NMS moved into the model's graph (ONNX ``NonMaxSuppression`` after the network,
:func:`with_nms_in_graph`) and only the gather, clipping, snapping and seam merge left in Python
(:func:`boxes_from_selected`). The ONNX spec leaves open in which order the NMS takes boxes of equal
score, where the detector takes the earlier anchor first as torchvision does:
``postprocess_in_graph_ranked`` ranks each class's candidates with ``TopK`` first, whose spec does
order equal values by index, so the result is torchvision's whatever the runtime;
``postprocess_in_graph`` feeds the NMS the scores and relies on ONNX Runtime's own order (the
anchor's, in every tie ``tests/test_bench_detector_path.py`` builds). Each variant's boxes are
compared with the Python post-processing's on every recorded frame (``nms_in_graph_frames_equal``).

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
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Final

import numpy as np
import onnxruntime as ort

from bench.harness import add_detector_model_argument, recorded_scans
from bench.machine import MachineInfo, machine_info
from bench.model_input import contiguous_input
from bench.report import write_report
from common.encoding import to_model_input
from common.inference import OnnxDetector, session_options
from common.messages import StackedTensor, decode_message, encode_message
from common.postprocess import (
    PostprocessSettings,
    detections_from_boxes,
    finish_kept_boxes,
    xywh_rows_to_xyxy,
)
from services.detector.batch_cap import check_batch, detector_model_and_batch
from services.detector.core import DetectorCore, default_workers
from services.encoder.core import EncoderCore

log = logging.getLogger(__spec__.name if __spec__ else __name__)  # the import path, also with -m

DEFAULT_OUT: Final[Path] = Path(__file__).resolve().parent / "results" / "detector_path.json"
SCANS: Final[int] = 60  # recorded scans: 58 distinct tensors, cycled through
STAGES: Final[tuple[str, ...]] = ("network", "model_input", "postprocess", "detections", "payload")
# Measured beside the chain: the postprocess stage with the NMS inside the graph.
NMS_IN_GRAPH: Final[str] = "postprocess_in_graph"
NMS_IN_GRAPH_RANKED: Final[str] = "postprocess_in_graph_ranked"
NMS_IN_GRAPH_STAGES: Final[dict[str, bool]] = {NMS_IN_GRAPH: False, NMS_IN_GRAPH_RANKED: True}  # → rank_ties
SELECTED_OUTPUT: Final[str] = "selected"

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
    # The lever: median over rounds of (postprocess − postprocess_in_graph) CPU per frame, in ms, and on
    # how many recorded frames the two gave the same boxes, scores and classes.
    nms_in_graph_saved_cpu_ms_per_frame: dict[str, float] = field(default_factory=dict)
    nms_in_graph_frames_equal: dict[str, list[int]] = field(default_factory=dict)  # stage → [equal, frames]
    # p50 µs of each piece alone on one thread: "back_to_back" (caches hot, as bench.hot_path's warm
    # figure) and "after_session_run" (each call right after a session.run of another frame, as in
    # the detector).
    piece_p50_us: dict[str, dict[str, float]] = field(default_factory=dict)
    machine: MachineInfo = field(default_factory=machine_info)


def float32_at_most(value: float) -> np.float32:
    """The float32 ``f`` for which ``iou > f`` (float32) holds exactly when ``iou > value`` (double).

    ONNX Runtime compares its float32 IoU with a float32 threshold, torchvision and the detector with a
    double one: ``float32(0.3)`` lies above 0.3, so an IoU of exactly ``float32(0.3)`` is above 0.3 for
    them but not above ``float32(0.3)``. The float32 just below fixes that; ``float32(0.45)`` already
    lies below 0.45 and stays.
    """
    nearest = np.float32(value)
    return nearest if float(nearest) <= value else np.nextafter(nearest, np.float32(-np.inf))


def with_nms_in_graph(model: Path, out: Path, settings: PostprocessSettings, *, rank_ties: bool) -> Path:
    """``model`` with the class choice and the NMS after its raw output ``[N, 4 + nc, A]``, to ``out``.

    A second output, ``selected`` (``int64[M, 3]``: frame, class, anchor), holds the anchors ONNX
    Runtime's ``NonMaxSuppression`` keeps, class by class, among each anchor's best class (the first of
    equal scores, as ``numpy.argmax``) scoring above ``conf_threshold``. The spec does not say in which
    order the NMS takes boxes of equal score; with ``rank_ties`` it is not fed the scores but each
    class's candidates ranked by ``TopK``, whose spec puts the lower index first among equal values:
    distinct ranks in torchvision's order (score, then anchor). No cap here: the detector caps after
    dropping non-finite boxes. The lever measured here, not a shipped format (bench/README.md, "The
    NMS inside the graph").
    """

    import onnx
    from onnx import TensorProto, helper, numpy_helper

    graph_model = onnx.load(str(model))
    graph = graph_model.graph
    raw = graph.output[0]
    dims = raw.type.tensor_type.shape.dim
    classes, anchors = dims[1].dim_value - 4, dims[2].dim_value
    constants = {
        "nms_0": np.array([0], np.int64),
        "nms_4": np.array([4], np.int64),
        "nms_end": np.array([4 + classes], np.int64),
        "nms_axis1": np.array([1], np.int64),
        "nms_anchors": np.array([anchors], np.int64),
        "nms_class_ids": np.arange(classes, dtype=np.int64).reshape(1, classes, 1),
        "nms_zero": np.array(0.0, np.float32),
        "nms_iou": np.array([float32_at_most(settings.iou_threshold)], np.float32),
    }
    if rank_ties:
        constants |= {
            "nms_conf": np.array(settings.conf_threshold, np.float32),  # compared as decode_yolov8 does
            # Rank A for a class's best candidate down to 1: exact in float32, all above the 0 threshold.
            "nms_ranks": np.arange(anchors, 0, -1, dtype=np.float32).reshape(1, 1, anchors),
            "nms_no_score_threshold": np.array([0.0], np.float32),
        }
    else:
        constants["nms_conf_threshold"] = np.array([settings.conf_threshold], np.float32)  # > conf
    graph.initializer.extend(numpy_helper.from_array(value, name) for name, value in constants.items())
    node = helper.make_node
    graph.node.extend(
        [
            node("Slice", [raw.name, "nms_0", "nms_4", "nms_axis1"], ["nms_xywh_rows"]),
            node("Transpose", ["nms_xywh_rows"], ["nms_xywh"], perm=[0, 2, 1]),
            node("Slice", [raw.name, "nms_4", "nms_end", "nms_axis1"], ["nms_scores"]),
            node("ArgMax", ["nms_scores"], ["nms_best"], axis=1, keepdims=1),
            node("Equal", ["nms_class_ids", "nms_best"], ["nms_is_best"]),
            node("Where", ["nms_is_best", "nms_scores", "nms_zero"], ["nms_best_scores"]),
        ]
    )
    if rank_ties:
        graph.node.extend(
            [
                node("Greater", ["nms_best_scores", "nms_conf"], ["nms_candidate"]),
                node("TopK", ["nms_best_scores", "nms_anchors"], ["nms_sorted", "nms_order"], axis=2),
                node("Shape", ["nms_best_scores"], ["nms_shape"]),
                node("Expand", ["nms_ranks", "nms_shape"], ["nms_rank_rows"]),
                node("ConstantOfShape", ["nms_shape"], ["nms_unranked"]),
                node("ScatterElements", ["nms_unranked", "nms_order", "nms_rank_rows"], ["nms_rank"], axis=2),
                node("Where", ["nms_candidate", "nms_rank", "nms_zero"], ["nms_candidate_rank"]),
            ]
        )
        nms_scores, score_threshold = "nms_candidate_rank", "nms_no_score_threshold"
    else:
        nms_scores, score_threshold = "nms_best_scores", "nms_conf_threshold"
    graph.node.append(
        node(
            "NonMaxSuppression",
            ["nms_xywh", nms_scores, "nms_anchors", "nms_iou", score_threshold],
            [SELECTED_OUTPUT],
            center_point_box=1,
        )
    )
    graph.output.append(helper.make_tensor_value_info(SELECTED_OUTPUT, TensorProto.INT64, ["selected", 3]))
    onnx.save(graph_model, str(out))
    return out


def boxes_from_selected(
    raw: np.ndarray, selected: np.ndarray, frame: int, settings: PostprocessSettings
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What ``postprocess`` returns for ``raw[frame]``, from the graph's ``selected`` rows: gather,
    order by score then anchor (the Python NMS's order), drop non-finite boxes, cap, clip, snap and
    merge seam copies. A frame with NaN or infinity in its raw output, which only a broken model gives,
    goes through the Python post-processing, whose decode drops such anchors before its NMS."""
    output = raw[frame]
    if not np.isfinite(output).all():
        return settings.postprocess(raw[frame : frame + 1])
    rows = selected[selected[:, 0] == frame]
    class_ids, anchors = rows[:, 1], rows[:, 2]
    scores = output[4 + class_ids, anchors]
    order = np.lexsort((anchors, -scores))
    class_ids, anchors, scores = class_ids[order], anchors[order], scores[order]
    boxes = xywh_rows_to_xyxy(output[:4, anchors])
    finite = np.isfinite(boxes).all(axis=1)  # x ± w/2 can still overflow
    keep = np.flatnonzero(finite)[: settings.max_detections]
    return finish_kept_boxes(
        boxes[keep],
        scores[keep],
        class_ids[keep].astype(np.int64),
        padding=settings.padding,
        box_grid=settings.box_grid,
    )


class DetectorPath:
    """The recorded frames in every form a stage starts from, and each stage's call per worker."""

    def __init__(self, model: Path, workers: int, batch: int) -> None:
        self.detectors = [OnnxDetector(model, intra_op_threads=1) for _ in range(workers)]
        self.core = DetectorCore(self.detectors[0])
        check_batch(batch, self.core.detector.batched, model)
        self.batch = batch
        self.settings = self.core.detector.postprocessing
        encoder = EncoderCore(self.core.detector.padding, invalid=self.core.detector.invalid)
        tensors = [t for scan in recorded_scans(SCANS) if (t := encoder.push(scan)) is not None]
        self.payloads = [encode_message(t) for t in tensors]
        self.tensors: list[StackedTensor] = [decode_message(p, StackedTensor) for p in self.payloads]
        for detector in self.detectors:
            detector.warmup(batch)
        # Per in-graph stage, one session per worker.
        self.nms_sessions: dict[str, list[ort.InferenceSession]] = {}
        with tempfile.TemporaryDirectory(prefix="triscan-detector-path-") as scratch:
            for stage, rank_ties in NMS_IN_GRAPH_STAGES.items():
                nms_model = with_nms_in_graph(
                    model, Path(scratch) / f"{stage}.onnx", self.settings, rank_ties=rank_ties
                )
                self.nms_sessions[stage] = [
                    ort.InferenceSession(
                        str(nms_model), session_options(1), providers=["CPUExecutionProvider"]
                    )
                    for _ in range(workers)
                ]
        self.nms_input = self.nms_sessions[NMS_IN_GRAPH][0].get_inputs()[0].name

    def nms_in_graph_boxes(self, stage: str, worker: int, frames: np.ndarray) -> list[tuple[np.ndarray, ...]]:
        """An in-graph ``stage``'s boxes for a batch of model inputs, one tuple per frame."""
        raw, selected = self.nms_sessions[stage][worker].run(None, {self.nms_input: frames})
        return [boxes_from_selected(raw, selected, frame, self.settings) for frame in range(len(frames))]

    def frames_equal_with_nms_in_graph(self, stage: str) -> list[int]:
        """[frames whose boxes, scores and classes ``stage`` reproduces bit for bit, frames]."""
        detector, equal = self.detectors[0], 0
        for stacked in self.tensors:
            expected = detector.detect_boxes(stacked.tensor)[:3]
            got = self.nms_in_graph_boxes(stage, 0, to_model_input(stacked.tensor))[0]
            equal += all(np.array_equal(a, b) for a, b in zip(expected, got, strict=True))
        return [equal, len(self.tensors)]

    def call(self, stage: str, worker: int) -> Call:
        """``stage``'s work on ``batch`` frames, the ``i``-th call of ``worker``."""
        detector, core, batch = self.detectors[worker], self.core, self.batch
        count = len(self.tensors)
        offset = worker * 7  # workers start at different frames, as robots' scans differ

        def picks(i: int) -> list[int]:
            return [(i * batch + k + offset) % count for k in range(batch)]

        def model_input(i: int) -> np.ndarray:
            return contiguous_input([self.tensors[k].tensor for k in picks(i)])  # as the detector does

        # The network stage's inputs, converted beforehand: only session.run is timed.
        inputs = [model_input(i) for i in range(count)] if stage == "network" else []

        def network(i: int) -> object:
            return detector._run(inputs[i % count])

        def with_model_input(i: int) -> object:
            return detector._run(model_input(i))

        def with_postprocess(i: int) -> object:
            return detector._boxes_many([self.tensors[k].tensor for k in picks(i)])

        def with_postprocess_in_graph(i: int) -> object:
            return self.nms_in_graph_boxes(stage, worker, model_input(i))

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
            **{in_graph: with_postprocess_in_graph for in_graph in NMS_IN_GRAPH_STAGES},
        }
        return calls[stage]

    def piece_p50_us(self, calls: int) -> dict[str, dict[str, float]]:
        """Each piece of the path alone on one thread: p50 µs back to back and right after a
        ``session.run`` of another frame (untimed), which is how the detector runs it."""
        detector, core, count = self.detectors[0], self.core, len(self.tensors)
        inputs = [to_model_input(t.tensor) for t in self.tensors]
        outputs = [detector._run(model_input)[0] for model_input in inputs]
        boxes = [self.settings.postprocess(output) for output in outputs]
        messages = [core.detect_many([tensor], detector)[0] for tensor in self.tensors]
        pieces: dict[str, Call] = {
            "model_input": lambda k: to_model_input(self.tensors[k].tensor),
            "postprocess": lambda k: self.settings.postprocess(outputs[k]),
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
) -> DetectorPathReport:
    path = DetectorPath(model, workers, batch)
    report = DetectorPathReport(model.name, workers, batch, seconds, rounds)
    report.nms_in_graph_frames_equal = {
        stage: path.frames_equal_with_nms_in_graph(stage) for stage in NMS_IN_GRAPH_STAGES
    }
    schedule = (*STAGES, *NMS_IN_GRAPH_STAGES)
    for round_index in range(rounds):
        shift = round_index % len(schedule)
        for stage in schedule[shift:] + schedule[:shift]:  # rotated: no stage always follows the same one
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
    summarise(report)
    if piece_calls:
        report.piece_p50_us = path.piece_p50_us(piece_calls)
    return report


def summarise(report: DetectorPathReport) -> None:
    def per_round(stage: str, metric: str) -> np.ndarray:
        runs = sorted((r for r in report.runs if r.stage == stage), key=lambda r: r.round)
        return np.array([getattr(r, metric) for r in runs], dtype=np.float64)

    for stage in (*STAGES, *NMS_IN_GRAPH_STAGES):
        report.frames_per_s[stage] = round(float(np.median(per_round(stage, "frames_per_s"))), 1)
        report.cpu_ms_per_frame[stage] = round(float(np.median(per_round(stage, "cpu_ms_per_frame"))), 3)
    for before, stage in itertools.pairwise(STAGES):
        added = per_round(stage, "cpu_ms_per_frame") - per_round(before, "cpu_ms_per_frame")
        report.added_cpu_ms_per_frame[stage] = round(float(np.median(added)), 3)
    first, last = STAGES[0], STAGES[-1]
    report.path_over_network_cpu = round(
        float(np.median(per_round(last, "cpu_ms_per_frame") / per_round(first, "cpu_ms_per_frame"))), 3
    )
    report.path_share_of_network_frames_per_s = round(
        float(np.median(per_round(last, "frames_per_s") / per_round(first, "frames_per_s"))), 3
    )
    for in_graph in NMS_IN_GRAPH_STAGES:
        saved = per_round("postprocess", "cpu_ms_per_frame") - per_round(in_graph, "cpu_ms_per_frame")
        report.nms_in_graph_saved_cpu_ms_per_frame[in_graph] = round(float(np.median(saved)), 3)


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
