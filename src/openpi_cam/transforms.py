"""Upstream OpenPI's inference data transforms, as plain callables over (nested) dicts of numpy arrays.

Each transform takes the dict produced by the previous one and returns the next, with upstream's semantics. Unlike
upstream, anything a client controls is checked where it enters the pipeline (`parse_image`, `parse_vector`,
`parse_prompt`, `require`) and rejected with `InvalidRequest` naming the key and the problem, instead of failing deep
inside numpy, PIL or the model.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol

import numpy as np

from openpi_cam.errors import InvalidRequest
from openpi_cam.image_tools import resize_with_pad_pil
from openpi_cam.letterbox import letterbox_geometry
from openpi_cam.nested import flatten_dict, unflatten_dict
from openpi_cam.normalize import NormStats

DataDict = dict[str, Any]
Transform = Callable[[DataDict], DataDict]


# --------------------------------------------------------------------------------------------------------------------
# Client input checks


def require(data: Mapping[str, Any], key: str) -> Any:
    """``data[key]``, or `InvalidRequest` naming the missing key."""
    if key not in data or data[key] is None:
        present = ", ".join(sorted(map(str, data))) or "none"
        raise InvalidRequest(f"missing observation key '{key}' (keys present: {present})")
    return data[key]


def _as_array(value: Any, key: str) -> np.ndarray:
    try:
        arr = np.asarray(value)
    except (ValueError, TypeError) as e:
        raise InvalidRequest(f"'{key}': cannot be read as an array ({e})") from e
    if arr.dtype == object or arr.dtype.kind in "USV":
        raise InvalidRequest(f"'{key}': expected numbers, got dtype {arr.dtype}")
    return arr


def _check_unit_range(img: np.ndarray, key: str) -> None:
    """A float image's values are finite and in ``[0, 1]``, or `InvalidRequest` says which is not."""
    if not np.all(np.isfinite(img)):
        raise InvalidRequest(f"'{key}': float image contains NaN or inf")
    if img.size and (img.min() < 0.0 or img.max() > 1.0):
        raise InvalidRequest(
            f"'{key}': float image values must lie in [0, 1], got [{float(img.min())}, {float(img.max())}]"
        )


def parse_image(value: Any, key: str, *, channels_first: bool | None = None) -> np.ndarray:
    """A client image as uint8 ``[H, W, 3]``, converted the way upstream's robot policies convert it.

    Accepts uint8 or float images (floats must lie in ``[0, 1]`` and become ``(255 * x).astype(uint8)``), channel-last
    or channel-first. ``channels_first=None`` applies upstream's rule (leading axis of size 3 means ``[3, H, W]``);
    ``True`` always transposes (upstream ALOHA).
    """
    img = _as_array(value, key)
    if not (img.dtype == np.uint8 or np.issubdtype(img.dtype, np.floating)):
        raise InvalidRequest(f"'{key}': image dtype {img.dtype} is not supported; send uint8 (or float in [0, 1])")
    if img.ndim != 3:
        raise InvalidRequest(f"'{key}': expected a 3-D image [H, W, 3] or [3, H, W], got shape {img.shape}")
    if np.issubdtype(img.dtype, np.floating):
        _check_unit_range(img, key)
        img = (255 * img).astype(np.uint8)
    transpose = img.shape[0] == 3 if channels_first is None else channels_first
    if transpose:
        if img.shape[0] != 3:
            raise InvalidRequest(f"'{key}': expected a channel-first image [3, H, W], got shape {img.shape}")
        img = img.transpose(1, 2, 0)
    if img.shape[-1] != 3:
        raise InvalidRequest(f"'{key}': expected 3 colour channels ([H, W, 3] or [3, H, W]), got shape {img.shape}")
    if img.shape[0] < 1 or img.shape[1] < 1:
        raise InvalidRequest(f"'{key}': empty image, shape {img.shape}")
    return np.ascontiguousarray(img)


