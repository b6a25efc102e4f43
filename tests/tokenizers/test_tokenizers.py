"""Tokenizers against upstream's goldens (tiny_policy_droid) and against their own defining properties."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest
from paths import GOLDEN_DIR

from openpi_cam.errors import InvalidRequest
from openpi_cam.tokenizers.fast import (
    DECODE_ERROR,
    DECODE_SHAPE_MISMATCH,
    FastActionTokenizer,
    dct_coefficients,
    resolve_fast_tokenizer_dir,
)
from openpi_cam.tokenizers.paligemma import load_paligemma_tokenizer, resolve_paligemma_tokenizer_path
from openpi_cam.tokenizers.pi0_fast import NO_ACTION_PREFIX, Pi0FastTokenizer, discretize_state

GOLDEN = GOLDEN_DIR / "tiny_policy_droid"
pytestmark = pytest.mark.skipif(not GOLDEN.is_dir(), reason=f"golden data not found at {GOLDEN}")

HORIZON, ACTION_DIM, MAX_LEN = 10, 8, 250  # the golden's Pi0FASTConfig
FAST_SCALE = 10  # golden processor_config.json


@pytest.fixture(scope="module")
def case() -> dict[str, np.ndarray]:
    with np.load(GOLDEN / "droid_case.npz") as data:
        return dict(data)


@pytest.fixture(scope="module")
def malformed() -> dict[str, np.ndarray]:
    with np.load(GOLDEN / "malformed_cases.npz") as data:
        return dict(data)


@pytest.fixture(scope="module")
def fast() -> FastActionTokenizer:
    return FastActionTokenizer.load(GOLDEN / "fast_tokenizer")


@pytest.fixture(scope="module")
def tokenizer(fast: FastActionTokenizer) -> Pi0FastTokenizer:
    return Pi0FastTokenizer(load_paligemma_tokenizer(GOLDEN / "paligemma_tokenizer_tiny.model"), fast, MAX_LEN)


def random_walk_chunks(n: int, horizon: int, dim: int, seed: int) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [np.clip(np.cumsum(rng.normal(0, 0.15, (horizon, dim)), axis=0), -1, 1) for _ in range(n)]


def quantisation_bound(horizon: int, scale: float) -> float:
    # Each DCT coefficient is rounded by at most 0.5/scale; the orthonormal IDCT keeps each column's L2 error.
    return 0.5 / scale * np.sqrt(horizon)


# --- PaliGemma SentencePiece location -----------------------------------------------------------------------------


def test_paligemma_path_explicit_and_missing(tmp_path: Path) -> None:
    model = GOLDEN / "paligemma_tokenizer_tiny.model"
    assert resolve_paligemma_tokenizer_path(model) == model.resolve()
    with pytest.raises(FileNotFoundError, match=r"nowhere\.model"):
        resolve_paligemma_tokenizer_path(tmp_path / "nowhere.model")


def test_paligemma_path_from_openpi_data_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OPENPI_DATA_HOME", str(tmp_path))
    expected = tmp_path / "big_vision" / "paligemma_tokenizer.model"
    with pytest.raises(FileNotFoundError) as error:
        resolve_paligemma_tokenizer_path(None)
    assert str(expected) in str(error.value) and "OPENPI_DATA_HOME" in str(error.value)
    expected.parent.mkdir()
    shutil.copy(GOLDEN / "paligemma_tokenizer_tiny.model", expected)
    assert resolve_paligemma_tokenizer_path(None) == expected.resolve()
    assert load_paligemma_tokenizer(None).vocab_size() == 1184  # golden README: 800 trained + 256 loc + 128 seg


# --- FAST --------------------------------------------------------------------------------------------------------


def test_fast_encode_matches_golden(fast: FastActionTokenizer, case: dict[str, np.ndarray]) -> None:
    assert fast.encode(case["hand/normalized_action_chunk"]) == case["hand/fast_token_ids"].tolist()


def test_fast_decode_round_trip(fast: FastActionTokenizer, case: dict[str, np.ndarray]) -> None:
    chunk = case["hand/normalized_action_chunk"]
    decoded, reason = fast.decode_checked(fast.encode(chunk), time_horizon=HORIZON, action_dim=ACTION_DIM)
    assert reason is None and decoded.shape == (HORIZON, ACTION_DIM)
    assert np.all(np.linalg.norm(decoded - chunk, axis=0) <= quantisation_bound(HORIZON, FAST_SCALE) + 1e-12)
    # Decoding is exact integer arithmetic then scipy's IDCT, as upstream: only float64 rounding may differ.
    np.testing.assert_allclose(decoded, case["hand/after_extract_actions"], rtol=0, atol=1e-12)


def test_fast_decode_reports_malformed_ids(fast: FastActionTokenizer, case: dict[str, np.ndarray]) -> None:
    ids = case["hand/fast_token_ids"].tolist()
    zeros = np.zeros((HORIZON, ACTION_DIM))
    actions, reason = fast.decode_checked(ids[:-3], time_horizon=HORIZON, action_dim=ACTION_DIM)
    assert reason == DECODE_SHAPE_MISMATCH
    np.testing.assert_array_equal(actions, zeros)
    actions, reason = fast.decode_checked([*ids[:5], -4], time_horizon=HORIZON, action_dim=ACTION_DIM)
    assert reason == DECODE_ERROR
    np.testing.assert_array_equal(actions, zeros)
    # Same ids, another shape with the same element count: the shape must be checked, not just the count.
    _, reason = fast.decode_checked(ids, time_horizon=HORIZON * 2, action_dim=ACTION_DIM // 2)
    assert reason is None
    np.testing.assert_array_equal(fast.decode(ids, time_horizon=HORIZON + 1, action_dim=ACTION_DIM), np.zeros((11, 8)))


def test_fast_rejects_bad_chunks(fast: FastActionTokenizer) -> None:
    with pytest.raises(ValueError, match="shape"):
        fast.encode(np.zeros((HORIZON,)))
    with pytest.raises(ValueError, match="NaN"):
        fast.encode(np.full((HORIZON, ACTION_DIM), np.nan))


def test_fast_load_names_missing_files(tmp_path: Path) -> None:
    (tmp_path / "tokenizer.json").write_text("{}")
    with pytest.raises(FileNotFoundError, match=r"processor_config\.json"):
        FastActionTokenizer.load(tmp_path)


def test_fast_fit_save_load_round_trip(tmp_path: Path) -> None:
    horizon, dim, scale = 8, 4, 10
    chunks = random_walk_chunks(300, horizon, dim, seed=1)
    fitted = FastActionTokenizer.fit(chunks, scale=scale, vocab_size=200, action_dim=dim, time_horizon=horizon)
    quantised = np.concatenate([np.around(dct_coefficients(chunk) * scale).ravel() for chunk in chunks])
    assert fitted.min_token == int(quantised.min())
    assert fitted.bpe_vocab_size <= 200

    loaded = FastActionTokenizer.load(fitted.save(tmp_path / "fast"))
    assert loaded.config == fitted.config
    held_out = random_walk_chunks(20, horizon, dim, seed=2)
    token_counts = []
    for chunk in held_out:
        ids = fitted.encode(chunk)
        assert loaded.encode(chunk) == ids
        decoded, reason = loaded.decode_checked(ids, time_horizon=horizon, action_dim=dim)
        assert reason is None
        assert np.all(np.linalg.norm(decoded - chunk, axis=0) <= quantisation_bound(horizon, scale) + 1e-12)
        token_counts.append(len(ids))
    assert np.mean(token_counts) < horizon * dim  # BPE merges must compress below one token per coefficient


def test_fast_fit_builds_the_same_bpe_pipeline_as_the_reference(tmp_path: Path) -> None:
    fitted = FastActionTokenizer.fit(random_walk_chunks(50, 10, 8, seed=3), vocab_size=256)
    ours = json.loads((fitted.save(tmp_path) / "tokenizer.json").read_text())
    reference = json.loads((GOLDEN / "fast_tokenizer" / "tokenizer.json").read_text())
    for key in ("normalizer", "pre_tokenizer", "post_processor", "decoder", "added_tokens"):
        assert ours[key] == reference[key], key
    model_settings = {k: v for k, v in reference["model"].items() if k not in ("vocab", "merges")}
    assert {k: ours["model"][k] for k in model_settings} == model_settings


def test_fast_fit_rejects_too_small_vocab() -> None:
    with pytest.raises(ValueError, match="vocab_size"):
        FastActionTokenizer.fit(random_walk_chunks(10, 10, 8, seed=4), vocab_size=5)


def test_resolve_fast_dir_from_hf_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("HF_HUB_CACHE", str(tmp_path))
    with pytest.raises(FileNotFoundError, match="physical-intelligence/fast"):
        resolve_fast_tokenizer_dir(None)
    repo = tmp_path / "models--physical-intelligence--fast"
    snapshot = repo / "snapshots" / "abc123"
    shutil.copytree(GOLDEN / "fast_tokenizer", snapshot)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text("abc123\n")
    assert resolve_fast_tokenizer_dir(None) == snapshot.resolve()


# --- pi0-FAST prompt tokenizer -----------------------------------------------------------------------------------


def test_discretize_state_matches_bin_formula() -> None:
    values = np.array([-1.5, -1.0, -0.999, 0.0, 0.5, 1 - 1e-9, 1.0, 2.0])
    inside = np.clip(np.floor((values + 1) / 2 * 256), 0, 255).astype(int)
    expected = np.where(values < -1, -1, inside)  # below the first edge upstream yields -1; at/above 1, bin 255
    np.testing.assert_array_equal(discretize_state(values), expected)


def test_tokenize_inference_matches_golden(tokenizer: Pi0FastTokenizer, case: dict[str, np.ndarray]) -> None:
    prompt = json.loads((GOLDEN / "case.json").read_text())["prompt"]
    got = tokenizer.tokenize(prompt, case["model_input/state"])
    names = ("tokenized_prompt", "tokenized_prompt_mask", "token_ar_mask", "token_loss_mask")
    for name, array in zip(names, got, strict=True):
        expected = case[f"model_input/{name}"]
        assert array.dtype == expected.dtype, name
        np.testing.assert_array_equal(array, expected, err_msg=name)


def test_tokenize_training_matches_golden(tokenizer: Pi0FastTokenizer, case: dict[str, np.ndarray]) -> None:
    got = tokenizer.tokenize(
        "pick up the red block", case["hand/state_normalized"], case["hand/normalized_action_chunk"]
    )
    for name, array in zip(("tokenized", "token_mask", "ar_mask", "loss_mask"), got, strict=True):
        np.testing.assert_array_equal(array, case[f"hand/training_{name}"], err_msg=name)


def test_tokenize_truncates_with_warning(
    tokenizer: Pi0FastTokenizer, case: dict[str, np.ndarray], caplog: pytest.LogCaptureFixture
) -> None:
    short = Pi0FastTokenizer(tokenizer.paligemma, tokenizer.fast, max_len=12)
    full, *_ = tokenizer.tokenize("pick up the block", case["hand/state_normalized"])
    with caplog.at_level(logging.WARNING):
        tokens, mask, ar, loss = short.tokenize("pick up the block", case["hand/state_normalized"])
    assert "exceeds max length (12), truncating" in caplog.text
    np.testing.assert_array_equal(tokens, full[:12])
    assert mask.all() and not ar.any() and not loss.any()


def test_tokenize_rejects_bad_client_input(tokenizer: Pi0FastTokenizer) -> None:
    with pytest.raises(InvalidRequest, match="prompt"):
        tokenizer.tokenize(b"pick", np.zeros(8))  # type: ignore[arg-type]
    with pytest.raises(InvalidRequest, match="1-D"):
        tokenizer.tokenize("pick", np.zeros((2, 4)))
    with pytest.raises(InvalidRequest, match="NaN"):
        tokenizer.tokenize("pick", np.array([0.0, np.nan]))


def test_extract_actions_matches_golden(tokenizer: Pi0FastTokenizer, case: dict[str, np.ndarray]) -> None:
    actions, reason = tokenizer.extract_actions_checked(case["hand/generated_tokens"], HORIZON, ACTION_DIM)
    assert reason is None
    # Measured max abs difference 0.0; 1e-12 leaves room for float64 rounding in a different scipy build.
    np.testing.assert_allclose(actions, case["hand/after_extract_actions"], rtol=0, atol=1e-12)
    # The random model's generation has no "Action: ": upstream returns zeros.
    actions, reason = tokenizer.extract_actions_checked(case["generated_tokens"], HORIZON, ACTION_DIM)
    assert reason == NO_ACTION_PREFIX and not actions.any()


@pytest.mark.parametrize(
    ("name", "reason"),
    [("no_action_prefix", NO_ACTION_PREFIX), ("truncated", DECODE_SHAPE_MISMATCH), ("edge_no_bar", None)],
)
def test_extract_actions_malformed_cases(
    tokenizer: Pi0FastTokenizer, malformed: dict[str, np.ndarray], name: str, reason: str | None
) -> None:
    tokens = malformed[f"{name}/generated_tokens"].astype(np.float32)  # the model's output dtype upstream
    expected = malformed[f"{name}/after_extract_actions"]
    actions, got_reason = tokenizer.extract_actions_checked(tokens, HORIZON, ACTION_DIM)
    assert got_reason == reason
    assert actions.dtype == expected.dtype  # upstream: float32 zeros without "Action: ", float64 from the IDCT
    np.testing.assert_allclose(actions, expected, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(tokenizer.extract_actions(tokens, HORIZON, ACTION_DIM), actions)


def test_action_token_steps_on_hand_generation(tokenizer: Pi0FastTokenizer, case: dict[str, np.ndarray]) -> None:
    generated = case["hand/generated_tokens"]
    steps = tokenizer.action_token_steps(generated)
    assert len(steps) == len(case["hand/fast_token_ids"]) == 30
    np.testing.assert_array_equal(tokenizer.paligemma_to_fast(generated[steps]), case["hand/fast_token_ids"])
    prefix_len = len(tokenizer.paligemma.encode("Action: "))
    np.testing.assert_array_equal(steps, np.arange(prefix_len, prefix_len + 30))
    assert generated[steps[-1] + 1] in tokenizer.end_of_action_token_ids


def test_action_token_steps_skip_chatter_and_whitespace(
    tokenizer: Pi0FastTokenizer, case: dict[str, np.ndarray]
) -> None:
    sp = tokenizer.paligemma
    action_ids = case["hand/paligemma_action_token_ids"].tolist()
    # Text before the prefix, a stray space after it, and a second "|" segment that upstream ignores.
    tokens = np.array(
        sp.encode("ok go ")
        + sp.encode("Action: ")
        + sp.encode(" ")
        + action_ids
        + sp.encode("| ")
        + action_ids[:3]
        + [sp.eos_id()]
        + [0] * 5
    )
    steps = tokenizer.action_token_steps(tokens)
    start = len(sp.encode("ok go ")) + len(sp.encode("Action: ")) + len(sp.encode(" "))
    np.testing.assert_array_equal(steps, np.arange(start, start + len(action_ids)))
    actions, reason = tokenizer.extract_actions_checked(tokens, HORIZON, ACTION_DIM)
    assert reason is None
    np.testing.assert_allclose(actions, case["hand/after_extract_actions"], rtol=0, atol=1e-12)
    assert len(tokenizer.action_token_steps(case["generated_tokens"])) == 0


def test_end_of_action_token_ids_are_exactly_the_bar_tokens(tokenizer: Pi0FastTokenizer) -> None:
    sp = tokenizer.paligemma
    ids = set(tokenizer.end_of_action_token_ids)
    assert set(sp.encode("|")) <= ids
    for token_id in range(sp.vocab_size()):
        if sp.is_control(token_id):
            assert token_id not in ids
        else:
            assert ("|" in sp.decode([token_id])) == (token_id in ids), sp.id_to_piece(token_id)


def test_from_files_loads_both_tokenizers(tokenizer: Pi0FastTokenizer, case: dict[str, np.ndarray]) -> None:
    loaded = Pi0FastTokenizer.from_files(
        GOLDEN / "paligemma_tokenizer_tiny.model", GOLDEN / "fast_tokenizer", max_len=MAX_LEN
    )
    got = loaded.tokenize("pick up the red block", case["hand/state_normalized"], case["hand/normalized_action_chunk"])
    np.testing.assert_array_equal(got[0], case["hand/training_tokenized"])
    with pytest.raises(FileNotFoundError, match="given directory"):
        Pi0FastTokenizer.from_files(GOLDEN / "paligemma_tokenizer_tiny.model", GOLDEN, max_len=MAX_LEN)
