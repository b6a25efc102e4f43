"""Faithfulness metrics for attribution maps over a camera's patch grid: pure functions of maps, boxes and the
scores the model gave painted frames (no model here; `Explainer.rescore` gives the scores).

Conventions shared by every function:
* A map is [Hp, Wp], or a per-token stack [T, Hp, Wp] that is reduced by its mean over T (`reduce_map`): the mean
  keeps each token's sign and scale, as the explained chunk score is a sum over tokens.
* Signs: orders (deletion, top-1, Spearman) use the signed map, highest first = most supporting. Mass-based
  metrics (mass on target, nuisance ratio) use the positive part only: negative evidence is not "looking at" a box.
  The pointing game uses the signed peak and counts a map whose peak is not positive as a miss.
* Ties: patches are ordered by value descending, ties by row-major patch index ascending, so every order is
  deterministic.
* Deletion paints patches with a baseline frame (`deletion_masks`: bool [K, Hp, Wp], True = painted), the model
  re-scores them in one call, and `deletion` turns the scores [K] into drops: score(nothing painted) -
  score(painted), from the same call.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from scipy import stats

from openpi_cam.cam.run_format import StepMeta


def reduce_map(cam_map: np.ndarray) -> np.ndarray:
    """[Hp, Wp] or [T, Hp, Wp] -> float64 [Hp, Wp] (mean over T)."""
    m = np.asarray(cam_map, np.float64)
    if m.ndim == 3:
        return m.mean(axis=0)
    if m.ndim != 2:
        raise ValueError(f"a map is [Hp, Wp] or [T, Hp, Wp], got shape {m.shape}")
    return m


def patch_order(cam_map: np.ndarray) -> np.ndarray:
    """Row-major patch indices, highest (signed) value first, ties by index. -> int [Hp * Wp]"""
    return np.argsort(-reduce_map(cam_map).ravel(), kind="stable")


def top_k_masks(order: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """Row k paints the first k patches of `order` (k = 0..N, N = Hp * Wp). -> bool [N + 1, Hp, Wp]"""
    n = grid[0] * grid[1]
    rank = np.empty(n, np.int64)
    rank[np.asarray(order)] = np.arange(n)
    return (rank[None, :] < np.arange(n + 1)[:, None]).reshape(n + 1, *grid)


def single_patch_masks(grid: tuple[int, int]) -> np.ndarray:
    """Row 0 paints nothing, row 1 + i paints patch i (row-major) alone. -> bool [N + 1, Hp, Wp]"""
    n = grid[0] * grid[1]
    return np.concatenate([np.zeros((1, n), bool), np.eye(n, dtype=bool)]).reshape(n + 1, *grid)


RANDOM = "random"  # the name of the random orders' curve (their mean) in `Deletion.curves`
_SINGLE = "single"  # the block of `DeletionMasks` that paints nothing, then each patch alone


@dataclasses.dataclass(frozen=True)
class DeletionMasks:
    """`deletion_masks`: the mask stack and where each block of it lies."""

    masks: np.ndarray  # bool [K, Hp, Wp], True = painted
    blocks: dict[str, slice]  # _SINGLE (N + 1 rows), each named order and RANDOM (k_max rows per order)
    grid: tuple[int, int]
    k_max: int
    random_orders: int


def deletion_masks(
    orders: Mapping[str, np.ndarray],
    grid: tuple[int, int],
    *,
    k_max: int | None = None,
    random_orders: int = 8,
    seed: int = 0,
) -> DeletionMasks:
    """The masks of one camera's deletion curves, for one re-scoring call: nothing painted, each patch alone
    (row-major; their drops are the occlusion optimum's candidates), then per named order (`orders`: name -> patch
    order, e.g. `patch_order` of each map kind) its top k patches for k = 1..k_max, then the same for `random_orders`
    uniformly random permutations (`numpy.random.default_rng(seed)`). `k_max` defaults to every patch."""
    if clash := {_SINGLE, RANDOM} & set(orders):
        raise ValueError(f"order names {sorted(clash)} are taken by the reference blocks")
    if random_orders < 1:
        raise ValueError(f"random_orders must be >= 1, got {random_orders}")
    n = grid[0] * grid[1]
    k_max = n if k_max is None else min(k_max, n)
    rng = np.random.default_rng(seed)
    blocks = {_SINGLE: single_patch_masks(grid)}  # row 0: nothing painted
    blocks |= {name: top_k_masks(order, grid)[1 : k_max + 1] for name, order in orders.items()}
    blocks[RANDOM] = np.concatenate(
        [top_k_masks(rng.permutation(n), grid)[1 : k_max + 1] for _ in range(random_orders)]
    )
    where, start = {}, 0
    for name, block in blocks.items():
        where[name] = slice(start, start + len(block))
        start += len(block)
    return DeletionMasks(np.concatenate(list(blocks.values())), where, grid, k_max, random_orders)


@dataclasses.dataclass(frozen=True)
class Deletion:
    """One camera's deletion curves, normalised by the single-patch occlusion optimum (the largest drop any one
    patch causes alone): occlusion's own map scores 1.0 at k = 1 by definition. A drop is score(nothing painted) -
    score(painted), both from the same call. Where no patch lowers the score (optimum <= 0) there is nothing to
    normalise by and every normalised value is NaN."""

    optimum: float
    single: np.ndarray  # [Hp, Wp] each patch's drop when painted alone
    drops: dict[str, np.ndarray]  # name (and RANDOM: the mean over random orders) -> [k_max] raw drops, k = 1..k_max
    curves: dict[str, np.ndarray]  # the same divided by the optimum

    def at_k(self, name: str, ks: Sequence[int]) -> np.ndarray:
        """The normalised drop after painting the top k patches of `name`'s order, for each k. -> [len(ks)]"""
        return self.curves[name][np.asarray(ks) - 1]

    def auc(self, name: str) -> float:
        """The mean over k = 1..k_max of the normalised drop (the area under the curve divided by k_max)."""
        return float(np.mean(self.curves[name]))


