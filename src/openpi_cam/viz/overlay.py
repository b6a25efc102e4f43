"""Placing a map's patch grid on an image: bilinear upsampling, letterbox inversion, colour blending.

Coordinates are continuous with pixel i covering [i, i + 1); a grid cell's value sits at its centre, so a map is
sampled at grid coordinate `pos * Hp / extent - 0.5` and clamped at the borders.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np

from openpi_cam.cam.run_format import CameraMeta, StepMeta
from openpi_cam.letterbox import LetterboxGeometry
from openpi_cam.viz.colormap import colorize


class StepView(Protocol):
    """One logged step as every renderer and statistic sees it: the maps of one kind, its frames and metadata
    (`viz.stats.MapView` over a run's steps)."""

    seq: int
    meta: StepMeta
    maps: Mapping[str, np.ndarray]
    frames: Mapping[str, np.ndarray]
    model_frames: Mapping[str, np.ndarray]
    extra: Mapping[str, Any]  # the client's `cam_extra/` values (`CAMStep.extra`)


def reduce_tokens(cam: np.ndarray) -> np.ndarray:
    """One displayable (Hp, Wp) map: multi-token maps (T, Hp, Wp) are averaged; NaN and negatives become 0."""
    m = np.asarray(cam, dtype=np.float64)
    if m.ndim == 3:
        m = m.mean(axis=0) if m.shape[0] else np.zeros(m.shape[1:])
    if m.ndim != 2:
        raise ValueError(f"expected a (Hp, Wp) or (T, Hp, Wp) map, got shape {np.shape(cam)}")
    return np.clip(np.nan_to_num(m, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)


def sample_grid(grid: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Bilinear samples of `grid` at the outer product of fractional cell indices `rows` x `cols`."""
    g = np.asarray(grid, dtype=np.float64)

    def axis_weights(pos: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        p = np.clip(np.asarray(pos, np.float64), 0.0, n - 1)
        lo = np.floor(p).astype(np.intp)
        hi = np.minimum(lo + 1, n - 1)
        return lo, hi, p - lo

    r0, r1, wr = axis_weights(rows, g.shape[0])
    c0, c1, wc = axis_weights(cols, g.shape[1])
    by_row = g[r0] * (1.0 - wr)[:, None] + g[r1] * wr[:, None]
    return by_row[:, c0] * (1.0 - wc)[None, :] + by_row[:, c1] * wc[None, :]


def upsample(grid: np.ndarray, out_h: int, out_w: int) -> np.ndarray:
    """Bilinear upsampling of a (Hp, Wp) grid stretched over an out_h x out_w image (the model image)."""
    hp, wp = np.shape(grid)
    rows = (np.arange(out_h) + 0.5) * hp / out_h - 0.5
    cols = (np.arange(out_w) + 0.5) * wp / out_w - 0.5
    return sample_grid(grid, rows, cols)


def map_on_original(grid: np.ndarray, box: LetterboxGeometry) -> np.ndarray:
    """The grid resampled onto the client's original (orig_h, orig_w) image, undoing the letterbox."""
    hp, wp = np.shape(grid)
    # x and y are independent in the letterbox, so one row and one column of pixel centres suffice.
    mx, my = box.original_to_model(np.arange(box.orig_w) + 0.5, np.arange(box.orig_h) + 0.5)
    return sample_grid(grid, my * hp / box.model_h - 0.5, mx * wp / box.model_w - 0.5)


def map_for_frame(grid: np.ndarray, frame_hw: tuple[int, int], box: LetterboxGeometry | None) -> np.ndarray:
    """The grid at the resolution of the frame it is drawn on.

    With a letterbox whose original size matches the frame, the letterbox is inverted; otherwise the frame is taken
    to be the model image and the grid is stretched over it.
    """
    if box is not None and (box.orig_h, box.orig_w) == tuple(frame_hw):
        return map_on_original(grid, box)
    return upsample(grid, *frame_hw)


def blend(frame: np.ndarray, heat: np.ndarray, alpha: float = 0.5) -> np.ndarray:
    """uint8 RGB overlay of `heat` (values in [0, 1], same H x W as frame) with constant opacity `alpha`."""
    base = np.asarray(frame, dtype=np.float64)
    if base.ndim == 2:
        base = np.repeat(base[..., None], 3, axis=-1)
    color = colorize(heat).astype(np.float64)
    out = (1.0 - alpha) * base[..., :3] + alpha * color
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def camera_image(step: StepView, camera: str) -> tuple[np.ndarray, LetterboxGeometry | None]:
    """The image a camera's map is drawn on, with the letterbox to invert (None: stretch the grid over it).

    Prefers the client's original frame; falls back to the model frame, then to a blank model-sized canvas.
    """
    info = step.meta.cameras.get(camera, CameraMeta())
    box = LetterboxGeometry.from_dict(info.geometry) if info.geometry else None
    if camera in step.frames:
        return np.asarray(step.frames[camera], dtype=np.uint8), box
    if camera in step.model_frames:
        return np.asarray(step.model_frames[camera], dtype=np.uint8), None
    hp, wp = info.grid or np.shape(step.maps[camera])[-2:]
    h, w = (box.model_h, box.model_w) if box else (hp * 14, wp * 14)
    return np.zeros((h, w, 3), np.uint8), None


def camera_overlay(step: StepView, camera: str, scale: float, alpha: float) -> np.ndarray:
    """The camera's map, divided by `scale` and colour-blended over its image; masked cameras stay plain."""
    image, box = camera_image(step, camera)
    info = step.meta.cameras.get(camera)
    if camera not in step.maps or (info is not None and not info.valid):
        return image
    heat = map_for_frame(reduce_tokens(step.maps[camera]), image.shape[:2], box)
    heat = heat / scale if scale > 0 else np.zeros_like(heat)
    return blend(image, heat, alpha)
