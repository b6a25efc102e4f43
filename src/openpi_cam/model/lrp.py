"""AttnLRP's propagation rules (Achtibat et al., ICML 2024, arXiv 2402.05602) as modified gradients: with a layer
stack's `rules` set to "lrp" (`config.RULES`), input x gradient of an explained score is its relevance, from one
backward pass. The forward pass is the same computation under either setting (every helper here is the identity,
or the same function, forwards), so nothing served changes; only the backward pass of an explanation differs.

Why a gradient can carry relevance: the epsilon rule of a linear layer z = W x, R_x = x * W^T (R_z / z), is the
gradient's own propagation once the quantity propagated is g = R / (the layer's output), so a chain of linear layers
needs no change, and relevance is read at the inputs as x * g. Each non-linear operation gets a backward rule that
keeps R = value * g true across it:

- linear operations (matmuls and einsums, LoRA, the patch convolution, additions and the residual stream, RoPE's
  rotation, constant scalings, the Euler update, the tied output projection): the epsilon rule, which here is the
  plain gradient with epsilon 0. No division is ever evaluated, so no stabiliser has to be chosen.
- element-wise non-linearities (GELU in SigLIP's MLP and Gemma's gate, SiLU in pi0's action-time MLP): the identity
  rule R_x = R_y, a gradient of f(x) / x, evaluated in closed form (GELU's tanh factor, SiLU's sigmoid), so it is
  finite at x = 0 without an epsilon (`gelu`, `swish`).
- normalisations (SigLIP's LayerNorm, Gemma's RMSNorm, pi0.5's adaptive RMSNorm): the normaliser 1 / sqrt(var + eps)
  is held constant (`constant`), which makes the norm linear: an RMSNorm passes relevance unchanged, element by
  element; a LayerNorm keeps its centring (a linear map) and its bias absorbs its share.
- bilinear products (q k^T, attention weights times V, Gemma's gate times up): the uniform rule, half of the
  product's relevance to each factor: the gradient halved at the product (`split`). In Gemma's attention, whose
  backward pass is written out (`gemma.attend`), the two products in series give q and k a quarter of the gradient
  and v half (`attention_operands`).
- softmax: the paper's rule R_x_i = x_i (R_i - s_i sum_j R_j) is input x gradient of the softmax, so the softmax
  keeps its plain gradient. It does not conserve: what the first-order expansion at the logits leaves out (its
  remainder s - J x, the softmax's implicit bias) absorbs the difference.

Decisions for this model family (docs/MAP_KINDS.md, "AttnLRP relevance"):

- What biases absorb: SigLIP's (the patch embedding's bias, the position embedding, LayerNorm's beta, every dense
  bias), the pi0 projections' (action in / out, state, time MLPs) and pi0.5's adaRMS shift keep their relevance
  b * g; Gemma has none. With each softmax's remainder they are why the relevance read at the inputs sums to the
  score only up to these terms (tests/model/test_lrp_models.py checks the balance on whole models).
- pi0.5's adaRMS modulation (scale, shift, gate from the time embedding alone) and its time MLP: they do not depend
  on the observation, only on the Euler step, so they are held constant, weights of that step like a norm's learned
  scale: normed * (1 + scale) and y * gate are linear in their image-dependent factor. The uniform rule would hand
  half of every modulated layer's relevance to the integration clock, which is no input of the robot's.
- pi0's action-time MLP mixes the action tokens (x_t, which depends on the image through the earlier Euler steps)
  with the time embedding: its SiLU gets the identity rule like any element-wise non-linearity, and its time half is
  an input of the step whose relevance, like a bias's, is not drawn.
- A log-softmax score (pi0-FAST's `chunk` and `generated-tokens`: a sum of log p(g_k)) keeps its plain gradient: the
  paper's softmax rule (first-order expansion at the logits) applied to log p_g. The logits receive z_i (1[i = g] -
  p_i), which sums to z_g - E_p[z] = log p_g + H(p): what it leaves out, -H(p) (the entropy of the explained
  distribution), is absorbed, small where the policy is confident. A token logit (`action-token`,
  `all-action-tokens`) is linear in the last layer.
- Where relevance is read: at the pixels of the model's input images (at the model resolution, in [-1, 1]), x * g
  summed over each patch's pixels and channels, one signed map per camera on its token grid, as every kind. The
  patch embedding is linear, so a patch's sum is the relevance of its embedding less what the embedding's bias and
  the position embedding absorb. A pixel value of 0 (mid-grey) carries no relevance, whatever its gradient: the
  input layer reads contributions relative to the zero image.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import TypeVar

import jax
import jax.numpy as jnp

from openpi_cam.model.config import RULES, GemmaConfig, SiglipConfig

C = TypeVar("C")


def with_rules(cfg: C, rules: str) -> C:
    """`cfg` (a family's config, or one stack's) with every layer stack's rules set to `rules`."""
    if rules not in RULES:
        raise ValueError(f"rules must be one of {RULES}, got {rules!r}")
    if isinstance(cfg, GemmaConfig | SiglipConfig):
        return dataclasses.replace(cfg, rules=rules)  # type: ignore[return-value]
    changes = {
        f.name: dataclasses.replace(v, rules=rules)
        for f in dataclasses.fields(cfg)  # type: ignore[arg-type]
        if isinstance(v := getattr(cfg, f.name), GemmaConfig | SiglipConfig)
    }
    return dataclasses.replace(cfg, **changes)  # type: ignore[type-var]


