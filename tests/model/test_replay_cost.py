"""The explanation replay stops at the last explained step (its length bucketed) and projects only the explained
outputs onto the vocabulary: same maps and scores as the full-length replay, a bounded number of compilations."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from paths import GOLDEN_DIR

from openpi_cam import golden
from openpi_cam.model import pi0_fast_maps as maps
from openpi_cam.model.observation import preprocess_observation
from openpi_cam.model.pi0_fast import Pi0FAST, embed_images, replay_prelogits

TINY = GOLDEN_DIR / "tiny_pi0_fast"
CAMERAS = ["base_0_rgb", "base_1_rgb", "wrist_0_rgb"]
# A decode of S = 100 steps: replays of 16, 32 and 64 tokens are cut, 100 (not a power of two) is the cap.
S = 100
STEPS = (0, 3, 20, 40, S - 1)  # buckets 16, 16, 32, 64, 100: the last generated step runs the full length
# Cut vs full-length replay of one quantity, max |difference| / its scale, measured on these cases (float32 sums in
# another order: attention over fewer slots, fewer vocabulary rows): maps, gradient-norm maps, alphas and gradient
# norms <= 1.1e-5 of their max |value|; logits <= 1.7e-6 of their max |value|, a token's score (one logit) <= 1.1e-6
# of the max |logit| at its output, a chunk's score (a sum of log-probabilities) <= 2.7e-7 of its |value|. Allowed:
GRAD_REL = 5e-5
LOGIT_REL = 1e-5


def observation(name: str):
    """A golden case's inputs (its outputs are for a 16-step decode; these tests feed their own sequences)."""
    with np.load(TINY / f"{name}.npz") as npz:
        return golden.load_observation({k: npz[k] for k in npz.files}, CAMERAS)


def sequence(batch: int, length: int, seed: int = 0) -> np.ndarray:
    """Generated tokens fed back by teacher forcing: any ids do (a random model rarely decodes 100 steps)."""
    return np.random.default_rng(seed).integers(2, 1024, (batch, length)).astype(np.int32)


def assert_close_rel(got, want, rel: float, what: str, scale: float | None = None) -> None:
    """max |got - want| <= rel x scale (default: max |want|)."""
    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    assert got.shape == want.shape, (what, got.shape, want.shape)
    error = np.abs(got - want).max()
    scale = np.abs(want).max() if scale is None else scale
    assert error <= rel * scale, f"{what}: max abs error {error:.3g} > {rel:g} x {scale:.3g}"


def full_length(monkeypatch: pytest.MonkeyPatch) -> None:
    """Makes every entry point replay all S generated tokens, as before the cut."""
    monkeypatch.setattr(maps, "replay_length", lambda last_step, decode_len: decode_len)


def assert_same_result(cut: maps.MapResult, full: maps.MapResult, what: str) -> None:
    fields = {"alphas": (cut.alphas, full.alphas), "grad_norms": (cut.grad_norms, full.grad_norms)}
    fields |= {kind: (cut.by_kind[kind], full.by_kind[kind]) for kind in full.by_kind}
    for field, (got, want) in fields.items():
        for c in CAMERAS:
            assert_close_rel(got[c], want[c], GRAD_REL, f"{what} {field} {c}")
    if full.logits is None:
        assert_close_rel(cut.score, full.score, LOGIT_REL, f"{what} score")
    else:
        assert_close_rel(cut.logits, full.logits, LOGIT_REL, f"{what} logits")
        scale = np.abs(full.logits).max()  # a logit's float32 error scales with the logit vector, not its own value
        assert_close_rel(cut.score, full.score, LOGIT_REL, f"{what} score", scale)
    np.testing.assert_array_equal(cut.token_ids, full.token_ids)
    np.testing.assert_array_equal(cut.positions, full.positions)


# The cases' rows in one batch (case_b's one row, then case_c's two): every program below compiles once for both.
ROWS = {"case_b": slice(0, 1), "case_c": slice(1, 3)}
CHUNK = [1, 5, 9, 30]


def rows_of(res: maps.MapResult, rows: slice) -> maps.MapResult:
    """The batch rows `rows` of every per-row field that `assert_same_result` compares."""
    per_camera = {f: {c: getattr(res, f)[c][rows] for c in CAMERAS} for f in ("alphas", "grad_norms")}
    return dataclasses.replace(
        res,
        by_kind={kind: {c: m[rows] for c, m in by_camera.items()} for kind, by_camera in res.by_kind.items()},
        score=res.score[rows],
        logits=None if res.logits is None else res.logits[rows],
        token_ids=res.token_ids[rows],
        positions=res.positions[rows],
        **per_camera,
    )


