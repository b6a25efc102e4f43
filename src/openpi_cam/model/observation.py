"""The model's input: images per camera (in camera order), their masks, state and the tokenized prompt."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from openpi_cam.image_tools import resize_with_pad

logger = logging.getLogger(__name__)


def uint8_to_model(image: Any) -> jax.Array:
    """A uint8 image as the model's float32 input in [-1, 1]: upstream's `x / 255 * 2 - 1`, computed by JAX as upstream
    computes it (NumPy rounds some values one ulp apart)."""
    return jnp.asarray(image).astype(jnp.float32) / 255.0 * 2.0 - 1.0


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Observation:
    images: dict[str, Any]  # camera -> [B, H, W, 3] float32 in [-1, 1]; dict order = token order in the prefix
    image_masks: dict[str, Any]  # camera -> [B] bool
    state: Any  # [B, S]
    tokenized_prompt: Any  # [B, L] int32
    tokenized_prompt_mask: Any  # [B, L] bool
    token_ar_mask: Any = None  # [B, L] int32
    token_loss_mask: Any = None  # [B, L] bool

    @property
    def camera_names(self) -> tuple[str, ...]:
        return tuple(self.images)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Observation:
        """Upstream's layout (`image`, `image_mask`, `state`, `tokenized_prompt`, ...); uint8 images become
        float32 `x / 255 * 2 - 1` as upstream's `Observation.from_dict` does."""
        if ("tokenized_prompt" in data) != ("tokenized_prompt_mask" in data):
            raise ValueError("tokenized_prompt and tokenized_prompt_mask must be provided together")
        images = {}
        for name, image in data["image"].items():
            if image.dtype == np.uint8:
                image = uint8_to_model(image)
            images[name] = image
        return cls(
            images=images,
            image_masks=dict(data.get("image_mask", {})),
            state=data["state"],
            tokenized_prompt=data.get("tokenized_prompt"),
            tokenized_prompt_mask=data.get("tokenized_prompt_mask"),
            token_ar_mask=data.get("token_ar_mask"),
            token_loss_mask=data.get("token_loss_mask"),
        )


def preprocess_observation(
    obs: Observation, image_resolution: tuple[int, int], image_keys: Sequence[str] | None = None
) -> Observation:
    """Inference-time preprocessing as upstream: resize-with-pad images that are not at the model resolution and
    default missing image masks to True. `image_keys` (pi0 / pi0.5 pass their config's cameras) fixes which cameras
    the model sees and in which order; None keeps the observation's own (pi0-FAST passes its dict order)."""
    batch_shape = obs.state.shape[:-1]
    if image_keys is not None and (missing := [k for k in image_keys if k not in obs.images]):
        raise ValueError(f"the observation lacks the camera(s) {missing}; this model reads {list(image_keys)}")
    images, masks = {}, {}
    for name in obs.images if image_keys is None else image_keys:
        image = obs.images[name]
        if tuple(image.shape[-3:-1]) != tuple(image_resolution):
            logger.info("Resizing image %s from %s to %s", name, image.shape[-3:-1], image_resolution)
            image = resize_with_pad(image, *image_resolution)
        images[name] = image
        mask = obs.image_masks.get(name)
        masks[name] = jnp.ones(batch_shape, jnp.bool_) if mask is None else jnp.asarray(mask)
    return dataclasses.replace(obs, images=images, image_masks=masks)


def stack_observations(observations: Sequence[Observation]) -> Observation:
    """B=1 observations of one config -> one [B, ...] observation (same cameras and shapes in every row)."""
    return jax.tree.map(lambda *x: np.concatenate([np.asarray(a) for a in x]), *observations)


def pad_rows(x: np.ndarray, rows: int) -> np.ndarray:
    """Repeats the last row until `x` has `rows` rows (padding rows are computed and then dropped)."""
    x = np.asarray(x)
    return x if x.shape[0] == rows else np.concatenate([x, np.repeat(x[-1:], rows - x.shape[0], axis=0)])
