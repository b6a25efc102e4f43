"""A small self-made colormap (dark -> purple -> red -> orange -> yellow -> white) as a 256-entry RGB LUT.

Kept in-house so rendering depends only on numpy and Pillow.
"""

from __future__ import annotations

import numpy as np

# (position, RGB) anchors; monotone in luminance so the map also reads in greyscale.
_ANCHORS: tuple[tuple[float, tuple[int, int, int]], ...] = (
    (0.00, (8, 6, 40)),
    (0.25, (96, 18, 118)),
    (0.50, (196, 42, 78)),
    (0.72, (244, 128, 34)),
    (0.90, (250, 226, 80)),
    (1.00, (255, 255, 224)),
)


def build_lut(size: int = 256) -> np.ndarray:
    """Returns a (size, 3) uint8 table by linear interpolation between the anchors."""
    pos = np.array([p for p, _ in _ANCHORS])
    rgb = np.array([c for _, c in _ANCHORS], dtype=np.float64)
    x = np.linspace(0.0, 1.0, size)
    lut = np.stack([np.interp(x, pos, rgb[:, ch]) for ch in range(3)], axis=-1)
    return np.round(lut).astype(np.uint8)


LUT = build_lut()


def colorize(values: np.ndarray) -> np.ndarray:
    """Maps values in [0, 1] (clipped; NaN -> 0) to uint8 RGB with shape values.shape + (3,)."""
    v = np.nan_to_num(np.asarray(values, dtype=np.float64), nan=0.0)
    idx = np.round(np.clip(v, 0.0, 1.0) * (len(LUT) - 1)).astype(np.intp)
    return LUT[idx]
