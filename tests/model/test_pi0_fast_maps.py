"""Maps in the model layer against upstream's goldens: they explain the logits decoding used, the gradient is
upstream's, the reduction is the defined one, and explaining other steps reuses one compilation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from paths import GOLDEN_DIR

from openpi_cam import golden
from openpi_cam.model import pi0_fast_maps as maps
from openpi_cam.model.attribution import gradcam_reduce
from openpi_cam.model.observation import preprocess_observation
from openpi_cam.model.pi0_fast import Pi0FAST, embed_images, replay_prelogits
from openpi_cam.vocabulary import MapOptions

TINY = GOLDEN_DIR / "tiny_pi0_fast"
CAMERAS = ["base_0_rgb", "base_1_rgb", "wrist_0_rgb"]
# The golden criteria (`golden.DEFAULT_TOLERANCES`, where the reasoning is): logits and scores, and the quantities
# derived from their gradients, each within its r of their max |value|.
LOGITS_REL = golden.DEFAULT_TOLERANCES.logits
GRAD_REL = golden.DEFAULT_TOLERANCES.gradcam


def case(name: str):
    with np.load(TINY / f"{name}.npz") as npz:
        data = {k: npz[k] for k in npz.files}
    return data, golden.load_observation(data, CAMERAS)


def assert_close_rel(got, want, rel: float, what: str = "") -> None:
    """The golden criterion (`golden.compare`): max |got - want| <= rel x max |want|."""
    comparison = golden.compare("", what, got, want, rel=rel)
    assert comparison.ok, comparison.line()


def stacked(per_camera: dict[str, np.ndarray]) -> np.ndarray:
    """A per-camera field of a `MapResult` with the camera axis after the batch axis, as the goldens store it."""
    return np.stack([per_camera[c] for c in CAMERAS], axis=1)


def log_softmax(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, np.float64)
    m = x.max(-1, keepdims=True)
    return x - m - np.log(np.exp(x - m).sum(-1, keepdims=True))


# case_c, the batch of two, compiles programs of its own: slow tier (the fast tier explains batches in
# cam/test_offline.py).
@pytest.mark.parametrize("name", ["case_a", "case_b", pytest.param("case_c", marks=pytest.mark.slow)])
def test_explained_logits_are_upstreams_decode_logits(tiny_fast_model: Pi0FAST, name: str):
    """Every one of the 16 steps, each row: the logit vector the explained score is taken from is the one upstream's
    decoding chose that token with (`decode_step_logits`), including case_b's masked camera."""
    data, obs = case(name)
    tokens = data["output_tokens"]
    # Four steps per call: the program the per-token tests below compile too (numbers of steps are padded to a
    # power of two), rather than one more for sixteen.
    parts = [maps.maps_for_steps(tiny_fast_model, obs, tokens, list(range(k, k + 4))) for k in range(0, 16, 4)]
    logits = np.concatenate([p.logits for p in parts], axis=1)
    assert_close_rel(logits, data["decode_step_logits"], LOGITS_REL, "logits")
    np.testing.assert_array_equal(np.concatenate([p.token_ids for p in parts], axis=1), tokens)
    picked = np.take_along_axis(data["decode_step_logits"], tokens[..., None], -1)[..., 0]
    assert_close_rel(np.concatenate([p.score for p in parts], axis=1), picked, LOGITS_REL, "score")


