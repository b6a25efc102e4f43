"""Fitting an occlusion head (`model.occlusion_head`) to a policy's own occlusion maps, read from maps datasets that
carry the head's input kinds and `occlusion` (`openpi-cam head fit`).

An example is one camera's maps of one explained score in one frame, where the camera was valid and its occlusion
map is not all zeros (nothing to rank); inputs and target are normalised as the head normalises them
(`occlusion_head.normalised`). The episodes are split by a seed into fitting and held-out ones, so that no held-out
frame has a sibling from its own episode in the fit (frames of one episode look alike, and a split by frame would
flatter the head). The head is fitted by Adam, full batch, from a seeded initialisation, on the mean over examples of
a listwise loss: the cross-entropy between the softmax over the camera's patches of the target and of the prediction,
both at temperature `temperature` (ListNet, Cao et al. 2007), which weighs the top patches most, plus `mse_weight`
times the squared error, which pins the scale and offset the softmax leaves free, so that the map reads as a share
of the camera's largest drop.

Held-out figures, per camera and over all examples: top-1 agreement with occlusion (the share of examples whose
highest patch is occlusion's) and Spearman's correlation with occlusion (median and mean), for the head, for each
input kind alone, and for the position prior (the fitting episodes' mean occlusion map per camera: where occlusion
tends to fall, whatever the frame; a head that only matches it has learnt the place, not read its inputs).
Deletion needs the model to re-score painted frames, so it is not measured here: explain frames with the kind and
run `openpi-cam faithfulness` on them.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

from openpi_cam.cam.faithfulness import spearman, top1_agreement
from openpi_cam.maps import dataset as fmt
from openpi_cam.model.occlusion_head import TARGET_KIND, OcclusionHead, check_inputs, normalised
from openpi_cam.vocabulary import DATASET_ACTIONS

# What `fit` records in place of deletion figures.
DELETION_NOT_MEASURED = (
    "not measured offline: deletion re-scores painted frames with the model; explain frames with the kind and run "
    "`openpi-cam faithfulness` on them"
)


@dataclasses.dataclass(frozen=True)
class HeadFitOptions:
    """How a head is fitted (module docstring). The inputs default to the kinds at most two backward passes give
    on every family (the gradient pass's Grad-CAM and gradient norm, AttnLRP's pass)."""

    inputs: tuple[str, ...] = ("gradcam", "gradnorm", "lrp")
    hidden: int = 16  # tanh units; 0: a linear head
    steps: int = 2000  # full-batch Adam steps
    learning_rate: float = 1e-2
    temperature: float = 0.1  # of the listwise softmax, in units of the camera's largest normalised value (1)
    mse_weight: float = 1.0
    # L2 on the weights (not the biases): on ~100-frame dev sets (docs/MAP_KINDS.md) 1e-2 held out as well as or
    # better than 1e-4, a linear head or fewer steps, which the small data sets' over-fitting favours
    weight_decay: float = 1e-2
    holdout: float = 0.25  # share of the episodes held out
    seed: int = 0  # the initialisation and the split

    def __post_init__(self) -> None:
        check_inputs(self.inputs)
        if self.hidden < 0 or self.steps < 1 or self.learning_rate <= 0:
            raise ValueError(f"need hidden >= 0, steps >= 1 and learning_rate > 0, got {self}")
        if self.temperature <= 0 or self.mse_weight < 0 or self.weight_decay < 0:
            raise ValueError(f"need temperature > 0, mse_weight >= 0 and weight_decay >= 0, got {self}")
        if not 0 < self.holdout < 1:
            raise ValueError(f"--holdout must be a share of the episodes strictly between 0 and 1, got {self.holdout}")


@dataclasses.dataclass(frozen=True)
class HeadExamples:
    """Normalised examples (module docstring): inputs [M, N, K] (K input kinds in `kinds` order, N patches),
    target [M, N], and per example its camera (index into `cameras`) and its episode (index into `episodes`, the
    unit the split keeps together)."""

    kinds: tuple[str, ...]
    cameras: tuple[str, ...]
    grid: tuple[int, int]
    target_name: str  # the explained target of the maps
    family: str
    model: dict[str, Any]
    inputs: np.ndarray
    target: np.ndarray
    camera: np.ndarray
    episode: np.ndarray
    episodes: tuple[str, ...]  # "DATASET#EPISODE"

    def subset(self, rows: np.ndarray) -> HeadExamples:
        return dataclasses.replace(
            self,
            inputs=self.inputs[rows],
            target=self.target[rows],
            camera=self.camera[rows],
            episode=self.episode[rows],
        )

    def __len__(self) -> int:
        return len(self.target)


def _describe(ds: fmt.MapsDataset) -> tuple[Any, ...]:
    """What must be the same in every dataset one head is fitted on."""
    info = ds.info
    target = "chunk" if info.target == DATASET_ACTIONS else info.target
    grids = tuple(tuple(info.grids[c]) for c in info.cameras)
    return (info.model.get("config"), info.family, tuple(info.cameras), grids, target)


def read_examples(paths: Sequence[pathlib.Path], kinds: Sequence[str]) -> HeadExamples:
    """The examples of every episode of the maps datasets at `paths`. A dataset that is not one, lacks a kind, or
    was made with another model, target or cameras than the first is refused in one line naming it."""
    kinds = check_inputs(kinds)
    if not paths:
        raise ValueError("no maps datasets to fit on")
    inputs, target, camera, episode, names = [], [], [], [], []
    first: tuple[Any, ...] | None = None
    for path in paths:
        ds = fmt.open_maps_dataset(path)
        missing = [k for k in (*kinds, TARGET_KIND) if k not in ds.kinds]
        if missing:
            raise ValueError(
                f"{path}: the maps dataset has no {missing} maps (it holds {ds.kinds}); explain it with --maps "
                f"{' '.join((*kinds, TARGET_KIND))}"
            )
        described = _describe(ds)
        if first is None:
            first, first_ds = described, ds
        elif described != first:
            fields = ("config", "family", "cameras", "grids", "target")
            diffs = [f"{f} {a!r} != {b!r}" for f, a, b in zip(fields, first, described, strict=True) if a != b]
            raise ValueError(f"{path}: made otherwise than {paths[0]} ({'; '.join(diffs)}): one head fits one policy")
        for e in ds.episodes:
            x, t, c = _episode_examples(ds, e, kinds)
            inputs.append(x)
            target.append(t)
            camera.append(c)
            episode.append(np.full(len(t), len(names)))
            names.append(f"{path}#{e}")
    assert first is not None
    _, family, cameras, grids, target_name = first
    if not sum(len(t) for t in target):
        raise ValueError(f"{paths[0]}: no frame has a valid camera with a non-zero occlusion map")
    return HeadExamples(
        kinds=kinds,
        cameras=cameras,
        grid=grids[0],
        target_name=target_name,
        family=family,
        model=dict(first_ds.info.model),
        inputs=np.concatenate(inputs),
        target=np.concatenate(target),
        camera=np.concatenate(camera),
        episode=np.concatenate(episode),
        episodes=tuple(names),
    )


def _episode_examples(
    ds: fmt.MapsDataset, episode: int, kinds: Sequence[str]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One episode's examples: inputs [M, N, K], target [M, N], camera index [M]."""
    columns = [fmt.CAMERAS_COLUMN, *(fmt.map_column(k, c) for k in (*kinds, TARGET_KIND) for c in ds.cameras)]
    table = ds.table(episode, columns)
    valid = [json.loads(text) if text else {} for text in table.column(fmt.CAMERAS_COLUMN).to_pylist()]
    xs, ts, cs = [], [], []
    for index, camera in enumerate(ds.cameras):
        n = int(np.prod(ds.grid(camera)))

        def flat(kind: str, camera: str = camera, n: int = n) -> np.ndarray:
            column = table.column(fmt.map_column(kind, camera))
            if column.null_count:
                raise ValueError(f"{ds.root}: episode {episode} has frames without {kind}/{camera} maps")
            return fmt.map_array(column, ds.grid(camera)).reshape(len(table), -1, n)  # [rows, scores, N]

        seen = np.array([bool(v.get(camera, {}).get("valid", True)) for v in valid])
        x = np.stack([flat(k) for k in kinds], axis=-1)[seen].reshape(-1, n, len(kinds))
        t = flat(TARGET_KIND)[seen].reshape(-1, n)
        keep = np.all(np.isfinite(x), axis=(1, 2)) & np.all(np.isfinite(t), axis=1) & np.any(t != 0, axis=1)
        xs.append(normalised(np.moveaxis(x[keep], -1, 1)).transpose(0, 2, 1))
        ts.append(normalised(t[keep]))
        cs.append(np.full(int(keep.sum()), index))
    return np.concatenate(xs), np.concatenate(ts), np.concatenate(cs)


