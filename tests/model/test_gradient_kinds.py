"""The kinds of the gradient program beside Grad-CAM and the gradient norm: gradient x input, occlusion's first-order
(Taylor) estimate and SmoothGrad, each against a computation that does not go through `gradient_maps`.

pi0 runs on the golden tiny model (224 px, 16 x 16 patches, three cameras, case_b's left wrist masked), whose files
hold upstream's image tokens and gradients. Tolerances: upstream's quantities within the golden criterion for
gradients (`golden.FLOW_GRAD_REL` / `DEFAULT_TOLERANCES.gradcam`, of the reference's largest magnitude); the same
quantity from two of our programs (one `jax.grad` of the score against the gradient program) within SAME_REL of its
largest magnitude: they differ by float32 rounding of differently fused programs (measured below 1e-6).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from paths import GOLDEN_DIR

from openpi_cam import golden
from openpi_cam.model import attribution, pi0
from openpi_cam.model import pi0_fast_maps as fast_maps
from openpi_cam.model.paligemma import embed_images
from openpi_cam.model.pi0_maps import CHUNK, maps_for_actions
from openpi_cam.vocabulary import MapOptions

SAME_REL = 1e-5
PI0_CAMERAS = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")
FAST_CAMERAS = ("base_0_rgb", "base_1_rgb", "wrist_0_rgb")


def assert_close(got, want, rel: float, what: str) -> None:
    """The golden criterion (`golden.compare`): max |got - want| <= rel x max |want|."""
    comparison = golden.compare("", what, got, want, rel=rel)
    assert comparison.ok, comparison.line()


@functools.cache
def pi0_model() -> pi0.Pi0:
    return pi0.Pi0.from_checkpoint(
        GOLDEN_DIR / "tiny_pi0" / "checkpoint" / "params", dtype="float32", action_horizon=10, max_token_len=48
    )


def golden_case(folder: str, name: str, cameras) -> tuple[dict, object]:
    with np.load(GOLDEN_DIR / folder / f"{name}.npz") as npz:
        data = {k: npz[k] for k in npz.files}
    return data, golden.load_observation(data, list(cameras))


def token_product(data: dict, key: str, cameras) -> np.ndarray:
    """sum_d E[n, d] G[n, d] from upstream's image tokens and gradient -> [B, C, 16, 16]."""
    E = np.stack([data[f"siglip_{c}"] for c in cameras], axis=1).astype(np.float64)
    return np.einsum("bcnd,bcnd->bcn", E, data[f"{key}_grad"].astype(np.float64)).reshape(*E.shape[:2], 16, 16)


def stacked(per_camera: dict[str, np.ndarray], cameras) -> np.ndarray:
    return np.stack([per_camera[c] for c in cameras], axis=1)


