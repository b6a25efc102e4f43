"""Statistics of a maps dataset (`openpi-cam stats MAPS_DATASET`): one row per explained frame, and the views that
only a whole dataset can give.

Every figure is computed on the displayable map the renderers draw (`viz.overlay.reduce_tokens`: multi-token maps
averaged, NaN and negatives set to 0), per camera, with the run statistics' own per-map figures (`viz.stats`: share
of the frame's mass over cameras, entropy, peak cell). Cameras the model masked (`valid: false`) and maps without
positive mass take no part in the views below.

Definitions (the frame's map of a camera normalised to sum 1 is `p`; the camera's patch count is `P`):

* **Positional prior** of a camera: the mean of `p` over the dataset's frames. How much of a frame's map it
  explains: `prior_cosine` (cosine similarity of `p` and the prior, in [0, 1] for non-negative maps) and `prior_r2`
  (1 - |p - prior|^2 / |p - mean(p)|^2: the share of the frame's variation from patch to patch that the prior
  accounts for; NaN for a flat map); over the dataset the R^2 is pooled (1 - sum of residuals / sum of variations).
  `prior_distance` is the total-variation distance 0.5 * sum |p - prior|, in [0, 1].
* **Hot patch**: a patch is in a frame's top-k when its value is positive and at least the frame's k-th largest
  value (ties at that value all count), with k = ceil(`top_fraction` * P) (at least 1). Its hot rate is the share of
  the camera's frames (valid, with mass) whose top-k holds it. A patch whose hot rate exceeds `hot_threshold` is
  flagged: a map unrelated to position puts a patch in its top-k in about k / P of the frames, so a patch in the
  top-k of most frames, whatever they show, points at the model's position embeddings more than at the image (the
  artefact of OpenPI issue #947). `peak_on_hot`, per frame: whether the frame's peak sits on a flagged patch.
* **Episode ranking**: an episode's entropy is the mean over its frames of the mean `entropy_norm` over the frame's
  cameras; episodes are ranked by it, largest first (the most diffuse maps first), with its z-score over the
  dataset's episodes (0 when they all lie at one value). Chosen by evidence (docs/MAP_KINDS.md, "Do the maps find
  the failures?"): on the demo's failing rollouts it ranks failed episodes first (ROC AUC 0.76 and 0.73 for
  pi0-FAST and pi0.5, gradient norm), where the earlier ranking by distance to the prior (still each episode's
  `distance`: the mean over its frames of the mean `prior_distance` over the frame's cameras) ranked them last
  (0.25, 0.27): failed episodes' maps are diffuse, and diffuse maps lie near the mean map.
* **Spot checks** (`check/<kind>/<camera>`, `check/random/<camera>`): per kind and camera, the share of frames whose
  top patch lowers the score more than the median random patch does (about 50% for a top patch no better than a
  random one) and more than every random patch (chance 1 / (R + 1) for R random patches).
* **Nuisance mass** of a frame's map, where the rows carry the task region (`extra/target_box`, a box in the first
  camera's client image): the share of the first camera's map mass outside the region's patches (Zhang et al.).
* **Reliance** (rows of a `--reliance` job): per camera and for the prompt, the explained score's drop and the action
  chunk's change without it (`cam.reliance`), averaged like the other figures.
* **Outcomes** (rows of a source with outcomes, `episode_success`): failed and successful episodes side by side
  (the group summary of each outcome's frames), and how well each episode figure finds the failures
  (`outcome_views`), also as early as the monitor would have to (`detection_views`: the AUROC of each figure's
  maximum over an episode's first N source frames).

Each view is one accumulator over the typed frames `MapsDataset.episode_frames` reads (`_FrameRows`, `_Prior`,
`_HotPatches`, `_SpotChecks`, `_Conditions`, then `_PriorFit` against the prior); `compute_views` feeds them and
assembles the summaries. Reading needs pyarrow and numpy only (no JAX): the maps are read an episode at a time, twice
(once for the prior, once for each frame's distance to it), so memory holds the rows but never every map.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from openpi_cam.cam.faithfulness import client_box_cells, nuisance_mass_ratio
from openpi_cam.cam.outcomes import finding
from openpi_cam.cam.run_format import RELIANCE_PROMPT
from openpi_cam.maps.dataset import (
    CHECK_RANDOM,
    EPISODE_LENGTH,
    EPISODE_SUCCESS,
    MONITOR_PREFIX,
    EpisodeFrames,
    MapsDataset,
    MapsInfo,
)
from openpi_cam.monitor.detection import FRAMES, ScoredEpisode, detection
from openpi_cam.monitor.signals import SAMPLE_SPREAD, STAC, TOKEN_ENTROPY
from openpi_cam.monitor.stream import SCORE
from openpi_cam.viz.overlay import reduce_tokens
from openpi_cam.viz.stats import camera_stats, mean_score
from openpi_cam.viz.text import finite_mean

# The carried feature (`--extra FEATURE=target_box`) holding the task region: a box (x0, y0, x1, y1) in the client
# image of the dataset's first camera, as the demo records `observation.target_box`.
TARGET_BOX = "target_box"
OUTCOMES = ("success", "failure")  # the order failed and successful episodes are set side by side in


@dataclasses.dataclass(frozen=True)
class ViewOptions:
    top_fraction: float = 0.05  # k = ceil(top_fraction * patches), at least 1: a frame's hottest patches
    hot_threshold: float = 0.5  # a patch in the top-k of more than this share of frames is flagged
    # The early-warning figures read each episode's first this many explained frames. 1: the first request alone,
    # which every episode has, so the figures cannot tell a short episode from a long one.
    early_frames: int = 1
    # The carried feature (`--extra FEATURE=NAME`, by its NAME) whose value names the condition each episode ran under
    # (the demo's perturbation index): with outcomes, failed and successful episodes are also set side by side per
    # condition. None: no conditions.
    group: str | None = None
    group_names: tuple[str, ...] = ()  # the conditions' names, indexed by the feature's value


@dataclasses.dataclass(frozen=True)
class HotPatch:
    camera: str
    row: int
    col: int
    rate: float  # share of the camera's frames whose top-k holds the patch


def top_k(cells: int, top_fraction: float) -> int:
    return max(1, math.ceil(top_fraction * cells))


def displayable(maps: np.ndarray) -> np.ndarray:
    """[N, Hp, Wp] or [N, T, Hp, Wp] raw maps -> [N, Hp, Wp] float64, as the renderers draw each of them."""
    maps = np.asarray(maps)
    if len(maps) == 0:
        return np.zeros((0, *maps.shape[-2:]))
    return np.stack([reduce_tokens(m) for m in maps])


def _rows(maps: np.ndarray) -> np.ndarray:
    """[N, Hp, Wp] -> [N, Hp * Wp], also for N = 0 (a camera the model masked in every frame)."""
    return maps.reshape(len(maps), int(np.prod(maps.shape[1:])))


def normalised(maps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[N, Hp, Wp] non-negative maps -> (each divided by its sum, [N] whether it has positive mass; zeros if not)."""
    maps = np.asarray(maps, np.float64)
    total = _rows(maps).sum(axis=1)
    has_mass = total > 0
    p = np.zeros_like(maps)
    p[has_mass] = maps[has_mass] / total[has_mass, None, None]
    return p, has_mass


