"""Attribution maps over the image tokens a VLA's language model sees, independent of the model family.

Gradient maps take the image tokens E [B, C, N, D] (C cameras, N tokens per camera) and the gradient G of a score
with respect to them ([..., B, C, N, D]; leading axes for several scores at once), and reduce them per camera.

Integrated gradients and occlusion need a *baseline*: an image a real robot could see that lacks the detail under
test (a blurred copy of the frame, or its mean colour), so the maps answer "what in this frame, compared with the
same frame without its detail, drives the score" rather than comparing with an all-zero token no camera produces.
The image helpers work on one camera's images [..., H, W, 3] at the model resolution; patch grids are row-major
(row r, column c covers pixels [r p, (r + 1) p) x [c p, (c + 1) p) for patch size p), as SigLIP's tokens.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

from openpi_cam.vocabulary import IG_RULES, MapOptions

# Score gaps below this are not resolved relative to themselves: float32 evaluations of the same logits differ by
# rounding errors of about this size (docs/DESIGN_NOTES.md), so 2% of a smaller gap would be rounding noise.
COMPLETENESS_FLOOR = 1e-3
# The IG steps stop doubling once a doubling leaves more than this share of the completeness error: the error is then
# the arithmetic's, not the quadrature's, and the attempt with the smallest error is kept. While the quadrature limits
# it, Gauss-Legendre's error shrinks several-fold per doubling, even across a kink in the integrand. In bfloat16, as
# real checkpoints are served, the scores are rounded to bfloat16 and the error stops shrinking at a floor, where
# doubling to the cap would multiply the cost for nothing (chosen by measurement: docs/DESIGN_NOTES.md).
IG_STALL = 0.75


@dataclasses.dataclass(frozen=True)
class IgCompleteness:
    """IG's completeness check per row (and explained token): attribution_sum should equal score - baseline_score."""

    score: np.ndarray  # [B] or [B, T]: score(E)
    baseline_score: np.ndarray  # score(E0), E0 the baseline frame's tokens
    attribution_sum: np.ndarray  # IG attributions summed over every camera and token
    steps: int  # quadrature steps of these attributions (ig_steps, doubled while that missed the target and helped)

    @property
    def error(self) -> np.ndarray:
        return np.abs(self.attribution_sum - (self.score - self.baseline_score))

    @property
    def relative_error(self) -> np.ndarray:
        """error / |score(E) - score(E0)| (the 2% target is on this); inf when the two scores coincide."""
        gap = np.abs(self.score - self.baseline_score)
        return np.divide(self.error, gap, out=np.full_like(gap, np.inf), where=gap > 0)


