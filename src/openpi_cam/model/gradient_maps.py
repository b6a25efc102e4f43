"""The gradient kinds for any PaliGemma-based family, given what it explains as a function of the image tokens.

A family supplies `output_fn`: an output y (and anything else it wants from the same forward pass) as a function of
the image tokens E [B, C, N, D], and the explained scores as cotangents of y, one per score (a one-hot row for a
token's logit, the chunk weighting for pi0's actions; score_t = sum(cotangents[t] * y)). Everything else is shared
and runs inside the family's jitted program (`gradient_kinds`), in up to three passes:

  tokens  one backward pass per score to the image tokens, G = dScore/dE: Grad-CAM and the gradient norm
          (`attribution.gradcam_reduce`) and gradient x input (`attribution.gradient_x_input`);
  pixels  the same pass continued through SigLIP to the model's input pixels: the first-order estimate of
          occlusion's drop (`attribution.taylor_patches`), which needs the baseline frame of `MapOptions`;
  noise   SmoothGrad: the backward pass repeated at `smoothgrad_samples` noisy copies of E, the gradients averaged
          in a loop carry (memory does not grow with the count) and reduced like the gradient norm.

What the program takes as data rather than compiling in (`GradientInputs`): SmoothGrad's seed, sample count and
noise level, so another seed, count or level reuses the compilation.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from openpi_cam.model.attribution import (
    baseline_images,
    gradcam_reduce,
    gradient_x_input,
    smoothgrad_noise,
    taylor_patches,
)
from openpi_cam.model.baseline_maps import camera_stack, with_images
from openpi_cam.model.observation import Observation
from openpi_cam.model.paligemma import VLMConfig, embed_images
from openpi_cam.vocabulary import MapOptions

# The passes of a gradient program (module docstring) and the kinds each gives.
PASS_KINDS = {"tokens": ("gradcam", "gradnorm", "gradxinput"), "pixels": ("taylor",), "noise": ("smoothgrad",)}

# What a gradient program computes unless told otherwise: the token pass (Grad-CAM, the gradient norm, gradient x
# input), with nothing of `MapOptions` compiled in.
TOKEN_PASS = ("tokens",)
COMPILED_DEFAULTS = MapOptions()

OutputFn = Callable[[jax.Array], tuple[jax.Array, Any]]  # image tokens [B, C, N, D] -> (y, aux)


class GradientInputs(NamedTuple):
    """SmoothGrad's draws as data: int32 [] seed, int32 [] sample count, float32 [] noise level."""

    seed: jax.Array
    samples: jax.Array
    sigma: jax.Array


def gradient_inputs(options: MapOptions) -> GradientInputs:
    return GradientInputs(
        jnp.int32(options.seed), jnp.int32(options.smoothgrad_samples), jnp.float32(options.smoothgrad_sigma)
    )


def passes(kinds: Sequence[str]) -> tuple[str, ...]:
    """The passes a gradient program runs for `kinds` (a static argument: every kind of one pass shares a
    compilation). The pixel pass continues the token pass, so it implies it."""
    needed = {p for p, of in PASS_KINDS.items() if any(k in kinds for k in of)}
    if "pixels" in needed:
        needed.add("tokens")
    return tuple(p for p in PASS_KINDS if p in needed)


def program_arguments(kinds: Sequence[str], options: MapOptions) -> tuple[GradientInputs | None, dict[str, Any]]:
    """A family's gradient program's data inputs for `kinds` (SmoothGrad's draws, None without it) and its static
    arguments ("program": the passes, "options": `compiled_options`)."""
    program = passes(kinds)
    inputs = gradient_inputs(options) if "noise" in program else None
    return inputs, {"program": program, "options": compiled_options(options, program)}


def compiled_options(options: MapOptions, program: Sequence[str]) -> MapOptions:
    """The options a gradient program with passes `program` depends on: the baseline frame for the pixel pass,
    nothing else (SmoothGrad's draws are `GradientInputs`), so other options reuse its compilation."""
    keep = {"baseline", "blur_sigma"} if "pixels" in program else set()
    defaults = MapOptions()
    return dataclasses.replace(
        options, **{f.name: getattr(defaults, f.name) for f in dataclasses.fields(MapOptions) if f.name not in keep}
    )


def gradient_kinds(
    params: dict,
    obs: Observation,
    cfg: VLMConfig,
    output_fn: OutputFn,
    cotangents: Callable[[jax.Array], jax.Array],
    program: Sequence[str],
    options: MapOptions,
    inputs: GradientInputs | None,
) -> tuple[jax.Array, Any, dict[str, jax.Array]]:
    """Traced core (call inside a jitted program). `program` are the passes to run (`passes`), `options` the
    compiled options (`compiled_options`), `inputs` SmoothGrad's draws (with the noise pass).

    Returns (y, aux, maps): maps "gradcam", "gradnorm", "gradxinput" (token pass), "taylor" (pixel pass),
    "smoothgrad" (noise pass), each float32 [T, B, C, N] with T the cotangents' leading axis, and "alpha" [T, B, C, D]
    (Grad-CAM's channel weights) with the token pass."""
    images, valid = camera_stack(obs)  # [C, B, H, W, 3]
    if "pixels" in program:

        def embed(stack: jax.Array) -> jax.Array:
            return embed_images(params, with_images(obs, dict(zip(obs.images, stack, strict=True))), cfg)

        E, embed_vjp = jax.vjp(embed, images)
    else:
        E = embed_images(params, obs, cfg)
    maps: dict[str, jax.Array] = {}
    if "tokens" in program:
        y, vjp_fn, aux = jax.vjp(output_fn, E, has_aux=True)
        cots = cotangents(y)
        # One cotangent after another (`lax.map`, as `attribution.per_score_grads` explains), each [B, C, N, D].
        G = jax.lax.map(lambda cot: vjp_fn(cot)[0], cots)
        maps["alpha"], maps["gradcam"], maps["gradnorm"] = gradcam_reduce(E, G)
        maps["gradxinput"] = gradient_x_input(E, G)
        if "pixels" in program:
            delta = images - baseline_images(images, valid, options)  # a masked camera is its own baseline: 0
            patch = cfg.siglip.patch_size
            maps["taylor"] = jax.lax.map(lambda g: taylor_patches(embed_vjp(g)[0], delta, patch), G)
    else:
        y, aux = output_fn(E)
        cots = cotangents(y)
    if "noise" in program:
        maps["smoothgrad"] = _smoothgrad(output_fn, E, cots, inputs)
    return y, aux, maps


def _smoothgrad(output_fn: OutputFn, E: jax.Array, cots: jax.Array, inputs: GradientInputs) -> jax.Array:
    """||mean over the samples of dScore/dE at E + noise|| per token -> [T, B, C, N]. The cotangents are the clean
    output's, so a score weighted by the explained output (pi0's chunk) keeps the explained weighting."""
    E = E.astype(jnp.float32)
    key = jax.random.key(inputs.seed)

    def sample(i, acc):
        noisy = E + smoothgrad_noise(jax.random.fold_in(key, i), E, inputs.sigma)
        _, vjp_fn, _ = jax.vjp(output_fn, noisy, has_aux=True)
        return acc + jax.lax.map(lambda cot: vjp_fn(cot)[0], cots).astype(jnp.float32)

    total = jax.lax.fori_loop(0, inputs.samples, sample, jnp.zeros((cots.shape[0], *E.shape), jnp.float32))
    mean = total / inputs.samples.astype(jnp.float32)
    return jnp.sqrt(jnp.sum(jnp.square(mean), axis=-1))