def in_top_k(maps: np.ndarray, k: int) -> np.ndarray:
    """bool [N, Hp, Wp]: the patches of each map that are positive and at least its k-th largest value."""
    maps = np.asarray(maps, np.float64)
    flat = _rows(maps)
    k = min(k, flat.shape[1])
    kth = -np.partition(-flat, k - 1, axis=1)[:, k - 1 : k] if len(flat) else np.zeros((0, 1))
    return ((flat >= kth) & (flat > 0)).reshape(maps.shape)


def hot_rates(maps: np.ndarray, k: int) -> np.ndarray:
    """[Hp, Wp]: for each patch, the share of the maps with positive mass whose top-k holds it."""
    maps = np.asarray(maps, np.float64)
    _, has_mass = normalised(maps)
    if not has_mass.any():
        return np.zeros(maps.shape[1:])
    return in_top_k(maps[has_mass], k).mean(axis=0)


def flag_hot(camera: str, rates: np.ndarray, threshold: float) -> list[HotPatch]:
    """The patches whose hot rate exceeds `threshold`, hottest first."""
    rows, cols = np.nonzero(rates > threshold)
    found = [HotPatch(camera, int(r), int(c), float(rates[r, c])) for r, c in zip(rows, cols, strict=True)]
    return sorted(found, key=lambda h: (-h.rate, h.row, h.col))


