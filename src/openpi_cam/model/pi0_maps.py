"""Maps over pi0 / pi0.5's SigLIP tokens, explaining the actions the served call returned.

The explained function is the whole flow-matching integration (`pi0.denoise`): x_0 as a function of the image tokens
E [B, C, N, D] the LLM sees, from the call's own noise (no gradient through SigLIP). A target is a fixed weighting W of
the chunk, score = sum(W * x_0): one action dimension at one horizon step (W one-hot at (h, d)), or the whole chunk
(W = stop_gradient(x_0), the goldens' `gc_chunk`: its gradient is sum_hd x_0[h, d] * dx_0[h, d] / dE). Several targets
share one forward pass and take one backward pass each. Each Euler step is rematerialised (`pi0.denoise`), so the
backward keeps one step's activations at a time.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from numpy.typing import ArrayLike

from openpi_cam.model.attribution import gradcam_reduce
from openpi_cam.model.config import Pi0Config
from openpi_cam.model.observation import Observation
from openpi_cam.model.paligemma import embed_images
from openpi_cam.model.pi0 import Pi0, denoise, preprocess

CHUNK = (-1, -1)  # the (h, d) that stands for the whole-chunk target


@dataclasses.dataclass(frozen=True)
class FlowMaps:
    """Raw maps per camera; leading axes [B, T] (T explained targets)."""

    cameras: tuple[str, ...]
    by_kind: dict[str, dict[str, np.ndarray]]  # kind -> camera -> float32 [B, T, Hp, Wp]
    alphas: dict[str, np.ndarray]  # camera -> float32 [B, T, D]: Grad-CAM's channel weights
    grad_norms: dict[str, np.ndarray]  # camera -> float32 [B, T]: Frobenius norm of the gradient
    spans: dict[str, tuple[int, int]]  # camera -> [start, end) of its tokens in the prefix
    valid: dict[str, np.ndarray]  # camera -> bool [B]
    score: np.ndarray  # float32 [B, T]
    targets: tuple[tuple[int, int], ...]  # (h, d) per explained target; CHUNK for the whole chunk
    actions: np.ndarray  # float32 [B, H, A]: x_0, the explained actions (equal to the served ones)


@functools.partial(jax.jit, static_argnames=("cfg", "targets"))
def _flow_cams(params, obs, noise, *, cfg: Pi0Config, targets: tuple[tuple[int, int], ...]):
    E = embed_images(params, obs, cfg)
    x_0, vjp_fn = jax.vjp(lambda image_tokens: denoise(params, image_tokens, obs, noise, cfg), E)
    weights = []
    for h, d in targets:
        if (h, d) == CHUNK:
            weights.append(jax.lax.stop_gradient(x_0))
        else:
            weights.append(jnp.zeros_like(x_0).at[:, h, d].set(1.0))
    weights = jnp.stack(weights)  # [T, B, H, A]
    G = jax.lax.map(lambda w: vjp_fn(w)[0], weights)  # [T, B, C, N, D]
    alpha, cam, token_norm = gradcam_reduce(E, G)
    score = jnp.einsum("tbha,bha->bt", weights, x_0)
    return score, x_0, jnp.moveaxis(alpha, 0, 1), jnp.moveaxis(cam, 0, 1), jnp.moveaxis(token_norm, 0, 1)


def maps_for_actions(model: Pi0, obs: Observation, noise: ArrayLike, targets: Sequence[tuple[int, int]]) -> FlowMaps:
    """Grad-CAM and the gradient norm of each target ((h, d), or `CHUNK`) for the actions sampled from `noise`
    [B, H, A] (the served call's noise: the explained x_0 is the returned one)."""
    cfg = model.config
    targets = tuple((int(h), int(d)) for h, d in targets)
    for h, d in targets:
        if (h, d) != CHUNK and not (0 <= h < cfg.action_horizon and 0 <= d < cfg.action_dim):
            raise ValueError(f"action ({h}, {d}) outside the chunk [{cfg.action_horizon}, {cfg.action_dim}]")
    if not targets:
        raise ValueError("no targets to explain")
    obs = preprocess(obs, cfg)
    noise = jnp.asarray(noise, jnp.float32)
    score, x_0, alpha, cam, token_norm = _flow_cams(model.params, obs, noise, cfg=cfg, targets=targets)
    cams, grid, n = tuple(obs.images), cfg.siglip.grid, cfg.siglip.num_tokens
    cam, token_norm = np.asarray(cam), np.asarray(token_norm)  # [B, T, C, N]
    grad_norm = np.sqrt(np.sum(np.square(token_norm.astype(np.float64)), axis=-1)).astype(np.float32)

    def per_camera(x: np.ndarray) -> dict[str, np.ndarray]:
        return {c: x[:, :, i].reshape(*x.shape[:2], *grid) for i, c in enumerate(cams)}

    return FlowMaps(
        cameras=cams,
        by_kind={"gradcam": per_camera(cam), "gradnorm": per_camera(token_norm)},
        alphas={c: np.asarray(alpha)[:, :, i] for i, c in enumerate(cams)},
        grad_norms={c: grad_norm[:, :, i] for i, c in enumerate(cams)},
        spans={c: (i * n, (i + 1) * n) for i, c in enumerate(cams)},
        valid={c: np.asarray(obs.image_masks[c], bool).reshape(-1) for c in cams},
        score=np.asarray(score),
        targets=targets,
        actions=np.asarray(x_0),
    )
