"""`Policy` end to end against upstream's tiny DROID reference, plus a user-declared robot at a non-224 resolution."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from openpi_cam.checkpoints import model_spec
from openpi_cam.errors import InvalidRequest
from openpi_cam.model.checkpoint import save_params
from openpi_cam.model.config import GemmaConfig, SiglipConfig, param_shapes
from openpi_cam.nested import unflatten_dict as unflatten
from openpi_cam.normalize import NormStats, save_norm_stats
from openpi_cam.policies import (
    GenericInputs,
    GenericOutputs,
    PolicyConfig,
    create_policy,
    droid,
    register_config,
)
from openpi_cam.policies.config import PI0_FAST_DROID, get_config

PROMPT = "Pick up the red_block and put it in the bowl"
EOS_STEP = 186  # README: the random model emits EOS (id 1) at step 186


@pytest.fixture(scope="module")
def case(golden_dir: Path) -> dict[str, np.ndarray]:
    with np.load(golden_dir / "tiny_policy_droid" / "droid_case.npz") as f:
        return dict(f)


def raw_obs(case: dict[str, np.ndarray]) -> dict:
    return {
        droid.EXTERIOR_IMAGE_KEY: case["raw/exterior_image_1_left"],
        droid.WRIST_IMAGE_KEY: case["raw/wrist_image_left"],
        droid.JOINT_POSITION_KEY: case["raw/joint_position"],
        droid.GRIPPER_POSITION_KEY: case["raw/gripper_position"],
        "prompt": PROMPT,
    }


@pytest.fixture(scope="module")
def traced(tiny_droid_policy, case):
    obs = raw_obs(case)
    before = {k: np.array(v, copy=True) for k, v in obs.items()}
    response, trace = tiny_droid_policy.infer_traced(obs)
    for k, v in before.items():  # the client's arrays must not be modified
        np.testing.assert_array_equal(obs[k], v)
    return response, trace


def test_float32_policy_reproduces_upstream_tokens_and_actions(traced, case):
    response, trace = traced
    assert trace.output.dtype == np.int32 and trace.output.shape == (256,)
    np.testing.assert_array_equal(trace.output, case["generated_tokens"])
    assert trace.output[EOS_STEP] == 1 and not trace.output[EOS_STEP + 1 :].any()
    # The generation has no "Action: ", so the actions are the quantile mid-points computed in float64: rounding only.
    assert set(response) == {"actions", "policy_timing"}  # DroidOutputs keeps only "actions", as upstream
    assert response["actions"].shape == (10, 8)
    np.testing.assert_allclose(response["actions"], case["policy_output/actions"], rtol=0, atol=1e-12)
    assert response["policy_timing"]["infer_ms"] > 0
    assert trace.malformed_reason == "no_action_prefix"


def test_trace_holds_the_exact_model_inputs(traced, case):
    _, trace = traced
    obs = trace.observation
    assert trace.camera_names == ("base_0_rgb", "base_1_rgb", "wrist_0_rgb")
    for cam in trace.camera_names:
        # Upstream converts after batching, i.e. on jax arrays; XLA's float32 division can differ from numpy's by
        # one ulp, so the reference is the same expression evaluated by jax.
        expected = np.asarray(jnp.asarray(case[f"model_input/image_{cam}"]).astype(np.float32) / 255.0 * 2.0 - 1.0)
        assert obs.images[cam].shape == (1, 224, 224, 3)
        np.testing.assert_array_equal(np.asarray(obs.images[cam][0]), expected)
        assert bool(obs.image_masks[cam][0])
    for key in ("tokenized_prompt", "tokenized_prompt_mask", "token_ar_mask", "token_loss_mask"):
        np.testing.assert_array_equal(np.asarray(getattr(obs, key)[0]), case[f"model_input/{key}"], err_msg=key)
    # State becomes float32 in the model (jax without x64), as upstream.
    np.testing.assert_array_equal(np.asarray(obs.state[0]), case["model_input/state"].astype(np.float32))

    assert trace.camera_sources == dict(droid.CAMERA_SOURCES["pi0_fast"])
    np.testing.assert_array_equal(trace.raw_images["base_0_rgb"], case["raw/exterior_image_1_left"])
    np.testing.assert_array_equal(trace.raw_images["wrist_0_rgb"], case["raw/wrist_image_left"])
    assert trace.raw_images["base_1_rgb"] is None
    geo = trace.geometry["base_0_rgb"]
    assert (geo.orig_h, geo.orig_w, geo.resized_h, geo.resized_w, geo.pad_top, geo.pad_left) == (
        180,
        320,
        126,
        224,
        49,
        0,
    )
    assert trace.prompt == PROMPT


def test_stats_metadata_and_accessors(tiny_droid_policy, traced):
    stats = tiny_droid_policy.stats()
    assert stats["requests"] >= 1 and stats["malformed"]["no_action_prefix"] == stats["requests"]
    assert tiny_droid_policy.metadata == {}  # pi0_fast_droid has no policy_metadata upstream
    assert tiny_droid_policy.image_resolution == (224, 224)
    steps = tiny_droid_policy.explainer.tokenizer.action_token_steps(traced[1].output)
    assert steps.size == 0  # nothing to explain in a generation without "Action: "


def test_bad_requests_raise_invalid_request(tiny_droid_policy, case):
    with pytest.raises(InvalidRequest, match="must be a dict"):
        tiny_droid_policy.infer([1, 2])
    obs = raw_obs(case)
    del obs[droid.EXTERIOR_IMAGE_KEY]
    with pytest.raises(InvalidRequest, match=droid.EXTERIOR_IMAGE_KEY):
        tiny_droid_policy.infer(obs)
    with pytest.raises(InvalidRequest, match="actions"):
        tiny_droid_policy.infer({**raw_obs(case), "actions": np.zeros((10, 8))})


def test_stop_at_action_end_only_shortens_decoding(tiny_policy_files, case):
    """Upstream's generation (README: EOS at step 186) cut right after its first `|` token, nothing else changed."""
    policy = create_policy(
        "pi0_fast_droid", tiny_policy_files.checkpoint, **tiny_policy_files.create_kwargs(), stop_at_action_end=True
    )
    stop_ids = set(policy.explainer.tokenizer.end_of_action_token_ids)
    full = case["generated_tokens"]
    hits = [i for i, t in enumerate(full[:EOS_STEP]) if int(t) in stop_ids]
    assert hits, "the golden generation contains a '|' token (README's decoded text)"
    _, trace = policy.infer_traced(raw_obs(case))
    stop = hits[0]
    np.testing.assert_array_equal(trace.output[: stop + 1], full[: stop + 1])
    assert not trace.output[stop + 1 :].any()


