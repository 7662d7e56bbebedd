"""The detector's ONNX Runtime session: a stacked tensor in, wire detections and stage timings out.

:class:`OnnxDetector` is what the detector service, ``triscan eval`` and the benchmarks run, so the
numbers they report come from the same session settings and the same post-processing. It runs on the
robot's base install: numpy and onnxruntime only, no torch, no Ultralytics.

Pipeline for one stacked tensor ``uint8[64, 384, 3]``:

1. ``to_model_input`` (the exact conversion training used) → ``float32[1, 3, 64, 384]``.
2. ONNX Runtime → Ultralytics' raw detect output ``float32[1, 4 + nc, A]``.
3. :mod:`common.postprocess`: decode, NMS, clipping, seam merging, wire ``Detection`` objects.

What a model file declares (padding, invalid rule, raster yaw, classes, box grid) is read by
:mod:`common.model_meta`; a loaded model that this pipeline would misread is refused here.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Final, NamedTuple

import numpy as np
import onnxruntime as ort

from common.encoding import (
    IMAGE_WIDTH,
    PADDINGS,
    RANGE_ROWS,
    STACK_DEPTH,
    InvalidRule,
    Padding,
    to_model_input,
)
from common.messages import Detection, Odometry, StageTimings
from common.model_meta import (
    ModelFacts,
    declared_box_grid,
    declared_classes,
    declared_invalid_rule,
    declared_padding,
    declared_raster_yaw,
    declared_stack_period,
    is_end_to_end,
    is_free_dimension,
    model_classes,
)
from common.model_spec import (
    BOX_GRIDS,
    INPUT_SHAPE,
    MAX_DETECTIONS,
    NUM_ANCHORS,
    PERSON,
    BoxGrid,
    file_model_id,
)
from common.moving_people import DEFAULT_MOTION_CONFIRM, MotionConfirm, confirm_people, still_by_odometry
from common.postprocess import DEFAULT_CONF, DEFAULT_IOU, PostprocessSettings, detections_many

log = logging.getLogger(__name__)

_NS_PER_MS: Final[float] = 1e6


class FrameTimings(NamedTuple):
    """Stage durations of one frame in milliseconds; a plain tuple so hot loops skip validation."""

    encode_ms: float
    inference_ms: float
    nms_ms: float

    def to_message(self) -> StageTimings:
        return StageTimings(encode_ms=self.encode_ms, inference_ms=self.inference_ms, nms_ms=self.nms_ms)


def session_options(
    intra_op_threads: int | None = None, *, optimise: bool = True, spin_wait: bool = True
) -> ort.SessionOptions:
    """The ONNX Runtime options every triscan session uses (detector, export checks, benchmarks).

    Sequential execution and one inter-op thread: the graph is one small chain with nothing to run
    in parallel. ``intra_op_threads`` None lets ONNX Runtime use every core. ``optimise`` False skips
    graph optimisation, for sessions that only read a model's metadata and signature. ``spin_wait``
    False makes the intra-op threads sleep instead of spinning while they wait for work: slower to
    wake, but the cores they would spin on go to the other processes of the pipeline.
    """
    options = ort.SessionOptions()
    options.graph_optimization_level = (
        ort.GraphOptimizationLevel.ORT_ENABLE_ALL if optimise else ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    )
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.inter_op_num_threads = 1
    if intra_op_threads is not None:
        options.intra_op_num_threads = intra_op_threads
    if not spin_wait:
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return options


def load_session(
    path: Path | str, sess_options: ort.SessionOptions, providers: list[str]
) -> ort.InferenceSession:
    """An ONNX Runtime session of ``path``; FileNotFoundError or ValueError in one line (onnxruntime's
    own errors are a zoo of types, with the file name deep inside) when it is missing or not a model."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"ONNX model {path} not found: give --model an existing .onnx file")
    try:
        return ort.InferenceSession(str(path), sess_options=sess_options, providers=providers)
    except Exception as exc:  # onnxruntime raises its own exception zoo for unreadable models
        detail = " ".join(str(exc).split())
        raise ValueError(
            f"{path} is not a loadable ONNX model ({detail}): give --model a file `triscan export` wrote"
        ) from exc