def parse_lerobot_image(value: Any, key: str) -> np.ndarray:
    """A camera frame as LeRobot takes it -> float32 ``[3, H, W]`` in ``[0, 1]``: uint8 ``[H, W, 3]`` (a robot's
    frame, divided by 255) or float ``[3, H, W]`` in ``[0, 1]`` (a LeRobot dataset's frame, kept as it is)."""
    img = _as_array(value, key)
    if img.dtype == np.uint8:
        if img.ndim != 3 or img.shape[-1] != 3:
            raise InvalidRequest(f"'{key}': a uint8 image must be [H, W, 3], got shape {img.shape}")
        img = img.transpose(2, 0, 1).astype(np.float32) / np.float32(255)
    elif np.issubdtype(img.dtype, np.floating):
        if img.ndim != 3 or img.shape[0] != 3:
            raise InvalidRequest(f"'{key}': a float image must be [3, H, W] in [0, 1], got shape {img.shape}")
        _check_unit_range(img, key)
        img = img.astype(np.float32)
    else:
        raise InvalidRequest(
            f"'{key}': image dtype {img.dtype} is not supported; send uint8 [H, W, 3] or float [3, H, W]"
        )
    if min(img.shape[1:]) < 1:
        raise InvalidRequest(f"'{key}': empty image, shape {img.shape}")
    return np.ascontiguousarray(img)


def parse_vector(value: Any, key: str, *, dim: int | None = None, allow_scalar: bool = False) -> np.ndarray:
    """A finite 1-D numeric vector (a scalar becomes length 1 when ``allow_scalar``), checked against ``dim``."""
    arr = _as_array(value, key)
    if arr.dtype.kind not in "biuf":
        raise InvalidRequest(f"'{key}': expected a numeric vector, got dtype {arr.dtype}")
    if arr.ndim == 0 and allow_scalar:
        arr = arr[np.newaxis]
    if arr.ndim != 1:
        raise InvalidRequest(f"'{key}': expected a 1-D vector, got shape {arr.shape}")
    if dim is not None and arr.shape[0] != dim:
        raise InvalidRequest(f"'{key}': expected {dim} values, got {arr.shape[0]}")
    if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        raise InvalidRequest(f"'{key}': contains NaN or inf")
    return arr


