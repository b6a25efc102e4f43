"""`openpi-cam export --to lerobot`: OpenPI orbax pi0 / pi0.5 checkpoints written as LeRobot policy folders, read
back as LeRobot folders (LeRobot's pipelines and time grid), serve the original's chunks; the statistics are the
checkpoint's own; what LeRobot's pipeline cannot express is refused in one line. (That LeRobot 0.6.1 itself loads and
runs such a folder is benchmarks/check_lerobot_export.py's job: it needs torch.)

Tolerance: the read-back chunk within `golden.FLOW_REL` of the original's largest magnitude. The two differ in how
float32 evaluates the same function: LeRobot's Euler times and float64 time embedding against OpenPI's float32
accumulation, and LeRobot's normaliser epsilon (1e-8) against OpenPI's (1e-6 added to the range); FLOW_REL is the
bound golden.py derives for the float32 evaluation error of these models. Distinct observations' chunks lie far
outside it, so serving the wrong frame or weights cannot pass.
"""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest
from demo_inputs import demo_observation
from paths import GOLDEN_DIR
from safetensors.numpy import load_file

from openpi_cam import golden
from openpi_cam.checkpoints import model_spec
from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.cli import export as export_cli
from openpi_cam.lerobot.export import export_lerobot
from openpi_cam.lerobot.policy import create_lerobot_policy
from openpi_cam.model.safetensors_weights import read_tensor_infos
from openpi_cam.normalize import load_checkpoint_norm_stats, save_norm_stats
from openpi_cam.policies import demo_reach
from openpi_cam.policies.checkpoint_format import checkpoint_format
from openpi_cam.policies.config import PolicyConfig
from openpi_cam.policies.policy import create_policy
from openpi_cam.policies.robot import GenericInputs, GenericOutputs

DEMO = demo_reach.ASSETS_PI05
DEMO_TOKENIZER = DEMO / demo_reach.PALIGEMMA_TOKENIZER.name
LIBERO = GOLDEN_DIR / "tiny_policy_pi0_libero"
# pi0 on the tiny LIBERO checkpoint through a generic robot (LeRobot's features), its blank right wrist masked.
PI0_GENERIC = PolicyConfig(
    name="tiny_pi0_generic",
    family="pi0",
    inputs=(
        GenericInputs(
            cameras={
                "base_0_rgb": "observation/image",
                "left_wrist_0_rgb": "observation/wrist_image",
                "right_wrist_0_rgb": None,
            },
            state_key="observation/state",
            state_dim=8,
            mask_blank=True,
        ),
    ),
    outputs=(GenericOutputs(action_dim=7),),
    asset_id="physical-intelligence/libero",
    action_dim=32,
    action_horizon=50,
    max_token_len=48,
    use_quantile_norm=False,
    lerobot_keys={
        "observation/image": "observation.images.image",
        "observation/wrist_image": "observation.images.wrist_image",
        "observation/state": "observation.state",
        "actions": "action",
    },
)


def demo_frames(count: int) -> list[tuple[dict, np.ndarray]]:
    rng = np.random.default_rng(0)
    frames = []
    for i in range(count):
        noise = rng.standard_normal((demo_reach.ACTION_HORIZON, 32)).astype(np.float32)
        frames.append((demo_observation(100 + i), noise))
    return frames


def assert_round_trip(original, back, frames, keys: dict[str, str]) -> None:
    chunks = []
    for obs, noise in frames:
        want, want_trace = original.infer_traced(obs, noise=noise)
        request = {keys[k]: v for k, v in obs.items() if k in keys} | {"prompt": obs["prompt"]}
        got, got_trace = back.infer_traced(request, noise=noise)
        np.testing.assert_array_equal(
            np.asarray(got_trace.observation.tokenized_prompt), np.asarray(want_trace.observation.tokenized_prompt)
        )
        c = golden.compare("", "actions", got["actions"], want["actions"], rel=golden.FLOW_REL)
        assert c.ok, c.line()
        chunks.append((want["actions"], c.bound))
    for i in range(len(chunks)):
        for j in range(i):
            assert np.abs(chunks[i][0] - chunks[j][0]).max() > 100 * chunks[i][1]


