"""LeRobot pi0 / pi0.5 policy folders, served as LeRobot runs them: its processor pipelines read from the folder's
own files, step by step in the folder's order, around the pi0 / pi0.5 model read from its `model.safetensors`.

A folder is what LeRobot's `save_pretrained` and the processors' `save_pretrained` write: `config.json` (`type`
pi0 / pi05, the features, the chunk size, the normalisation modes), `model.safetensors`, `policy_preprocessor.json`
and `policy_postprocessor.json` with the normaliser statistics each names (`<feature>.<stat>` keys). Which steps
there are, in which order, and where the statistics live differ between LeRobot versions, so nothing is assumed:
each step of the lists is built from its own entry by the builder registered under its LeRobot registry name
(`STEPS`, filled by `register_step` as LeRobot's `ProcessorStepRegistry.register(name=)` fills its registry), and a
step not registered for its pipeline is refused naming it.

Requests carry the checkpoint's own feature names: `observation.images.<name>` (uint8 [H, W, 3] from a robot, or
float [3, H, W] in [0, 1] from a LeRobot dataset), `observation.state`, and the task as `prompt` (openpi-client) or
`task`. Between the steps a request is a flat dict as LeRobot's transition holds it (feature -> array, `task` ->
text); `ModelInputs` then lays it out for the model, and `LeRobotResizeImages` prepares the images as LeRobot's
policy does before SigLIP (`_preprocess_images`: torch's bilinear letterbox, then x * 2 - 1). The response is the
post-processed chunk: `chunk_size` rows of the action feature's dims.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

import jax
import ml_dtypes
import numpy as np
import sentencepiece
from safetensors.numpy import load_file

from openpi_cam.errors import InvalidRequest, load_json, reading
from openpi_cam.image_tools import resize_with_pad_torch_bilinear, unit_to_uint8
from openpi_cam.model.pi0 import MAX_PERIOD, MIN_PERIOD, Pi0
from openpi_cam.policies.checkpoint_format import (
    CONFIG_FILE,
    POSTPROCESSOR_FILE,
    PREPROCESSOR_FILE,
    WEIGHTS_FILE,
    checkpoint_format,
    read_head_counts,
)
from openpi_cam.policies.family import Sampler
from openpi_cam.policies.pi0_family import FlowExplainer, flow_sampler
from openpi_cam.policies.policy import Policy
from openpi_cam.policies.robot import GenericOutputs, lookup
from openpi_cam.tokenizers.fast import huggingface_hub_cache
from openpi_cam.tokenizers.paligemma import PALIGEMMA_HUB_ID, hf_cached_file, load_paligemma_tokenizer
from openpi_cam.tokenizers.pi0 import pad_tokens, pi05_prompt
from openpi_cam.transforms import (
    OUTPUT_CONTEXT,
    DataDict,
    PadStatesAndActions,
    PassActions,
    ResizeImages,
    Transform,
    parse_lerobot_image,
    parse_prompt,
    parse_vector,
)

OBS_STATE = "observation.state"
OBS_IMAGES = "observation.images."
ACTION = "action"
TASK = "task"
TOKENS = "observation.language.tokens"
TOKEN_MASK = "observation.language.attention_mask"
SERVED_TYPES = ("pi0", "pi05")
FAST_TYPES = ("pi0_fast", "pi0fast")  # LeRobot's pi0-FAST (0.5 and later; earlier releases)
NORM_MODES = ("IDENTITY", "MEAN_STD", "MIN_MAX", "QUANTILES", "QUANTILE10")
# The statistics (low, high) each range mode maps onto [-1, 1].
_RANGE_STATS = {"MIN_MAX": ("min", "max"), "QUANTILES": ("q01", "q99"), "QUANTILE10": ("q10", "q90")}


# --------------------------------------------------------------------------------------------------------------------
# The folder's files


@dataclasses.dataclass(frozen=True)
class PolicyFeature:
    """A feature as a policy config declares it (LeRobot's `PolicyFeature`); a dataset's is `lerobot.writer.Feature`."""

    type: str  # VISUAL, STATE, ACTION, ENV, ...
    shape: tuple[int, ...]


def _features(raw: Any, where: str) -> dict[str, PolicyFeature]:
    if not isinstance(raw, Mapping):
        raise ValueError(f"{where}: expected a mapping of features, got {type(raw).__name__}")
    out = {}
    for name, spec in raw.items():
        if not isinstance(spec, Mapping) or "type" not in spec or "shape" not in spec:
            raise ValueError(f"{where}: feature {name!r} needs a type and a shape")
        out[str(name)] = PolicyFeature(str(spec["type"]), tuple(int(d) for d in spec["shape"]))
    return out


@dataclasses.dataclass(frozen=True)
class LeRobotConfig:
    """What serving reads from a LeRobot pi0 / pi0.5 `config.json` (the rest configures training)."""

    type: str
    input_features: dict[str, PolicyFeature]
    output_features: dict[str, PolicyFeature]
    chunk_size: int
    max_state_dim: int
    max_action_dim: int
    num_inference_steps: int
    tokenizer_max_length: int
    image_resolution: tuple[int, int]
    empty_cameras: int
    normalization_mapping: dict[str, str]
    dtype: str

    @classmethod
    def read(cls, path: Path) -> LeRobotConfig:
        where = str(path)
        data = load_json(path)
        kind = data.get("type")
        if kind in FAST_TYPES:
            raise ValueError(
                f"{where}: type {kind!r} is LeRobot's pi0-FAST, which is not served: its processor loads the FAST "
                "tokenizer's code from the Hugging Face Hub, so no reference of it could be made offline"
            )
        if kind not in SERVED_TYPES:
            raise ValueError(f"{where}: type {kind!r} is not served (LeRobot pi0 / pi0.5: {', '.join(SERVED_TYPES)})")
        periods = (data.get("min_period", MIN_PERIOD), data.get("max_period", MAX_PERIOD))
        if periods != (MIN_PERIOD, MAX_PERIOD):
            raise ValueError(f"{where}: time embedding periods {periods} differ from pi0's {(MIN_PERIOD, MAX_PERIOD)}")
        inputs = _features(data.get("input_features", {}), f"{where}: input_features")
        outputs = _features(data.get("output_features", {}), f"{where}: output_features")
        try:
            return cls(
                type=kind,
                input_features=inputs,
                output_features=outputs,
                chunk_size=int(data["chunk_size"]),
                max_state_dim=int(data.get("max_state_dim", 32)),
                max_action_dim=int(data.get("max_action_dim", 32)),
                num_inference_steps=int(data.get("num_inference_steps", 10)),
                tokenizer_max_length=int(data["tokenizer_max_length"]),
                image_resolution=tuple(int(d) for d in data.get("image_resolution", (224, 224))),  # type: ignore[arg-type]
                empty_cameras=int(data.get("empty_cameras", 0)),
                normalization_mapping={str(k): str(v) for k, v in data.get("normalization_mapping", {}).items()},
                dtype=str(data.get("dtype", "float32")),
            )
        except KeyError as e:
            raise ValueError(f"{where}: missing {e.args[0]!r}") from None
        except (AttributeError, TypeError, ValueError) as e:  # a field of another JSON type than LeRobot writes
            raise ValueError(f"{where}: {e}") from None

    @property
    def empty_camera_names(self) -> tuple[str, ...]:
        """The blank cameras LeRobot adds for `empty_cameras` (masked, -1 in the model image)."""
        return tuple(f"{OBS_IMAGES}empty_camera_{i}" for i in range(self.empty_cameras))

    @property
    def cameras(self) -> tuple[str, ...]:
        """The cameras the model reads, in LeRobot's token order: the image features a request brings, in the
        config's order, then the blank ones (LeRobot appends the cameras missing from a batch)."""
        real = [k for k, f in self.input_features.items() if f.type == "VISUAL" and k not in self.empty_camera_names]
        return (*real, *self.empty_camera_names)

    @property
    def real_cameras(self) -> tuple[str, ...]:
        return tuple(c for c in self.cameras if c not in self.empty_camera_names)

    @property
    def state_dim(self) -> int:
        feature = self.input_features.get(OBS_STATE)
        return feature.shape[0] if feature is not None else self.max_state_dim  # LeRobot's default for a missing one

    @property
    def action_dim(self) -> int:
        feature = self.output_features.get(ACTION)
        return feature.shape[0] if feature is not None else self.max_action_dim


@dataclasses.dataclass(frozen=True)
class StepSpec:
    """One entry of a processor pipeline file."""

    name: str  # the registry name (or the class path of an unregistered step)
    config: dict[str, Any]
    state_file: str | None


def read_pipeline(path: Path) -> list[StepSpec]:
    where = str(path)
    data = load_json(path)
    steps = data.get("steps")
    if not isinstance(steps, list):
        raise ValueError(f"{where}: no 'steps' list")
    out = []
    for i, entry in enumerate(steps):
        name = entry.get("registry_name") or entry.get("class") if isinstance(entry, dict) else None
        if not isinstance(name, str):
            raise ValueError(f"{where}: step {i} names no registry_name")
        out.append(StepSpec(name, dict(entry.get("config") or {}), entry.get("state_file")))
    return out


def read_stats(folder: Path, spec: StepSpec, where: str) -> dict[str, dict[str, np.ndarray]]:
    """A normaliser's statistics from the state file it names: `<feature>.<stat>` -> float32 arrays."""
    if spec.state_file is None:
        raise ValueError(f"{where}: step {spec.name} names no state_file with its statistics")
    path = folder / spec.state_file
    if not path.is_file():
        raise FileNotFoundError(f"{where}: step {spec.name}'s statistics {path} are missing")
    stats: dict[str, dict[str, np.ndarray]] = {}
    with reading(path, "safetensors file"):
        tensors = load_file(str(path))
    for key, value in tensors.items():
        feature, _, stat = key.rpartition(".")
        stats.setdefault(feature, {})[stat] = np.asarray(value, np.float32)
    return stats


# --------------------------------------------------------------------------------------------------------------------
# Processor steps (each a transform over the flat request dict)


@dataclasses.dataclass(frozen=True)
class Normalizer:
    """LeRobot's (un)normaliser: per feature type the mode of `modes`, with its formulas and zero-range guards, in
    float32; observation features are (un)normalised where the request has them, the action under `actions`."""

    features: Mapping[str, PolicyFeature]
    modes: Mapping[str, str]  # feature type -> mode
    stats: Mapping[str, Mapping[str, np.ndarray]]
    eps: float
    inverse: bool
    only: frozenset[str] | None = None  # LeRobot's normalize_observation_keys

    def _apply(self, key: str, feature_type: str, x: np.ndarray) -> np.ndarray:
        mode = self.modes.get(feature_type, "IDENTITY")
        if mode == "IDENTITY" or key not in self.stats:
            return x
        s, eps, x = self.stats[key], np.float32(self.eps), np.asarray(x, np.float32)
        if mode == "MEAN_STD":
            return x * s["std"] + s["mean"] if self.inverse else (x - s["mean"]) / (s["std"] + eps)
        low_name, high_name = _RANGE_STATS[mode]
        low = s[low_name]
        denom = s[high_name] - low
        denom = np.where(denom == 0, eps, denom).astype(np.float32)
        if mode == "MIN_MAX":
            return (x + 1) / 2 * denom + low if self.inverse else 2 * (x - low) / denom - 1
        return (x + 1) * denom / 2 + low if self.inverse else 2 * (x - low) / denom - 1

    def __call__(self, data: DataDict) -> DataDict:
        out = dict(data)
        for key, feature in self.features.items():
            if feature.type != "ACTION" and key in out and (self.only is None or key in self.only):
                out[key] = self._apply(key, feature.type, out[key])
        if "actions" in out:  # LeRobot (un)normalises the action as `action` whatever its features list
            out["actions"] = self._apply(ACTION, "ACTION", out["actions"])
        return out


def _normalizer(folder: Path, spec: StepSpec, where: str, *, inverse: bool) -> Normalizer:
    cfg = spec.config
    features = _features(cfg.get("features", {}), f"{where}: step {spec.name} features")
    modes = {str(k): str(v) for k, v in cfg.get("norm_map", {}).items()}
    if unknown := sorted(set(modes.values()) - set(NORM_MODES)):
        raise ValueError(f"{where}: step {spec.name}: normalisation mode {unknown[0]!r} is not LeRobot's")
    stats = read_stats(folder, spec, where)
    for key, feature in features.items():
        mode = modes.get(feature.type, "IDENTITY")
        if mode == "IDENTITY" or key not in stats:
            continue
        needed = ("mean", "std") if mode == "MEAN_STD" else _RANGE_STATS[mode]
        for stat in needed:
            if stat not in stats[key]:
                raise ValueError(f"{where}: {mode} of {key!r} needs {key}.{stat} in {spec.state_file}")
            value = stats[key][stat]
            if feature.type == "VISUAL" and value.ndim == 1:  # LeRobot broadcasts flat image stats per channel
                stats[key][stat] = value = value.reshape(-1, 1, 1)
            elif feature.type != "VISUAL" and value.shape != feature.shape:
                raise ValueError(
                    f"{where}: {key}.{stat} in {spec.state_file} has shape {list(value.shape)}, the feature "
                    f"{list(feature.shape)}"
                )
    only = cfg.get("normalize_observation_keys")
    return Normalizer(
        features, modes, stats, float(cfg.get("eps", 1e-8)), inverse, None if only is None else frozenset(only)
    )


@dataclasses.dataclass(frozen=True)
class Rename:
    """`rename_observations_processor`: observation keys renamed by the map, the others kept."""

    rename_map: Mapping[str, str]

    def __call__(self, data: DataDict) -> DataDict:
        return {self.rename_map.get(k, k): v for k, v in data.items()}


@dataclasses.dataclass(frozen=True)
class Passthrough:
    """Steps without effect on one request here: batching (the policy batches), device placement."""

    name: str

    def __call__(self, data: DataDict) -> DataDict:
        return data


# `device_processor`'s float dtypes (torch's names) as NumPy dtypes.
_FLOAT_DTYPES = {
    "float16": np.float16, "half": np.float16, "float32": np.float32, "float": np.float32,
    "float64": np.float64, "double": np.float64, "bfloat16": ml_dtypes.bfloat16,
}  # fmt: skip


@dataclasses.dataclass(frozen=True)
class CastFloats:
    """`device_processor` with a float dtype: every float array of the request rounded through it, as LeRobot casts
    them (the model then computes in its own dtype)."""

    dtype: str

    def __call__(self, data: DataDict) -> DataDict:
        cast = _FLOAT_DTYPES[self.dtype]
        return {
            k: v.astype(cast).astype(np.float32) if isinstance(v, np.ndarray) and v.dtype.kind == "f" else v
            for k, v in data.items()
        }


@dataclasses.dataclass(frozen=True)
class RelativeActionsStep:
    """`relative_actions_processor`: at inference it only remembers the state it sees (for the postprocessor's
    `absolute_actions_processor`); `mask` says which action dims are relative (LeRobot's `_build_mask`)."""

    enabled: bool
    exclude_joints: tuple[str, ...]
    action_names: tuple[str, ...] | None

    def mask(self, action_dim: int) -> np.ndarray:
        tokens = [str(name).lower() for name in self.exclude_joints if name]
        if not tokens or self.action_names is None:
            return np.ones(action_dim, bool)
        mask = [not any(t == str(n).lower() or t in str(n).lower() for t in tokens) for n in self.action_names]
        return np.asarray((mask + [True] * action_dim)[:action_dim], bool)

    def __call__(self, data: DataDict) -> DataDict:
        if OBS_STATE not in data:
            return data
        context = {**data.get(OUTPUT_CONTEXT, {}), "relative_state": np.asarray(data[OBS_STATE], np.float32)}
        return {**data, OUTPUT_CONTEXT: context}


@dataclasses.dataclass(frozen=True)
class AbsoluteActionsStep:
    """`absolute_actions_processor`: the remembered state added back on the relative dims, when enabled."""

    enabled: bool
    relative: RelativeActionsStep | None

    def __call__(self, data: DataDict) -> DataDict:
        if not self.enabled:
            return data
        actions = np.array(data["actions"], np.float32)
        state = np.asarray(data["relative_state"], np.float32)
        mask = self.relative.mask(actions.shape[-1])  # type: ignore[union-attr]  (checked when built)
        dims = min(len(mask), state.shape[-1])
        actions[..., :dims] += state[:dims] * mask[:dims]
        return {**data, "actions": actions}


@dataclasses.dataclass(frozen=True)
class NewLine:
    """`pi0_new_line_processor`: the task ends with a newline (appended unless present)."""

    def __call__(self, data: DataDict) -> DataDict:
        task = data.get(TASK)
        if isinstance(task, str) and not task.endswith("\n"):
            return {**data, TASK: task + "\n"}
        return data


@dataclasses.dataclass(frozen=True)
class Pi05Prompt:
    """`pi05_prepare_state_tokenizer_processor_step`: the task becomes pi0.5's prompt with the (normalised) state
    discretised into 256 bins."""

    task_key: str = TASK

    def __call__(self, data: DataDict) -> DataDict:
        if OBS_STATE not in data:
            raise InvalidRequest(f"pi0.5 needs '{OBS_STATE}' for its prompt")
        return {**data, self.task_key: pi05_prompt(data[self.task_key], np.asarray(data[OBS_STATE], np.float32))}


@dataclasses.dataclass(frozen=True)
class Tokenize:
    """`tokenizer_processor`: the task with BOS, right-padded with the pad id to `max_length` (truncated), as the
    Hugging Face PaliGemma tokenizer LeRobot calls does with the same SentencePiece model."""

    sp: sentencepiece.SentencePieceProcessor
    max_length: int
    task_key: str = TASK

    def __call__(self, data: DataDict) -> DataDict:
        pad_id = self.sp.pad_id() if self.sp.pad_id() >= 0 else 0
        tokens, mask = pad_tokens(self.sp.encode(data[self.task_key], add_bos=True), self.max_length, pad_id)
        return {**data, TOKENS: tokens, TOKEN_MASK: mask}


# --------------------------------------------------------------------------------------------------------------------
# Around the steps: the request in, the model's layout out


@dataclasses.dataclass(frozen=True)
class LeRobotInputs:
    """A request with the checkpoint's feature names -> the flat dict LeRobot's preprocessor starts from; knows which
    request key feeds each model camera (the keys before the folder's renaming)."""

    cameras: Mapping[str, str | None]  # model camera -> request key (None: a blank camera)
    state_key: str
    state_dim: int
    shapes: Mapping[str, tuple[int, ...]]  # model camera -> declared [C, H, W] (the example's frame sizes)
    default_prompt: str | None = None

    @property
    def camera_sources(self) -> Mapping[str, str | None]:
        return dict(self.cameras)

    def camera_sources_for(self, obs: Mapping[str, Any]) -> dict[str, str | None]:
        return dict(self.cameras)

    def example(self) -> dict[str, Any]:
        """Random uint8 frames at each camera's declared size, a random state and a prompt."""
        rng = np.random.default_rng(0)
        obs: dict[str, Any] = {self.state_key: rng.random(self.state_dim).astype(np.float32), "prompt": "do something"}
        for camera, key in self.cameras.items():
            if key is not None:
                _, h, w = self.shapes[camera]
                obs[key] = rng.integers(256, size=(h, w, 3), dtype=np.uint8)
        return obs

    def __call__(self, data: DataDict) -> DataDict:
        out: DataDict = {key: parse_lerobot_image(lookup(data, key), key) for key in self.cameras.values() if key}
        state = parse_vector(lookup(data, self.state_key), self.state_key, dim=self.state_dim)
        out[self.state_key] = state.astype(np.float32)
        prompt = next((data[k] for k in ("prompt", TASK) if data.get(k) is not None), self.default_prompt)
        if prompt is None:
            raise InvalidRequest("missing 'prompt' (or 'task'), and no default prompt is configured")
        out[TASK] = out["prompt"] = parse_prompt(prompt)
        return out


@dataclasses.dataclass(frozen=True)
class ModelInputs:
    """The preprocessed request in the model's layout: images [H, W, 3] in [0, 1] per model camera (blank ones black,
    at the model's resolution, masked), the normalised state, the tokens."""

    cameras: tuple[str, ...]
    blank: tuple[str, ...]
    resolution: tuple[int, int]

    def __call__(self, data: DataDict) -> DataDict:
        images = {
            c: np.zeros((*self.resolution, 3), np.float32) if c in self.blank else np.moveaxis(data[c], 0, -1)
            for c in self.cameras
        }
        return {
            "image": images,
            "image_mask": {c: np.bool_(c not in self.blank) for c in self.cameras},
            "state": np.asarray(data[OBS_STATE], np.float32),
            "tokenized_prompt": np.asarray(data[TOKENS], np.int32),
            "tokenized_prompt_mask": np.asarray(data[TOKEN_MASK], bool),
            OUTPUT_CONTEXT: dict(data.get(OUTPUT_CONTEXT, {})),
        }


@dataclasses.dataclass(frozen=True)
class LeRobotResizeImages(ResizeImages):
    """LeRobot's image preparation before SigLIP: float images in [0, 1] letterboxed with torch's bilinear
    interpolation (no antialiasing, clamped, centred zero padding), then x * 2 - 1."""

    def client_frame(self, image: np.ndarray) -> np.ndarray:
        return unit_to_uint8(image)

    def resize(self, image: np.ndarray) -> np.ndarray:
        return resize_with_pad_torch_bilinear(image, self.height, self.width) * np.float32(2) - 1


@dataclasses.dataclass(frozen=True)
class ActionDims:
    """The model's chunk cut to the action feature's dims (LeRobot's `predict_action_chunk`), other entries kept."""

    action_dim: int

    def __call__(self, data: DataDict) -> DataDict:
        return {**data, "actions": np.asarray(data["actions"], np.float32)[..., : self.action_dim]}


# --------------------------------------------------------------------------------------------------------------------
# The tokenizer


def resolve_tokenizer(
    folder: Path, tokenizer_name: str | None, override: str | Path | sentencepiece.SentencePieceProcessor | None
) -> sentencepiece.SentencePieceProcessor:
    """`override` (a SentencePiece model), else `tokenizer.model` in the directory the tokenizer step names (relative
    to the folder, or absolute), else in the Hugging Face cache's snapshot of that repository (LeRobot's default is
    PaliGemma's). Nothing is downloaded."""
    if isinstance(override, sentencepiece.SentencePieceProcessor):
        return override
    if override is not None:
        return load_paligemma_tokenizer(override)
    name = tokenizer_name or PALIGEMMA_HUB_ID
    candidates = [folder / name / "tokenizer.model", Path(name).expanduser() / "tokenizer.model"]
    for candidate in candidates:
        if candidate.is_file():
            return load_paligemma_tokenizer(candidate)
    if name.count("/") == 1 and (cached := hf_cached_file(name, "tokenizer.model")) is not None:
        return load_paligemma_tokenizer(cached)
    raise FileNotFoundError(
        f"{folder}: tokenizer {name!r} not found: looked at {candidates[0]}, {candidates[1]} and the Hugging Face "
        f"cache {huggingface_hub_cache()}; pass a SentencePiece model (paligemma_tokenizer=) or copy "
        f"{PALIGEMMA_HUB_ID}'s tokenizer.model to one of those places (nothing is downloaded)"
    )


# --------------------------------------------------------------------------------------------------------------------
# The step registry: each step a pipeline file may name, by LeRobot's registry name (`ProcessorStepRegistry`)

Pipeline = Literal["preprocessor", "postprocessor"]
PIPELINE_FILES: dict[Pipeline, str] = {"preprocessor": PREPROCESSOR_FILE, "postprocessor": POSTPROCESSOR_FILE}


@dataclasses.dataclass(frozen=True)
class StepContext:
    """What building a step may read beside its own entry: the folder (statistics, tokenizer), the pipeline file
    errors name, the PaliGemma tokenizer given, and the steps built before it (the postprocessor's steps follow the
    preprocessor's)."""

    folder: Path
    pipeline: Pipeline
    paligemma_tokenizer: str | Path | sentencepiece.SentencePieceProcessor | None
    before: tuple[Transform, ...]

    @property
    def where(self) -> str:
        return str(self.folder / PIPELINE_FILES[self.pipeline])


StepBuilder = Callable[[StepSpec, StepContext], Transform]


@dataclasses.dataclass(frozen=True)
class RegisteredStep:
    build: StepBuilder
    pipelines: tuple[Pipeline, ...]  # the pipelines the step may stand in


STEPS: dict[str, RegisteredStep] = {}


def register_step(
    *names: str, pipelines: tuple[Pipeline, ...] = ("preprocessor",)
) -> Callable[[StepBuilder], StepBuilder]:
    """Registers a step's builder under LeRobot's registry names for it (as `ProcessorStepRegistry.register(name=)`
    registers LeRobot's own classes): a decorator."""

    def add(build: StepBuilder) -> StepBuilder:
        for name in names:
            if name in STEPS:
                raise ValueError(f"processor step {name!r} is registered twice")
            STEPS[name] = RegisteredStep(build, pipelines)
        return build

    return add


@register_step("rename_observations_processor")
def _rename(spec: StepSpec, ctx: StepContext) -> Transform:
    return Rename(dict(spec.config.get("rename_map") or {}))


@register_step("to_batch_processor")
def _batch(spec: StepSpec, ctx: StepContext) -> Transform:
    return Passthrough(spec.name)


@register_step("device_processor", pipelines=("preprocessor", "postprocessor"))
def _device(spec: StepSpec, ctx: StepContext) -> Transform:
    """Device placement does nothing here; the preprocessor's float dtype rounds the request as LeRobot casts it."""
    dtype = spec.config.get("float_dtype")
    if ctx.pipeline == "postprocessor":
        return Passthrough(spec.name)
    if dtype is not None and dtype not in _FLOAT_DTYPES:
        raise ValueError(f"{ctx.where}: device_processor float_dtype {dtype!r} is not one of torch's")
    return Passthrough(spec.name) if dtype in (None, "float32", "float") else CastFloats(str(dtype))


@register_step("relative_actions_processor")
def _relative(spec: StepSpec, ctx: StepContext) -> Transform:
    names = spec.config.get("action_names")
    return RelativeActionsStep(
        bool(spec.config.get("enabled", False)),
        tuple(spec.config.get("exclude_joints") or ()),
        None if names is None else tuple(names),
    )


@register_step("normalizer_processor")
def _normalize(spec: StepSpec, ctx: StepContext) -> Transform:
    return _normalizer(ctx.folder, spec, ctx.where, inverse=False)


@register_step("unnormalizer_processor", pipelines=("postprocessor",))
def _unnormalize(spec: StepSpec, ctx: StepContext) -> Transform:
    return _normalizer(ctx.folder, spec, ctx.where, inverse=True)


@register_step("pi0_new_line_processor", "smolvla_new_line_processor")
def _new_line(spec: StepSpec, ctx: StepContext) -> Transform:
    return NewLine()


@register_step("pi05_prepare_state_tokenizer_processor_step")
def _pi05_prompt(spec: StepSpec, ctx: StepContext) -> Transform:
    return Pi05Prompt(str(spec.config.get("task_key", TASK)))


@register_step("tokenizer_processor")
def _tokenize(spec: StepSpec, ctx: StepContext) -> Transform:
    cfg = spec.config
    if (cfg.get("padding", "max_length"), cfg.get("padding_side", "right")) != ("max_length", "right"):
        raise ValueError(f"{ctx.where}: step tokenizer_processor pads {cfg.get('padding')!r} on the "
                         f"{cfg.get('padding_side')!r}; served: 'max_length' on the right")  # fmt: skip
    sp = resolve_tokenizer(ctx.folder, cfg.get("tokenizer_name"), ctx.paligemma_tokenizer)
    return Tokenize(sp, int(cfg.get("max_length", 512)), str(cfg.get("task_key", TASK)))


@register_step("absolute_actions_processor", pipelines=("postprocessor",))
def _absolute(spec: StepSpec, ctx: StepContext) -> Transform:
    enabled = bool(spec.config.get("enabled", False))
    relative = next((s for s in ctx.before if isinstance(s, RelativeActionsStep)), None)
    if enabled and (relative is None or not relative.enabled):
        raise ValueError(f"{ctx.where}: absolute_actions_processor is enabled without an enabled relative step")
    return AbsoluteActionsStep(enabled, relative)


def pipeline_steps(
    folder: Path,
    specs: Sequence[StepSpec],
    pipeline: Pipeline,
    *,
    paligemma_tokenizer: str | Path | sentencepiece.SentencePieceProcessor | None = None,
    before: Sequence[Transform] = (),
) -> list[Transform]:
    """A pipeline file's steps as transforms, in the file's order, each built by its registered builder; a step not
    registered for the pipeline is refused naming it."""
    steps: list[Transform] = []
    for spec in specs:
        ctx = StepContext(folder, pipeline, paligemma_tokenizer, (*before, *steps))
        registered = STEPS.get(spec.name)
        if registered is None or pipeline not in registered.pipelines:
            raise ValueError(f"{ctx.where}: processor step {spec.name!r} is not implemented")
        steps.append(registered.build(spec, ctx))
    return steps


# --------------------------------------------------------------------------------------------------------------------
# The policy's parts


def _request_key(feature: str, renames: Sequence[Mapping[str, str]]) -> str:
    """The request key that the preprocessor's renaming turns into `feature`."""
    for rename_map in reversed(renames):
        feature = next((old for old, new in rename_map.items() if new == feature), feature)
    return feature


@dataclasses.dataclass(frozen=True)
class RequestLayout:
    """What a LeRobot folder's requests carry, read from its config and preprocessor alone (no weights): the request
    key of each model camera (None: a blank one), of the state and of the recorded action."""

    config: LeRobotConfig
    camera_sources: dict[str, str | None]
    state_key: str

    @classmethod
    def read(cls, folder: str | Path) -> RequestLayout:
        folder = Path(folder)
        return cls.of(LeRobotConfig.read(folder / CONFIG_FILE), read_pipeline(folder / PREPROCESSOR_FILE))

    @classmethod
    def of(cls, cfg: LeRobotConfig, specs: Sequence[StepSpec]) -> RequestLayout:
        """The layout of a folder's config and preprocessor entries."""
        renames = [dict(s.config.get("rename_map") or {}) for s in specs if s.name == "rename_observations_processor"]
        sources = {c: _request_key(c, renames) for c in cfg.real_cameras} | {c: None for c in cfg.empty_camera_names}
        return cls(cfg, sources, _request_key(OBS_STATE, renames))

    @property
    def dataset_keys(self) -> dict[str, str]:
        """Observation key -> dataset feature for a dataset recorded with the checkpoint's own features: each request
        key is the feature of that name, and `actions` the recorded action."""
        keys = {key: key for key in (*self.camera_sources.values(), self.state_key) if key is not None}
        return keys | ({"actions": ACTION} if ACTION in self.config.output_features else {})


@dataclasses.dataclass(frozen=True)
class LeRobotParts:
    """A LeRobot folder's model and pipelines (`build_lerobot`), which `policy` assembles into its served `Policy`."""

    config: LeRobotConfig
    model: Pi0
    preprocessor: tuple[Transform, ...]  # the request in, then the folder's preprocessor steps: LeRobot's batch
    transforms: tuple[Transform, ...]  # the preprocessor, then the model's layout and image preparation
    output_transforms: tuple[Transform, ...]
    sample: Sampler
    explainer: FlowExplainer
    decoder: PassActions
    metadata: dict[str, Any]

    def policy(self, rng: jax.Array | None = None) -> Policy:
        return Policy(
            self.model,
            transforms=self.transforms,
            sample=self.sample,
            decoder=self.decoder,
            explainer=self.explainer,
            output_transforms=self.output_transforms,
            rng=rng,
            metadata=self.metadata,
        )


def create_lerobot_policy(
    folder: str | Path,
    *,
    paligemma_tokenizer: str | Path | sentencepiece.SentencePieceProcessor | None = None,
    dtype: str = "float32",
    default_prompt: str | None = None,
    rng: jax.Array | None = None,
) -> Policy:
    """The served policy of a LeRobot pi0 / pi0.5 folder (`build_lerobot`; `paligemma_tokenizer` None: the
    tokenizer its preprocessor names, then the Hugging Face cache)."""
    parts = build_lerobot(folder, paligemma_tokenizer=paligemma_tokenizer, dtype=dtype, default_prompt=default_prompt)
    return parts.policy(rng)


def build_lerobot(
    folder: str | Path,
    *,
    paligemma_tokenizer: str | Path | sentencepiece.SentencePieceProcessor | None = None,
    dtype: str = "float32",
    default_prompt: str | None = None,
) -> LeRobotParts:
    """The model and the pipelines of a LeRobot pi0 / pi0.5 folder; every file is checked (one line naming what is
    wrong) before the weights are read."""
    folder = Path(folder)
    if (kind := checkpoint_format(folder)) != "lerobot":
        raise ValueError(f"{folder} is an OpenPI checkpoint ({kind}), not a LeRobot policy folder")
    cfg = LeRobotConfig.read(folder / CONFIG_FILE)
    pre_specs, post_specs = read_pipeline(folder / PREPROCESSOR_FILE), read_pipeline(folder / POSTPROCESSOR_FILE)
    pre = pipeline_steps(folder, pre_specs, "preprocessor", paligemma_tokenizer=paligemma_tokenizer)
    tokenizer = next((s for s in pre if isinstance(s, Tokenize)), None)
    if tokenizer is None:
        raise ValueError(f"{folder / PREPROCESSOR_FILE}: no tokenizer_processor step")
    if tokenizer.max_length != cfg.tokenizer_max_length:
        # LeRobot builds the tokenizer step from the config's value, so folders that disagree were edited by hand:
        # which length the model was trained with cannot be told.
        raise ValueError(
            f"{folder / CONFIG_FILE}: tokenizer_max_length {cfg.tokenizer_max_length}, but "
            f"{folder / PREPROCESSOR_FILE}'s tokenizer_processor pads to max_length {tokenizer.max_length}"
        )
    post = pipeline_steps(folder, post_specs, "postprocessor", before=pre)
    if cfg.image_resolution[0] != cfg.image_resolution[1]:
        raise ValueError(f"{folder / CONFIG_FILE}: image_resolution {cfg.image_resolution} is not square")
    model = Pi0.from_safetensors(
        folder / WEIGHTS_FILE,
        dtype=dtype,
        heads=read_head_counts(folder),
        action_horizon=cfg.chunk_size,
        max_token_len=tokenizer.max_length,
        num_steps=cfg.num_inference_steps,
        image_keys=cfg.cameras,
        flow_time="lerobot",
    )
    where = str(folder / CONFIG_FILE)
    if model.family != cfg.type:
        raise ValueError(f"{where}: type {cfg.type!r}, but {folder / WEIGHTS_FILE} holds a {model.family} model")
    if model.config.image_resolution != cfg.image_resolution:
        raise ValueError(f"{where}: image_resolution {cfg.image_resolution}, the weights' SigLIP reads "
                         f"{model.config.image_resolution}")  # fmt: skip
    if (cfg.max_state_dim, cfg.max_action_dim) != (model.config.action_dim,) * 2:
        raise ValueError(f"{where}: max_state_dim {cfg.max_state_dim} / max_action_dim {cfg.max_action_dim}, the "
                         f"weights' projections take {model.config.action_dim}")  # fmt: skip
    if cfg.action_dim > cfg.max_action_dim or cfg.state_dim > cfg.max_state_dim:
        raise ValueError(f"{where}: state {cfg.state_dim} / action {cfg.action_dim} dims exceed the model's 32")
    layout = RequestLayout.of(cfg, pre_specs)
    shapes = {c: cfg.input_features[c].shape for c in cfg.real_cameras}
    inputs = LeRobotInputs(layout.camera_sources, layout.state_key, cfg.state_dim, shapes, default_prompt)
    preprocessor = (inputs, *pre)
    transforms = (
        *preprocessor,
        ModelInputs(cfg.cameras, cfg.empty_camera_names, cfg.image_resolution),
        LeRobotResizeImages(*cfg.image_resolution),
        PadStatesAndActions(cfg.max_state_dim),
    )
    outputs = (ActionDims(cfg.action_dim), *post, GenericOutputs(cfg.action_dim))
    metadata = {
        "lerobot": {
            "type": cfg.type,
            "cameras": list(cfg.real_cameras),
            "state": layout.state_key,
            "state_dim": cfg.state_dim,
            "action_dim": cfg.action_dim,
            "chunk_size": cfg.chunk_size,
        }
    }
    return LeRobotParts(
        cfg,
        model,
        preprocessor,
        transforms,
        outputs,
        flow_sampler(model),
        FlowExplainer(model),
        PassActions(),
        metadata,
    )