def patch_sums(x: np.ndarray, patch: int) -> np.ndarray:
    """[B, H, W, 3] summed over each patch (row-major) -> [B, H / patch, W / patch]."""
    b, h, w, _ = x.shape
    return x.reshape(b, h // patch, patch, w // patch, patch, 3).sum(axis=(2, 4, 5))


def test_one_pass_gives_gradient_x_input_and_the_taylor_estimate_beside_upstreams_maps():
    """pi0, one call for four kinds: Grad-CAM and the gradient norm stay upstream's with the pixel pass added;
    gradient x input is upstream's gradient dotted with upstream's tokens; taylor is the gradient of the score with
    respect to the model's input pixels (`jax.grad` through SigLIP and the denoising) times frame - mean-colour frame,
    summed per patch; the masked camera gets exactly zero."""
    model = pi0_model()
    data, obs = golden_case("tiny_pi0", "case_b", PI0_CAMERAS)
    kinds = ("gradcam", "gradnorm", "gradxinput", "taylor")
    res = maps_for_actions(model, obs, data["noise"], [(0, 6), CHUNK], kinds=kinds)
    for t, key in enumerate(("gc_h0_d6", "gc_chunk")):
        at = {k: stacked(res.by_kind[k], PI0_CAMERAS)[:, :, t] for k in kinds}
        assert_close(at["gradcam"], data[f"{key}_cam"], golden.FLOW_GRAD_REL, f"{key} cam")
        norms = np.linalg.norm(data[f"{key}_grad"], axis=-1).reshape(at["gradnorm"].shape)
        assert_close(at["gradnorm"], norms, golden.FLOW_GRAD_REL, f"{key} gradient norm")
        assert_close(at["gradxinput"], token_product(data, key, PI0_CAMERAS), golden.FLOW_GRAD_REL, f"{key} g x i")

    cfg = model.config
    prepared = pi0.preprocess(obs, cfg)
    noise = jnp.asarray(data["noise"], jnp.float32)
    chunk = jax.lax.stop_gradient(res.actions)

    @jax.jit
    def pixel_grads(images):
        def scores(imgs):
            tokens = embed_images(model.params, dataclasses.replace(prepared, images=imgs), cfg)
            x_0 = pi0.denoise(model.params, tokens, prepared, noise, cfg)
            return x_0[:, 0, 6].sum(), jnp.sum(chunk * x_0)

        return jax.jacrev(scores)(images)

    grads = pixel_grads(dict(prepared.images))
    patch = cfg.siglip.patch_size
    for c in PI0_CAMERAS:
        frame = np.asarray(prepared.images[c], np.float64)
        delta = frame - frame.mean(axis=(1, 2), keepdims=True)
        for t in range(2):
            want = patch_sums(np.asarray(grads[t][c], np.float64) * delta, patch)
            got = res.by_kind["taylor"][c][:, t]
            if c == "left_wrist_0_rgb":  # masked: it is its own baseline frame
                np.testing.assert_array_equal(got, 0.0)
            else:
                assert np.abs(want).max() > 0
                assert_close(got, want, SAME_REL, f"taylor {c} target {t}")


@pytest.mark.parametrize("baseline", ["mean", "blur"])
def test_taylor_is_exhaustive_occlusion_of_a_score_linear_in_the_pixels(baseline):
    """For score = sum(W * frames) painting patch p changes the score by exactly the linear term, so the Taylor
    estimate equals the occlusion map of the same painting (`paint`, `region_masks`, `region_map`), in row-major
    patch order. The frames (2 cameras x 3 rows, 18 x 10 px, patch 4) leave pixels beyond the last full patch, which
    neither kind may count."""
    rng = np.random.default_rng(0)
    patch, grid = 4, (4, 2)
    images = jnp.asarray(rng.uniform(-1, 1, (2, 3, 18, 10, 3)), jnp.float32)
    weights = jnp.asarray(rng.normal(size=images.shape), jnp.float32)
    valid = jnp.asarray([[True, True, False], [True, True, True]])
    base = attribution.baseline_images(images, valid, MapOptions(baseline=baseline, blur_sigma=2.0))

    def score(x):
        return jnp.sum(weights * x, axis=(-3, -2, -1))  # [C, B]

    taylor = attribution.taylor_patches(jax.grad(lambda x: score(x).sum())(images), images - base, patch)
    regions = attribution.region_masks(grid, 1)
    for c in range(2):
        painted = attribution.paint(images[c][None], base[c][None], regions[:, None], patch)  # [M, B, H, W, 3]
        drops = np.asarray(score(images)[c] - jnp.sum(weights[c] * painted, axis=(-3, -2, -1)), np.float64)
        occlusion = attribution.region_map(regions, drops)  # [B, 4, 2]
        got = np.asarray(taylor[:, c]).reshape(3, *grid)
        np.testing.assert_allclose(got, occlusion, rtol=0, atol=1e-5 * np.abs(occlusion).max())
        assert np.abs(got - occlusion.transpose(0, 2, 1).reshape(3, *grid)).max() > 0.1  # row-major, not transposed
    np.testing.assert_array_equal(np.asarray(taylor[2, 0]), 0.0)  # an invalid camera is its own baseline


def test_smoothgrad_is_the_gradient_averaged_over_seeded_noise():
    """pi0, targets (0, 6) and the chunk: with sigma 0 SmoothGrad is the gradient norm; with noise it is the norm of
    the mean of `jax.grad` at E + noise for the noise `attribution.smoothgrad_noise` draws from the seed (the chunk
    target keeps the clean chunk as its weighting); the same seed gives the same map, another seed another."""
    model = pi0_model()
    data, obs = golden_case("tiny_pi0", "case_a", PI0_CAMERAS)
    targets = [(0, 6), CHUNK]

    def smoothgrad(**options) -> np.ndarray:
        opts = MapOptions(**options)
        res = maps_for_actions(model, obs, data["noise"], targets, kinds=("smoothgrad", "gradnorm"), options=opts)
        return stacked(res.by_kind["smoothgrad"], PI0_CAMERAS), stacked(res.by_kind["gradnorm"], PI0_CAMERAS)

    plain, gradnorm = smoothgrad(smoothgrad_sigma=0.0, smoothgrad_samples=2)
    assert_close(plain, gradnorm, SAME_REL, "smoothgrad at sigma 0")

    noisy, _ = smoothgrad(smoothgrad_sigma=0.5, smoothgrad_samples=2, seed=7)
    again, _ = smoothgrad(smoothgrad_sigma=0.5, smoothgrad_samples=2, seed=7)
    other, _ = smoothgrad(smoothgrad_sigma=0.5, smoothgrad_samples=2, seed=8)
    np.testing.assert_array_equal(noisy, again)
    assert np.abs(noisy - other).max() > 0.01 * np.abs(noisy).max()
    assert np.abs(noisy - gradnorm).max() > 0.01 * np.abs(gradnorm).max()

    cfg = model.config
    prepared = pi0.preprocess(obs, cfg)
    noise = jnp.asarray(data["noise"], jnp.float32)
    E = embed_images(model.params, prepared, cfg)
    chunk = pi0.denoise(model.params, E, prepared, noise, cfg)

    @jax.jit
    def grads_at(e):
        def scores(x):
            x_0 = pi0.denoise(model.params, x, prepared, noise, cfg)
            return x_0[:, 0, 6].sum(), jnp.sum(chunk * x_0)

        return jnp.stack(jax.jacrev(scores)(e))  # [T, B, C, N, D]

    key = jax.random.key(7)
    mean = sum(grads_at(E + attribution.smoothgrad_noise(jax.random.fold_in(key, i), E, 0.5)) for i in range(2)) / 2
    want = np.moveaxis(np.linalg.norm(np.asarray(mean, np.float64), axis=-1), 0, 2).reshape(noisy.shape)
    assert_close(noisy, want, SAME_REL, "smoothgrad against jax.grad at the noisy tokens")


def test_gradient_x_input_of_a_pi0_fast_token_is_upstreams(tiny_fast_model):
    """pi0-FAST, step 0 of case_a (`gc_tf_k0`: for k = 0 the teacher-forced score is the decode-time one): gradient x
    input equals upstream's gradient dotted with upstream's image tokens, beside the gradient kinds it shares the pass
    with."""
    data, obs = golden_case("tiny_pi0_fast", "case_a", FAST_CAMERAS)
    kinds = ("gradnorm", "gradxinput")
    res = fast_maps.gradcam_for_action_token(tiny_fast_model, obs, data["output_tokens"], 0, kinds=kinds)
    want = token_product(data, "gc_tf_k0", FAST_CAMERAS)
    assert_close(stacked(res.by_kind["gradxinput"], FAST_CAMERAS), want, golden.DEFAULT_TOLERANCES.gradcam, "g x i")