def test_bfloat16_policy_against_upstream_create_trained_policy(tiny_policy_files, case):
    """`dtype="bfloat16"` restores bf16 weights and computes in bf16. Measured (README): the first 7 of 256 tokens
    equal upstream's `create_trained_policy` run, which restores bf16 params too, then they diverge (bf16 rounding
    differs between XLA builds). Upstream's float32 tokens share those first 7, so agreeing there does not show the
    flag took effect: the bf16 generation must also differ from the float32 one."""
    kwargs = {**tiny_policy_files.create_kwargs(), "dtype": "bfloat16"}
    policy = create_policy("pi0_fast_droid", tiny_policy_files.checkpoint, **kwargs)
    assert {str(v.dtype) for v in jax.tree.leaves(policy.model.params)} == {"bfloat16"}
    response, trace = policy.infer_traced(raw_obs(case))
    # The computation runs in bf16 too (upstream's create_trained_policy with a bf16 config), not only the weights:
    # the image tokens the LLM sees come out of SigLIP in bf16.
    assert policy.model.embed_images(trace.observation).dtype == jnp.bfloat16
    upstream_bf16 = case["create_trained_policy_bf16/generated_tokens"]
    float32 = case["generated_tokens"]
    assert int(np.cumprod(float32 == upstream_bf16).sum()) == 7
    # Same model inputs as in float32 (prompt and state tokens), so a difference comes from the computation.
    np.testing.assert_array_equal(
        np.asarray(trace.observation.tokenized_prompt[0]), case["model_input/tokenized_prompt"]
    )
    agree = int(np.cumprod(trace.output == upstream_bf16).sum())
    print(f"bf16: first {agree} of 256 generated tokens equal upstream's create_trained_policy")
    assert agree >= 7
    assert not np.array_equal(trace.output, float32), "bfloat16 decoded upstream's float32 tokens: dtype ignored?"
    # Neither generation holds "Action: " (upstream's bf16 actions are the mid-points too), so the outputs agree.
    assert trace.malformed_reason == "no_action_prefix"
    np.testing.assert_allclose(response["actions"], case["create_trained_policy_bf16/actions"], rtol=0, atol=1e-12)