def gradcam_reduce(E: jax.Array, G: jax.Array) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Grad-CAM as the founding spec defines it, plus the per-token gradient norm from the same gradient.

    alpha_c = mean over camera c's tokens of G (one weight per channel); cam_c = ReLU(E_c @ alpha_c);
    token_norm_c[n] = ||G_c[n]||. -> alpha [..., B, C, D], cam [..., B, C, N], token_norm [..., B, C, N]."""
    E, G = E.astype(jnp.float32), G.astype(jnp.float32)
    alpha = jnp.mean(G, axis=-2)
    cam = jax.nn.relu(jnp.einsum("bcnd,...bcd->...bcn", E, alpha))
    return alpha, cam, jnp.sqrt(jnp.sum(jnp.square(G), axis=-1))


def gradient_x_input(E: jax.Array, G: jax.Array) -> jax.Array:
    """Gradient x input per token: sum_d E[n, d] G[n, d], signed (the linear term of scaling the token to zero).
    E [B, C, N, D], G [..., B, C, N, D] -> [..., B, C, N] float32."""
    return jnp.einsum("bcnd,...bcnd->...bcn", E.astype(jnp.float32), G.astype(jnp.float32))


def taylor_patches(pixel_grad: jax.Array, delta: jax.Array, patch: int) -> jax.Array:
    """Occlusion's first-order estimate per patch: sum over the patch's pixels and channels of dScore/dPixel x
    (frame - baseline frame). Painting patch p changes the frame by -delta on p alone, so to first order the score
    drops by grad . delta restricted to p; pixels beyond the last full patch are in no patch.
    pixel_grad, delta [C, B, H, W, 3] -> [B, C, N] float32."""
    h, w = (n - n % patch for n in delta.shape[-3:-1])
    product = pixel_grad.astype(jnp.float32) * delta.astype(jnp.float32)
    return jnp.sum(patchify(product[..., :h, :w, :], patch), axis=-1)


def smoothgrad_noise(key: jax.Array, E: jax.Array, sigma: jax.Array | float) -> jax.Array:
    """SmoothGrad's noise for the image tokens E [B, C, N, D]: Gaussian, std sigma x the spread (standard deviation
    over the camera's tokens) of each channel of each row and camera, so every channel is perturbed in proportion to
    how much it varies across the image. The standard normal draw [C, N, D] is shared by the rows: a row's noise
    does not depend on the batch it is explained in."""
    spread = jnp.std(E.astype(jnp.float32), axis=2, keepdims=True)  # [B, C, 1, D]
    return sigma * spread * jax.random.normal(key, E.shape[1:], jnp.float32)[None]


# ----------------------------------------------------------------------------------------------------------------
# Baseline images


def blur_matrix(n: int, sigma: float, truncate: float = 4.0) -> np.ndarray:
    """[n, n] matrix of a 1-D Gaussian filter, so a separable blur is two matmuls (no padding logic in the graph).

    Same filter as `scipy.ndimage.gaussian_filter1d(mode="reflect", truncate=truncate)`: radius
    int(truncate * sigma + 0.5), edges mirrored about the border (d c b a | a b c d | d c b a), which keeps a
    blurred frame's colours those of the frame near its borders. sigma 0 is the identity."""
    if sigma == 0:
        return np.eye(n)
    radius = int(truncate * sigma + 0.5)
    offsets = np.arange(-radius, radius + 1)
    kernel = np.exp(-0.5 * (offsets / sigma) ** 2)
    kernel /= kernel.sum()
    src = np.mod(np.arange(n)[:, None] + offsets[None, :], 2 * n)  # [n, taps], folded into one mirror period
    src = np.where(src >= n, 2 * n - 1 - src, src)
    out = np.zeros((n, n))
    np.add.at(out, (np.repeat(np.arange(n), offsets.size), src.ravel()), np.tile(kernel, n))
    return out


def blur_images(images: jax.Array, sigma: float) -> jax.Array:
    """Gaussian blur of images [..., H, W, 3] (sigma in pixels), per channel."""
    h, w = images.shape[-3:-1]
    mh = jnp.asarray(blur_matrix(h, sigma), images.dtype)
    mw = jnp.asarray(blur_matrix(w, sigma), images.dtype)
    return jnp.einsum("hH,...HWk,wW->...hwk", mh, images, mw, precision=jax.lax.Precision.HIGHEST)


def mean_images(images: jax.Array) -> jax.Array:
    """Every pixel replaced by the image's mean colour (per image, per channel). [..., H, W, 3] -> same."""
    return jnp.broadcast_to(jnp.mean(images, axis=(-3, -2), keepdims=True), images.shape)


def baseline_images(images: jax.Array, valid: jax.Array, options: MapOptions) -> jax.Array:
    """The baseline frame of every image [..., B, H, W, 3]; rows with valid [..., B] False keep their own image, so
    a camera the model masks out contributes nothing to IG or occlusion."""
    base = blur_images(images, options.blur_sigma) if options.baseline == "blur" else mean_images(images)
    return jnp.where(valid[..., None, None, None], base, images)


# ----------------------------------------------------------------------------------------------------------------
# Integrated gradients


