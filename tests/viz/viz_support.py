"""An overlay computed from a step file's arrays and metadata with NumPy and SciPy alone, from the definitions in
docs/FORMAT.md ("Geometry") and the README (what an overlay is), never through `openpi_cam.viz`: the reference the
renderers' output is compared with.

Only the colour table is shared (`viz.colormap.LUT`, tested on its own as data): a renderer that picked the wrong
colour index, normalised by the wrong maximum, placed the grid wrongly or ignored a camera's mask still differs.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from scipy import ndimage

from openpi_cam.viz.colormap import LUT


def display_map(m: np.ndarray) -> np.ndarray:
    """A (T, Hp, Wp) stack averaged over T; NaN and negative cells carry no attention."""
    m = np.asarray(m, np.float64)
    m = m.mean(axis=0) if m.ndim == 3 else m
    return np.clip(np.nan_to_num(m, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)


def valid(meta: Mapping[str, Any], camera: str) -> bool:
    return bool(meta.get("cameras", {}).get(camera, {}).get("valid", True))


def step_peak(meta: Mapping[str, Any], maps: Mapping[str, np.ndarray]) -> float:
    """Per-step normalisation: the largest displayed cell over the step's valid cameras."""
    return max((display_map(m).max() for c, m in maps.items() if valid(meta, c)), default=0.0)


def shares(meta: Mapping[str, Any], maps: Mapping[str, np.ndarray]) -> dict[str, float]:
    """Each valid camera's part of the step's total displayed mass (masked cameras: 0)."""
    mass = {c: display_map(m).sum() if valid(meta, c) else 0.0 for c, m in maps.items()}
    total = sum(mass.values())
    return {c: float(v / total) if total > 0 else 0.0 for c, v in mass.items()}


def heat_on(grid: np.ndarray, height: int, width: int, geometry: Mapping[str, int] | None) -> np.ndarray:
    """The grid bilinearly sampled at every pixel centre of an image: through the letterbox for the client's
    original frame (`geometry`), stretched over the whole image otherwise. Cell values sit at cell centres and the
    grid's border cells extend to the image border."""
    hp, wp = grid.shape
    y, x = np.arange(height) + 0.5, np.arange(width) + 0.5
    if geometry is not None:
        g = geometry
        y = y * g["resized_h"] / g["orig_h"] + g["pad_top"]  # model-image row of each original pixel centre
        x = x * g["resized_w"] / g["orig_w"] + g["pad_left"]
        y, x = y * hp / g["model_h"] - 0.5, x * wp / g["model_w"] - 0.5
    else:
        y, x = y * hp / height - 0.5, x * wp / width - 0.5
    rows, cols = np.meshgrid(y, x, indexing="ij")
    return ndimage.map_coordinates(grid, [rows, cols], order=1, mode="nearest")


def expected_overlay(
    meta: Mapping[str, Any],
    maps: Mapping[str, np.ndarray],
    frames: Mapping[str, np.ndarray],
    model_frames: Mapping[str, np.ndarray],
    camera: str,
    scale: float,
    alpha: float = 0.5,
) -> np.ndarray:
    """What an overlay of `camera` must show: its map / `scale`, coloured and blended over the client frame (else the
    model frame); a masked camera shows its image unchanged."""
    if camera in frames:
        image, geometry = np.asarray(frames[camera]), meta["cameras"][camera].get("geometry")
        if geometry is not None and (geometry["orig_h"], geometry["orig_w"]) != image.shape[:2]:
            geometry = None
    else:
        image, geometry = np.asarray(model_frames[camera]), None
    if camera not in maps or not valid(meta, camera):
        return image
    heat = heat_on(display_map(maps[camera]), image.shape[0], image.shape[1], geometry)
    level = np.round(np.clip(heat / scale if scale > 0 else 0 * heat, 0.0, 1.0) * 255).astype(int)
    blended = (1 - alpha) * image.astype(np.float64) + alpha * LUT[level].astype(np.float64)
    return np.clip(np.round(blended), 0, 255).astype(np.uint8)


def assert_overlay_matches(got: np.ndarray, want: np.ndarray, what: str) -> None:
    """Exact up to float rounding at a colour-index or blend boundary. Measured: the Rerun sink and render agree with
    this reference on every value of every test image; one level on 0.1% of the values is left for float64 sums in
    another order. A wrong scale, place, kind or mask changes whole regions by tens of levels."""
    assert got.shape == want.shape and got.dtype == np.uint8, what
    diff = np.abs(got.astype(int) - want.astype(int))
    assert diff.max() <= 1, f"{what}: max diff {diff.max()}"
    assert (diff > 0).mean() < 0.001, f"{what}: {(diff > 0).mean():.2%} of the values differ"