def test_create_policy_reports_missing_files(tmp_path, tiny_policy_files):
    with pytest.raises(FileNotFoundError, match=str(tmp_path / "params")):
        create_policy("pi0_fast_droid", tmp_path, **tiny_policy_files.create_kwargs())
    (tmp_path / "params").mkdir()
    with pytest.raises(FileNotFoundError, match="_METADATA is missing"):
        create_policy("pi0_fast_droid", tmp_path, **tiny_policy_files.create_kwargs())
    (tmp_path / "params").rmdir()
    (tmp_path / "params").symlink_to(tiny_policy_files.checkpoint / "params")
    with pytest.raises(FileNotFoundError, match=str(tmp_path / "assets" / "droid" / "norm_stats.json")):
        create_policy("pi0_fast_droid", tmp_path, **tiny_policy_files.create_kwargs())
    with pytest.raises(KeyError, match="pi0_fast_droid"):
        get_config("no_such_config")


# ------------------------------------------------------------------------------------ user-declared robot at 28x28


def _tiny_checkpoint(root: Path, image_size: int, vocab: int) -> None:
    gemma = GemmaConfig(width=32, depth=1, mlp_dim=64, num_heads=2, num_kv_heads=1, head_dim=16, vocab_size=vocab)
    siglip = SiglipConfig(width=16, depth=1, mlp_dim=32, num_heads=2, patch_size=14, image_size=image_size, out_dim=32)
    rng = np.random.default_rng(0)
    flat = {k: (0.05 * rng.standard_normal(s)).astype(np.float32) for k, s in param_shapes(gemma, siglip).items()}
    save_params(root / "params", unflatten(flat))
    stats = NormStats(mean=np.zeros(3), std=np.ones(3), q01=-np.ones(3), q99=np.ones(3))
    save_norm_stats(root / "assets" / "toy_reach", {"state": stats, "actions": dataclasses.replace(stats)})


def test_custom_config_takes_resolution_from_the_model(tmp_path, tiny_policy_files):
    _tiny_checkpoint(tmp_path, image_size=28, vocab=1184)  # vocab of the tokenizer stand-in
    config = register_config(
        PolicyConfig(
            name="test_toy_reach",
            inputs=(GenericInputs(cameras={"top": "obs/top", "spare": None}, state_key="obs/state", state_dim=3),),
            outputs=(GenericOutputs(action_dim=2),),
            asset_id="toy_reach",
            action_dim=3,
            action_horizon=4,
            max_token_len=48,
            default_prompt="reach the dot",
            policy_metadata={"robot": "toy"},
        )
    )
    assert config.camera_sources == {"top": "obs/top", "spare": None}
    policy = create_policy(
        "test_toy_reach", tmp_path, **tiny_policy_files.create_kwargs(), max_decoding_steps=6, rng=jax.random.key(3)
    )
    assert policy.image_resolution == (28, 28) and policy.metadata == {"robot": "toy"}
    image = np.zeros((30, 60, 3), np.uint8)
    image[:, 45:] = 255
    response, trace = policy.infer_traced({"obs/top": image, "obs/state": np.array([0.1, -0.2, 0.3])})
    assert trace.camera_names == ("spare", "top")  # jax pytree order (sorted), as upstream's batching gives
    assert trace.observation.images["top"].shape == (1, 28, 28, 3)
    assert trace.output.shape == (6,)
    assert trace.prompt == "reach the dot"
    geo = trace.geometry["top"]
    assert (geo.resized_h, geo.resized_w, geo.pad_top) == (14, 28, 7)
    # The bright right quarter of the client image lands in the right quarter of the model image's content rows.
    model_top = np.asarray(trace.observation.images["top"][0])
    assert model_top[geo.pad_top + 7, 27, 0] == 1.0 and model_top[geo.pad_top + 7, 0, 0] == -1.0
    assert model_top[0, 27, 0] == -1.0  # padding row (uint8 0 -> -1)
    assert trace.raw_images["spare"] is None
    np.testing.assert_array_equal(trace.raw_images["top"], image)
    assert response["actions"].shape == (4, 2)
    with pytest.raises(ValueError, match="already registered"):
        register_config(dataclasses.replace(config, action_horizon=5))
    assert PI0_FAST_DROID.camera_sources["base_1_rgb"] is None


def test_stop_at_action_end_keeps_well_formed_actions_and_saves_steps(demo_policy, demo_observations):
    """On the bundled demo model, whose generations are well formed and whose actions differ between these
    observations (asserted by the fixture), stopping at `|` returns each observation's own actions."""
    stopping = model_spec.create_demo_policy(stop_at_action_end=True)
    saved = []
    for obs in demo_observations:
        full, full_trace = demo_policy.infer_traced(obs)
        short, short_trace = stopping.infer_traced(obs)
        assert full_trace.malformed_reason is None
        np.testing.assert_array_equal(short["actions"], full["actions"])
        saved.append(int(np.count_nonzero(full_trace.output) - np.count_nonzero(short_trace.output)))
    assert min(saved) >= 1  # at least the EOS after '|' is never decoded