def test_the_demo_pi05_round_trips_through_a_lerobot_folder(tmp_path):
    out = tmp_path / "demo_lerobot"
    code = export_cli.main(out)  # the default: the bundled pi0.5, its own tokenizer shipped
    assert code == 0 and checkpoint_format(out) == "lerobot"
    config = json.loads((out / "config.json").read_text())
    assert (config["type"], config["empty_cameras"], config["chunk_size"]) == ("pi05", 1, demo_reach.ACTION_HORIZON)
    assert list(config["input_features"])[:2] == ["observation.images.base", "observation.images.wrist"]
    back = create_lerobot_policy(out, dtype="float32")
    original = model_spec.create_demo_policy("pi05", dtype="float32")
    assert_round_trip(original, back, demo_frames(4), demo_reach.LEROBOT_KEYS)


def test_a_bfloat16_export_is_the_float32_folder_with_its_weights_stored_in_bfloat16(tmp_path):
    """`--dtype bfloat16`: LeRobot's `dtype` field says bfloat16 and every weight is stored in it, the statistics stay
    float32; read back, the folder computes in bfloat16 and serves exactly what the float32 folder serves in
    bfloat16 (the same weights, rounded once to bfloat16 either way)."""
    assert export_cli.main(tmp_path / "f32", ModelSpec(config="demo_reach_pi05")) == 0
    assert export_cli.main(tmp_path / "bf16", ModelSpec(config="demo_reach_pi05", dtype="bfloat16")) == 0
    f32, bf16 = tmp_path / "f32", tmp_path / "bf16"
    assert json.loads((bf16 / "config.json").read_text())["dtype"] == "bfloat16"
    assert json.loads((f32 / "config.json").read_text())["dtype"] == "float32"  # the default: LeRobot's
    assert {info.dtype for info in read_tensor_infos(bf16 / "model.safetensors").values()} == {"BF16"}
    stats = next(bf16.glob("policy_preprocessor_step_*.safetensors"))
    assert {v.dtype for v in load_file(str(stats)).values()} == {np.dtype(np.float32)}
    assert ModelSpec(bf16).resolved().dtype == "bfloat16"
    ours, reference = ModelSpec(bf16).create(), create_lerobot_policy(f32, dtype="bfloat16")
    for obs, noise in demo_frames(2):
        request = {demo_reach.LEROBOT_KEYS[k]: v for k, v in obs.items() if k in demo_reach.LEROBOT_KEYS}
        request["prompt"] = obs["prompt"]
        np.testing.assert_array_equal(
            ours.infer(request, noise=noise)["actions"], reference.infer(request, noise=noise)["actions"]
        )


def test_a_lerobot_folder_has_no_place_for_a_fast_tokenizer_or_a_default_prompt(tmp_path, capsys):
    for flags, flag in ((ModelSpec(default_prompt="reach"), "--default-prompt"),
                        (ModelSpec(fast_tokenizer=demo_reach.FAST_TOKENIZER), "--fast-tokenizer")):  # fmt: skip
        assert export_cli.main(tmp_path / "out", flags) == 2
        (line,) = capsys.readouterr().err.splitlines()
        assert line.startswith(f"openpi-cam export: {flag}: a LeRobot pi0 / pi0.5 folder")
    assert not (tmp_path / "out").exists()