@functools.partial(jax.custom_vjp, nondiff_argnums=(1,))
def scale_gradient(x: jax.Array, factor: float) -> jax.Array:
    """x unchanged forwards; backwards the incoming gradient times `factor`."""
    return x


def _scale_fwd(x, factor):
    return x, None


def _scale_bwd(factor, _, g):
    return (g * jnp.asarray(factor, g.dtype),)


scale_gradient.defvjp(_scale_fwd, _scale_bwd)


def split(product: jax.Array, rules: str) -> jax.Array:
    """The uniform rule at the output of a bilinear product (two factors that both carry relevance): each factor
    receives half of the product's relevance."""
    return scale_gradient(product, 0.5) if rules == "lrp" else product


def attention_operands(q: jax.Array, k: jax.Array, v: jax.Array, rules: str) -> tuple[jax.Array, ...]:
    """q, k, v before a softmax attention whose backward pass cannot be marked inside (`gemma.attend`). The weights
    times V split the output's relevance in half between the weights and v; the weights' half reaches the logits
    through the softmax's plain gradient, and q k^T splits it in half again: q and k a quarter each, v a half."""
    if rules != "lrp":
        return q, k, v
    return scale_gradient(q, 0.25), scale_gradient(k, 0.25), scale_gradient(v, 0.5)


def constant(x: jax.Array, rules: str) -> jax.Array:
    """A factor that the rules hold constant (a normaliser, pi0.5's time modulation): no gradient through it."""
    return jax.lax.stop_gradient(x) if rules == "lrp" else x


_SQRT_2_OVER_PI = math.sqrt(2.0 / math.pi)


def _gelu_factor(x: jax.Array) -> jax.Array:
    """gelu(x) / x of the tanh approximation, in closed form (finite at 0)."""
    x = x.astype(jnp.float32)
    return 0.5 * (1.0 + jnp.tanh(_SQRT_2_OVER_PI * (x + 0.044715 * x**3)))


@jax.custom_vjp
def _gelu_identity(x: jax.Array) -> jax.Array:
    return jax.nn.gelu(x, approximate=True)


def _gelu_fwd(x):
    return jax.nn.gelu(x, approximate=True), x


def _gelu_bwd(x, g):
    return ((g.astype(jnp.float32) * _gelu_factor(x)).astype(x.dtype),)


_gelu_identity.defvjp(_gelu_fwd, _gelu_bwd)


@jax.custom_vjp
def _swish_identity(x: jax.Array) -> jax.Array:
    return jax.nn.swish(x)


def _swish_fwd(x):
    return jax.nn.swish(x), x


def _swish_bwd(x, g):
    return ((g.astype(jnp.float32) * jax.nn.sigmoid(x.astype(jnp.float32))).astype(x.dtype),)


_swish_identity.defvjp(_swish_fwd, _swish_bwd)


def gelu(x: jax.Array, rules: str) -> jax.Array:
    """GELU (tanh approximation, as SigLIP and Gemma use it); under "lrp" with the identity rule backwards."""
    return _gelu_identity(x) if rules == "lrp" else jax.nn.gelu(x, approximate=True)


def swish(x: jax.Array, rules: str) -> jax.Array:
    """SiLU; under "lrp" with the identity rule backwards."""
    return _swish_identity(x) if rules == "lrp" else jax.nn.swish(x)
