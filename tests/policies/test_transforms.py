"""Transforms, robot pipelines and letterbox geometry against upstream's tiny DROID reference (`tiny_policy_droid`)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from openpi_cam.errors import InvalidRequest
from openpi_cam.image_tools import resize_with_pad, resize_with_pad_pil
from openpi_cam.letterbox import letterbox_geometry
from openpi_cam.normalize import (
    NormStats,
    compute_norm_stats,
    load_checkpoint_norm_stats,
    load_norm_stats,
    norm_stats_path,
    save_norm_stats,
)
from openpi_cam.policies import aloha, droid, libero
from openpi_cam.policies.config import PI0_FAST_ALOHA, PI0_FAST_DROID, PI0_FAST_LIBERO
from openpi_cam.policies.policy import build_transforms
from openpi_cam.policies.robot import GenericInputs
from openpi_cam.tokenizers.pi0_fast import Pi0FastTokenizer
from openpi_cam.transforms import (
    AbsoluteActions,
    DeltaActions,
    ExtractFASTActions,
    Normalize,
    ResizeImages,
    TokenizeFASTInputs,
    Unnormalize,
    compose,
    make_bool_mask,
)

PROMPT = "Pick up the red_block and put it in the bowl"  # droid_case's raw prompt (README / case.json)


@pytest.fixture(scope="module")
def droid_dir(golden_dir: Path) -> Path:
    return golden_dir / "tiny_policy_droid"


@pytest.fixture(scope="module")
def case(droid_dir: Path) -> dict[str, np.ndarray]:
    with np.load(droid_dir / "droid_case.npz") as f:
        return dict(f)


@pytest.fixture(scope="module")
def tokenizer(tiny_policy_files) -> Pi0FastTokenizer:
    return Pi0FastTokenizer.from_files(
        tiny_policy_files.paligemma_tokenizer, tiny_policy_files.fast_tokenizer, max_len=PI0_FAST_DROID.max_token_len
    )


@pytest.fixture(scope="module")
def stats(droid_dir: Path) -> dict[str, NormStats]:
    return load_checkpoint_norm_stats(droid_dir / "checkpoint", "droid")


@pytest.fixture(scope="module")
def chains(stats, tokenizer):
    """(input transforms, the FAST decoder, output transforms) of `pi0_fast_droid`, as `create_policy` builds them."""
    inputs, outputs = build_transforms(PI0_FAST_DROID, stats, (TokenizeFASTInputs(tokenizer),), (224, 224))
    return inputs, ExtractFASTActions(tokenizer, PI0_FAST_DROID.action_horizon, PI0_FAST_DROID.action_dim), outputs


def raw_obs(case: dict[str, np.ndarray]) -> dict:
    return {
        droid.EXTERIOR_IMAGE_KEY: case["raw/exterior_image_1_left"].copy(),
        droid.WRIST_IMAGE_KEY: case["raw/wrist_image_left"].copy(),
        droid.JOINT_POSITION_KEY: case["raw/joint_position"].copy(),
        droid.GRIPPER_POSITION_KEY: case["raw/gripper_position"].copy(),
        "prompt": PROMPT,
    }


# ---------------------------------------------------------------------------------------------------- input chain


def test_droid_input_chain_reproduces_upstream_model_inputs_exactly(case, chains):
    inputs, _, _ = chains
    out = compose(inputs)(raw_obs(case))
    assert list(out["image"]) == ["base_0_rgb", "base_1_rgb", "wrist_0_rgb"]
    for cam in out["image"]:
        img = out["image"][cam]
        assert img.dtype == np.uint8 and img.shape == (224, 224, 3)
        np.testing.assert_array_equal(img, case[f"model_input/image_{cam}"], err_msg=cam)
        assert bool(out["image_mask"][cam]) == bool(case[f"model_input/image_mask_{cam}"])
    # Quantile normalisation in float64 like upstream; exact up to float64 rounding of the same expression.
    assert out["state"].dtype == np.float64
    np.testing.assert_allclose(out["state"], case["model_input/state"], rtol=0, atol=1e-15)
    for key in ("tokenized_prompt", "tokenized_prompt_mask", "token_ar_mask", "token_loss_mask"):
        np.testing.assert_array_equal(out[key], case[f"model_input/{key}"], err_msg=key)
    assert "prompt" not in out


def test_input_chain_leaves_client_dict_alone_and_accepts_scalar_gripper(case, chains):
    inputs, _, _ = chains
    obs = raw_obs(case)
    obs[droid.GRIPPER_POSITION_KEY] = float(case["raw/gripper_position"][0])  # upstream accepts a scalar too
    out = compose(inputs)(dict(obs))
    np.testing.assert_array_equal(out["tokenized_prompt"], case["model_input/tokenized_prompt"])


def test_float_chw_images_are_converted_like_upstream(case, chains):
    # LeRobot-style float [3, H, W] in [0, 1] must become the uint8 HWC image (255 * x).astype(uint8) would give.
    inputs, _, _ = chains
    obs = raw_obs(case)
    hwc = case["raw/exterior_image_1_left"]
    obs[droid.EXTERIOR_IMAGE_KEY] = (hwc.astype(np.float32) / 255.0).transpose(2, 0, 1)
    expected = (255 * (hwc.astype(np.float32) / 255.0)).astype(np.uint8)
    got = droid.DroidInputs()(dict(obs))["image"]["base_0_rgb"]
    np.testing.assert_array_equal(got, expected)
    assert compose(inputs)(obs)["image"]["base_0_rgb"].shape == (224, 224, 3)


def test_default_prompt_injected_only_when_missing(case, stats, tokenizer):
    tokenize = TokenizeFASTInputs(tokenizer)
    inputs, _ = build_transforms(PI0_FAST_DROID, stats, (tokenize,), (224, 224), default_prompt=PROMPT)
    obs = raw_obs(case)
    del obs["prompt"]
    np.testing.assert_array_equal(compose(inputs)(obs)["tokenized_prompt"], case["model_input/tokenized_prompt"])
    other = raw_obs(case)
    other["prompt"] = "wipe the table"
    assert not np.array_equal(compose(inputs)(other)["tokenized_prompt"], case["model_input/tokenized_prompt"])


@pytest.mark.parametrize(
    ("mutate", "needle"),
    [
        (lambda o: o.pop(droid.WRIST_IMAGE_KEY), droid.WRIST_IMAGE_KEY),
        (lambda o: o.pop("prompt"), "prompt"),
        (lambda o: o.update({droid.JOINT_POSITION_KEY: np.array([0.1, np.nan, 0, 0, 0, 0, 0])}), "NaN"),
        (lambda o: o.update({droid.JOINT_POSITION_KEY: np.zeros(6)}), "expected 7 values"),
        (lambda o: o.update({droid.GRIPPER_POSITION_KEY: np.array(["a"])}), droid.GRIPPER_POSITION_KEY),
        (lambda o: o.update({droid.EXTERIOR_IMAGE_KEY: np.zeros((180, 320), np.uint8)}), "3-D image"),
        (lambda o: o.update({droid.EXTERIOR_IMAGE_KEY: np.zeros((180, 320, 4), np.uint8)}), "3 colour channels"),
        (lambda o: o.update({droid.EXTERIOR_IMAGE_KEY: np.zeros((180, 320, 3), np.int64)}), "dtype int64"),
        (lambda o: o.update({droid.EXTERIOR_IMAGE_KEY: np.full((180, 320, 3), 200.0)}), "[0, 1]"),
        (lambda o: o.update({droid.EXTERIOR_IMAGE_KEY: np.zeros((1, 400, 3), np.uint8)}), "elongated"),
        (lambda o: o.update({"prompt": 5}), "prompt"),
    ],
)
def test_bad_client_input_is_rejected_with_a_message_naming_it(case, chains, mutate, needle):
    inputs, _, _ = chains
    obs = raw_obs(case)
    mutate(obs)
    with pytest.raises(InvalidRequest) as info:
        compose(inputs)(obs)
    assert needle in str(info.value)


# --------------------------------------------------------------------------------------------------- output chain


def test_hand_made_generation_through_output_chain(case, chains):
    _, extract, outputs = chains
    data = {"state": case["hand/state_normalized"].astype(np.float32), "actions": case["hand/generated_tokens"]}
    normalized = extract(dict(data))["actions"]
    # Decode path: sentencepiece + BPE + idct of the same integers as upstream; float64 rounding only.
    np.testing.assert_allclose(normalized, case["hand/after_extract_actions"], rtol=0, atol=1e-12)
    actions, reason = extract.extract(case["hand/generated_tokens"])
    assert reason is None
    out = compose(outputs)({"state": data["state"], "actions": actions})
    assert list(out) == ["actions"]  # DroidOutputs returns only the actions, as upstream
    np.testing.assert_allclose(out["actions"], case["hand/policy_output_actions"], rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    ("name", "expected_reason"), [("no_action_prefix", "no_action_prefix"), ("truncated", "*"), ("edge_no_bar", None)]
)
def test_malformed_generations(golden_dir, chains, name, expected_reason):
    _, extract, outputs = chains
    with np.load(golden_dir / "tiny_policy_droid" / "malformed_cases.npz") as f:
        cases = dict(f)
    tokens = cases[f"{name}/generated_tokens"].astype(np.float32)  # fed as float32 like a model output
    state = cases["state_normalized"].astype(np.float32)
    actions, reason = extract.extract(tokens)
    np.testing.assert_allclose(actions, cases[f"{name}/after_extract_actions"], rtol=0, atol=1e-12)
    if expected_reason == "*":
        assert isinstance(reason, str) and reason
    else:
        assert reason == expected_reason
    out = compose(outputs)({"state": state, "actions": actions})
    np.testing.assert_allclose(out["actions"], cases[f"{name}/policy_output_actions"], rtol=0, atol=1e-12)
    # The plain upstream-style transform gives the same numbers.
    plain = ExtractFASTActions(extract.tokenizer, extract.action_horizon, extract.action_dim)({"actions": tokens})
    np.testing.assert_array_equal(plain["actions"], actions)


# ---------------------------------------------------------------------------------------------- normalisation


def test_normalize_round_trip_and_strictness(stats):
    x = np.array([[0.3, -0.2, 0.0, 1.0, 0.5, -1.0, 0.2, 0.9]])
    for quantiles in (True, False):
        back = Unnormalize(stats, use_quantiles=quantiles)(
            {"state": Normalize(stats, use_quantiles=quantiles)({"state": x})["state"], "actions": x}
        )
        np.testing.assert_allclose(back["state"], x, rtol=0, atol=1e-12)
    # Unnormalize is strict (every key in the stats must be present); Normalize by default is not.
    with pytest.raises(ValueError, match="actions"):
        Unnormalize(stats, use_quantiles=True)({"state": x})
    assert "actions" not in Normalize(stats, use_quantiles=True)({"state": x})
    with pytest.raises(ValueError, match="actions"):
        Normalize(stats, use_quantiles=True, strict=True)({"state": x})
    with pytest.raises(InvalidRequest, match="'state' has 9 values"):
        Normalize(stats, use_quantiles=True)({"state": np.zeros(9)})
    with pytest.raises(ValueError, match="q01"):
        Normalize({"state": NormStats(mean=np.zeros(2), std=np.ones(2))}, use_quantiles=True)


def test_unnormalize_passes_dims_beyond_stats_through(stats):
    x = np.linspace(-1, 1, 10 * 12).reshape(10, 12)
    out = Unnormalize(stats, use_quantiles=True)({"state": np.zeros(8), "actions": x})["actions"]
    np.testing.assert_array_equal(out[:, 8:], x[:, 8:])
    q = stats["actions"]
    np.testing.assert_allclose(out[:, :8], (x[:, :8] + 1) / 2 * (q.q99 - q.q01 + 1e-6) + q.q01)


def test_norm_stats_save_load_round_trip_in_upstream_format(tmp_path, droid_dir, stats):
    path = save_norm_stats(tmp_path / "assets" / "droid", stats)
    assert path == norm_stats_path(tmp_path, "droid")
    # Same JSON layout as upstream's file: the same nesting and the same numbers (JSON floats round-trip exactly).
    written = json.loads(path.read_text())
    assert written == json.loads(norm_stats_path(droid_dir / "checkpoint", "droid").read_text())
    loaded = load_norm_stats(path)
    for key, value in stats.items():
        for field in ("mean", "std", "q01", "q99"):
            np.testing.assert_array_equal(getattr(loaded[key], field), getattr(value, field))
    with pytest.raises(FileNotFoundError, match=str(tmp_path / "assets" / "nope" / "norm_stats.json")):
        load_checkpoint_norm_stats(tmp_path, "nope")
    computed = compute_norm_stats(np.arange(300.0).reshape(100, 3))
    np.testing.assert_allclose(computed.q01, np.quantile(np.arange(0, 300, 3.0), 0.01) + np.arange(3))


# ---------------------------------------------------------------------------------------------- other robots


LIBERO_DIR = "tiny_policy_pi0_libero"


@pytest.mark.parametrize("name", ["case_1", "case_2"])
def test_libero_transforms_reproduce_upstreams_numbers(golden_dir: Path, name: str):
    """Upstream's `pi0_libero` policy on a raw LIBERO observation (tiny_policy_pi0_libero; a pi0 policy, so z-score
    stats and a pi0 prompt, but the same robot transforms): our LIBERO image mapping, resizing (case_2 sends 256x256),
    normalisation and output chain (Unnormalize -> AbsoluteActions -> LiberoOutputs) give its numbers."""
    root = golden_dir / LIBERO_DIR
    with np.load(root / f"{name}.npz") as f:
        case = dict(f)
    stats = load_checkpoint_norm_stats(root / "checkpoint", "physical-intelligence/libero")
    raw = {
        libero.IMAGE_KEY: case["raw/image"],
        libero.WRIST_IMAGE_KEY: case["raw/wrist_image"],
        libero.STATE_KEY: case["raw/state"],
        "prompt": json.loads((root / "case.json").read_text())["cases"][name]["prompt"],
    }
    robot = libero.LiberoInputs()(dict(raw))
    # Image mapping: image -> base_0_rgb, wrist_image -> left_wrist_0_rgb, a black right_wrist_0_rgb.
    assert list(robot["image"]) == ["base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb"]
    np.testing.assert_array_equal(robot["image"]["base_0_rgb"], case["raw/image"])
    np.testing.assert_array_equal(robot["image"]["left_wrist_0_rgb"], case["raw/wrist_image"])
    # The padding camera: pi0 masks it (the golden), pi0-FAST does not (README quirk 1), so ours stays True.
    assert not case["model_input/image_mask/right_wrist_0_rgb"] and bool(robot["image_mask"]["right_wrist_0_rgb"])
    for cam in ("base_0_rgb", "left_wrist_0_rgb"):
        assert bool(robot["image_mask"][cam]) == bool(case[f"model_input/image_mask/{cam}"])
    # Resize to 224 (case_1 passes through unchanged, case_2 shrinks 256 -> 224 without padding).
    resized = ResizeImages(224, 224)({"image": dict(robot["image"])})["image"]
    for cam in robot["image"]:
        np.testing.assert_array_equal(resized[cam], case[f"model_input/image/{cam}"], err_msg=cam)
    # z-score normalisation of the state (the golden pads it to the model's 32 dims afterwards).
    state = Normalize(stats, use_quantiles=False)({"state": robot["state"]})["state"]
    np.testing.assert_allclose(state, case["model_input/state"][:8], rtol=0, atol=1e-12)
    assert not case["model_input/state"][8:].any()
    # Output chain: the model's raw [50, 32] output and the float32 normalised padded state Policy.infer passes on.
    outputs = compose([Unnormalize(stats, use_quantiles=False), *PI0_FAST_LIBERO.outputs])
    actions = outputs({"state": case["model_input/state"].astype(np.float32), "actions": case["model_output/actions"]})[
        "actions"
    ]
    assert actions.shape == (50, 7)
    # Upstream computed these in float64 from the same float32 inputs: rounding only.
    np.testing.assert_allclose(actions, case["policy_output/actions"], rtol=0, atol=1e-9)
    # AbsoluteActions really contributes: without it, dims 0-5 are off by the state.
    plain = compose([Unnormalize(stats, use_quantiles=False), libero.LiberoOutputs()])(
        {"state": case["model_input/state"].astype(np.float32), "actions": case["model_output/actions"]}
    )["actions"]
    assert np.abs(plain[:, :6] - case["policy_output/actions"][:, :6]).min() > 1e-3
    np.testing.assert_allclose(plain[:, 6], case["policy_output/actions"][:, 6], rtol=0, atol=1e-9)


# ALOHA: no upstream golden exists. Expected numbers below are derived by hand from upstream's documented formulas
# (openpi `aloha_policy.py`, adapt_to_pi=True), not from our code:
# - joints: multiplied by the flip mask [1, -1, -1, 1, 1, 1, 1] per arm (dims 1, 2, 8, 9 negate);
# - state grippers (dims 6, 13): linear = 0.01844 + g * (0.05800 - 0.01844) (ALOHA puppet gripper positions), the
#   Interbotix linkage inverted with horn radius 0.022 and arm length 0.036:
#   angle = asin((0.022^2 + linear^2 - 0.036^2) / (2 * 0.022 * linear)), then normalised to pi0's range:
#   (angle - 0.5476) / (1.6296 - 0.5476). For g = 0: asin(-0.58170) = -0.62081 -> -1.07987; g = 0.5: linear 0.03822,
#   asin(0.38579) = 0.39606 -> -0.14006; g = 1: the ratio is exactly 1 -> pi/2 -> 0.94565.
# - action grippers: (a + 0.5476 - (-0.6213)) / (1.4910 - (-0.6213)), e.g. 0.3 -> 0.69540, -0.1 -> 0.50604.
ALOHA_STATE_GRIPPER = {0.0: -1.07987, 0.5: -0.14006, 1.0: 0.94565}
ALOHA_ACTION_GRIPPER = {0.3: 0.69540, -0.1: 0.50604}
ALOHA_FLIP = np.array([1, -1, -1, 1, 1, 1, 1] * 2, float)


def test_aloha_adapt_to_pi_against_upstreams_formulas():
    joints = np.array([0.1, 0.2, -0.3, 0.4, 0.5, 0.6])
    for left, right in ((0.0, 0.5), (1.0, 0.0)):
        state = np.concatenate([joints, [left], -joints, [right]])
        obs = aloha.make_aloha_example(height=48, width=64)
        obs["state"] = state
        out = aloha.AlohaInputs(adapt_to_pi=True)(obs)
        want = ALOHA_FLIP * state
        want[[6, 13]] = ALOHA_STATE_GRIPPER[left], ALOHA_STATE_GRIPPER[right]
        np.testing.assert_allclose(out["state"], want, rtol=0, atol=1e-5)  # the hand values carry 5 decimals
        np.testing.assert_array_equal(obs["state"], state)  # the client's array is not modified
    # Images arrive [3, H, W] and become [H, W, 3]; a missing wrist camera is black and masked (even for FAST).
    obs = aloha.make_aloha_example(height=48, width=64)
    del obs["images"]["cam_right_wrist"]
    out = aloha.AlohaInputs()(dict(obs))
    np.testing.assert_array_equal(out["image"]["base_0_rgb"], obs["images"]["cam_high"].transpose(1, 2, 0))
    np.testing.assert_array_equal(out["image"]["left_wrist_0_rgb"], obs["images"]["cam_left_wrist"].transpose(1, 2, 0))
    assert not out["image"]["right_wrist_0_rgb"].any()
    assert [bool(out["image_mask"][c]) for c in out["image"]] == [True, True, False]
    assert aloha.AlohaInputs().camera_sources_for(obs)["right_wrist_0_rgb"] is None
    with pytest.raises(InvalidRequest, match="unknown cameras"):
        aloha.AlohaInputs()({**obs, "images": {**obs["images"], "cam_extra": obs["images"]["cam_high"]}})


def test_aloha_output_chain_against_upstreams_formulas():
    """pi0_fast_aloha's outputs: AbsoluteActions on the joints (pi0-space state added back, grippers absolute), then
    AlohaOutputs (flip, gripper to ALOHA's joint range), keeping 14 of the model's 32 dims."""
    rng = np.random.default_rng(0)
    state = rng.uniform(-0.5, 0.5, 14)  # the pi0-space state (after AlohaInputs), as the output transforms get it
    actions = rng.uniform(-0.5, 0.5, (4, 32))
    actions[:, 6], actions[:, 13] = 0.3, -0.1
    out = compose(PI0_FAST_ALOHA.outputs)({"state": state, "actions": actions.copy()})["actions"]
    want = actions[:, :14].copy()
    joints = [i for i in range(14) if i not in (6, 13)]
    want[:, joints] += state[joints]
    want = ALOHA_FLIP * want
    want[:, 6], want[:, 13] = ALOHA_ACTION_GRIPPER[0.3], ALOHA_ACTION_GRIPPER[-0.1]
    assert out.shape == (4, 14)
    np.testing.assert_allclose(out, want, rtol=0, atol=1e-5)
    # Training direction: the inverse maps ALOHA actions back (what AlohaInputs does with `actions`).
    back = aloha.encode_actions_inv(out.copy(), adapt_to_pi=True)
    np.testing.assert_allclose(back[:, [6, 13]], [[0.3, -0.1]] * 4, atol=1e-12)


def test_delta_and_absolute_actions_invert_each_other():
    mask = make_bool_mask(6, -1)
    assert mask == (True,) * 6 + (False,)
    state = np.arange(7.0)
    actions = np.ones((3, 7))
    delta = DeltaActions(mask)({"state": state, "actions": actions.copy()})["actions"]
    np.testing.assert_array_equal(delta[:, 6], 1.0)
    np.testing.assert_array_equal(delta[0, :6], 1.0 - state[:6])
    back = AbsoluteActions(mask)({"state": state, "actions": delta})["actions"]
    np.testing.assert_array_equal(back, actions)
    assert PI0_FAST_LIBERO.outputs[0] == AbsoluteActions(mask)  # upstream pi0_fast_libero: extra_delta_transform


@pytest.mark.parametrize("dtype", [np.int64, np.int32, np.float32])
def test_delta_and_absolute_actions_keep_the_input_dtype(dtype):
    """Upstream changes the actions in place, so integer state and actions stay integer (and float32 stays float32);
    a mask shorter than the actions leaves the remaining dims alone."""
    state = np.array([1, 2, 3], dtype=dtype)
    actions = np.array([[3, 4, 5], [5, 6, 7]], dtype=dtype)
    sent = actions.copy()
    delta = DeltaActions([False, True])({"state": state, "actions": actions})["actions"]
    assert delta.dtype == dtype
    np.testing.assert_array_equal(delta, [[3, 2, 5], [5, 4, 7]])
    np.testing.assert_array_equal(actions, sent)  # the caller's array is not changed
    back = AbsoluteActions([False, True])({"state": state, "actions": delta})["actions"]
    assert back.dtype == dtype
    np.testing.assert_array_equal(back, sent)


def test_generic_inputs_synthesise_blank_cameras():
    inputs = GenericInputs(cameras={"top": "obs/top", "blank": None}, state_key="obs/state", state_dim=3)
    out = inputs({"obs/top": np.full((10, 20, 3), 7, np.uint8), "obs/state": [1.0, 2.0, 3.0]})
    assert out["image"]["blank"].shape == (10, 20, 3) and not out["image"]["blank"].any()
    nested = inputs({"obs": {"top": np.zeros((10, 20, 3), np.uint8), "state": np.zeros(3)}})
    assert nested["state"].shape == (3,)
    with pytest.raises(InvalidRequest, match="obs/state"):
        inputs({"obs/top": np.zeros((10, 20, 3), np.uint8)})


# -------------------------------------------------------------------------------------------- letterbox geometry


def test_resize_with_pad_jax_and_pil_agree_on_geometry(case):
    raw = case["raw/exterior_image_1_left"]
    geo = letterbox_geometry(*raw.shape[:2], 224, 224)
    assert (geo.resized_h, geo.resized_w, geo.pad_top, geo.pad_left) == (126, 224, 49, 0)  # README: 49 rows each side
    pil = resize_with_pad_pil(raw, 224, 224)
    jx = np.asarray(resize_with_pad(raw, 224, 224))
    for img in (pil, jx):
        assert not img[: geo.pad_top].any() and not img[geo.pad_top + geo.resized_h :].any()
    # The two bilinear implementations differ by at most one grey level (rounding of nearly equal weights).
    assert np.abs(pil.astype(int) - jx.astype(int)).max() <= 1
    flt = np.asarray(resize_with_pad(raw.astype(np.float32) / 127.5 - 1.0, 224, 224))
    assert flt.dtype == np.float32 and (flt[: geo.pad_top] == -1.0).all()  # float images pad with -1 (black)
    batched = np.asarray(resize_with_pad(np.stack([raw, raw])[None], 224, 224))
    assert batched.shape == (1, 2, 224, 224, 3)
    np.testing.assert_array_equal(batched[0, 1], jx)


def test_geometry_maps_original_points_into_a_non_square_letterbox():
    # A 100 x 300 image (portrait padding): a bright marker at original (x=210..240, y=40..60).
    orig = np.zeros((100, 300, 3), np.uint8)
    orig[40:60, 210:240] = 255
    geo = letterbox_geometry(100, 300, 96, 96)
    assert (geo.resized_h, geo.resized_w, geo.pad_top, geo.pad_left) == (32, 96, 32, 0)
    model = resize_with_pad_pil(orig, 96, 96)
    ys, xs = np.nonzero(model[..., 0] > 128)
    cx, cy = xs.mean() + 0.5, ys.mean() + 0.5  # pixel-centre convention
    mx, my = geo.original_to_model(225.0, 50.0)  # the marker's centre in the original
    # One model pixel is 300/96 = 3.125 original pixels: the resampled marker's centroid is within one model pixel.
    assert abs(mx - cx) <= 1.0 and abs(my - cy) <= 1.0
    # The original's corners land on the content's corners, inside the padding band; arrays map elementwise.
    xs, ys = geo.original_to_model(np.array([0.0, 150.0, 300.0]), np.array([0.0, 50.0, 100.0]))
    np.testing.assert_allclose(xs, [0.0, 48.0, 96.0])
    np.testing.assert_allclose(ys, [32.0, 48.0, 64.0])
    assert type(geo).from_dict(geo.as_dict()) == geo
    tall = letterbox_geometry(300, 100, 96, 96)
    assert (tall.resized_w, tall.pad_left, tall.pad_top) == (32, 32, 0)
    assert tall.original_to_model(50.0, 150.0) == (32 + 16, 48)