@pytest.fixture(scope="module")
def cut_and_full(tiny_fast_model: Pi0FAST):
    """One token at each of STEPS and the chunk CHUNK, explained with the cut replay and with the full one, for the
    rows of case_b and case_c together."""
    obs = jax.tree.map(lambda *x: np.concatenate(x), *(observation(name) for name in ROWS))
    generated = sequence(obs.state.shape[0], S)

    def run():
        one = [maps.gradcam_for_action_token(tiny_fast_model, obs, generated, k) for k in STEPS]
        return one, maps.maps_for_chunk(tiny_fast_model, obs, generated, CHUNK)

    cut = run()
    with pytest.MonkeyPatch.context() as m:
        full_length(m)
        full = run()
    return cut, full


@pytest.mark.slow
@pytest.mark.parametrize("name", ["case_b", "case_c"])
def test_cut_replay_gives_the_full_length_maps_and_scores(cut_and_full, name: str):
    """One token at steps in four buckets (case_b: a masked camera, whose rows softmax over the full cache; case_c:
    two rows with different prompt lengths), and a chunk cut at 32 tokens, against the full 100-token replay."""
    assert [maps.replay_length(k, S) for k in STEPS] == [16, 16, 32, 64, S]
    assert maps.replay_length(max(CHUNK), S) == 32
    (cut_one, cut_chunk), (full_one, full_chunk) = cut_and_full
    rows = ROWS[name]
    for k, cut, full in zip(STEPS, cut_one, full_one, strict=True):
        assert_same_result(rows_of(cut, rows), rows_of(full, rows), f"{name} step {k}")
    assert_same_result(rows_of(cut_chunk, rows), rows_of(full_chunk, rows), f"{name} chunk")


def test_masked_rows_see_the_decode_length(tiny_fast_model: Pi0FAST):
    """Why the cut replay keeps the full cache size for fully masked rows (`hidden_steps`): case_b's masked camera
    reaches decoding through upstream's window, and its rows average over every slot of the cache. Cut to 16
    tokens of a 100-step decode, the replay equals the full one's first 16 rows only when it knows S."""
    obs = observation("case_b")
    model = tiny_fast_model
    obs = preprocess_observation(obs, model.config.image_resolution)
    fed = jnp.asarray(sequence(1, S))
    E = embed_images(model.params, obs, model.config)
    replay = jax.jit(replay_prelogits, static_argnames=("cfg", "decode_len"))
    full = np.asarray(replay(model.params, E, obs, fed, model.config, decode_len=S))[:, :16]
    cut = np.asarray(replay(model.params, E, obs, fed[:, :16], model.config, decode_len=S))
    short = np.asarray(replay(model.params, E, obs, fed[:, :16], model.config, decode_len=16))
    assert_close_rel(cut, full, LOGIT_REL, "cut replay")  # measured 1.9e-6
    np.testing.assert_array_equal(short[:, 0], cut[:, 0])  # step 0 comes from the prefill's valid last row
    assert np.abs(short[:, 1:] - full[:, 1:]).max() > 100 * LOGIT_REL * np.abs(full).max()  # measured 9e-3


@pytest.mark.slow
def test_compilations_over_all_steps_of_a_request(tiny_fast_model: Pi0FAST):
    """Every step of a 48-step decode, one token at a time, compiles one program per replay bucket (16, 32, 48);
    chunks of every size compile one per bucket too (their vocabulary rows are bucketed with the replay)."""
    obs = observation("case_a")
    generated = sequence(1, 48, seed=1)
    before = maps._token_gradient_maps._cache_size()
    for k in range(48):
        maps.gradcam_for_action_token(tiny_fast_model, obs, generated, k)
    assert maps._token_gradient_maps._cache_size() - before == 3
    before = maps._chunk_gradient_maps._cache_size()
    for k in (0, 7, 15, 16, 31, 32, 47):
        maps.maps_for_chunk(tiny_fast_model, obs, generated, list(range(k + 1)))
    assert maps._chunk_gradient_maps._cache_size() - before == 3