@pytest.mark.slow
def test_without_logits_the_maps_and_scores_are_the_same(tiny_fast_model: Pi0FAST):
    """`logits=False` (what the side channel and `explain` ask for) leaves out only the vocabulary projection: same
    scores and maps, for the gradient pass and for a baseline kind alone (which then reports the score itself)."""
    data, obs = case("case_a")
    tokens = data["output_tokens"]
    # 8 x 8-patch regions: 4 painted variants per camera rather than 256, each a full re-run of SigLIP and Gemma;
    # what is compared (the program with and without the vocabulary projection) does not depend on the region size.
    options = MapOptions(occlusion_region=8)
    steps = [1, 2, 3]  # padded to four, as in the test above: its gradient program serves `full` here
    for kinds in (("gradcam", "gradnorm"), ("occlusion",)):
        full = maps.maps_for_steps(tiny_fast_model, obs, tokens, steps, kinds=kinds, options=options)
        lean = maps.maps_for_steps(tiny_fast_model, obs, tokens, steps, kinds=kinds, options=options, logits=False)
        assert full.logits is not None and full.logits.shape[:2] == (1, 3) and lean.logits is None
        np.testing.assert_array_equal(lean.score, full.score)
        for kind in kinds:
            for c in CAMERAS:
                np.testing.assert_array_equal(lean.by_kind[kind][c], full.by_kind[kind][c])
            assert any(np.abs(full.by_kind[kind][c]).max() > 0 for c in CAMERAS)  # maps with something to compare


def test_naive_teacher_forcing_would_explain_other_logits(tiny_fast_model: Pi0FAST):
    """Guards the reason for replaying decoding: contiguous positions give different argmaxes (golden: k = 3)."""
    data, obs = case("case_a")
    assert not np.array_equal(data["gc_tf_k3_logits"].argmax(-1), data["output_tokens"][:, 3])
    res = maps.gradcam_for_action_token(tiny_fast_model, obs, data["output_tokens"], 3)
    assert res.logits.argmax(-1)[0] == data["output_tokens"][0, 3]


def test_gradient_is_upstreams_and_maps_reduce_it(tiny_fast_model: Pi0FAST):
    """The full gradient dScore/dE of step 0 equals upstream's (`gc_tf_k0_grad`, case_a: for k = 0 the teacher-forced
    score is the decode-time one, README), and the reported alphas, gradient-norm maps and grad norms are the
    defined reductions of that upstream gradient."""
    data, obs = case("case_a")
    model = tiny_fast_model
    obs = preprocess_observation(obs, model.config.image_resolution)
    fed = jnp.asarray(data["output_tokens"], jnp.int32)

    @jax.jit
    def gradient(image_tokens):
        def score(e):
            pre = replay_prelogits(model.params, e, obs, fed, model.config)
            return maps._gathered_logits(model.params, pre, fed)[0, 0]

        return jax.grad(score)(image_tokens)

    upstream = data["gc_tf_k0_grad"].astype(np.float64)  # [1, 3, 256, 128]
    ours = np.asarray(gradient(embed_images(model.params, obs, model.config)))
    assert_close_rel(ours, upstream, GRAD_REL, "dScore/dE")

    res = maps.gradcam_for_action_token(model, obs, data["output_tokens"], 0)
    assert_close_rel(stacked(res.alphas), upstream.mean(axis=2), GRAD_REL, "alpha = mean over tokens")
    per_token = np.linalg.norm(upstream, axis=-1).reshape(1, 3, 16, 16)  # row-major over the patch grid
    assert_close_rel(stacked(res.by_kind["gradnorm"]), per_token, GRAD_REL, "gradient-norm map")
    assert_close_rel(stacked(res.grad_norms), np.linalg.norm(upstream, axis=(2, 3)), GRAD_REL, "grad norm")


