"""Aspect-preserving resize with zero/black padding ("letterboxing"), as upstream OpenPI does it.

Upstream has two implementations with the same geometry:

* `resize_with_pad` (JAX, ``jax.image.resize`` linear): what upstream's model applies to float images that are not at
  the model resolution, and usable on uint8 images too.
* `resize_with_pad_pil` (PIL bilinear, uint8 only): what upstream's `ResizeImages` data transform applies to client
  images (it imports the ``openpi_client`` version). The two differ by up to one grey level, so the transform must use
  this one to reproduce upstream's model inputs bit for bit.

Both place the image with `letterbox.letterbox_geometry`, which the side channel stores with each step so that a map
over the model image can be drawn on the image the client sent.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from PIL import Image

from openpi_cam.letterbox import LetterboxGeometry, letterbox_geometry


def resize_with_pad(images: jax.Array | np.ndarray, height: int, width: int) -> jax.Array:
    """Letterbox ``[..., H, W, C]`` images to ``[..., height, width, C]`` with ``jax.image.resize`` (linear).

    uint8 images are rounded and clipped back to uint8 and padded with 0; float images must be in ``[-1, 1]``, are
    clipped to that range and padded with -1 (black), as upstream does.
    """
    images = jnp.asarray(images)
    if images.ndim < 3:
        raise ValueError(f"expected images shaped [..., H, W, C], got shape {images.shape}")
    if images.dtype not in (jnp.uint8, jnp.float32, jnp.bfloat16, jnp.float16):
        raise ValueError(f"unsupported image dtype {images.dtype}; expected uint8 or float")
    geo = letterbox_geometry(images.shape[-3], images.shape[-2], height, width)
    return _resize_with_pad_jit(images, geo)


@functools.partial(jax.jit, static_argnums=(1,))
def _resize_with_pad_jit(images: jax.Array, geo: LetterboxGeometry) -> jax.Array:
    lead = images.shape[:-3]
    resized = jax.image.resize(images, (*lead, geo.resized_h, geo.resized_w, images.shape[-1]), method="linear")
    if images.dtype == jnp.uint8:
        resized = jnp.round(resized).clip(0, 255).astype(jnp.uint8)
        fill = 0
    else:
        resized = resized.clip(-1.0, 1.0)
        fill = -1.0
    pad_bottom = geo.model_h - geo.resized_h - geo.pad_top
    pad_right = geo.model_w - geo.resized_w - geo.pad_left
    pads = [(0, 0)] * len(lead) + [(geo.pad_top, pad_bottom), (geo.pad_left, pad_right), (0, 0)]
    return jnp.pad(resized, pads, constant_values=fill)


def resize_with_pad_pil(images: np.ndarray, height: int, width: int) -> np.ndarray:
    """Letterbox uint8 ``[..., H, W, C]`` images with PIL bilinear resampling and zero padding (upstream's client tool).

    Images already at the target size are returned unchanged (upstream short-circuits the same way).
    """
    images = np.asarray(images)
    if images.ndim < 3:
        raise ValueError(f"expected images shaped [..., H, W, C], got shape {images.shape}")
    if images.dtype != np.uint8:
        raise ValueError(f"PIL letterboxing needs uint8 images, got {images.dtype}")
    if images.shape[-3:-1] == (height, width):
        return images
    geo = letterbox_geometry(images.shape[-3], images.shape[-2], height, width)
    flat = images.reshape(-1, *images.shape[-3:])
    out = np.zeros((flat.shape[0], height, width, images.shape[-1]), dtype=np.uint8)
    for i, image in enumerate(flat):
        # PIL needs 2-D arrays for single-channel images.
        pil = Image.fromarray(image[..., 0] if image.shape[-1] == 1 else image)
        resized = np.asarray(pil.resize((geo.resized_w, geo.resized_h), resample=Image.BILINEAR))
        out[i, geo.pad_top : geo.pad_top + geo.resized_h, geo.pad_left : geo.pad_left + geo.resized_w] = (
            resized.reshape(geo.resized_h, geo.resized_w, -1)
        )
    return out.reshape(*images.shape[:-3], height, width, images.shape[-1])
