"""Aspect-preserving resize with zero/black padding ("letterboxing"), as upstream OpenPI does it.

Upstream has two implementations with the same geometry:

* `resize_with_pad` (JAX, ``jax.image.resize`` linear): what upstream's model applies to float images that are not at
  the model resolution, and usable on uint8 images too.
* `resize_with_pad_pil` (PIL bilinear, uint8 only): what upstream's `ResizeImages` data transform applies to client
  images (it imports the ``openpi_client`` version). The two differ by up to one grey level, so the transform must use
  this one to reproduce upstream's model inputs bit for bit.

`letterbox_geometry` describes where the original image lands inside the model image, so that positions found in the
model image (e.g. Grad-CAM peaks) can be mapped back onto the image the client sent.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from PIL import Image

ArrayLike = float | np.ndarray


def _scalar_or_array(a: np.ndarray) -> ArrayLike:
    return float(a) if a.ndim == 0 else a


@dataclasses.dataclass(frozen=True)
class LetterboxGeometry:
    """Placement of an ``orig_h x orig_w`` image inside a ``model_h x model_w`` letterboxed model image.

    Coordinates are continuous pixel-edge coordinates: pixel ``i`` covers ``[i, i + 1)``, so its centre is ``i + 0.5``.
    Both resize implementations use half-pixel centres, which makes the mapping below a pure scale plus offset.
    """

    orig_h: int
    orig_w: int
    model_h: int
    model_w: int
    resized_h: int
    resized_w: int
    pad_top: int
    pad_left: int

    @property
    def scale_x(self) -> float:
        """Original pixels per model pixel along x."""
        return self.orig_w / self.resized_w

    @property
    def scale_y(self) -> float:
        """Original pixels per model pixel along y."""
        return self.orig_h / self.resized_h

    def contains_model_point(self, x: ArrayLike, y: ArrayLike) -> ArrayLike:
        """Whether model-image points lie on image content rather than padding (elementwise for arrays)."""
        x, y = np.asarray(x), np.asarray(y)
        inside = (
            (x >= self.pad_left)
            & (x <= self.pad_left + self.resized_w)
            & (y >= self.pad_top)
            & (y <= self.pad_top + self.resized_h)
        )
        return bool(inside) if inside.ndim == 0 else inside

    def model_to_original(self, x: ArrayLike, y: ArrayLike, *, clip: bool = False) -> tuple[ArrayLike, ArrayLike]:
        """Map points ``(x, y)`` in model-image coordinates to original-image coordinates (scalars or arrays).

        Points in the padding map outside ``[0, orig_w] x [0, orig_h]``; ``clip=True`` clamps them onto the border.
        """
        ox = (np.asarray(x, dtype=np.float64) - self.pad_left) * self.scale_x
        oy = (np.asarray(y, dtype=np.float64) - self.pad_top) * self.scale_y
        if clip:
            ox, oy = np.clip(ox, 0.0, self.orig_w), np.clip(oy, 0.0, self.orig_h)
        return _scalar_or_array(ox), _scalar_or_array(oy)

    def original_to_model(self, x: ArrayLike, y: ArrayLike) -> tuple[ArrayLike, ArrayLike]:
        """Inverse of `model_to_original` (without clipping)."""
        mx = np.asarray(x, dtype=np.float64) / self.scale_x + self.pad_left
        my = np.asarray(y, dtype=np.float64) / self.scale_y + self.pad_top
        return _scalar_or_array(mx), _scalar_or_array(my)

    def model_box_to_original(
        self, box: tuple[float, float, float, float], *, clip: bool = True
    ) -> tuple[float, float, float, float]:
        """Map an ``(x0, y0, x1, y1)`` box from model-image to original-image coordinates (clamped by default)."""
        x0, y0 = self.model_to_original(box[0], box[1], clip=clip)
        x1, y1 = self.model_to_original(box[2], box[3], clip=clip)
        return x0, y0, x1, y1

    def as_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> LetterboxGeometry:
        return cls(**{f.name: int(d[f.name]) for f in dataclasses.fields(cls)})


def letterbox_geometry(orig_h: int, orig_w: int, out_h: int, out_w: int) -> LetterboxGeometry:
    """The placement both resize functions use; the float expressions match upstream's so the rounding does too."""
    if min(orig_h, orig_w, out_h, out_w) < 1:
        raise ValueError(f"image sizes must be positive, got {orig_h}x{orig_w} -> {out_h}x{out_w}")
    ratio = max(orig_w / out_w, orig_h / out_h)
    resized_h = int(orig_h / ratio)
    resized_w = int(orig_w / ratio)
    if resized_h < 1 or resized_w < 1:
        raise ValueError(f"a {orig_h}x{orig_w} image is too elongated to letterbox into {out_h}x{out_w}")
    return LetterboxGeometry(
        orig_h=int(orig_h),
        orig_w=int(orig_w),
        model_h=int(out_h),
        model_w=int(out_w),
        resized_h=resized_h,
        resized_w=resized_w,
        pad_top=(out_h - resized_h) // 2,
        pad_left=(out_w - resized_w) // 2,
    )


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
