"""Where a client image lands inside the letterboxed model image (aspect-preserving resize, then padding).

Both of upstream's resize implementations (`image_tools.resize_with_pad`, `image_tools.resize_with_pad_pil`) place
the image with `letterbox_geometry`; the side channel stores each camera's placement with its step, so that a map over
the model image can be drawn on the frame the client sent. This module needs NumPy only: the viewers (`render`,
`stats`) read runs without loading JAX.
"""

from __future__ import annotations

import dataclasses

import numpy as np

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

    def original_to_model(self, x: ArrayLike, y: ArrayLike) -> tuple[ArrayLike, ArrayLike]:
        """Map points ``(x, y)`` in original-image coordinates to model-image coordinates (scalars or arrays)."""
        mx = np.asarray(x, dtype=np.float64) / self.scale_x + self.pad_left
        my = np.asarray(y, dtype=np.float64) / self.scale_y + self.pad_top
        return _scalar_or_array(mx), _scalar_or_array(my)

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
