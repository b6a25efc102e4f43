"""Aspect-preserving resize with zero/black padding ("letterboxing"), as upstream OpenPI does it.

Upstream has two implementations with the same geometry:

* `resize_with_pad` (JAX, ``jax.image.resize`` linear): what upstream's model applies to float images that are not at
  the model resolution, and usable on uint8 images too.
* `resize_with_pad_pil` (PIL bilinear, uint8 only): what upstream's `ResizeImages` data transform applies to client
  images (it imports the ``openpi_client`` version). The two differ by up to one grey level, so the transform must use
  this one to reproduce upstream's model inputs bit for bit.

Both place the image with `letterbox.letterbox_geometry`, which the side channel stores with each step so that a map
over the model image can be drawn on the image the client sent. LeRobot's PyTorch port of pi0 / pi0.5 letterboxes
float images with the same placement but torch's bilinear interpolation (`resize_with_pad_torch_bilinear`).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from PIL import Image

from openpi_cam.letterbox import LetterboxGeometry, letterbox_geometry


def unit_to_uint8(images: np.ndarray) -> np.ndarray:
    """Float images in [0, 1] as uint8, rounded to the nearest level (values outside are clipped)."""
    return np.clip(np.round(np.asarray(images, np.float32) * 255.0), 0, 255).astype(np.uint8)


def client_frame_uint8(image: np.ndarray) -> np.ndarray:
    """A client image as uint8 HWC RGB: clients may send [3, H, W] and float images in [0, 1] (as upstream accepts)."""
    x = np.asarray(image)
    if x.ndim == 3 and x.shape[0] == 3 and x.shape[-1] != 3:
        x = np.moveaxis(x, 0, -1)
    if x.dtype != np.uint8:
        x = unit_to_uint8(x)
    return np.ascontiguousarray(x)


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


def _torch_linear_taps(in_size: int, out_size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(low index, high index, low weight, high weight) per output index, as torch's CPU bilinear kernel computes
    them for `align_corners=False` without antialiasing: the float32 source coordinate scale * (i + 0.5) - 0.5,
    rounded once (torch's build fuses the multiply-add; exact in float64 here), clamped at 0; the low tap its floor
    (at most the last index), the high tap the next one unless the low one is the last."""
    scale = np.float32(in_size) / np.float32(out_size)
    centres = np.arange(out_size, dtype=np.float64) + 0.5
    src = np.maximum((np.float64(scale) * centres - 0.5).astype(np.float32), np.float32(0))
    low = np.minimum(np.floor(src).astype(np.int64), in_size - 1)
    high_weight = np.clip(src - low.astype(np.float32), 0, 1).astype(np.float32)
    high = np.where(low < in_size - 1, low + 1, low)
    return low, high, (np.float32(1) - high_weight).astype(np.float32), high_weight


def resize_with_pad_torch_bilinear(images: np.ndarray, height: int, width: int) -> np.ndarray:
    """Letterbox float32 ``[..., H, W, C]`` images in ``[0, 1]`` as LeRobot's `resize_with_pad_torch` does: torch's
    `interpolate(bilinear, align_corners=False)` (no antialiasing) to the letterbox size, clamped to ``[0, 1]``, then
    zero-padded with the centred placement of `letterbox_geometry`. Images already at the target size are returned
    unchanged (LeRobot skips the resize for them)."""
    images = np.asarray(images, np.float32)
    if images.ndim < 3:
        raise ValueError(f"expected images shaped [..., H, W, C], got shape {images.shape}")
    if images.shape[-3:-1] == (height, width):
        return images
    geo = letterbox_geometry(images.shape[-3], images.shape[-2], height, width)
    y0, y1, wy0, wy1 = _torch_linear_taps(geo.orig_h, geo.resized_h)
    x0, x1, wx0, wx1 = _torch_linear_taps(geo.orig_w, geo.resized_w)
    wx0, wx1 = wx0[:, None], wx1[:, None]
    # torch blends along the width first, then weighs the two rows: (a * wx0 + b * wx1) * wy0 + (...) * wy1.
    top = images[..., y0, :, :]
    bottom = images[..., y1, :, :]
    top = top[..., x0, :] * wx0 + top[..., x1, :] * wx1
    bottom = bottom[..., x0, :] * wx0 + bottom[..., x1, :] * wx1
    resized = top * wy0[:, None, None] + bottom * wy1[:, None, None]
    out = np.zeros((*images.shape[:-3], height, width, images.shape[-1]), np.float32)
    rows = slice(geo.pad_top, geo.pad_top + geo.resized_h)
    cols = slice(geo.pad_left, geo.pad_left + geo.resized_w)
    out[..., rows, cols, :] = np.clip(resized, 0.0, 1.0)
    return out