def parse_prompt(value: Any, key: str = "prompt") -> str:
    """A prompt as ``str``: accepts str, bytes (UTF-8) or a 0-d numpy string array (what upstream's `.item()` reads)."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value.item()
    if isinstance(value, bytes):
        try:
            value = value.decode("utf-8")
        except UnicodeDecodeError as e:
            raise InvalidRequest(f"'{key}': bytes are not valid UTF-8") from e
    if not isinstance(value, str):
        raise InvalidRequest(f"'{key}': expected a string, got {type(value).__name__}")
    return value


# --------------------------------------------------------------------------------------------------------------------
# Dict helpers


def pad_to_dim(x: np.ndarray, target_dim: int, axis: int = -1, value: float = 0.0) -> np.ndarray:
    """Pad ``x`` with ``value`` along ``axis`` up to ``target_dim`` (no-op when already that long)."""
    current = x.shape[axis]
    if current >= target_dim:
        return x
    widths = [(0, 0)] * x.ndim
    widths[axis] = (0, target_dim - current)
    return np.pad(x, widths, constant_values=value)


def make_bool_mask(*dims: int) -> tuple[bool, ...]:
    """``make_bool_mask(6, -1)`` -> six True then one False (positive = True run, negative = False run)."""
    mask: list[bool] = []
    for d in dims:
        mask.extend([d > 0] * abs(d))
    return tuple(mask)


# --------------------------------------------------------------------------------------------------------------------
# Transforms


# Values an input transform leaves for the output transforms of the same request (a LeRobot relative-action step's
# state): `Policy` takes this entry out of the model inputs and adds its items to what the output transforms see.
OUTPUT_CONTEXT = "output_context"


@dataclasses.dataclass(frozen=True)
class CompositeTransform:
    transforms: Sequence[Transform]

    def __call__(self, data: DataDict) -> DataDict:
        for transform in self.transforms:
            data = transform(data)
        return data


def compose(transforms: Sequence[Transform]) -> CompositeTransform:
    return CompositeTransform(tuple(transforms))


@dataclasses.dataclass(frozen=True)
class InjectDefaultPrompt:
    prompt: str | None

    def __call__(self, data: DataDict) -> DataDict:
        if self.prompt is not None and "prompt" not in data:
            data["prompt"] = np.asarray(self.prompt)
        return data


def _check_quantiles(norm_stats: Mapping[str, NormStats]) -> None:
    for k, v in flatten_dict(norm_stats).items():
        if not v.has_quantiles:
            raise ValueError(f"quantile normalisation needs q01 and q99, but the stats for '{k}' lack them")


def _apply_stats(
    data: DataDict,
    norm_stats: Mapping[str, NormStats],
    fn: Callable[[str, np.ndarray, NormStats], np.ndarray],
    *,
    strict: bool,
) -> DataDict:
    flat = flatten_dict(data)
    stats = flatten_dict(norm_stats)
    if strict:
        for k in stats:
            if k not in flat:
                raise ValueError(f"norm stats key '{k}' not found in the data")
    return unflatten_dict({k: fn(k, v, stats[k]) if k in stats else v for k, v in flat.items()})


@dataclasses.dataclass(frozen=True)
class Normalize:
    """Quantile (``[q01, q99] -> [-1, 1]``) or z-score normalisation of the keys the stats name."""

    norm_stats: Mapping[str, NormStats] | None
    use_quantiles: bool = False
    strict: bool = False

    def __post_init__(self) -> None:
        if self.norm_stats is not None and self.use_quantiles:
            _check_quantiles(self.norm_stats)

    def __call__(self, data: DataDict) -> DataDict:
        if self.norm_stats is None:
            return data
        return _apply_stats(data, self.norm_stats, self._normalize, strict=self.strict)

    def _normalize(self, key: str, x: np.ndarray, stats: NormStats) -> np.ndarray:
        x = np.asarray(x)
        n = x.shape[-1]
        # Stats longer than the data are sliced (upstream does this too); data longer than the stats cannot be mapped.
        if n > stats.mean.shape[-1]:
            raise InvalidRequest(f"'{key}' has {n} values but the normalisation stats cover {stats.mean.shape[-1]}")
        if self.use_quantiles:
            q01, q99 = stats.q01[..., :n], stats.q99[..., :n]
            return (x - q01) / (q99 - q01 + 1e-6) * 2.0 - 1.0
        mean, std = stats.mean[..., :n], stats.std[..., :n]
        return (x - mean) / (std + 1e-6)


@dataclasses.dataclass(frozen=True)
class Unnormalize:
    """Inverse of `Normalize`; strict (every key in the stats must be present), as upstream."""

    norm_stats: Mapping[str, NormStats] | None
    use_quantiles: bool = False

    def __post_init__(self) -> None:
        if self.norm_stats is not None and self.use_quantiles:
            _check_quantiles(self.norm_stats)

    def __call__(self, data: DataDict) -> DataDict:
        if self.norm_stats is None:
            return data
        return _apply_stats(data, self.norm_stats, self._unnormalize, strict=True)

    def _unnormalize(self, key: str, x: np.ndarray, stats: NormStats) -> np.ndarray:
        x = np.asarray(x)
        if self.use_quantiles:
            q01, q99 = stats.q01, stats.q99
            dim = q01.shape[-1]
            if dim < x.shape[-1]:
                # Dimensions beyond the stats (model padding) pass through unchanged.
                head = (x[..., :dim] + 1.0) / 2.0 * (q99 - q01 + 1e-6) + q01
                return np.concatenate([head, x[..., dim:]], axis=-1)
            return (x + 1.0) / 2.0 * (q99 - q01 + 1e-6) + q01
        mean = pad_to_dim(stats.mean, x.shape[-1], value=0.0)
        std = pad_to_dim(stats.std, x.shape[-1], value=1.0)
        return x * (std + 1e-6) + mean


@dataclasses.dataclass(frozen=True)
class ResizeImages:
    """Letterbox every ``image/*`` entry to the model resolution with upstream's PIL bilinear resize."""

    height: int
    width: int

    def client_frame(self, image: np.ndarray) -> np.ndarray:
        """An image this transform receives as the uint8 ``[H, W, 3]`` frame a trace records (here: itself)."""
        return image

    def resize(self, image: np.ndarray) -> np.ndarray:
        """One camera's image, its letterbox geometry already checked, as the model reads it."""
        return resize_with_pad_pil(image, self.height, self.width)

    def __call__(self, data: DataDict) -> DataDict:
        images = data["image"]
        for name, img in images.items():
            try:
                letterbox_geometry(img.shape[-3], img.shape[-2], self.height, self.width)
            except ValueError as e:
                raise InvalidRequest(f"image for camera '{name}': {e}") from e
        data["image"] = {k: self.resize(v) for k, v in images.items()}
        return data


class FastPromptTokenizer(Protocol):
    """What the FAST transforms need from `openpi_cam.tokenizers.Pi0FastTokenizer`."""

    def tokenize(
        self, prompt: str, state: np.ndarray, actions: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]: ...

    def extract_actions(self, tokens: np.ndarray, action_horizon: int, action_dim: int) -> np.ndarray: ...

    def extract_actions_checked(
        self, tokens: np.ndarray, action_horizon: int, action_dim: int
    ) -> tuple[np.ndarray, str | None]: ...


@dataclasses.dataclass(frozen=True)
class TokenizeFASTInputs:
    """Prompt + discretised state (+ actions when training) -> pi0-FAST token arrays."""

    tokenizer: FastPromptTokenizer

    def __call__(self, data: DataDict) -> DataDict:
        if data.get("prompt") is None:
            raise InvalidRequest("missing 'prompt' (and no default prompt is configured)")
        prompt = parse_prompt(data.pop("prompt"))
        tokens, token_mask, ar_mask, loss_mask = self.tokenizer.tokenize(prompt, data["state"], data.get("actions"))
        return {
            **data,
            "tokenized_prompt": tokens,
            "tokenized_prompt_mask": token_mask,
            "token_ar_mask": ar_mask,
            "token_loss_mask": loss_mask,
        }


@dataclasses.dataclass(frozen=True)
class ExtractFASTActions:
    """Generated token ids (in ``actions``) -> normalised action chunk ``[action_horizon, action_dim]``."""

    tokenizer: FastPromptTokenizer
    action_horizon: int
    action_dim: int

    def extract(self, tokens: np.ndarray) -> tuple[np.ndarray, str | None]:
        """Actions plus why the generation was malformed (None when it was well formed)."""
        tokens = np.asarray(tokens).astype(np.int32)
        return self.tokenizer.extract_actions_checked(tokens, self.action_horizon, self.action_dim)

    def __call__(self, data: DataDict) -> DataDict:
        if "actions" not in data:
            return data
        tokens = np.asarray(data.pop("actions")).astype(np.int32)
        return {**data, "actions": self.tokenizer.extract_actions(tokens, self.action_horizon, self.action_dim)}


@dataclasses.dataclass(frozen=True)
class DeltaActions:
    """Actions -> deltas w.r.t. the state on the masked dims (a no-op at inference, where there are no actions)."""

    mask: Sequence[bool] | None

    def __call__(self, data: DataDict) -> DataDict:
        if "actions" not in data or self.mask is None:
            return data
        mask = np.asarray(self.mask)
        dims = mask.shape[-1]
        # A copy of the actions, changed in place: the result keeps the actions' dtype (integer actions stay integer,
        # as upstream's in-place update leaves them), and the caller's array is not touched.
        state, actions = data["state"], np.array(data["actions"])
        self._apply(actions[..., :dims], np.expand_dims(np.where(mask, state[..., :dims], 0), axis=-2))
        data["actions"] = actions
        return data

    @staticmethod
    def _apply(actions: np.ndarray, state: np.ndarray) -> None:
        actions -= state


@dataclasses.dataclass(frozen=True)
class AbsoluteActions(DeltaActions):
    """Inverse of `DeltaActions`: add the state back on the masked dims."""

    @staticmethod
    def _apply(actions: np.ndarray, state: np.ndarray) -> None:
        actions += state


class PromptTokenizer(Protocol):
    """What `TokenizePrompt` needs from `openpi_cam.tokenizers.pi0.Pi0PromptTokenizer`."""

    def tokenize(self, prompt: str, state: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]: ...


@dataclasses.dataclass(frozen=True)
class TokenizePrompt:
    """pi0 / pi0.5: the prompt (and with `discrete_state_input` the normalised state) -> `tokenized_prompt`."""

    tokenizer: PromptTokenizer
    discrete_state_input: bool = False

    def __call__(self, data: DataDict) -> DataDict:
        if data.get("prompt") is None:
            raise InvalidRequest("missing 'prompt' (and no default prompt is configured)")
        prompt = parse_prompt(data.pop("prompt"))
        tokens, mask = self.tokenizer.tokenize(prompt, data["state"] if self.discrete_state_input else None)
        return {**data, "tokenized_prompt": tokens, "tokenized_prompt_mask": mask}


@dataclasses.dataclass(frozen=True)
class PadStatesAndActions:
    """Zero-pads the state (and actions, when training) to the model's action dim, after the prompt saw the state."""

    model_action_dim: int

    def __call__(self, data: DataDict) -> DataDict:
        out = {**data, "state": pad_to_dim(np.asarray(data["state"]), self.model_action_dim)}
        if "actions" in data:
            out["actions"] = pad_to_dim(np.asarray(data["actions"]), self.model_action_dim)
        return out


@dataclasses.dataclass(frozen=True)
class PassActions:
    """The output decoder of the flow-matching families: the model's output already is the action chunk."""

    def extract(self, output: np.ndarray) -> tuple[np.ndarray, str | None]:
        return np.asarray(output), None