def quadrature(rule: str, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes a in [0, 1] and weights (summing to 1) of `steps` gradient evaluations approximating an integral over
    the path E0 + a (E - E0).

    gauss-legendre: exact for polynomial integrands of degree 2 steps - 1 (the integrand, a gradient along the path
    of a smooth network, is smooth, so this converges fastest per evaluation); midpoint and trapezoid: second order;
    right-riemann: a = k / steps, k = 1..steps, the rule of the IG paper (Sundararajan et al. 2017), first order."""
    if rule == "gauss-legendre":
        x, w = np.polynomial.legendre.leggauss(steps)
        return (x + 1.0) / 2.0, w / 2.0
    if rule == "midpoint":
        return (np.arange(steps) + 0.5) / steps, np.full(steps, 1.0 / steps)
    if rule == "trapezoid":
        w = np.full(steps, 1.0 / (steps - 1))
        w[[0, -1]] /= 2.0
        return np.linspace(0.0, 1.0, steps), w
    if rule == "right-riemann":
        return np.arange(1, steps + 1) / steps, np.full(steps, 1.0 / steps)
    raise ValueError(f"unknown quadrature rule {rule!r}; expected one of {IG_RULES}")


def completeness_error(score: np.ndarray, baseline_score: np.ndarray, attribution_sum: np.ndarray) -> float:
    """The worst explained score's completeness error relative to its gap (below COMPLETENESS_FLOOR, to the floor):
    `MapOptions.ig_tolerance` is a bound on this."""
    gap = np.abs(np.asarray(score, np.float64) - baseline_score)
    error = np.abs(attribution_sum - (np.asarray(score, np.float64) - baseline_score))
    return float(np.max(error / np.maximum(gap, COMPLETENESS_FLOOR)))


def per_score_grads(vjp_fn: Callable, scores: jax.Array) -> jax.Array:
    """Gradients of each score row scores[t] (shape [T, B]) from one VJP closure -> [T, *input shape].

    Rows of the batch are independent, so one cotangent per t (ones over B) gives every row's gradient. The
    cotangents run as `lax.map`, not `vmap`: `vmap` of the decoding replay's VJP gave wrong gradients for all but the
    first cotangent on XLA:CPU at real prefix lengths (docs/DESIGN_NOTES.md), while `lax.map` agrees with one VJP per
    score (tests/model/test_pi0_fast_maps.py checks the stack against upstream's per-step maps)."""
    t = scores.shape[0]
    cotangents = jnp.broadcast_to(jnp.eye(t, dtype=scores.dtype)[:, :, None], (t, *scores.shape))  # [T, T, B]
    return jax.lax.map(lambda cot: vjp_fn(cot)[0], cotangents)


def patchify(images: jax.Array, patch: int) -> jax.Array:
    """[C, B, H, W, 3] -> [B, C, N, patch * patch * 3], patches in SigLIP's token order (row-major)."""
    c, b, h, w, ch = images.shape
    x = images.reshape(c, b, h // patch, patch, w // patch, patch, ch)
    return jnp.einsum("cbipjqk->bcijpqk", x).reshape(b, c, (h // patch) * (w // patch), patch * patch * ch)


def unpatchify(patches: jax.Array, patch: int, hw: tuple[int, int]) -> jax.Array:
    """The inverse of `patchify`: [B, C, N, patch * patch * 3] -> [C, B, H, W, 3]."""
    b, c = patches.shape[:2]
    h, w = hw
    x = patches.reshape(b, c, h // patch, w // patch, patch, patch, -1)
    return jnp.einsum("bcijpqk->cbipjqk", x).reshape(c, b, h, w, x.shape[-1])


def quadrature_buffer(rule: str, steps: int, length: int) -> tuple[np.ndarray, np.ndarray]:
    """`quadrature(rule, steps)` padded with zero-weight nodes to `length` entries: float32 nodes and weights [length],
    the first `steps` of which are used. A program takes the points as data in a buffer of fixed length, so one
    compilation serves every rule and step count up to `length`."""
    if steps > length:
        raise ValueError(f"{steps} quadrature steps do not fit a buffer of {length}")
    nodes, weights = (np.zeros(length, np.float32) for _ in range(2))
    nodes[:steps], weights[:steps] = quadrature(rule, steps)
    return nodes, weights


def integrated_gradients(
    score_fn: Callable[[jax.Array], jax.Array],
    E: jax.Array,
    E0: jax.Array,
    nodes: jax.Array,
    weights: jax.Array,
    count: jax.Array | int | None = None,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """Integrated gradients over the image tokens (or any [B, C, N, D] input, e.g. patchified pixels), with its
    completeness terms.

    score_fn maps tokens [B, C, N, D] to scores [T, B]. attr[t, b, c, n] = sum_d (E - E0)[b, c, n, d] *
    int_0^1 dscore_t/dE (E0 + a (E - E0))[b, c, n, d] da, the integral by the quadrature points nodes[:count],
    weights[:count] (`quadrature`, or `quadrature_buffer` with the count as a run-time value; None: all of them).
    Completeness: attr summed over cameras and tokens equals score(E) - score(E0) up to the quadrature error, which
    is how the step count is judged. The weighted gradient sum is a loop carry, so memory does not grow with the
    count. -> attr [T, B, C, N], score(E) [T, B], score(E0) [T, B]."""
    nodes, weights = jnp.asarray(nodes, jnp.float32), jnp.asarray(weights, jnp.float32)
    count = nodes.shape[0] if count is None else count
    # The path runs in float32 even for a bfloat16 model (score_fn casts to the compute dtype): bfloat16 points on
    # the path would round the small steps of a fine quadrature away.
    E, E0 = E.astype(jnp.float32), E0.astype(jnp.float32)
    delta = E - E0
    score_e = score_fn(E)

    def point(i, acc):
        scores, vjp_fn = jax.vjp(score_fn, E0 + nodes[i] * delta)
        return acc + weights[i] * per_score_grads(vjp_fn, scores).astype(acc.dtype)

    init = jnp.zeros((score_e.shape[0], *E.shape), jnp.float32)
    mean_grad = jax.lax.fori_loop(0, count, point, init)
    attr = jnp.einsum("bcnd,tbcnd->tbcn", delta, mean_grad)
    return attr, score_e, score_fn(E0)


# ----------------------------------------------------------------------------------------------------------------
# Occlusion


def region_masks(grid: tuple[int, int], region: int) -> np.ndarray:
    """Square regions of `region` x `region` patches tiling the grid row-major (the last row/column of regions is
    cut short when the side does not divide the grid). -> bool [R, Hp, Wp], True = painted; every patch in
    exactly one region."""
    hp, wp = grid
    rows, cols = np.arange(hp) // region, np.arange(wp) // region
    label = rows[:, None] * (-(-wp // region)) + cols[None, :]  # region index of every patch
    return label[None] == np.arange(label.max() + 1)[:, None, None]


def random_region_masks(grid: tuple[int, int], region: int, num: int, keep_prob: float, seed: int) -> np.ndarray:
    """Random masks for the Interventional Significance Score (Zhang et al., ICML 2026): every region is kept with
    probability keep_prob, independently per mask (numpy `default_rng(seed)`). -> bool [num, Hp, Wp], True =
    painted, constant over each region."""
    regions = region_masks(grid, region)  # [R, Hp, Wp]
    painted = np.random.default_rng(seed).random((num, regions.shape[0])) >= keep_prob  # [M, R]
    return np.einsum("mr,rhw->mhw", painted, regions).astype(bool)


def pixel_mask(masks: jax.Array, patch: int, image_hw: tuple[int, int]) -> jax.Array:
    """Patch masks [..., Hp, Wp] -> pixel masks [..., H, W]; pixels beyond the last full patch (never seen by the
    patch embedding) are not painted."""
    pix = jnp.repeat(jnp.repeat(masks, patch, axis=-2), patch, axis=-1)
    h, w = image_hw
    pad = [(0, 0)] * (pix.ndim - 2) + [(0, h - pix.shape[-2]), (0, w - pix.shape[-1])]
    return jnp.pad(pix, pad)


def paint(images: jax.Array, baseline: jax.Array, masks: jax.Array, patch: int) -> jax.Array:
    """images [..., H, W, 3] with the patches masks [..., Hp, Wp] marks replaced by the baseline's pixels."""
    return jnp.where(pixel_mask(masks, patch, images.shape[-3:-1])[..., None], baseline, images)


def region_map(masks: np.ndarray, drops: np.ndarray) -> np.ndarray:
    """Exhaustive occlusion: every patch gets the drop of the one region that paints it.

    masks bool [M, Hp, Wp] (disjoint, covering: `region_masks`), drops [M, ...] -> [..., Hp, Wp]."""
    masks = np.asarray(masks, bool)
    if not np.all(masks.sum(0) == 1):
        raise ValueError("region masks must tile the grid (every patch painted by exactly one mask)")
    return np.einsum("m...,mhw->...hw", np.asarray(drops, np.float64), masks.astype(np.float64))


def iss_map(masks: np.ndarray, drops: np.ndarray) -> np.ndarray:
    """Interventional Significance Score per patch: mean drop over the masks that paint it minus mean drop over the
    masks that keep it. For an additive score (drop = sum of painted patches' effects) its expectation is the
    patch's own effect, the exhaustive single-region drop. A patch never painted, or never kept, gets 0.

    masks bool [M, Hp, Wp], drops [M, ...] -> [..., Hp, Wp]."""
    painted = np.asarray(masks, np.float64)
    drops = np.asarray(drops, np.float64)
    n_painted, n_kept = painted.sum(0), (1.0 - painted).sum(0)
    mean_painted = np.einsum("m...,mhw->...hw", drops, painted) / np.maximum(n_painted, 1)
    mean_kept = np.einsum("m...,mhw->...hw", drops, 1.0 - painted) / np.maximum(n_kept, 1)
    return np.where((n_painted > 0) & (n_kept > 0), mean_painted - mean_kept, 0.0)