def prior_fit(p: np.ndarray, prior: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For normalised maps p [N, Hp, Wp] against the prior [Hp, Wp]: (cosine, R^2, total-variation distance, residual
    sum of squares, variation sum of squares), each [N]."""
    flat = _rows(np.asarray(p, np.float64))
    ref = np.asarray(prior, np.float64).reshape(-1)
    norms = np.linalg.norm(flat, axis=1) * np.linalg.norm(ref)
    with np.errstate(invalid="ignore", divide="ignore"):
        cosine = np.where(norms > 0, flat @ ref / np.where(norms > 0, norms, 1.0), np.nan)
        sse = ((flat - ref) ** 2).sum(axis=1)
        sst = ((flat - flat.mean(axis=1, keepdims=True)) ** 2).sum(axis=1)
        r2 = np.where(sst > 0, 1.0 - sse / np.where(sst > 0, sst, 1.0), np.nan)
    distance = 0.5 * np.abs(flat - ref).sum(axis=1)
    return cosine, r2, distance, sse, sst


def episode_ranking(values: Mapping[int, float]) -> list[tuple[int, float, float]]:
    """(episode, value, z-score) ranked by value, largest first; NaN values (no map with mass) last."""
    finite = np.array([d for d in values.values() if math.isfinite(d)])
    mean = float(finite.mean()) if finite.size else math.nan
    std = float(finite.std()) if finite.size else math.nan
    ranked = []
    for episode, d in values.items():
        z = (d - mean) / std if math.isfinite(d) and std > 0 else (0.0 if math.isfinite(d) else math.nan)
        ranked.append((episode, d, z))
    return sorted(ranked, key=lambda t: (not math.isfinite(t[1]), -t[1] if math.isfinite(t[1]) else 0.0, t[0]))


@dataclasses.dataclass
class DatasetViews:
    """A maps dataset's per-frame rows and dataset-level views of one kind of map (see the module docstring)."""

    kind: str
    cameras: list[str]
    camera_sources: dict[str, str]
    options: ViewOptions
    rows: list[dict[str, Any]]
    prior: dict[str, np.ndarray]  # camera -> mean normalised map [Hp, Wp] (zeros without any map with mass)
    hot_rate: dict[str, np.ndarray]  # camera -> [Hp, Wp] share of frames whose top-k holds the patch
    hot: dict[str, list[HotPatch]]
    fit: dict[str, dict[str, Any]]  # camera -> dataset-level prior fit
    episodes: list[dict[str, Any]]  # ranked, most diffuse maps first
    tasks: list[dict[str, Any]]
    checks: list[dict[str, Any]]  # per kind and camera: the spot checks' summary
    info: MapsInfo
    outcomes: dict[str, Any] | None = None  # `outcome_views`, when the source records outcomes
    # per condition (`_Conditions.views`), when the source records outcomes and carries `ViewOptions.group`
    groups: list[dict[str, Any]] | None = None

    def summary(self) -> dict[str, Any]:
        """The dataset-level views as plain JSON data."""
        k = {c: top_k(int(np.prod(self.prior[c].shape)), self.options.top_fraction) for c in self.cameras}
        return {
            "maps_dataset": {
                "source": self.info.source,
                "source_version": self.info.source_version,
                "config": self.info.model.get("config"),
                "target": self.info.target,
            },
            "kind": self.kind,
            "frames": len(self.rows),
            "episodes": len(self.episodes),
            "cameras": {
                c: {
                    "feature": self.camera_sources.get(c),
                    "grid": list(self.prior[c].shape),
                    "prior": self.prior[c].tolist(),
                    "prior_fit": self.fit[c],
                    "top_k": k[c],
                    "hot_rate": self.hot_rate[c].tolist(),
                    "hot_patches": [dataclasses.asdict(h) for h in self.hot[c]],
                    "hot_chance": k[c] / max(1, int(np.prod(self.prior[c].shape))),
                }
                for c in self.cameras
            },
            "hot_rule": f"a patch is hot in a frame when it is among the frame's top-k (k = ceil("
            f"{self.options.top_fraction} * patches)); flagged when hot in more than {self.options.hot_threshold:.0%}"
            " of the camera's frames",
            "episode_ranking": self.episodes,
            "tasks": self.tasks,
            "spot_checks": self.checks,
            **({} if self.outcomes is None else {"outcomes": self.outcomes}),
            **({} if self.groups is None else {"groups": self.groups}),
        }


def _finite_or_none(x: Any) -> Any:
    return None if isinstance(x, float) and not math.isfinite(x) else x


def _check_figures(top: Any, randoms: Any) -> tuple[float, float, float]:
    """(top patch's drop, median random drop, largest random drop), NaN where the frame has no check."""
    drops = [float(d) for d in (randoms or []) if d is not None and math.isfinite(d)]
    top = float(top) if top is not None and math.isfinite(top) else math.nan
    if not drops:
        return top, math.nan, math.nan
    return top, float(np.median(drops)), max(drops)


def _nuisance(box: Sequence[float] | None, cameras: Mapping[str, Any], camera: str, m: np.ndarray) -> float | None:
    """The nuisance mass ratio of `camera`'s map where the frame carries the task region's box (given in that
    camera's client image); None without one."""
    if box is None:
        return None
    cells = client_box_cells(box, cameras.get(camera, {}).get("geometry"), m.shape, None)
    return None if cells is None else nuisance_mass_ratio(m, cells)


@dataclasses.dataclass(frozen=True)
class _Shown:
    """An episode's frames with each camera's map as the renderers draw it (`displayable`), normalised to sum 1, and
    which frames take part in the views (the model saw the camera and the map has positive mass)."""

    frames: EpisodeFrames
    maps: dict[str, np.ndarray]  # camera -> [N, Hp, Wp]
    p: dict[str, np.ndarray]  # camera -> [N, Hp, Wp], zeros without mass
    valid: dict[str, np.ndarray]  # camera -> bool [N]
    use: dict[str, np.ndarray]  # camera -> bool [N]

    @classmethod
    def of(cls, frames: EpisodeFrames) -> _Shown:
        maps = {c: displayable(m) for c, m in frames.maps.items()}
        valid = {c: frames.valid(c) for c in maps}
        normalised_maps = {c: normalised(m) for c, m in maps.items()}
        p = {c: n[0] for c, n in normalised_maps.items()}
        return cls(frames, maps, p, valid, {c: valid[c] & normalised_maps[c][1] for c in maps})


class _FrameRows:
    """The per-frame rows: each frame's dataset columns and, per camera, the run statistics' figures of its map, its
    nuisance mass (None without a task region) and this kind's spot check (the prior's columns stay None until
    `_PriorFit` fills them)."""

    def __init__(self, kind: str, box: str | None) -> None:
        self.kind, self.box = kind, box
        self.rows: list[dict[str, Any]] = []

    def add(self, shown: _Shown) -> None:
        frames, cameras = shown.frames, list(shown.maps)
        for i, meta in enumerate(frames.meta):
            maps = {c: shown.maps[c][i] for c in cameras}
            valid = {c: bool(shown.valid[c][i]) for c in cameras}
            box = frames.extra[self.box][i] if self.box is not None else None
            nuisance = _nuisance(box, frames.cameras[i], cameras[0], maps[cameras[0]])
            checks = {c: (frames.checks[self.kind][c][i], frames.checks[CHECK_RANDOM][c][i]) for c in cameras}
            self.rows.append(_frame_row(meta, maps, valid, checks, {cameras[0]: nuisance}))


def _frame_row(
    meta: Mapping[str, Any],
    maps: Mapping[str, np.ndarray],
    valid: Mapping[str, bool],
    checks: Mapping[str, tuple[Any, Any]],
    nuisance: Mapping[str, float | None],
) -> dict[str, Any]:
    """One frame's row (`_FrameRows`); `checks`: per camera the top patch's drop and the random patches' drops."""
    total = sum(float(m.sum()) for c, m in maps.items() if valid[c])
    per_camera = {c: camera_stats(m, valid[c], total) for c, m in maps.items()}
    best = max(per_camera.items(), key=lambda kv: kv[1].share, default=None)
    row: dict[str, Any] = dict(meta)
    row["dominant"] = best[0] if best is not None and best[1].share > 0 else None
    for c, cs in per_camera.items():
        top, rand_median, rand_max = _check_figures(*checks[c])
        row |= {
            f"{c}/valid": cs.valid,
            f"{c}/share": cs.share,
            f"{c}/entropy": _finite_or_none(cs.entropy),
            f"{c}/entropy_norm": _finite_or_none(cs.entropy_norm),
            f"{c}/peak_row": cs.peak[0] if cs.peak else None,
            f"{c}/peak_col": cs.peak[1] if cs.peak else None,
            f"{c}/peak_value": _finite_or_none(cs.peak_value),
            f"{c}/check_top_drop": _finite_or_none(top),
            f"{c}/check_random_median": _finite_or_none(rand_median),
            f"{c}/check_random_max": _finite_or_none(rand_max),
            f"{c}/nuisance_mass": _finite_or_none(nuisance.get(c)),
            f"{c}/prior_cosine": None,
            f"{c}/prior_r2": None,
            f"{c}/prior_distance": None,
            f"{c}/peak_on_hot": None,
        }
    return row


class _Prior:
    """The positional prior: per camera the mean normalised map over the frames that take part."""

    def __init__(self, grids: Mapping[str, tuple[int, int]]) -> None:
        self.sums = {c: np.zeros(g) for c, g in grids.items()}
        self.frames = dict.fromkeys(grids, 0)

    def add(self, shown: _Shown) -> None:
        for c, use in shown.use.items():
            self.sums[c] += shown.p[c][use].sum(axis=0)
            self.frames[c] += int(use.sum())

    def mean(self) -> dict[str, np.ndarray]:
        return {c: total / self.frames[c] if self.frames[c] else np.zeros_like(total) for c, total in self.sums.items()}


class _HotPatches:
    """Per camera and patch, the share of the frames that take part whose top-k holds it, and the flagged ones."""

    def __init__(self, grids: Mapping[str, tuple[int, int]], options: ViewOptions) -> None:
        self.options = options
        self.k = {c: top_k(g[0] * g[1], options.top_fraction) for c, g in grids.items()}
        self.counts = {c: np.zeros(g, np.int64) for c, g in grids.items()}
        self.frames = dict.fromkeys(grids, 0)

    def add(self, shown: _Shown) -> None:
        for c, use in shown.use.items():
            self.counts[c] += in_top_k(shown.maps[c][use], self.k[c]).sum(axis=0)
            self.frames[c] += int(use.sum())

    def rates(self) -> dict[str, np.ndarray]:
        return {c: n / self.frames[c] if self.frames[c] else np.zeros(n.shape) for c, n in self.counts.items()}

    def flagged(self) -> dict[str, list[HotPatch]]:
        return {c: flag_hot(c, rates, self.options.hot_threshold) for c, rates in self.rates().items()}


class _SpotChecks:
    """Per kind and camera, the figures of every frame whose spot check has a top patch and random patches
    (`check_summary`)."""

    def __init__(self, kinds: Sequence[str]) -> None:
        self.kinds = list(kinds)
        self.figures: dict[tuple[str, str], list[tuple[float, float, float, int]]] = {}

    def add(self, shown: _Shown) -> None:
        checks = shown.frames.checks
        for i in range(len(shown.frames)):
            for kind in self.kinds:
                for c in shown.maps:
                    randoms = checks[CHECK_RANDOM][c][i] or []
                    top, rand_median, rand_max = _check_figures(checks[kind][c][i], randoms)
                    if math.isfinite(top) and math.isfinite(rand_median):
                        count = sum(1 for d in randoms if d is not None and math.isfinite(d))
                        self.figures.setdefault((kind, c), []).append((top, rand_median, rand_max, count))


class _Conditions:
    """With outcomes and `ViewOptions.group`: each episode's condition, and per (condition, failed, camera) the sum of
    the normalised maps of the frames that take part and their count."""

    def __init__(self, grids: Mapping[str, tuple[int, int]], group: str | None) -> None:
        self.grids, self.group = grids, group
        self.episode_group: dict[int, int] = {}
        self.maps: dict[tuple[int, bool, str], list[Any]] = {}

    def add(self, shown: _Shown) -> None:
        frames = shown.frames
        if self.group is None or not len(frames):
            return
        group = self.episode_group[frames.episode] = int(np.asarray(frames.extra[self.group][0]).reshape(-1)[0])
        for c, use in shown.use.items():
            total = self.maps.setdefault((group, _failed(frames.meta), c), [np.zeros(self.grids[c]), 0])
            total[0] = total[0] + shown.p[c][use].sum(axis=0)
            total[1] += int(use.sum())

    def views(
        self, by_episode: Mapping[int, Sequence[Mapping[str, Any]]], cameras: Sequence[str], names: Sequence[str]
    ) -> list[dict[str, Any]]:
        """Per condition (named by `names` where its value indexes them): its episodes and successes, failed and
        successful episodes side by side (the group summary of each outcome's frames) and each camera's mean
        normalised map over each outcome's frames (None where the outcome has no frame with mass)."""
        out = []
        for group in sorted(set(self.episode_group.values())):
            episodes = [e for e in sorted(by_episode) if self.episode_group.get(e) == group]
            mean_maps = {}
            for name in OUTCOMES:
                mean_maps[name] = {}
                for c in cameras:
                    total, frames = self.maps.get((group, name == "failure", c), (None, 0))
                    mean_maps[name][c] = (total / frames).tolist() if frames else None
            out.append(
                {
                    self.group: group,
                    "name": names[group] if 0 <= group < len(names) else None,
                    "episodes": len(episodes),
                    "successes": sum(not _failed(by_episode[e]) for e in episodes),
                    "by_outcome": by_outcome(by_episode, episodes, cameras),
                    "mean_maps": mean_maps,
                }
            )
        return out


class _PriorFit:
    """Pass two: each frame's map against the prior into its row (cosine, R^2, total-variation distance, whether its
    peak sits on a flagged patch), and per camera the sums of the pooled R^2."""

    def __init__(
        self, prior: Mapping[str, np.ndarray], hot: Mapping[str, Sequence[HotPatch]], rows: list[dict[str, Any]]
    ) -> None:
        self.prior, self.rows = prior, rows
        self.hot_cells = {c: {(h.row, h.col) for h in flagged} for c, flagged in hot.items()}
        self.sums = {c: {"sse": 0.0, "sst": 0.0} for c in prior}
        self.first = 0  # the row of the next episode's first frame

    def add(self, shown: _Shown) -> None:
        for c, use in shown.use.items():
            cosine, r2, distance, sse, sst = prior_fit(shown.p[c], self.prior[c])
            self.sums[c]["sse"] += float(sse[use].sum())
            self.sums[c]["sst"] += float(sst[use].sum())
            for i in np.nonzero(use)[0]:
                row = self.rows[self.first + i]
                row[f"{c}/prior_cosine"] = _finite_or_none(float(cosine[i]))
                row[f"{c}/prior_r2"] = _finite_or_none(float(r2[i]))
                row[f"{c}/prior_distance"] = float(distance[i])
                row[f"{c}/peak_on_hot"] = (row[f"{c}/peak_row"], row[f"{c}/peak_col"]) in self.hot_cells[c]
        self.first += len(shown.frames)

    def summary(self, frames: Mapping[str, int]) -> dict[str, dict[str, Any]]:
        """Per camera the dataset-level fit; `frames`: the frames that took part in the prior."""
        fit = {}
        for c, sums in self.sums.items():
            cos = [x for row in self.rows if (x := row[f"{c}/prior_cosine"]) is not None]
            fit[c] = {
                "frames": frames[c],
                "mean_cosine": finite_mean(cos),
                "median_cosine": _finite_or_none(float(np.median(cos))) if cos else None,
                "pooled_r2": 1.0 - sums["sse"] / sums["sst"] if sums["sst"] > 0 else None,
                "mean_distance": finite_mean(row[f"{c}/prior_distance"] for row in self.rows),
                "peak_on_hot": finite_mean(p for row in self.rows if (p := row[f"{c}/peak_on_hot"]) is not None),
            }
        return fit


def compute_views(
    ds: MapsDataset, kind: str, options: ViewOptions = ViewOptions(), episodes: Sequence[int] | None = None
) -> DatasetViews:
    """Per-frame rows and the dataset-level views of `kind`'s maps over `episodes` (default: every written one)."""
    ds.require_kind(kind)
    cameras, grids = ds.cameras, {c: ds.grid(c) for c in ds.cameras}
    episodes = list(ds.episodes if episodes is None else episodes)
    carried = ds.info.extra.values()
    box = TARGET_BOX if TARGET_BOX in carried else None
    group = options.group if ds.info.outcome is not None and options.group in carried else None
    rows, prior, hot = _FrameRows(kind, box), _Prior(grids), _HotPatches(grids, options)
    checks, conditions = _SpotChecks(ds.kinds), _Conditions(grids, group)
    for episode in episodes:
        shown = _Shown.of(ds.episode_frames(episode, kind, checks=True, extra=[n for n in (box, group) if n]))
        for view in (rows, prior, hot, checks, conditions):
            view.add(shown)
    flagged = hot.flagged()
    fit = _PriorFit(prior.mean(), flagged, rows.rows)
    for episode in episodes:
        fit.add(_Shown.of(ds.episode_frames(episode, kind)))
    by_episode: dict[int, list[dict[str, Any]]] = {}
    for row in rows.rows:
        by_episode.setdefault(int(row["episode_index"]), []).append(row)
    return DatasetViews(
        kind=kind,
        cameras=cameras,
        camera_sources=dict(ds.info.camera_sources),
        options=options,
        rows=rows.rows,
        prior=prior.mean(),
        hot_rate=hot.rates(),
        hot=flagged,
        fit=fit.summary(prior.frames),
        episodes=_ranked_episodes(by_episode, episodes, cameras),
        tasks=_task_rows(rows.rows, cameras),
        checks=check_summary(checks.figures),
        info=ds.info,
        outcomes=outcome_views(by_episode, cameras, options) if ds.info.outcome is not None else None,
        groups=conditions.views(by_episode, cameras, options.group_names) if group is not None else None,
    )


def _ranked_episodes(
    by_episode: Mapping[int, Sequence[Mapping[str, Any]]], episodes: Sequence[int], cameras: Sequence[str]
) -> list[dict[str, Any]]:
    """The episode ranking (`episode_ranking` by `episode_entropy`), each with its figures and group summary."""
    entropies = {e: episode_entropy(by_episode.get(e, []), cameras) for e in episodes}
    ranked = []
    for rank, (episode, entropy, z) in enumerate(episode_ranking(entropies), start=1):
        group = by_episode.get(episode, [])
        tasks = Counter(str(row["task"]) for row in group)
        ranked.append(
            {
                "rank": rank,
                "episode_index": episode,
                "task": tasks.most_common(1)[0][0] if tasks else None,
                "entropy": _finite_or_none(entropy),
                "z": _finite_or_none(z),
                "distance": _finite_or_none(episode_distance(group, cameras)),
                **episode_outcome(group),
                **group_summary(group, cameras),
            }
        )
    return ranked


def _task_rows(rows: Sequence[Mapping[str, Any]], cameras: Sequence[str]) -> list[dict[str, Any]]:
    by_task: dict[str, list[Mapping[str, Any]]] = {}
    for row in rows:
        by_task.setdefault(str(row["task"]), []).append(row)
    return [
        {"task": task, "episodes": len({int(row["episode_index"]) for row in group}), **group_summary(group, cameras)}
        for task, group in sorted(by_task.items())
    ]


def _failed(rows: Sequence[Mapping[str, Any]]) -> bool:
    """Whether an episode (its rows, which carry the `episode_*` columns) failed."""
    return not rows[0][EPISODE_SUCCESS]


def by_outcome(
    by_episode: Mapping[int, Sequence[Mapping[str, Any]]], episodes: Sequence[int], cameras: Sequence[str]
) -> dict[str, dict[str, Any]]:
    """The successful and the failed ones of `episodes` side by side: per outcome, its episodes and the group summary
    of their frames."""
    out = {}
    for name in OUTCOMES:
        chosen = [e for e in episodes if _failed(by_episode[e]) == (name == "failure")]
        out[name] = {"episodes": len(chosen), **group_summary([row for e in chosen for row in by_episode[e]], cameras)}
    return out


def _frames_mean(rows: Sequence[Mapping[str, Any]], cameras: Sequence[str], field: str) -> float:
    """The mean over frames of the mean of a per-camera field over the frame's cameras that have it (valid, with
    mass); NaN when no frame has it."""
    per_frame = []
    for row in rows:
        values = [row[f"{c}/{field}"] for c in cameras if row.get(f"{c}/{field}") is not None]
        if values:
            per_frame.append(float(np.mean(values)))
    return float(np.mean(per_frame)) if per_frame else math.nan


def episode_entropy(rows: Sequence[Mapping[str, Any]], cameras: Sequence[str]) -> float:
    """How diffuse an episode's maps are: the mean over its frames of the mean normalised entropy over the frame's
    cameras. What the episode ranking sorts by."""
    return _frames_mean(rows, cameras, "entropy_norm")


def episode_distance(rows: Sequence[Mapping[str, Any]], cameras: Sequence[str]) -> float:
    """How far an episode's maps lie from the prior: the mean over its frames of the mean `prior_distance` over the
    frame's cameras."""
    return _frames_mean(rows, cameras, "prior_distance")


def episode_outcome(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """An episode's length and success from its rows (the `episode_*` columns; nothing without outcomes)."""
    if not rows or EPISODE_SUCCESS not in rows[0]:
        return {}
    return {"success": rows[0][EPISODE_SUCCESS], "length": rows[0][EPISODE_LENGTH]}


# The per-camera means of `group_summary` that `outcome_views` tries as failure detectors.
CAMERA_FIGURES = (
    "mean_share",
    "mean_entropy_norm",
    "mean_prior_distance",
    "mean_nuisance_mass",
    "mean_reliance_score",
    "mean_reliance_actions",
)
PROMPT_FIGURES = ("mean_reliance_score", "mean_reliance_actions")


def episode_figures(rows: Sequence[Mapping[str, Any]], cameras: Sequence[str]) -> dict[str, float]:
    """The single figures of an episode (or of its first frames) that `outcome_views` tries as failure detectors:
    the ranking's entropy, the distance to the prior, the mean explained score, per camera `CAMERA_FIGURES` and the
    prompt's `PROMPT_FIGURES`. NaN: not measured."""
    summary = group_summary(rows, cameras)
    figures = {
        "entropy": episode_entropy(rows, cameras),
        "distance": episode_distance(rows, cameras),
        "mean_score": summary["mean_score"],
    }
    figures |= {f"{c}/{key}": summary["cameras"][c][key] for c in cameras for key in CAMERA_FIGURES}
    figures |= {f"{RELIANCE_PROMPT}/{key}": summary[RELIANCE_PROMPT][key] for key in PROMPT_FIGURES}
    return {k: math.nan if v is None else float(v) for k, v in figures.items()}


def _findings(failed: np.ndarray, figures: Sequence[Mapping[str, float]]) -> dict[str, dict[str, Any]]:
    """`cam.outcomes.finding` of each figure some episode has."""
    names = [n for n in (figures[0] if figures else {}) if any(math.isfinite(f[n]) for f in figures)]
    return {name: finding(failed, [f[name] for f in figures]) for name in names}


def outcome_views(
    by_episode: Mapping[int, Sequence[Mapping[str, Any]]], cameras: Sequence[str], options: ViewOptions
) -> dict[str, Any]:
    """Failed and successful episodes side by side (the group summary of each outcome's frames), and how well each
    episode figure finds the failures (`cam.outcomes.finding`: ROC AUC, larger = failure, with its interval, and
    precision at the number of failures, next to chance): over whole episodes, with the episode's length as the
    baseline every figure must beat (failures run to the step limit, successes stop early), and from each episode's
    first `early_frames` explained frames only (what a user watching a live robot has; length cannot help there)."""
    episodes = sorted(by_episode)
    failed = np.array([_failed(by_episode[e]) for e in episodes], bool)
    whole = [
        episode_figures(by_episode[e], cameras) | {"length": float(by_episode[e][0][EPISODE_LENGTH])} for e in episodes
    ]
    early = [
        episode_figures(sorted(by_episode[e], key=lambda r: r["frame_index"])[: options.early_frames], cameras)
        for e in episodes
    ]
    return {
        "episodes": len(episodes),
        "failures": int(failed.sum()),
        "by_outcome": by_outcome(by_episode, episodes, cameras),
        "failure_finding": _findings(failed, whole),
        "early_warning": {"frames": options.early_frames, "figures": _findings(failed, early)},
        "detection": detection_views(by_episode, cameras),
    }


# The monitor's columns of a row that `detection_views` ranks, each under its figure's name: the monitor's own score
# (the one name holding `monitor`, so a reader finds the monitor among the baselines) and the training-free
# baselines that come with every served call, and the sample spread where it was drawn (`--sample-spread`).
MONITOR_FIGURES = {
    MONITOR_PREFIX + SCORE: "monitor",
    MONITOR_PREFIX + STAC: STAC,
    MONITOR_PREFIX + TOKEN_ENTROPY: TOKEN_ENTROPY,
    MONITOR_PREFIX + SAMPLE_SPREAD: SAMPLE_SPREAD,
}


def step_figures(row: Mapping[str, Any], cameras: Sequence[str]) -> dict[str, float]:
    """One explained frame's figures as step scores of a failure detector: `episode_figures` of the frame alone (the
    map figures under the names `failure_finding` gives them) and the monitor's columns the row carries
    (`MONITOR_FIGURES`). NaN: not measured."""
    figures = episode_figures([row], cameras)
    for column, name in MONITOR_FIGURES.items():
        value = row.get(column)
        figures[name] = math.nan if value is None else float(value)
    return figures


def detection_views(
    by_episode: Mapping[int, Sequence[Mapping[str, Any]]], cameras: Sequence[str], frames: Sequence[int] = FRAMES
) -> list[dict[str, Any]]:
    """`monitor.detection.detection` over the episodes' explained frames: for N in `frames` and the whole episode,
    each figure's AUROC of failure over the episodes' maxima of its step scores (`step_figures`) within their first
    N source frames (`frame_index`). Figures keep the orientation `failure_finding` gives them (the figure itself,
    larger ranking as failing; an AUROC below 0.5 ranks the other way). Figures no frame measured are left out."""
    episodes = []
    for e in sorted(by_episode):
        rows = sorted(by_episode[e], key=lambda r: r["frame_index"])
        steps = [step_figures(row, cameras) for row in rows]
        scores = {name: np.array([step[name] for step in steps]) for name in steps[0]} if steps else {}
        episodes.append(ScoredEpisode(np.array([row["frame_index"] for row in rows]), scores, _failed(rows)))
    measured = {name for e in episodes for name, s in e.scores.items() if np.isfinite(s).any()}
    kept = [dataclasses.replace(e, scores={n: s for n, s in e.scores.items() if n in measured}) for e in episodes]
    return detection(kept, frames)


def detection_lines(entries: Sequence[Mapping[str, Any]]) -> list[str]:
    """`detection_views` as a short table: per figure its AUROC at each N (`-`: no AUROC), the monitor's first."""
    if not entries:
        return []
    names = sorted(entries[0]["figures"], key=lambda n: ("monitor" not in n, n))
    width = max([len("figure"), *(len(n) for n in names)])
    head = "".join(f"{('N=' + str(e['frames'])) if isinstance(e['frames'], int) else e['frames']:>9}" for e in entries)
    lines = [
        "failure detection: AUROC of each figure's maximum over an episode's first N source frames",
        f"{'figure':<{width}}{head}",
    ]
    for name in names:
        cells = [e["figures"][name]["auroc"] for e in entries]
        lines.append(f"{name:<{width}}" + "".join(f"{'-' if a is None else f'{a:.3f}':>9}" for a in cells))
    return lines


def group_summary(rows: Sequence[Mapping[str, Any]], cameras: Sequence[str]) -> dict[str, Any]:
    """A group of frames (an episode, a task, an outcome): frames, mean score, malformed generations, per camera the
    mean share, normalised entropy, the most frequent peak cell (with its rate), the mean peak cell, the fit to the
    prior, the mean nuisance mass and reliance, and the prompt's mean reliance (None where not measured)."""
    out: dict[str, Any] = {
        "frames": len(rows),
        "mean_score": finite_mean(mean_score(row["score"]) for row in rows),
        "malformed": sum(1 for row in rows if row["malformed"]),
        "dominant": dict(Counter(row["dominant"] for row in rows if row["dominant"] is not None)),
    }
    per_camera = {}
    for c in cameras:
        valid = [row for row in rows if row[f"{c}/valid"]]
        peaks = Counter(
            (row[f"{c}/peak_row"], row[f"{c}/peak_col"]) for row in valid if row[f"{c}/peak_row"] is not None
        )
        mode, count = peaks.most_common(1)[0] if peaks else (None, 0)
        per_camera[c] = {
            "valid_frames": len(valid),
            "mean_share": finite_mean(row[f"{c}/share"] for row in valid),
            "mean_entropy": finite_mean(row[f"{c}/entropy"] for row in valid),
            "mean_entropy_norm": finite_mean(row[f"{c}/entropy_norm"] for row in valid),
            "peak_mode": list(mode) if mode else None,
            "peak_mode_rate": count / sum(peaks.values()) if peaks else None,
            "mean_peak": [
                finite_mean(row[f"{c}/peak_row"] for row in valid),
                finite_mean(row[f"{c}/peak_col"] for row in valid),
            ],
            "mean_prior_cosine": finite_mean(row.get(f"{c}/prior_cosine") for row in valid),
            "mean_prior_distance": finite_mean(row.get(f"{c}/prior_distance") for row in valid),
            "mean_nuisance_mass": finite_mean(row.get(f"{c}/nuisance_mass") for row in valid),
            "mean_reliance_score": finite_mean(row.get(f"{c}/reliance_score") for row in valid),
            "mean_reliance_actions": finite_mean(row.get(f"{c}/reliance_actions") for row in valid),
        }
    out["cameras"] = per_camera
    out[RELIANCE_PROMPT] = {
        "mean_reliance_score": finite_mean(row.get(f"{RELIANCE_PROMPT}/reliance_score") for row in rows),
        "mean_reliance_actions": finite_mean(row.get(f"{RELIANCE_PROMPT}/reliance_actions") for row in rows),
    }
    return out


def check_summary(checks: Mapping[tuple[str, str], Sequence[tuple[float, float, float, int]]]) -> list[dict[str, Any]]:
    """Per (kind, camera): frames checked, median top-patch drop, median of the frames' median random drop, the share
    of frames whose top patch beats the median random patch (about 50% by chance) and every random patch (chance
    1 / (R + 1))."""
    out = []
    for (kind, camera), figures in checks.items():
        top = np.array([f[0] for f in figures])
        median = np.array([f[1] for f in figures])
        largest = np.array([f[2] for f in figures])
        out.append(
            {
                "kind": kind,
                "camera": camera,
                "frames": len(figures),
                "median_top_drop": float(np.median(top)),
                "median_random_drop": float(np.median(median)),
                "beats_median_random": float(np.mean(top > median)),
                "beats_every_random": float(np.mean(top > largest)),
                "chance_every": float(np.mean([1.0 / (f[3] + 1) for f in figures])),
            }
        )
    return out