def _unoptimised_session(path: Path | str) -> ort.InferenceSession:
    """A session only to read a model's metadata and signature: no graph optimisation, so it is cheap."""
    return load_session(path, session_options(optimise=False), ["CPUExecutionProvider"])


def model_facts(path: Path | str) -> ModelFacts:
    """Padding, invalid-return rule and batch axis of a model, from one cheap metadata session, so a
    launcher can start the encoder to match the detector's model and refuse a ``--batch`` the model
    cannot run before any process starts."""
    return ModelFacts.of_session(_unoptimised_session(path), path)


def model_class_names(path: Path | str) -> tuple[str, ...]:
    """The classes a model predicts (a prefix of the project's list), from one cheap metadata session,
    so that a launcher can score the loop on the model's own classes without loading it."""
    session = _unoptimised_session(path)
    return model_classes(declared_classes(session), int(session.get_outputs()[0].shape[1]) - 4, Path(path))


def default_providers() -> list[str]:
    """CUDA when this onnxruntime build has it (CPU stays as fallback for unsupported nodes), else CPU."""
    if "CUDAExecutionProvider" in ort.get_available_providers():
        return ["CUDAExecutionProvider", "CPUExecutionProvider"]
    return ["CPUExecutionProvider"]


class OnnxDetector:
    """An exported YOLOv8 detect model in ONNX Runtime, plus :mod:`common.postprocess`.

    One instance per model and process; ``detect`` is not meant to be called from several threads at
    once (ONNX Runtime sessions are thread-safe, but the timings would interleave).
    """

    def __init__(
        self,
        model_path: Path | str,
        *,
        conf_threshold: float = DEFAULT_CONF,
        iou_threshold: float = DEFAULT_IOU,
        max_detections: int = MAX_DETECTIONS,
        padding: Padding | None = None,
        intra_op_threads: int | None = None,
        providers: list[str] | None = None,
        spin_wait: bool = True,
        box_grid: BoxGrid | None = None,
        motion_confirm: MotionConfirm | None = DEFAULT_MOTION_CONFIRM,
    ) -> None:
        """``padding`` defaults to the model's own ``triscan.padding`` metadata (``zero`` if absent);
        asking for the other one than the model was trained with is refused. ``box_grid`` defaults to
        the model's ``triscan.box_grid`` (``none`` if absent); either value may be asked for, as it
        changes only the post-processing. ``spin_wait``: see :func:`session_options`.
        ``motion_confirm``: a model with a person class reports the person candidates below the
        threshold that a still sensor sees walk, and adds people where walking legs have no candidate
        (:mod:`common.moving_people`); None turns it off."""
        path = Path(model_path)
        if not 0.0 <= conf_threshold <= 1.0:
            raise ValueError(f"conf_threshold must lie in [0, 1], got {conf_threshold}")
        if not 0.0 <= iou_threshold <= 1.0:
            raise ValueError(f"iou_threshold must lie in [0, 1], got {iou_threshold}")
        if max_detections < 1:
            raise ValueError(f"max_detections must be >= 1, got {max_detections}")
        if padding is not None and padding not in PADDINGS:
            raise ValueError(f"padding must be one of {PADDINGS}, got {padding!r}")
        if box_grid is not None and box_grid not in BOX_GRIDS:
            raise ValueError(f"box_grid must be one of {BOX_GRIDS}, got {box_grid!r}")
        if intra_op_threads is not None and intra_op_threads < 1:
            raise ValueError(f"intra_op_threads must be >= 1, got {intra_op_threads}")
        self._session = load_session(
            path, session_options(intra_op_threads, spin_wait=spin_wait), providers or default_providers()
        )
        self.model_path = path
        self.model_id = file_model_id(path)
        self.providers: list[str] = self._session.get_providers()
        self._input_name, self._output_names, num_classes, self.num_anchors, batched = self._check_model(path)
        # A free batch axis (the ``-batch`` model files): ``detect_many`` runs several frames per call.
        self.batched: bool = batched
        self.invalid: InvalidRule = declared_invalid_rule(self._session, path)
        # Seconds between the scans the model stacks (None: consecutive, whatever the sensor's rate).
        self.stack_period_s: float | None = declared_stack_period(self._session, path)
        # Degrees the model's raster is turned by (common.encoding): its tensors must be encoded with
        # it, and its boxes' bearings are turned back by it; 0 (the paper's raster) when it does not say.
        self.raster_yaw_deg: float = declared_raster_yaw(self._session, path)
        # The one home of this detector's thresholds, padding, class count and box grid.
        self.postprocessing = PostprocessSettings(
            conf_threshold,
            iou_threshold,
            max_detections,
            self._padding_of_model(path, padding),
            num_classes,
            box_grid or declared_box_grid(self._session, path),
        )
        # Motion confirmation needs a person class; the class it keeps candidates of below the threshold.
        self.motion_confirm = motion_confirm if PERSON in self.class_names else None
        self._person_id = self.class_names.index(PERSON) if self.motion_confirm is not None else -1
        self._low_class: tuple[int, float] | None = None
        if self.motion_confirm is not None and self.motion_confirm.floor < conf_threshold:
            self._low_class = (self._person_id, self.motion_confirm.floor)
        log.info(
            "loaded %s (%d classes, %d anchors, %s) on %s, padding=%s raster yaw=%g box grid=%s conf=%.3g "
            "iou=%.3g",
            self.model_id,
            self.num_classes,
            self.num_anchors,
            "free batch axis" if self.batched else "batch 1",
            ",".join(self.providers),
            self.padding,
            self.raster_yaw_deg,
            self.box_grid,
            conf_threshold,
            iou_threshold,
        )

    @property
    def padding(self) -> Padding:
        """The padding this detector's model was trained with: what its input tensors must use."""
        return self.postprocessing.padding

    @property
    def box_grid(self) -> BoxGrid:
        """Whether box edges are snapped to whole pixels after the NMS (the model's metadata by default)."""
        return self.postprocessing.box_grid

    @property
    def num_classes(self) -> int:
        """Classes the model predicts (:attr:`class_names`); ids are the project's."""
        return len(self.class_names)

    def _padding_of_model(self, path: Path, requested: Padding | None) -> Padding:
        trained = declared_padding(self._session, path)
        if requested is not None and trained is not None and requested != trained:
            raise ValueError(
                f"{path} was trained with {trained!r} padding; running it on {requested!r} tensors would "
                "misplace every object near the seam"
            )
        return requested or trained or "zero"

    def _check_model(self, path: Path) -> tuple[str, list[str], int, int, bool]:
        """Refuse, with the reason, any model this pipeline would misread rather than fail later."""
        if is_end_to_end(self._session):
            raise ValueError(
                f"{path} is an end-to-end (NMS-free) export; "
                "export the raw detect head (nms=False, end2end off)"
            )
        inputs = self._session.get_inputs()
        if len(inputs) != 1:
            raise ValueError(f"{path} must have exactly one input, got {[i.name for i in inputs]}")
        model_input = inputs[0]
        in_shape = list(model_input.shape)
        batch = in_shape[0] if in_shape else 1
        free_batch = is_free_dimension(batch)
        if (
            len(in_shape) != 4
            or not (batch == 1 or free_batch)
            or in_shape[1:] != list(INPUT_SHAPE[1:])
            or model_input.type != "tensor(float)"
        ):
            raise ValueError(
                f"{path} input {model_input.name!r} is {model_input.type}{in_shape}, expected "
                f"tensor(float){list(INPUT_SHAPE)} or a free batch axis in front "
                "(export with `triscan export`, imgsz=(64, 384))"
            )
        output = self._session.get_outputs()[0]
        shape = list(output.shape)
        if (
            len(shape) != 3
            or not all(isinstance(d, int) for d in shape[1:])
            or (not is_free_dimension(shape[0]) if free_batch else shape[0] != 1)
            or shape[1] < 5
        ):
            raise ValueError(
                f"{path} output {output.name!r} has shape {shape}, expected [batch, 4 + nc, anchors]"
            )
        num_classes = shape[1] - 4
        if shape[2] != NUM_ANCHORS:
            raise ValueError(f"{path} has {shape[2]} anchors, a 64×384 YOLOv8 head has {NUM_ANCHORS}")
        self.class_names = model_classes(declared_classes(self._session), num_classes, path)
        return model_input.name, [output.name], num_classes, shape[2], free_batch

    def infer(self, tensor: np.ndarray) -> np.ndarray:
        """Raw model output ``float32[1, 4 + nc, A]`` for a stacked ``uint8[64, 384, 3]`` tensor (any
        model, batch or not)."""
        return self._run(self._model_input(tensor))[0]

    def _model_input(self, tensor: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        if not isinstance(tensor, np.ndarray):
            raise ValueError(f"detector input must be a numpy uint8 array, got {type(tensor).__name__}")
        return to_model_input(tensor, out)  # the exact conversion training used; raises a ValueError

    def _run(self, model_input: np.ndarray) -> tuple[np.ndarray, float]:
        """Raw output for a model input, and the ``session.run`` time in ms."""
        started = time.perf_counter_ns()
        output = self._session.run(self._output_names, {self._input_name: model_input})[0]
        return output, (time.perf_counter_ns() - started) / _NS_PER_MS

    def _boxes_many(
        self, tensors: Sequence[np.ndarray], still: Sequence[bool | None] | None = None
    ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, FrameTimings]]:
        """The one frame pipeline behind every ``detect*`` method: convert, run, post-process.

        Every tensor is converted (and so checked) before anything runs. A batch model runs several
        frames in one ``session.run``, whose whole time each of them reports as ``inference_ms``; their
        frames are converted straight into one batch array, not concatenated afterwards. ``still``
        says per tensor what odometry knows of the sensor's motion over its scans, for motion
        confirmation (:func:`common.moving_people.confirm_people`; None: nothing).
        """
        if not tensors:
            return []
        batch = np.empty((len(tensors), *INPUT_SHAPE[1:]), np.float32) if self.batched else None
        inputs, encode_ms = [], []
        for index, tensor in enumerate(tensors):
            started = time.perf_counter_ns()
            try:
                inputs.append(self._model_input(tensor, None if batch is None else batch[index : index + 1]))
            except ValueError as exc:
                if len(tensors) == 1:
                    raise
                raise ValueError(f"tensor {index} of {len(tensors)}: {exc}") from exc
            encode_ms.append((time.perf_counter_ns() - started) / _NS_PER_MS)
        if batch is not None and len(inputs) > 1:
            outputs, inference_ms = self._run(batch)
            inference = [inference_ms] * len(inputs)
        else:
            runs = [self._run(model_input) for model_input in inputs]
            outputs = np.concatenate([output for output, _ in runs]) if len(runs) > 1 else runs[0][0]
            inference = [ms for _, ms in runs]
        started = time.perf_counter_ns()
        finals = self.postprocessing.postprocess_many(outputs, self._low_class)
        if self.motion_confirm is not None:
            stills = still if still is not None else [None] * len(tensors)
            finals = [
                self._confirmed(tensor, *final, still=frame_still)
                for tensor, final, frame_still in zip(tensors, finals, stills, strict=True)
            ]
        nms_ms = (time.perf_counter_ns() - started) / _NS_PER_MS / len(inputs)  # each frame's share
        return [
            (boxes, scores, class_ids, FrameTimings(frame_encode_ms, frame_inference_ms, nms_ms))
            for (boxes, scores, class_ids), frame_encode_ms, frame_inference_ms in zip(
                finals, encode_ms, inference, strict=True
            )
        ]

    def _confirmed(
        self,
        tensor: np.ndarray,
        boxes: np.ndarray,
        scores: np.ndarray,
        class_ids: np.ndarray,
        *,
        still: bool | None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One frame's boxes after motion confirmation: the person candidates below the threshold that
        it confirmed are kept with their raised score, the others dropped, and the people it added
        appended; highest score first."""
        assert self.motion_confirm is not None
        config = self.motion_confirm
        scores, added = confirm_people(tensor, boxes, scores, class_ids, self._person_id, config, still)
        if len(added) and config.add_score is not None:
            boxes = np.concatenate([boxes, added.astype(boxes.dtype)])
            scores = np.concatenate([scores, np.full(len(added), config.add_score, scores.dtype)])
            class_ids = np.concatenate([class_ids, np.full(len(added), self._person_id, class_ids.dtype)])
        keep = scores > np.float32(self.postprocessing.conf_threshold)
        order = np.flatnonzero(keep)[np.argsort(-scores[keep], kind="stable")]
        order = order[: self.postprocessing.max_detections]
        return boxes[order], scores[order], class_ids[order]

    def still_by_odometry(self, poses: Sequence[Odometry | None]) -> bool | None:
        """What the odometry poses of a tensor's scans (oldest first) tell motion confirmation
        (:func:`common.moving_people.still_by_odometry`): the ``still`` of :meth:`detect_boxes`; None
        when this detector confirms nothing."""
        return None if self.motion_confirm is None else still_by_odometry(poses, self.motion_confirm)

    def detect_boxes(
        self, tensor: np.ndarray, still: bool | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, FrameTimings]:
        """Final boxes (xyxy pixels), scores and class ids, highest score first, and stage timings.

        ``encode_ms`` is only the uint8 → float32 conversion done here (the service adds its raster
        time); ``nms_ms`` covers decode, NMS, clipping, seam merging and motion confirmation, for which
        ``still`` is what odometry says of the sensor over the tensor's scans (None: nothing).
        """
        return self._boxes_many([tensor], [still])[0]

    def detect(self, tensor: np.ndarray) -> tuple[list[Detection], StageTimings]:
        """Wire detections and timings for one tensor; ``nms_ms`` includes building the detections."""
        return self.detect_many([tensor])[0]

    def detect_many(
        self, tensors: Sequence[np.ndarray], still: Sequence[bool | None] | None = None
    ) -> list[tuple[list[Detection], StageTimings]]:
        """:meth:`detect` for several robots' tensors, in one ``session.run`` when the model allows.

        With a batch model (:attr:`batched`, the ``-batch`` files) the frames share one call, which
        costs less per frame than one call each on a CPU; with a fixed
        batch-1 model they run one by one. Each frame's detections equal what :meth:`detect` gives it
        alone. Timings per frame: ``encode_ms`` its own conversion, ``inference_ms`` the whole shared
        call (every frame in the batch waited for all of it), ``nms_ms`` its share of the batch's
        post-processing, which runs for every frame at once.

        Every tensor is checked before anything runs, so one bad tensor raises a ``ValueError`` that
        names its index instead of failing the batch half-way. ``still``: as for :meth:`detect_boxes`,
        one per tensor.
        """
        frames = self._boxes_many(tensors, still)
        if not frames:
            return []
        started = time.perf_counter_ns()
        finals = [(boxes, scores, class_ids) for boxes, scores, class_ids, _ in frames]
        detections = detections_many(finals, self.raster_yaw_deg)
        convert_ms = (time.perf_counter_ns() - started) / _NS_PER_MS / len(frames)  # each frame's share
        return [
            (frame_detections, timings._replace(nms_ms=timings.nms_ms + convert_ms).to_message())
            for frame_detections, (_, _, _, timings) in zip(detections, frames, strict=True)
        ]

    def call_ms_by_batch(self, sizes: Sequence[int], repeats: int = 2) -> dict[int, float]:
        """The fastest of ``repeats`` ``session.run`` calls on blank frames at each batch size, in ms,
        each size run once untimed first (ONNX Runtime plans the memory of a new shape on its first run).
        A network's cost does not depend on what the frames hold."""
        if not self.batched and any(size != 1 for size in sizes):
            raise ValueError(f"{self.model_id} is fixed at batch 1: cannot time batches {list(sizes)}")
        timings = {}
        for size in sizes:
            blank = np.zeros((size, *INPUT_SHAPE[1:]), np.float32)
            self._run(blank)
            timings[size] = min(self._run(blank)[1] for _ in range(repeats))
        return timings

    def warmup(self, max_batch: int = 1) -> None:
        """Run blank frames through the whole path, so the first real frame's timing is honest.

        ONNX Runtime allocates its arenas and plans memory on the first run of each input shape; the
        benchmarks measure after one warm-up. With a batch model every batch size up to ``max_batch`` is run
        once, so the first batch of each size in service does not pay for it.
        """
        if max_batch < 1:
            raise ValueError(f"max_batch must be >= 1, got {max_batch}")
        blank = np.zeros((RANGE_ROWS, IMAGE_WIDTH, STACK_DEPTH), dtype=np.uint8)
        for size in range(1, (max_batch if self.batched else 1) + 1):
            self.detect_many([blank] * size)