def split(examples: HeadExamples, holdout: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(fitting rows, held-out rows): a seeded choice of round(holdout x episodes) episodes, at least one and at
    most all but one, held out whole."""
    groups = np.unique(examples.episode)
    if len(groups) < 2:
        raise ValueError(f"a held-out check needs at least 2 episodes with examples, got {len(groups)}")
    count = min(max(1, round(holdout * len(groups))), len(groups) - 1)
    held = np.random.default_rng(seed).choice(groups, size=count, replace=False)
    is_held = np.isin(examples.episode, held)
    return np.flatnonzero(~is_held), np.flatnonzero(is_held)


def _forward(params: dict[str, jax.Array], x: jax.Array, camera: jax.Array, cameras: int) -> jax.Array:
    """The head's formula (`OcclusionHead.forward`) over examples: x [M, N, K], camera [M] -> [M, N]."""
    onehot = jnp.broadcast_to(jax.nn.one_hot(camera, cameras)[:, None, :], (*x.shape[:2], cameras))
    f = jnp.concatenate([x, onehot], axis=-1)
    if "w1" in params:
        f = jnp.tanh(f @ params["w1"] + params["b1"])
    return f @ params["w2"] + params["b2"] + params["position_bias"][camera]


def _loss(params, x, target, camera, *, cameras: int, options: HeadFitOptions) -> jax.Array:
    y = _forward(params, x, camera, cameras)
    tau = options.temperature
    listwise = -jnp.sum(jax.nn.softmax(target / tau, axis=-1) * jax.nn.log_softmax(y / tau, axis=-1), axis=-1)
    decay = sum(jnp.sum(params[k] ** 2) for k in ("w1", "w2") if k in params)
    return jnp.mean(listwise) + options.mse_weight * jnp.mean((y - target) ** 2) + options.weight_decay * decay


def train(examples: HeadExamples, options: HeadFitOptions) -> tuple[dict[str, np.ndarray], float]:
    """The head's weights fitted to `examples` (float64) and the final loss."""
    k, c, n = len(examples.kinds), len(examples.cameras), examples.target.shape[1]
    features = k + c
    key1, key2 = jax.random.split(jax.random.key(options.seed))
    if options.hidden:
        h = options.hidden
        params = {
            "w1": jax.random.normal(key1, (features, h)) / np.sqrt(features),
            "b1": jnp.zeros(h),
            "w2": jax.random.normal(key2, (h,)) / np.sqrt(h),
        }
    else:
        params = {"w2": jnp.zeros(features)}
    params |= {"b2": jnp.zeros(()), "position_bias": jnp.zeros((c, n))}
    data = tuple(jnp.asarray(a) for a in (examples.inputs, examples.target, examples.camera))
    optimiser = optax.adam(options.learning_rate)

    @jax.jit
    def run(params):
        def step(carry, _):
            params, state = carry
            loss, grads = jax.value_and_grad(_loss)(params, *data, cameras=c, options=options)
            updates, state = optimiser.update(grads, state, params)
            return (optax.apply_updates(params, updates), state), loss

        (params, _), losses = jax.lax.scan(step, (params, optimiser.init(params)), None, length=options.steps)
        return params, losses[-1]

    fitted, loss = run(params)
    return {name: np.asarray(v, np.float64) for name, v in fitted.items()}, float(loss)


def head_from(examples: HeadExamples, weights: dict[str, np.ndarray], fit: dict[str, Any]) -> OcclusionHead:
    return OcclusionHead(
        inputs=examples.kinds,
        cameras=examples.cameras,
        grid=examples.grid,
        target=examples.target_name,
        family=examples.family,
        w1=weights.get("w1"),
        b1=weights.get("b1"),
        w2=weights["w2"],
        b2=float(weights["b2"]),
        position_bias=weights["position_bias"],
        model=examples.model,
        fit=fit,
    )


def _agreement(predicted: np.ndarray, target: np.ndarray, grid: tuple[int, int]) -> dict[str, Any]:
    """Top-1 agreement and Spearman of predicted [M, N] with target [M, N]."""
    if not len(target):
        return {"examples": 0, "top1": None, "spearman_median": None, "spearman_mean": None}
    top1 = [top1_agreement(p.reshape(grid), t.reshape(grid)) for p, t in zip(predicted, target, strict=True)]
    rho = np.array([spearman(p.reshape(grid), t.reshape(grid)) for p, t in zip(predicted, target, strict=True)])
    finite = rho[np.isfinite(rho)]
    return {
        "examples": len(target),
        "top1": float(np.mean(top1)),
        "spearman_median": float(np.median(finite)) if finite.size else None,
        "spearman_mean": float(np.mean(finite)) if finite.size else None,
    }


def position_prior(examples: HeadExamples) -> np.ndarray:
    """[C, N]: each camera's mean normalised occlusion map over `examples` (zeros for a camera without any): the
    map that says only where occlusion tends to fall, which a head must beat to have read its inputs."""
    prior = np.zeros((len(examples.cameras), examples.target.shape[1]))
    for index in range(len(examples.cameras)):
        rows = examples.camera == index
        if rows.any():
            prior[index] = examples.target[rows].mean(axis=0)
    return prior


def evaluate(head: OcclusionHead, examples: HeadExamples, prior: np.ndarray) -> dict[str, Any]:
    """The agreement with occlusion on `examples`, per camera and over all, of the head (applied as served:
    `OcclusionHead.forward`), of each input kind alone and of `prior` ([C, N], `position_prior` of the fitting
    examples)."""
    predicted = np.empty_like(examples.target)
    for index in range(len(head.cameras)):
        rows = examples.camera == index
        predicted[rows] = head.forward(examples.inputs[rows], index)

    def figures(rows: np.ndarray) -> dict[str, Any]:
        return {
            "head": _agreement(predicted[rows], examples.target[rows], head.grid),
            "prior": _agreement(prior[examples.camera[rows]], examples.target[rows], head.grid),
            "inputs": {
                kind: _agreement(examples.inputs[rows, :, k], examples.target[rows], head.grid)
                for k, kind in enumerate(examples.kinds)
            },
        }

    every = np.ones(len(examples), bool)
    return {
        "all": figures(every),
        "by_camera": {camera: figures(examples.camera == i) for i, camera in enumerate(head.cameras)},
    }


def fit(paths: Sequence[pathlib.Path], options: HeadFitOptions) -> OcclusionHead:
    """A head fitted on the maps datasets at `paths` (module docstring), recording how, on what, and its figures on
    the held-out episodes and on the fitting ones."""
    examples = read_examples(paths, options.inputs)
    fitting, held = split(examples, options.holdout, options.seed)
    weights, loss = train(examples.subset(fitting), options)
    held_episodes = sorted({examples.episodes[e] for e in examples.episode[held]})
    record = {
        "options": dataclasses.asdict(options),
        "datasets": [str(pathlib.Path(p).resolve()) for p in paths],
        "episodes": len(examples.episodes),
        "held_out_episodes": held_episodes,
        "examples": {"fitting": len(fitting), "held_out": len(held)},
        "final_loss": loss,
    }
    head = head_from(examples, weights, record)
    prior = position_prior(examples.subset(fitting))
    figures = {
        "held_out": evaluate(head, examples.subset(held), prior),
        "fitting": evaluate(head, examples.subset(fitting), prior),
        "deletion": DELETION_NOT_MEASURED,
    }
    # as the file holds it (tuples as lists), so that a head and its saved copy are equal
    return dataclasses.replace(head, fit=json.loads(json.dumps({**record, "figures": figures}, allow_nan=False)))
