"""What a triscan ONNX file declares about itself: the ``triscan.*`` metadata, written and read here.

``triscan export`` records how the model reads scans (padding, invalid-return rule, raster yaw), the
classes it was trained for and whether its boxes snap to the pixel grid, so that a detector or a launcher can
match the encoder to the model, or refuse a model it would misread, before any frame is lost. The
keys are named in :mod:`common.model_spec`; this module is the one place that turns them into values
(:func:`metadata_entries` for the writer, the ``declared_*`` readers for everyone else). Opening a
file to read them is :func:`common.inference.model_facts`' job.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import onnxruntime as ort

from common.encoding import INVALID_RULES, PADDINGS, InvalidRule, Padding, check_raster_yaw
from common.model_spec import (
    BOX_GRIDS,
    CLASS_NAMES,
    DEFAULT_BOX_GRID,
    FURNITURE_CLASSES,
    META_BOX_GRID,
    META_CLASSES,
    META_INVALID,
    META_PADDING,
    META_RASTER_YAW,
    META_STACK_PERIOD,
    BoxGrid,
)


def metadata_entries(
    *,
    padding: str,
    invalid: str,
    box_grid: str,
    classes: Sequence[str],
    stack_period_s: float | None = None,
    raster_yaw_deg: float = 0.0,
) -> dict[str, str]:
    """The ``triscan.*`` entries an exported model carries, as the readers below expect them. A raster
    yaw of 0 (the paper's raster) is written as no entry, as models without the key read."""
    entries = {
        META_PADDING: padding,
        META_INVALID: invalid,
        META_BOX_GRID: box_grid,
        META_CLASSES: json.dumps(list(classes)),
    }
    if stack_period_s is not None:
        entries[META_STACK_PERIOD] = repr(float(stack_period_s))
    if (yaw := check_raster_yaw(raster_yaw_deg)) != 0.0:
        entries[META_RASTER_YAW] = repr(yaw)
    return entries


def declared_raster_yaw(session: ort.InferenceSession, path: Path | str) -> float:
    """Degrees the model's raster is turned by (``triscan.raster_yaw_deg``, :mod:`common.encoding`),
    in ``[0, 360)``; 0, the paper's raster, for a model that does not say."""
    value = session.get_modelmeta().custom_metadata_map.get(META_RASTER_YAW)
    if value is None:
        return 0.0
    try:
        return check_raster_yaw(float(value))
    except ValueError:  # a ScanError too
        raise ValueError(f"{path} declares an invalid {META_RASTER_YAW} {value!r}") from None


def declared_stack_period(session: ort.InferenceSession, path: Path | str) -> float | None:
    """Seconds between the scans the model was trained to stack (``triscan.stack_period_s``); None for
    a model that does not say, whose scans are stacked as they come."""
    value = session.get_modelmeta().custom_metadata_map.get(META_STACK_PERIOD)
    if value is None:
        return None
    try:
        period = float(value)
    except ValueError:
        period = math.nan
    if not period > 0.0 or not math.isfinite(period):
        raise ValueError(f"{path} declares an invalid {META_STACK_PERIOD} {value!r}")
    return period


def _declared(
    session: ort.InferenceSession, path: Path | str, key: str, allowed: tuple[str, ...], absent: str | None
) -> Any:
    """One ``triscan.*`` metadata value of the model, checked against ``allowed``; ``absent`` when the
    model does not have the key (it was exported before the key existed)."""
    value = session.get_modelmeta().custom_metadata_map.get(key, absent)
    if value is not None and value not in allowed:
        raise ValueError(f"{path} declares an unknown {key} {value!r}")
    return value


def declared_padding(session: ort.InferenceSession, path: Path | str) -> Padding | None:
    """The model's ``triscan.padding`` metadata, checked; None for a model without it."""
    return _declared(session, path, META_PADDING, PADDINGS, None)


def declared_box_grid(session: ort.InferenceSession, path: Path | str) -> BoxGrid:
    """The model's ``triscan.box_grid`` (``none`` when absent: models exported before the key)."""
    return _declared(session, path, META_BOX_GRID, BOX_GRIDS, DEFAULT_BOX_GRID)


def declared_invalid_rule(session: ort.InferenceSession, path: Path | str) -> InvalidRule:
    """The model's ``triscan.invalid`` metadata (``sentinel``, the paper's rule, when it does not say)."""
    return _declared(session, path, META_INVALID, INVALID_RULES, "sentinel")


def model_classes(declared: tuple[str, ...] | None, outputs: int, path: Path) -> tuple[str, ...]:
    """The classes a model with ``outputs`` class scores predicts, as it ``declared`` them.

    Class ids are the project's (``CLASS_NAMES``) on the wire, in the viewer and in ROS, so a model
    predicts the first ``outputs`` of them in that order: the paper's four, or those and ``person``.
    A model exported before the metadata existed predicts the paper's four.
    """
    if declared is not None and declared != CLASS_NAMES[: len(declared)]:
        raise ValueError(
            f"{path} was trained for the classes {list(declared)}; triscan's ids are {list(CLASS_NAMES)} "
            "and a model predicts a prefix of them (the class list lives in common/model_spec.py)"
        )
    if declared is None and outputs == len(FURNITURE_CLASSES):
        declared = FURNITURE_CLASSES
    if declared is None or len(declared) != outputs:
        raise ValueError(
            f"{path} predicts {outputs} classes but declares {list(declared or [])}: "
            "re-export it with `triscan export`"
        )
    return declared


def declared_classes(session: ort.InferenceSession) -> tuple[str, ...] | None:
    """The class names the model was trained for (``triscan.classes``); None for a model without them."""
    declared = session.get_modelmeta().custom_metadata_map.get(META_CLASSES)
    return None if declared is None else tuple(json.loads(declared))


def is_end_to_end(session: ort.InferenceSession) -> bool:
    """Whether Ultralytics exported the model with its NMS inside (``end2end``): its output is final
    boxes, not the raw detect head this project post-processes."""
    return str(session.get_modelmeta().custom_metadata_map.get("end2end", "")).lower() == "true"


def is_free_dimension(dim: object) -> bool:
    """ONNX Runtime reports a symbolic dimension as its name (a str) and an unnamed one as None."""
    return dim is None or isinstance(dim, str)


class ModelFacts(NamedTuple):
    """What a triscan ONNX file says about itself, read without running it."""

    padding: Padding  # ``zero`` for a model that does not say
    invalid: InvalidRule  # ``sentinel`` for a model that does not say
    takes_batches: bool  # a free batch axis (a ``-batch`` file)
    stack_period_s: float | None = None  # seconds between stacked scans; None: as they come
    raster_yaw_deg: float = 0.0  # degrees the raster is turned by (common.encoding); 0: the paper's

    @classmethod
    def of_session(cls, session: ort.InferenceSession, path: Path | str) -> ModelFacts:
        shape = session.get_inputs()[0].shape
        return cls(
            padding=declared_padding(session, path) or "zero",
            invalid=declared_invalid_rule(session, path),
            takes_batches=bool(shape) and is_free_dimension(shape[0]),
            stack_period_s=declared_stack_period(session, path),
            raster_yaw_deg=declared_raster_yaw(session, path),
        )

    def encoder_flags(self) -> list[str]:
        """``python -m services.encoder`` flags that make its tensors this model's: padding, invalid-return
        rule, stacking period and raster yaw (a detector refuses tensors that do not match)."""
        return [
            *("--padding", self.padding, "--invalid", self.invalid),
            *(("--stack-period-s", repr(self.stack_period_s)) if self.stack_period_s else ()),
            *(("--raster-yaw", repr(self.raster_yaw_deg)) if self.raster_yaw_deg else ()),
        ]