def test_reduction_is_the_defined_one():
    """alpha = mean over a camera's tokens of G; cam = ReLU(E . alpha); norm = ||G|| per token, for a leading score
    axis too. Distinct sizes on every axis, so a reduction over the wrong one cannot line up."""
    rng = np.random.default_rng(0)
    t, b, c, n, d = 2, 3, 4, 5, 7
    E = rng.standard_normal((b, c, n, d))
    G = rng.standard_normal((t, b, c, n, d))
    alpha, cam, norm = (np.asarray(x, np.float64) for x in gradcam_reduce(jnp.asarray(E), jnp.asarray(G)))
    want_alpha = G.sum(axis=3) / n
    want_cam = np.maximum(np.einsum("bcnd,tbcd->tbcn", E, want_alpha), 0.0)
    want_norm = np.sqrt((G**2).sum(axis=4))
    assert alpha.shape == (t, b, c, d) and cam.shape == norm.shape == (t, b, c, n)
    np.testing.assert_allclose(alpha, want_alpha, rtol=1e-5, atol=1e-6)  # float32 sums of 5-7 terms
    np.testing.assert_allclose(cam, want_cam, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(norm, want_norm, rtol=1e-5, atol=1e-6)
    assert (want_cam == 0).any() and (want_cam > 0).any()  # the ReLU both clips and passes here


def test_all_tokens_in_one_call_are_upstreams_per_token_maps(tiny_fast_model: Pi0FAST):
    """Several steps of a batch of 2 in one call (the stacked backward passes) equal upstream's per-step maps."""
    data, obs = case("case_c")
    steps = [0, 3, 7]
    res = maps.maps_for_steps(tiny_fast_model, obs, data["output_tokens"], steps)
    assert res.by_kind["gradcam"]["base_0_rgb"].shape == (2, len(steps), 16, 16)
    for i, k in enumerate(steps):
        ref = f"gc_replay_k{k}"
        assert_close_rel(stacked(res.by_kind["gradcam"])[:, :, i], data[f"{ref}_cam"], GRAD_REL, f"{ref} cam")
        assert_close_rel(stacked(res.alphas)[:, :, i], data[f"{ref}_alpha"], GRAD_REL, f"{ref} alpha")
        assert_close_rel(stacked(res.grad_norms)[:, :, i], data[f"{ref}_grad_norm"], GRAD_REL, f"{ref} norm")
        assert_close_rel(res.score[:, i], data[f"{ref}_score"], LOGITS_REL, f"{ref} score")
        # The gradient-norm map's squares add up to upstream's grad norm (Frobenius norm over tokens x channels).
        total = np.sqrt((stacked(res.by_kind["gradnorm"])[:, :, i].astype(np.float64) ** 2).sum((-2, -1)))
        assert_close_rel(total, data[f"{ref}_grad_norm"], GRAD_REL, f"{ref} gradnorm map")


@pytest.mark.slow
def test_explaining_other_steps_does_not_recompile(tiny_fast_model: Pi0FAST):
    data, obs = case("case_a")
    maps.gradcam_for_action_token(tiny_fast_model, obs, data["output_tokens"], 0)
    before = maps._token_gradient_maps._cache_size()
    for k in (5, 9, 15):
        maps.gradcam_for_action_token(tiny_fast_model, obs, data["output_tokens"], k)
    assert maps._token_gradient_maps._cache_size() == before
    maps.maps_for_chunk(tiny_fast_model, obs, data["output_tokens"], [1, 2, 3])
    chunk_before = maps._chunk_gradient_maps._cache_size()
    maps.maps_for_chunk(tiny_fast_model, obs, data["output_tokens"], list(range(10)))
    assert maps._chunk_gradient_maps._cache_size() == chunk_before


def test_token_api_by_step_by_position_and_counterfactual(tiny_fast_model: Pi0FAST):
    data, obs = case("case_a")
    gen = data["output_tokens"][0]
    k = 3
    prefill_len = int(data["prefill_len"][0])
    kwargs = {"token_id": int(gen[k]), "generated_prefix": gen[:k], "max_decoding_steps": 16}
    by_step = maps.gradcam_for_token(tiny_fast_model, obs, step=k, **kwargs)
    # README: generated token j sits at position prefill_len + 1 + j, so step k > 0 is predicted by g_{k-1}'s output
    # at prefill_len + k; step 0 by the last prefix token at prefill_len - 1.
    by_pos = maps.gradcam_for_token(tiny_fast_model, obs, position=prefill_len + k, **kwargs)
    for res in (by_step, by_pos):
        assert res.positions[0, 0] == prefill_len + k
        assert_close_rel(stacked(res.by_kind["gradcam"]), data["gc_replay_k3_cam"], GRAD_REL, "cam")
        assert_close_rel(res.score, data["gc_replay_k3_score"], LOGITS_REL, "score")
    first = maps.gradcam_for_token(tiny_fast_model, obs, step=0, token_id=int(gen[0]), max_decoding_steps=16)
    assert first.positions[0, 0] == prefill_len - 1
    assert_close_rel(first.score, data["gc_replay_k0_score"], LOGITS_REL, "step 0 score")
    # A token decoding did not choose: its own entry of upstream's logit vector at that output is explained.
    other = (int(gen[k]) + 1) % tiny_fast_model.config.gemma.vocab_size
    cf = maps.gradcam_for_token(tiny_fast_model, obs, step=k, token_id=other, generated_prefix=gen[:k],
                                max_decoding_steps=16)  # fmt: skip
    scale = np.abs(data["gc_replay_k3_logits"]).max()
    assert abs(cf.score[0] - data["gc_replay_k3_logits"][0, other]) <= LOGITS_REL * scale
    cam = data["gc_replay_k3_cam"]
    assert np.abs(stacked(cf.by_kind["gradcam"]) - cam).max() > 10 * GRAD_REL * cam.max()
    with pytest.raises(ValueError, match="needs the 3 tokens generated before it"):
        maps.gradcam_for_token(tiny_fast_model, obs, step=k, token_id=1, generated_prefix=gen[:2])


def test_masked_camera_is_flagged_and_spans_are_explicit(tiny_fast_model: Pi0FAST):
    data, obs = case("case_b")
    res = maps.gradcam_for_action_token(tiny_fast_model, obs, data["output_tokens"], 3)
    assert [bool(res.valid[c][0]) for c in CAMERAS] == [True, False, True]
    assert res.spans == {"base_0_rgb": (0, 256), "base_1_rgb": (256, 512), "wrist_0_rgb": (512, 768)}
    assert res.cameras == tuple(CAMERAS)
    # Upstream's decode window reaches the masked camera for k > 0 (README point 3): its gradient is upstream's, not 0.
    assert data["gc_replay_k3_grad_norm"][0, 1] > 1
    assert_close_rel(stacked(res.grad_norms), data["gc_replay_k3_grad_norm"], GRAD_REL, "grad norms")


def test_rows_may_explain_different_steps(tiny_fast_model: Pi0FAST):
    """Batched offline explanation gives every row its own steps; each row is upstream's map of its own step."""
    data, obs = case("case_c")
    rows = [[0, 3, 7], [7, 0, 3]]  # three steps, as in the test above: the same compiled program
    per_row = maps.maps_for_steps(tiny_fast_model, obs, data["output_tokens"], rows)
    assert per_row.decode_steps.tolist() == rows
    gradcam = stacked(per_row.by_kind["gradcam"])
    for b, steps in enumerate(rows):
        for i, k in enumerate(steps):
            ref = f"gc_replay_k{k}"
            assert_close_rel(gradcam[b, :, i], data[f"{ref}_cam"][b], GRAD_REL, f"row {b} {ref}")
            assert_close_rel(per_row.score[b, i], data[f"{ref}_score"][b], LOGITS_REL, f"row {b} {ref} score")
    # Chunks of different lengths per row: each score is the sum of upstream's log-probabilities of its own steps.
    chunk = maps.maps_for_chunk(tiny_fast_model, obs, data["output_tokens"], [[0, 1, 2], [5, 6]])
    assert chunk.decode_steps.tolist() == [[0, 1, 2], [5, 6, -1]] and chunk.token_ids[1, 2] == -1
    logp = np.take_along_axis(log_softmax(data["decode_step_logits"]), data["output_tokens"][..., None], -1)[..., 0]
    want = np.array([logp[0, [0, 1, 2]].sum(), logp[1, [5, 6]].sum()])
    assert_close_rel(chunk.score, want, LOGITS_REL, "chunk scores")