def test_a_pi0_round_trips_with_its_mean_std_statistics_and_newline_prompt(tmp_path):
    out = export_lerobot(LIBERO / "checkpoint", PI0_GENERIC, tmp_path / "pi0",
                         paligemma_tokenizer=LIBERO / "paligemma_tokenizer_tiny.model")  # fmt: skip
    assert json.loads((out / "config.json").read_text())["normalization_mapping"]["STATE"] == "MEAN_STD"
    kwargs = {"paligemma_tokenizer": LIBERO / "paligemma_tokenizer_tiny.model", "dtype": "float32"}
    original = create_policy(PI0_GENERIC, LIBERO / "checkpoint", **kwargs)
    back = create_lerobot_policy(out, dtype="float32")
    prompt = json.loads((LIBERO / "case.json").read_text())["cases"]["case_1"]["prompt"]
    with np.load(LIBERO / "case_1.npz") as npz:
        obs = {"observation/" + k[len("raw/") :]: npz[k] for k in npz.files if k.startswith("raw/")} | {
            "prompt": prompt
        }
    # Frames at the model's 224 x 224: at other sizes LeRobot's bilinear resize (no antialiasing) is not OpenPI's PIL
    # resize, so the two policies see other images (that difference is LeRobot's, and the export keeps it).
    mirrored = obs | {k: v[:, ::-1] for k, v in obs.items() if k.endswith("image")}
    mirrored["observation/state"] = -obs["observation/state"]
    noises = np.random.default_rng(0).standard_normal((2, 50, 32)).astype(np.float32)
    frames = list(zip((obs, mirrored), noises, strict=True))
    assert_round_trip(original, back, frames, dict(PI0_GENERIC.lerobot_keys))


def test_the_statistics_are_the_checkpoints_own(tmp_path):
    """OpenPI's converter copies assets/ from the checkpoint's parent; the export reads the checkpoint's own."""
    checkpoint = tmp_path / "run" / "checkpoint"
    shutil.copytree(DEMO / "checkpoint", checkpoint)
    own = load_checkpoint_norm_stats(checkpoint, demo_reach.ASSET_ID)
    decoy = {k: dataclasses.replace(v, q01=v.q01 - 1, q99=v.q99 + 1) for k, v in own.items()}
    save_norm_stats(tmp_path / "run" / "assets" / demo_reach.ASSET_ID, decoy)
    out = export_lerobot(checkpoint, demo_reach.DEMO_PI05_CONFIG, tmp_path / "out", paligemma_tokenizer=DEMO_TOKENIZER)
    steps = json.loads((out / "policy_preprocessor.json").read_text())["steps"]
    stats = load_file(str(out / next(s["state_file"] for s in steps if "state_file" in s)))
    for feature, ours in (("observation.state", "state"), ("action", "actions")):
        for name in ("mean", "std", "q01", "q99"):
            np.testing.assert_array_equal(stats[f"{feature}.{name}"], getattr(own[ours], name)[:2].astype(np.float32))
    post = json.loads((out / "policy_postprocessor.json").read_text())["steps"][0]
    assert set(load_file(str(out / post["state_file"]))) == {f"action.{n}" for n in ("mean", "std", "q01", "q99")}


def test_what_lerobots_pipeline_cannot_express_is_refused_in_one_line(tmp_path):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("")
    cases = [
        (LIBERO / "checkpoint", "pi0_libero", tmp_path / "a", ValueError, "only a GenericInputs robot"),
        (DEMO / "checkpoint", "pi0_fast_droid", tmp_path / "b", ValueError, "serves pi0_fast"),
        (DEMO / "checkpoint", dataclasses.replace(demo_reach.DEMO_PI05_CONFIG, default_prompt="reach"),
         tmp_path / "c", ValueError, "default prompt"),
        (DEMO / "checkpoint", "demo_reach_pi05", tmp_path / "full", FileExistsError, "is not empty"),
        (GOLDEN_DIR / "lerobot_pi05_tiny", "demo_reach_pi05", tmp_path / "d", ValueError, "is a lerobot checkpoint"),
    ]  # fmt: skip
    for checkpoint, config, out, error, words in cases:
        with pytest.raises(error) as raised:
            export_lerobot(checkpoint, config, out)
        assert "\n" not in str(raised.value) and words in str(raised.value)
    assert export_cli.main(tmp_path / "e", ModelSpec(LIBERO / "checkpoint", "pi0_libero")) == 2
    assert not (tmp_path / "a").exists()  # refused before anything was written
