"""Attribution maps over the image tokens a VLA's language model sees, independent of the model family.

Every function takes the image tokens E [B, C, N, D] (C cameras, N tokens per camera) and the gradient G of a score
with respect to them ([..., B, C, N, D]; leading axes for several scores at once), and reduces them per camera.
"""

from __future__ import annotations

from typing import Literal, get_args

import jax
import jax.numpy as jnp

# The maps the model layer computes: Grad-CAM as the founding spec defines it, and the per-token gradient norm from
# the same backward pass.
MapKind = Literal["gradcam", "gradnorm"]
MAP_KINDS: tuple[str, ...] = get_args(MapKind)


def gradcam_reduce(E: jax.Array, G: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Grad-CAM as the founding spec defines it, plus the per-token gradient norm from the same gradient.

    alpha_c = mean over camera c's tokens of G (one weight per channel); cam_c = ReLU(E_c @ alpha_c);
    token_norm_c[n] = ||G_c[n]||. -> alpha [..., B, C, D], cam [..., B, C, N], token_norm [..., B, C, N]."""
    E, G = E.astype(jnp.float32), G.astype(jnp.float32)
    alpha = jnp.mean(G, axis=-2)
    cam = jax.nn.relu(jnp.einsum("bcnd,...bcd->...bcn", E, alpha))
    return alpha, cam, jnp.sqrt(jnp.sum(jnp.square(G), axis=-1))