def deletion(masks: DeletionMasks, scores: np.ndarray) -> Deletion:
    """The deletion curves of `masks` from the model's scores of them ([K], in the mask stack's order)."""
    scores = np.asarray(scores, np.float64).reshape(-1)
    if scores.shape[0] != masks.masks.shape[0]:
        raise ValueError(f"{scores.shape[0]} scores for {masks.masks.shape[0]} masks")
    drops_all = scores[0] - scores
    single = drops_all[masks.blocks[_SINGLE]][1:].reshape(masks.grid)
    optimum = float(single.max())
    drops = {name: drops_all[where] for name, where in masks.blocks.items() if name not in (_SINGLE, RANDOM)}
    drops[RANDOM] = drops_all[masks.blocks[RANDOM]].reshape(masks.random_orders, masks.k_max).mean(axis=0)
    scale = optimum if optimum > 0 else np.nan
    return Deletion(optimum, single, drops, {name: d / scale for name, d in drops.items()})


def top1_agreement(cam_map: np.ndarray, reference: np.ndarray) -> bool:
    """Do the two maps' top patches (signed, ties by index) coincide? Against an occlusion map: does the map's
    peak name the patch whose removal alone lowers the score most."""
    return bool(patch_order(cam_map)[0] == patch_order(reference)[0])


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Spearman rank correlation of two (reduced, signed) maps over patches, ties given their average rank; NaN when
    either map is constant."""
    x, y = reduce_map(a).ravel(), reduce_map(b).ravel()
    if np.ptp(x) == 0 or np.ptp(y) == 0:
        return float("nan")
    return float(stats.spearmanr(x, y).statistic)


def bootstrap_mean_ci(
    values: Sequence[float], *, resamples: int = 10_000, level: float = 0.95, seed: int = 0
) -> tuple[float, float, float]:
    """(mean, low, high): percentile bootstrap interval of the mean over steps; `resamples` resamples with
    replacement drawn by `numpy.random.default_rng(seed)`. Non-finite values (e.g. Spearman of a constant map)
    are dropped first; NaNs when nothing is left."""
    x = np.asarray(values, np.float64)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return float("nan"), float("nan"), float("nan")
    means = x[np.random.default_rng(seed).integers(0, x.size, size=(resamples, x.size))].mean(axis=1)
    tail = (1.0 - level) / 2.0 * 100.0
    return float(x.mean()), float(np.percentile(means, tail)), float(np.percentile(means, 100.0 - tail))


def randomisation_abs_spearman(maps: Sequence[np.ndarray], random_maps: Sequence[np.ndarray]) -> np.ndarray:
    """Model randomisation (Adebayo et al. 2018): |Spearman| between each map and the same method's map of the same
    step from a re-initialised model. A method that depends on what the model learned scores near the null
    (`null_abs_spearman`); one that mostly reflects the input scores high. -> [n]"""
    if len(maps) != len(random_maps):
        raise ValueError("one randomised map per map")
    return np.abs([spearman(a, b) for a, b in zip(maps, random_maps, strict=True)])


def null_abs_spearman(maps: Sequence[np.ndarray]) -> np.ndarray:
    """|Spearman| between maps of unrelated steps (same camera, same method): map i against map i + 1 (cyclic), so
    n maps give n pairs. The level randomisation should be compared with. -> [n]"""
    n = len(maps)
    if n < 2:
        raise ValueError("the null needs maps of at least two steps")
    return np.abs([spearman(maps[i], maps[(i + 1) % n]) for i in range(n)])


def box_visible(box: Sequence[float]) -> bool:
    """Whether a target box (x0, y0, x1, y1), end exclusive, holds any pixel: simulators send zeros for a target
    that is out of view or fully occluded."""
    x0, y0, x1, y1 = (float(v) for v in box)
    return x1 > x0 and y1 > y0


def box_cells(box: Sequence[int], grid: tuple[int, int], image_size: int | tuple[int, int]) -> np.ndarray:
    """bool [Hp, Wp]: the patches sharing at least one pixel with box (x0, y0, x1, y1), end exclusive, for an image
    of `image_size` (side, or (H, W)) pixels cut into the grid."""
    h, w = (image_size, image_size) if np.ndim(image_size) == 0 else image_size
    x0, y0, x1, y1 = box
    ph, pw = h / grid[0], w / grid[1]
    rows = (np.arange(grid[0]) * ph < y1) & ((np.arange(grid[0]) + 1) * ph > y0)
    cols = (np.arange(grid[1]) * pw < x1) & ((np.arange(grid[1]) + 1) * pw > x0)
    return rows[:, None] & cols[None, :]


def pointing_hit(cam_map: np.ndarray, cells: np.ndarray) -> bool:
    """Pointing game: the peak patch (signed, ties by index) lies in `cells`, and its value is positive."""
    m = reduce_map(cam_map)
    peak = patch_order(m)[0]
    return bool(m.ravel()[peak] > 0 and np.asarray(cells, bool).ravel()[peak])


def pointing_chance(cells: np.ndarray) -> float:
    """Hit rate of a peak placed uniformly at random: the share of patches in `cells`."""
    return float(np.mean(cells))


def mass_on_target(cam_map: np.ndarray, cells: np.ndarray) -> float:
    """Share of the map's positive mass on `cells` (chance: `pointing_chance(cells)`, a uniform map); NaN
    without positive mass."""
    pos = np.maximum(reduce_map(cam_map), 0.0)
    total = pos.sum()
    return float(pos[np.asarray(cells, bool)].sum() / total) if total > 0 else float("nan")


def nuisance_mass_ratio(cam_map: np.ndarray, relevant_cells: np.ndarray) -> float:
    """Nuisance mass ratio (Zhang et al.): share of positive mass outside the task-relevant cells (chance:
    1 - their share of patches); NaN without positive mass."""
    inside = mass_on_target(cam_map, relevant_cells)
    return 1.0 - inside


def target_cells(
    meta: StepMeta,
    camera: str,
    grid: tuple[int, int],
    model_hw: Sequence[int] | None,
    extra: Mapping[str, Any] | None = None,
) -> np.ndarray | None:
    """The patches of the ground-truth box a client sent with a step (`cam_extra/target_box`: x0, y0, x1, y1 in the
    client image of `cam_extra/target_camera`, default the step's first camera), on `camera`'s model frame of size
    `model_hw` (taken from the camera's letterbox geometry when the step has it). None when the step has no box for
    that camera. `extra`: the step's `cam_extra/` values (`CAMStep.extra`: arrays included); default: `meta.extra`.
    -> bool [Hp, Wp]"""
    extra = meta.extra if extra is None else extra
    box = extra.get("target_box")
    if box is None or camera != extra.get("target_camera", next(iter(meta.cameras), None)):
        return None
    info = meta.cameras.get(camera)
    return client_box_cells(box, None if info is None else info.geometry, grid, model_hw)


def client_box_cells(
    box: Sequence[float], geometry: Mapping[str, Any] | None, grid: tuple[int, int], model_hw: Sequence[int] | None
) -> np.ndarray | None:
    """The patches of a box (x0, y0, x1, y1) in a client image, on the model frame of size `model_hw` that the
    camera's letterbox `geometry` (`LetterboxGeometry.as_dict`) places it in (its own size, when given); None
    without either, and None for an empty box (the target is hidden in that frame: a map cannot point at it, so the
    frame is not scored). -> bool [Hp, Wp]"""
    x0, y0, x1, y1 = (float(v) for v in box)
    if not box_visible((x0, y0, x1, y1)):
        return None
    if geometry:  # client pixels -> model pixels through the letterbox
        sx, sy = geometry["resized_w"] / geometry["orig_w"], geometry["resized_h"] / geometry["orig_h"]
        x0, x1 = geometry["pad_left"] + x0 * sx, geometry["pad_left"] + x1 * sx
        y0, y1 = geometry["pad_top"] + y0 * sy, geometry["pad_top"] + y1 * sy
        model_hw = (geometry["model_h"], geometry["model_w"])
    if model_hw is None:
        return None
    return box_cells((x0, y0, x1, y1), grid, (int(model_hw[0]), int(model_hw[1])))
