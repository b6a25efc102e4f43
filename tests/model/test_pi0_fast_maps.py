"""Grad-CAM in the model layer: it explains the logits decoding used, its gradient is right, and it compiles once."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from paths import GOLDEN_DIR

from openpi_cam import golden
from openpi_cam.model import pi0_fast_maps as maps
from openpi_cam.model.observation import preprocess_observation
from openpi_cam.model.pi0_fast import Pi0FAST, embed_images, replay_prelogits, sample_tokens_jit

TINY = GOLDEN_DIR / "tiny_pi0_fast"
CAMERAS = ["base_0_rgb", "base_1_rgb", "wrist_0_rgb"]
# Logit tolerance: upstream's own float32 evaluations of these logits differ by up to 5.4e-4 (golden README).
LOGIT_ATOL = 2e-3


@pytest.fixture(scope="module")
def model() -> Pi0FAST:
    return Pi0FAST.from_checkpoint(
        TINY / "checkpoint" / "params", dtype="float32", action_dim=8, action_horizon=10, max_token_len=48
    )


def case(name: str):
    with np.load(TINY / f"{name}.npz") as npz:
        data = {k: npz[k] for k in npz.files}
    return data, golden.load_observation(data, CAMERAS)


@pytest.mark.parametrize("name", ["case_a", "case_b", "case_c"])
def test_explained_logits_are_the_decode_time_logits(model, name):
    _, obs = case(name)
    tokens, n_steps, step_logits = sample_tokens_jit(
        model.params,
        obs,
        jax.random.key(0),
        cfg=model.config,
        max_decoding_steps=16,
        temperature=0.0,
        record_logits=True,
    )
    step_logits = np.asarray(step_logits)
    res = maps.gradcam_for_steps(model, obs, tokens, list(range(int(n_steps))))
    np.testing.assert_allclose(res.logits, step_logits[:, : int(n_steps)], atol=LOGIT_ATOL, rtol=0)
    np.testing.assert_array_equal(res.logits.argmax(-1), np.asarray(tokens)[:, : int(n_steps)])
    np.testing.assert_array_equal(res.token_ids, np.asarray(tokens)[:, : int(n_steps)])
    # The score is the explained token's entry of that logit vector.
    picked = np.take_along_axis(res.logits, res.token_ids[..., None], -1)[..., 0]
    np.testing.assert_allclose(res.score, picked, atol=1e-4)


def test_naive_teacher_forcing_would_explain_other_logits(model):
    """Guards the reason for replaying decoding: contiguous positions give different argmaxes (golden: k = 3)."""
    data, obs = case("case_a")
    assert not np.array_equal(data["gc_tf_k3_logits"].argmax(-1), data["output_tokens"][:, 3])
    res = maps.gradcam_for_action_token(model, obs, data["output_tokens"], 3)
    assert res.logits.argmax(-1)[0] == data["output_tokens"][0, 3]


def test_gradient_matches_finite_differences(model):
    """Central differences of the replayed score w.r.t. the image tokens, in float32.

    Tolerance 1e-2 relative: the golden's own float32 FD check (README table) agrees with the analytic gradient to
    1e-4 relative on the largest entry and 3e-3 on a random direction."""
    data, obs = case("case_a")
    obs = preprocess_observation(obs, model.config.image_resolution)
    fed = jnp.asarray(data["output_tokens"], jnp.int32)
    k = 3

    def score(E):
        pre = replay_prelogits(model.params, E, obs, fed, model.config)
        return maps._gathered_logits(model.params, pre, fed)[0, k]

    E = embed_images(model.params, obs, model.config)
    grad = np.asarray(jax.grad(score)(E))
    entry = np.unravel_index(np.abs(grad).argmax(), grad.shape)
    eps = 1e-2
    bump = jnp.zeros_like(E).at[entry].set(eps)
    fd = (float(score(E + bump)) - float(score(E - bump))) / (2 * eps)
    assert abs(fd - grad[entry]) <= 1e-2 * abs(grad[entry])
    direction = jax.random.normal(jax.random.key(1), E.shape)
    direction = direction / jnp.linalg.norm(direction)
    analytic = float(jnp.vdot(grad, direction))
    fd_dir = (float(score(E + 0.3 * direction)) - float(score(E - 0.3 * direction))) / 0.6
    assert abs(fd_dir - analytic) <= 1e-2 * abs(analytic) + 1e-5
    # And the reported alpha is the per-camera mean of exactly this gradient, the gradient-norm map its per-token
    # norm on the patch grid, and grad_norm (checked against the golden elsewhere) the root sum of that map's squares.
    res = maps.gradcam_for_action_token(model, obs, data["output_tokens"], k)
    for c, cam in enumerate(CAMERAS):
        np.testing.assert_allclose(res.alphas[cam][0], grad[0, c].mean(0), atol=1e-4 * np.abs(grad).max())
        per_token = np.linalg.norm(grad[0, c], axis=-1)
        assert res.gradnorm_maps[cam].shape == res.maps[cam].shape == (len(grad), 16, 16)
        np.testing.assert_allclose(res.gradnorm_maps[cam][0].ravel(), per_token, atol=1e-4 * per_token.max())
        np.testing.assert_allclose(res.grad_norms[cam], np.sqrt((res.gradnorm_maps[cam] ** 2).sum((1, 2))), rtol=1e-5)


def test_all_tokens_in_one_call_equals_the_per_token_loop(model):
    data, obs = case("case_c")
    steps = [0, 3, 7, 12]
    stacked = maps.gradcam_for_steps(model, obs, data["output_tokens"], steps)
    for i, k in enumerate(steps):
        single = maps.gradcam_for_action_token(model, obs, data["output_tokens"], k)
        for cam in CAMERAS:
            assert stacked.maps[cam].shape == (2, len(steps), 16, 16)
            scale = np.abs(single.maps[cam]).max() + 1e-12
            np.testing.assert_allclose(stacked.maps[cam][:, i], single.maps[cam], atol=1e-4 * scale)
            scale = single.gradnorm_maps[cam].max() + 1e-12
            np.testing.assert_allclose(stacked.gradnorm_maps[cam][:, i], single.gradnorm_maps[cam], atol=1e-4 * scale)
        np.testing.assert_allclose(stacked.score[:, i], single.score, atol=1e-5)


def test_explaining_other_steps_does_not_recompile(model):
    data, obs = case("case_a")
    maps.gradcam_for_action_token(model, obs, data["output_tokens"], 0)
    before = maps._token_cams._cache_size()
    for k in (5, 9, 15):
        maps.gradcam_for_action_token(model, obs, data["output_tokens"], k)
    assert maps._token_cams._cache_size() == before
    maps.gradcam_for_chunk(model, obs, data["output_tokens"], [1, 2, 3])
    chunk_before = maps._chunk_cam._cache_size()
    maps.gradcam_for_chunk(model, obs, data["output_tokens"], list(range(10)))
    assert maps._chunk_cam._cache_size() == chunk_before


def test_token_api_by_position_and_counterfactual(model):
    data, obs = case("case_a")
    gen = data["output_tokens"][0]
    k = 4
    prefill_len = int(data["prefill_len"][0])
    by_step = maps.gradcam_for_token(
        model, obs, step=k, token_id=int(gen[k]), generated_prefix=gen[:k], max_decoding_steps=16
    )
    by_pos = maps.gradcam_for_token(
        model, obs, position=prefill_len + k, token_id=int(gen[k]), generated_prefix=gen[:k], max_decoding_steps=16
    )
    np.testing.assert_allclose(by_pos.maps["base_0_rgb"], by_step.maps["base_0_rgb"], atol=1e-6)
    assert by_step.positions[0, 0] == prefill_len + k
    first = maps.gradcam_for_token(model, obs, step=0, token_id=int(gen[0]), max_decoding_steps=16)
    assert first.positions[0, 0] == prefill_len - 1
    # A token decoding did not choose: its own logit is explained, from the same logit vector.
    other = (int(gen[k]) + 1) % model.config.gemma.vocab_size
    cf = maps.gradcam_for_token(model, obs, step=k, token_id=other, generated_prefix=gen[:k], max_decoding_steps=16)
    np.testing.assert_allclose(cf.score[0], by_step.logits[0, other], atol=1e-4)
    assert not np.allclose(cf.maps["base_0_rgb"], by_step.maps["base_0_rgb"])
    with pytest.raises(ValueError, match="needs the 4 tokens generated before it"):
        maps.gradcam_for_token(model, obs, step=k, token_id=1, generated_prefix=gen[:2], max_decoding_steps=16)


def test_masked_camera_is_flagged_and_spans_are_explicit(model):
    data, obs = case("case_b")
    res = maps.gradcam_for_action_token(model, obs, data["output_tokens"], 3)
    assert [bool(res.valid[c][0]) for c in CAMERAS] == [True, False, True]
    assert res.spans == {"base_0_rgb": (0, 256), "base_1_rgb": (256, 512), "wrist_0_rgb": (512, 768)}
    assert res.cameras == tuple(CAMERAS)
    # Upstream's decode window reaches the masked camera for k > 0, so its gradient is not zero (golden case_b).
    assert res.grad_norms["base_1_rgb"][0] > 0
    assert all(m.dtype == np.float32 and (m >= 0).all() for m in res.maps.values())


def test_rows_may_explain_different_steps(model):
    """Batched offline explanation gives every row its own steps; each row equals its own shared-step call."""
    data, obs = case("case_c")
    per_row = maps.gradcam_for_steps(model, obs, data["output_tokens"], [[0, 3], [7, 12]])
    assert per_row.decode_steps.tolist() == [[0, 3], [7, 12]]
    for b, steps in enumerate(([0, 3], [7, 12])):
        shared = maps.gradcam_for_steps(model, obs, data["output_tokens"], steps)
        np.testing.assert_allclose(per_row.score[b], shared.score[b], atol=1e-5)
        scale = np.abs(shared.maps["wrist_0_rgb"][b]).max()
        np.testing.assert_allclose(per_row.maps["wrist_0_rgb"][b], shared.maps["wrist_0_rgb"][b], atol=1e-4 * scale)
    chunk = maps.gradcam_for_chunk(model, obs, data["output_tokens"], [[0, 1, 2], [5, 6]])
    assert chunk.decode_steps.tolist() == [[0, 1, 2], [5, 6, -1]] and chunk.token_ids[1, 2] == -1
    alone = maps.gradcam_for_chunk(model, obs, data["output_tokens"], [5, 6])
    np.testing.assert_allclose(chunk.score[1], alone.score[1], atol=1e-5)
