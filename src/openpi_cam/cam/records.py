"""What one explained inference becomes on disk, shared by the live side channel and offline explanation."""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from typing import Any

import numpy as np

from openpi_cam.cam.run_format import IMAGE_INPUT, CameraMeta, Reliance, SpotCheck, StepMeta, StepRecord
from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.image_tools import client_frame_uint8, unit_to_uint8
from openpi_cam.model.observation import uint8_to_model
from openpi_cam.monitor.stream import StepScore
from openpi_cam.policies.family import Explanation
from openpi_cam.policies.policy import InferenceTrace
from openpi_cam.vocabulary import EXTRA_PREFIX, ExplainOptions, SaveFrames

_ARRAY_KEY = re.compile(r"[A-Za-z0-9_.\-/]+")


def split_extra(obs: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """(the observation without `cam_extra/` keys, those values keyed without the prefix). Anything but a mapping
    passes through unchanged, for the policy to refuse by name."""
    if not isinstance(obs, Mapping):
        return obs, {}
    extra = {k[len(EXTRA_PREFIX) :]: v for k, v in obs.items() if isinstance(k, str) and k.startswith(EXTRA_PREFIX)}
    if not extra:
        return obs, extra
    return {k: v for k, v in obs.items() if not (isinstance(k, str) and k.startswith(EXTRA_PREFIX))}, extra


def jsonable(value: Any) -> Any:
    """A client value (numpy scalar or array) as plain JSON data for the step metadata."""
    arr = np.asarray(value)
    return arr.item() if arr.ndim == 0 else arr.tolist()


def is_extra_array(key: str, value: Any) -> bool:
    """Whether a `cam_extra/` value is stored as an array in the step file (`extra/<key>`): a numeric array (not a
    scalar) under a key an npz member can safely be named after."""
    return (
        isinstance(value, np.ndarray)
        and value.ndim >= 1
        and value.dtype.kind in "biuf"
        and len(key) <= 200
        and _ARRAY_KEY.fullmatch(key) is not None
        and all(part not in ("", ".", "..") for part in key.split("/"))
    )


def split_extra_values(extra: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """(the values for meta["extra"] as JSON data, the numeric arrays for the step file) of `cam_extra/` values."""
    arrays = {k: v for k, v in extra.items() if is_extra_array(k, v)}
    return {k: jsonable(v) for k, v in extra.items() if k not in arrays}, arrays


def _stored_size(key: str, value: Any) -> int:
    if is_extra_array(key, value):
        return value.nbytes + len(key)
    return len(json.dumps(jsonable(value), default=str)) + len(key)


def bounded_extra(
    extra: dict[str, Any], max_value_bytes: int, max_total_bytes: int
) -> tuple[dict[str, Any], list[str]]:
    """The `cam_extra/` values that fit: each at most `max_value_bytes` and together at most `max_total_bytes` as
    stored (an array's bytes, other values' JSON text; in key order), and the keys dropped for exceeding them (their
    names cut to 60 characters)."""
    kept, dropped, total = {}, [], 0
    for key, value in extra.items():
        # No value takes less than one byte per element (per character for text) as stored: a too large one is
        # refused before it is converted or encoded (each conversion would copy it again).
        least = len(value) if isinstance(value, str | bytes) else np.size(value)
        size = max_value_bytes + 1 if least > max_value_bytes else _stored_size(key, value)
        if size > max_value_bytes or total + size > max_total_bytes:
            dropped.append(key[:60])
            continue
        kept[key], total = value, total + size
    return kept, dropped


def model_frame_uint8(image: Any) -> np.ndarray:
    """The model's input image ([-1, 1] float, batch row 0) back as uint8 RGB (exact for uint8-derived inputs)."""
    x = np.asarray(image, np.float32)
    return unit_to_uint8(((x[0] if x.ndim == 4 else x) + 1.0) / 2.0)


def model_inputs(trace: InferenceTrace, frames: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The explained call's non-image model inputs and raw output (batch row 0): with the model frames (`frames`,
    `model_frame_uint8` of each camera) they are what re-running the explained score needs (`openpi-cam
    faithfulness`)."""
    obs = trace.observation
    inputs = {"output": np.asarray(trace.output), **{k: np.asarray(v) for k, v in trace.sample_inputs.items()}}
    for name in ("state", "tokenized_prompt", "tokenized_prompt_mask", "token_ar_mask"):
        value = getattr(obs, name)
        if value is not None:
            inputs[name] = np.asarray(value)[0]
    for camera, image in obs.images.items():
        # A model image the uint8 model frame does not hold exactly (LeRobot resizes in float) is kept as it is.
        x = np.asarray(image, np.float32)[0]
        if not np.array_equal(np.asarray(uint8_to_model(frames[camera])), x):
            inputs[IMAGE_INPUT + camera] = x
    return inputs


def step_record(
    trace: InferenceTrace,
    explanation: Explanation,
    *,
    connection: str,
    step: int,
    timestamp: float,
    save_frames: SaveFrames,
    extra: Mapping[str, Any],
    explain_ms: float,
    check: SpotCheck | None = None,
    reliance: Reliance | None = None,
    monitor: StepScore | None = None,
) -> StepRecord:
    """The logger record of one explained inference, in the layout docs/FORMAT.md describes; `extra`: the client's
    `cam_extra/` values (numeric arrays go to the step file, the rest to `StepMeta.extra`); `check`: its spot check
    (`cam.spot_check`), stored as `StepMeta.check` when given; `reliance` (`cam.reliance`) as `StepMeta.reliance`;
    `monitor`: the call's failure-monitor score with its inputs (`monitor/...` arrays)."""
    extra_values, extra_arrays = split_extra_values(extra)
    frames, client_inputs = {}, {}
    if save_frames in ("raw", "both"):  # what replaying the step needs: the client's frames and its other values
        frames = {c: client_frame_uint8(im) for c, im in trace.raw_images.items() if im is not None}
        client_inputs = {k: v for k, v in trace.client_inputs.items() if is_extra_array(k, v)}
    model_frames = {c: model_frame_uint8(im) for c, im in trace.observation.images.items()}
    cameras = {
        c: CameraMeta.from_json(
            {
                "obs_key": trace.camera_sources.get(c),
                **info,
                "geometry": trace.geometry[c].as_dict() if trace.geometry.get(c) is not None else None,
            }
        )
        for c, info in explanation.cameras.items()
    }
    meta = StepMeta(
        target=explanation.target,
        score=explanation.score,
        map_kinds=tuple(explanation.maps),
        prompt=trace.prompt,
        cameras=cameras,
        malformed=trace.malformed_reason,
        explain_ms=round(explain_ms, 3),
        extra=extra_values,
        extra_arrays=tuple(sorted(extra_arrays)),  # stored as `extra/<key>` in the step file
        check=check,
        reliance=reliance,
        details=dict(explanation.details),
    )
    return StepRecord(
        connection,
        step,
        timestamp,
        explanation.maps,
        frames=frames,
        model_frames=model_frames if save_frames in ("model", "both") else {},
        inputs=model_inputs(trace, model_frames),
        meta=meta.to_json(),
        extra_arrays=extra_arrays,
        client_inputs=client_inputs,
        monitor={} if monitor is None else monitor.arrays(),
    )


def resume_mismatch(
    recorded_model: Mapping[str, Any], recorded_options: Mapping[str, Any], model: ModelSpec, options: ExplainOptions
) -> list[str]:
    """What differs between the model and explanation options a run or maps dataset recorded and those of new steps
    to add to it: the one list of what must match to resume (runs and maps datasets alike)."""
    return model.mismatch(recorded_model) + options.mismatch(recorded_options)
