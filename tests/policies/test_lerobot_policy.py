"""LeRobot pi0 / pi0.5 policy folders served as LeRobot runs them, against LeRobot 0.6.1's own arrays
(`../shared/golden/lerobot_pi05_tiny`, `lerobot_pi0_tiny`), and every way a folder or a request can be wrong.

Tolerances are `openpi_cam.golden`'s for LeRobot goldens, where the reasoning is: chunks and the explained objective
within SAFETY times the golden's own float32 variation (its batch rows against the same frames alone), the gradient
GRADIENT_AMPLIFICATION times that, model-space images within 4 float32 epsilons; preprocessed state, prompt text,
tokens and masks exactly. Folders are changed in copies under tmp_path, never in ../shared.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from lerobot_cases import CAMERAS, cases, request
from one_line import assert_one_line
from paths import GOLDEN_DIR
from safetensors.numpy import load_file, save_file
from safetensors_edit import edit_safetensors, read_tensor
from shared_copies import edit_json, writable_copy

from openpi_cam import golden
from openpi_cam.checkpoints.model_spec import BundledModel, LeRobotFolder, ModelSpec, OpenPICheckpoint
from openpi_cam.cli import golden as cli_golden
from openpi_cam.errors import InvalidRequest
from openpi_cam.lerobot.golden import run_lerobot_golden
from openpi_cam.lerobot.policy import LeRobotConfig, Normalizer, PolicyFeature, create_lerobot_policy
from openpi_cam.letterbox import letterbox_geometry
from openpi_cam.model.pi0 import Pi0
from openpi_cam.model.safetensors_weights import save_safetensors_params
from openpi_cam.policies.checkpoint_format import checkpoint_format, write_sizes_record
from openpi_cam.policies.policy import create_policy
from openpi_cam.vocabulary import ExplainOptions

FOLDERS = {"pi05": GOLDEN_DIR / "lerobot_pi05_tiny", "pi0": GOLDEN_DIR / "lerobot_pi0_tiny"}
PI05 = FOLDERS["pi05"]
# Layer 1's: layer 0's projections are the anchors the architecture is read from, so another tensor disagrees with
# a misshapen one of them.
Q_PROJ = "model.paligemma_with_expert.paligemma.model.language_model.layers.1.self_attn.q_proj.weight"


def policy_of(folder: Path, **kwargs):
    return create_lerobot_policy(folder, dtype="float32", **kwargs)


def copy_folder(tmp_path: Path, folder: Path = PI05) -> Path:
    return writable_copy(folder, tmp_path / folder.name)


# ------------------------------------------------------------------------------------------- parity with LeRobot


@pytest.mark.parametrize("family", list(FOLDERS))
def test_lerobots_pipelines_model_and_gradient_are_reproduced(family):
    """Every frame (the batch's two rows served alone): preprocessed state and prompt text, tokens, masks, model
    images, normalised and post-processed chunks; the gradient w.r.t. the first camera's model image."""
    results = run_lerobot_golden(FOLDERS[family], verbose=False)
    failed = [r.line() for r in results if not r.ok]
    assert not failed, "\n".join(failed)
    names = {(r.case, r.name) for r in results}
    for case in ("case0", "case1", "case2", "batch2[0]", "batch2[1]"):
        for name in ("pre/task", "pre/observation.state", "pre/observation.language.tokens", "action",
                     "action_normalized_padded", f"model/{CAMERAS[0]}", f"model/{CAMERAS[1]}"):  # fmt: skip
            assert (case, name) in names
    assert ("grad", "d_objective_d_model_image0") in names
    assert (("case0", "model/state_padded") in names) == (family == "pi0")  # pi0's state enters through state_proj


def test_the_stable_entry_point_serves_the_post_processed_chunk():
    d = cases(PI05)
    policy = ModelSpec(PI05, paligemma_tokenizer=PI05 / "tokenizer" / "tokenizer.model", dtype="float32").create()
    response = policy.infer(request(d), noise=d["case0/noise"][0])
    want = d["case0/action"][0]
    assert response["actions"].shape == (10, 7)
    rel = golden.SAFETY * golden.lerobot_variation(
        d["meta/batch2_row_vs_single_maxdiff"], d["batch2/action_normalized"]
    )
    assert (c := golden.compare("case0", "action", response["actions"], want, rel=rel)).ok, c.line()
    # The prompt may come as openpi-client sends it; another frame gives other actions.
    as_prompt = {k: v for k, v in request(d).items() if k != "task"} | {"prompt": str(d["case0/input/task"])}
    np.testing.assert_array_equal(policy.infer(as_prompt, noise=d["case0/noise"][0])["actions"], response["actions"])
    other = policy.infer(request(d, "case1"), noise=d["case0/noise"][0])["actions"]
    assert np.abs(other - response["actions"]).max() > 1e-2
    assert policy.metadata["lerobot"]["cameras"] == list(CAMERAS)


def test_the_trace_describes_lerobots_placement_and_the_maps_explain_the_served_chunk():
    d = cases(PI05)
    policy = policy_of(PI05)
    _, trace = policy.infer_traced(request(d), noise=d["case0/noise"][0])
    assert policy.model.config.image_keys == CAMERAS  # LeRobot's token order: the config's image features
    assert set(trace.camera_names) == set(CAMERAS)
    assert trace.camera_sources == {c: c for c in CAMERAS}
    assert trace.prompt == str(d["case0/input/task"])
    for camera in CAMERAS:
        np.testing.assert_array_equal(trace.raw_images[camera], d[f"case0/input_uint8_hwc/{camera}"])
        assert bool(np.asarray(trace.observation.image_masks[camera])[0])
    assert trace.geometry[CAMERAS[0]] == letterbox_geometry(120, 160, 224, 224)
    assert (trace.geometry[CAMERAS[0]].pad_top, trace.geometry[CAMERAS[0]].resized_h) == (28, 168)
    (explanation,) = policy.explainer.explain(
        trace.observation, trace.output[None], ExplainOptions(target="chunk", maps=("gradcam",)),
        {k: v[None] for k, v in trace.sample_inputs.items()},
    )  # fmt: skip
    assert set(explanation.maps["gradcam"]) == set(CAMERAS)
    assert all(m.shape == (16, 16) for m in explanation.maps["gradcam"].values())
    # The explanation re-runs the served chunk (LeRobot's time grid included): the same numbers.
    assert explanation.details["replay_max_abs_diff"] <= 1e-5 * np.abs(trace.output).max()


# ---------------------------------------------------------------------------------------------------- formats


def openpi_pytorch_export(tmp_path: Path) -> tuple[Path, Path]:
    """The tiny pi0.5 DROID policy's checkpoint as OpenPI's PyTorch export lays it out (bare keys, its assets)."""
    orbax = GOLDEN_DIR / "tiny_policy_pi05_droid" / "checkpoint"
    model = Pi0.from_checkpoint(orbax / "params", dtype="float32")
    export = tmp_path / "pi05_droid_pytorch"
    export.mkdir()
    save_safetensors_params(export / "model.safetensors", model.params, model.config, prefix="")
    shutil.copytree(orbax / "assets", export / "assets")
    write_sizes_record(export, model.config)
    return orbax, export


def test_formats_are_recognised_in_one_place(tmp_path):
    orbax, export = openpi_pytorch_export(tmp_path)
    assert checkpoint_format(orbax) == "orbax"
    assert checkpoint_format(PI05) == "lerobot"
    assert checkpoint_format(export) == "openpi_pytorch"
    shutil.rmtree(export / "assets")
    with pytest.raises(FileNotFoundError) as raised:
        checkpoint_format(export)
    assert_one_line(raised.value, "assets/")
    with pytest.raises(FileNotFoundError) as raised:
        checkpoint_format(tmp_path / "nothing")
    assert_one_line(raised.value, "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError) as raised:
        checkpoint_format(tmp_path / "empty")
    assert_one_line(raised.value, "params", "policy_preprocessor.json", "OpenPI PyTorch export")


def test_a_model_spec_is_resolved_once_into_its_source(tmp_path, monkeypatch):
    """No folder is the bundled model, an OpenPI checkpoint keeps the config it is named with (pi0_fast_droid by
    default), a LeRobot folder's config.json is read once however many questions the spec answers; a LeRobot folder
    named with a config is refused in one line."""
    orbax, export = openpi_pytorch_export(tmp_path)
    bundled = ModelSpec().source
    assert isinstance(bundled, BundledModel) and bundled.installed and bundled.config == "demo_reach"
    assert ModelSpec(orbax, "pi05_droid").source == OpenPICheckpoint(orbax.resolve(), "pi05_droid", "orbax")
    assert ModelSpec(export).source == OpenPICheckpoint(export.resolve(), "pi0_fast_droid", "openpi_pytorch")
    read, reads = LeRobotConfig.read, []
    monkeypatch.setattr(LeRobotConfig, "read", lambda path: reads.append(path) or read(path))
    spec = ModelSpec(PI05)
    assert isinstance(spec.source, LeRobotFolder) and spec.resolved().dtype == "float32"
    assert spec.dataset_keys()[0] and spec.facts().family == "pi05" and spec.tokenizers() == (None, None)
    assert reads == [PI05.resolve() / "config.json"]
    with pytest.raises(ValueError) as raised:
        ModelSpec(PI05, "pi05_droid").source  # noqa: B018
    assert_one_line(raised.value, "LeRobot policy folder", "'pi05_droid'")


def test_openpis_pytorch_export_is_served_like_its_orbax_checkpoint(tmp_path):
    orbax, export = openpi_pytorch_export(tmp_path)
    root = GOLDEN_DIR / "tiny_policy_pi05_droid"
    with np.load(root / "case_1.npz") as npz:
        d = {k: npz[k] for k in npz.files}
    prompt = json.loads((root / "case.json").read_text())["cases"]["case_1"]["prompt"]
    obs = {"observation/" + k[len("raw/") :]: v for k, v in d.items() if k.startswith("raw/")} | {"prompt": prompt}
    kwargs = {"paligemma_tokenizer": root / "paligemma_tokenizer_tiny.model", "dtype": "float32"}
    from_orbax = create_policy("pi05_droid", orbax, **kwargs).infer(obs, noise=d["noise"])
    from_export = create_policy("pi05_droid", export, **kwargs).infer(obs, noise=d["noise"])
    np.testing.assert_array_equal(from_export["actions"], from_orbax["actions"])
    with pytest.raises(ValueError) as raised:
        create_policy(None, export, **kwargs)
    assert_one_line(raised.value, "name the config")
    with pytest.raises(ValueError) as raised:
        create_policy("pi05_droid", PI05, **kwargs)
    assert_one_line(raised.value, "LeRobot policy folder", "'pi05_droid'")


# ------------------------------------------------------------------------------------------------ bad folders


def test_a_missing_file_is_named(tmp_path):
    folder = copy_folder(tmp_path)
    (folder / "policy_postprocessor.json").unlink()
    with pytest.raises(FileNotFoundError) as raised:
        policy_of(folder)
    assert_one_line(raised.value, "policy_postprocessor.json")
    folder = copy_folder(tmp_path / "b")
    (folder / "policy_preprocessor_step_3_normalizer_processor.safetensors").unlink()
    with pytest.raises(FileNotFoundError) as raised:
        policy_of(folder)
    assert_one_line(raised.value, "normalizer_processor", "policy_preprocessor_step_3_normalizer_processor.safetensors")


@pytest.mark.parametrize(
    ("edit", "names"),
    [
        ({"drop": (Q_PROJ,)}, ("missing tensor", Q_PROJ)),
        ({"add": {"model.extra.weight": np.zeros(2, np.float32)}}, ("unexpected tensor", "model.extra.weight")),
        ({"replace": {Q_PROJ: np.zeros((64, 64), np.float32)}}, (Q_PROJ, "[64, 64], expected [128, 64]")),
    ],
)
def test_a_bad_weight_is_named(tmp_path, edit, names):
    folder = copy_folder(tmp_path)
    edit_safetensors(PI05 / "model.safetensors", folder / "model.safetensors", **edit)
    with pytest.raises(ValueError) as raised:
        policy_of(folder)
    assert_one_line(raised.value, *names)


def test_a_weight_of_no_float_type_is_named(tmp_path):
    """A tensor stored as integers (a quantised or corrupted export) is refused before any weight is read, naming the
    tensor and its dtype."""
    folder = copy_folder(tmp_path)
    tensors = load_file(str(PI05 / "model.safetensors"))
    tensors[Q_PROJ] = tensors[Q_PROJ].astype(np.int32)
    (folder / "model.safetensors").unlink()
    save_file(tensors, str(folder / "model.safetensors"))
    with pytest.raises(ValueError) as raised:
        policy_of(folder)
    assert_one_line(raised.value, Q_PROJ, "dtype I32", "expected a float type")


def test_an_unknown_processor_step_or_type_is_named(tmp_path):
    folder = copy_folder(tmp_path)
    edit_json(folder / "policy_preprocessor.json", lambda d: d["steps"].insert(2, {"registry_name": "crop_processor"}))
    with pytest.raises(ValueError) as raised:
        policy_of(folder)
    assert_one_line(raised.value, "'crop_processor'", "not implemented", "policy_preprocessor.json")
    # a registered step in a pipeline it has no place in (the tokenizer after the model)
    folder = copy_folder(tmp_path / "post")
    step = {"registry_name": "tokenizer_processor", "config": {"max_length": 48}}
    edit_json(folder / "policy_postprocessor.json", lambda d: d["steps"].append(step))
    with pytest.raises(ValueError) as raised:
        policy_of(folder)
    assert_one_line(raised.value, "'tokenizer_processor'", "not implemented", "policy_postprocessor.json")
    for kind, words in (("pi052", ("'pi052'", "not served")), ("pi0_fast", ("pi0-FAST", "Hugging Face Hub"))):
        folder = copy_folder(tmp_path / kind)
        edit_json(folder / "config.json", lambda d, kind=kind: d.update(type=kind))
        with pytest.raises(ValueError) as raised:
            policy_of(folder)
        assert_one_line(raised.value, *words)


def test_a_tokenizer_length_other_than_the_configs_is_refused_naming_both(tmp_path):
    """LeRobot builds the tokenizer step from `tokenizer_max_length`: a folder whose two values disagree is refused
    before its weights are read, naming both values and both files (either file may be the edited one)."""
    folder = copy_folder(tmp_path)
    edit_json(folder / "policy_preprocessor.json", lambda p: p["steps"][5]["config"].update(max_length=64))
    with pytest.raises(ValueError) as raised:
        policy_of(folder)
    assert_one_line(
        raised.value, "config.json", "tokenizer_max_length 200", "policy_preprocessor.json", "max_length 64"
    )


def test_the_tokenizer_is_found_in_the_folder_then_the_hugging_face_cache_and_never_downloaded(tmp_path, monkeypatch):
    d = cases(PI05)
    folder = copy_folder(tmp_path)
    tokenizer = folder / "tokenizer" / "tokenizer.model"
    snapshot = tmp_path / "hf" / "hub" / "models--tiny--paligemma" / "snapshots" / "0123abc"
    snapshot.mkdir(parents=True)
    shutil.copy(tokenizer, snapshot / "tokenizer.model")
    shutil.rmtree(folder / "tokenizer")
    edit_json(folder / "policy_preprocessor.json",
              lambda p: p["steps"][5]["config"].update(tokenizer_name="tiny/paligemma"))  # fmt: skip
    monkeypatch.delenv("HF_HUB_CACHE", raising=False)
    monkeypatch.setenv("HF_HOME", str(tmp_path / "hf"))
    served = policy_of(folder).infer_traced(request(d), noise=d["case0/noise"][0])[1]
    np.testing.assert_array_equal(
        np.asarray(served.observation.tokenized_prompt)[0], d["case0/pre/observation.language.tokens"][0]
    )
    monkeypatch.setenv("HF_HOME", str(tmp_path / "empty"))
    with pytest.raises(FileNotFoundError) as raised:
        policy_of(folder)
    assert_one_line(raised.value, "'tiny/paligemma'", "nothing is downloaded")


def test_bad_requests_are_named():
    d = cases(PI05)
    policy = policy_of(PI05)
    good = request(d)
    bad = {
        "observation.images.wrist": ({k: v for k, v in good.items() if k != CAMERAS[1]}, InvalidRequest),
        "expected 8 values": (good | {"observation.state": np.zeros(9, np.float32)}, InvalidRequest),
        "a float image must be [3, H, W]": (good | {CAMERAS[0]: np.zeros((120, 160, 3), np.float32)}, InvalidRequest),
        "missing 'prompt' (or 'task')": ({k: v for k, v in good.items() if k != "task"}, InvalidRequest),
    }
    for message, (obs, error) in bad.items():
        with pytest.raises(error) as raised:
            policy.infer(obs, noise=d["case0/noise"][0])
        assert_one_line(raised.value, message)


# ------------------------------------------------------------------------------- steps the goldens do not cover


def test_every_normalisation_mode_maps_its_statistics_to_the_unit_range_and_back():
    x = np.asarray([-1.5, 0.25, 3.0, 7.0], np.float32)
    stats = {
        "mean": np.asarray([0.5, 0.0, 1.0, 7.0], np.float32), "std": np.asarray([2.0, 1.0, 0.5, 0.0], np.float32),
        "min": np.asarray([-2.0, -1.0, 0.0, 7.0], np.float32), "max": np.asarray([2.0, 1.0, 4.0, 7.0], np.float32),
        "q01": np.asarray([-1.5, -0.5, 0.5, 7.0], np.float32), "q99": np.asarray([1.5, 0.5, 3.0, 7.0], np.float32),
        "q10": np.asarray([-1.0, -0.25, 1.0, 7.0], np.float32), "q90": np.asarray([1.0, 0.25, 3.0, 7.0], np.float32),
    }  # fmt: skip
    features = {"observation.state": PolicyFeature("STATE", (4,)), "action": PolicyFeature("ACTION", (4,))}
    ranges = {"MIN_MAX": ("min", "max"), "QUANTILES": ("q01", "q99"), "QUANTILE10": ("q10", "q90")}
    for mode in ("MEAN_STD", "MIN_MAX", "QUANTILES", "QUANTILE10", "IDENTITY"):
        modes = {"STATE": mode, "ACTION": mode}
        forward = Normalizer(features, modes, {k: stats for k in features}, 1e-8, inverse=False)
        inverse = dataclasses.replace(forward, inverse=True)
        y = forward({"observation.state": x})["observation.state"]
        assert y.dtype == np.float32 and np.all(np.isfinite(y)), mode  # dim 3 has a zero range: guarded, no inf
        back = inverse({"actions": y})["actions"]
        np.testing.assert_allclose(back[:3], x[:3], rtol=1e-6, err_msg=mode)
        if mode in ranges:
            low, high = (stats[name] for name in ranges[mode])
            ends = forward({"observation.state": np.stack([low, high])})["observation.state"]
            np.testing.assert_allclose(ends[:, :3], [[-1] * 3, [1] * 3], atol=1e-6, err_msg=mode)
            assert ends[0, 3] == -1  # a zero range maps its value to -1, as LeRobot's epsilon does
        elif mode == "MEAN_STD":
            np.testing.assert_allclose(y[:3], ((x - stats["mean"])[:3] / stats["std"][:3]), rtol=1e-6)
        else:
            np.testing.assert_array_equal(y, x)


def test_relative_actions_add_the_raw_state_back_on_their_dims(tmp_path):
    d = cases(PI05)
    names = ["j0", "j1", "j2", "j3", "j4", "j5", "gripper"]
    folder = copy_folder(tmp_path)

    def enable(steps: list, relative: bool) -> None:
        step = next(s for s in steps if s["registry_name"].startswith("relative" if relative else "absolute"))
        step["config"].update(enabled=True, **({"action_names": names} if relative else {}))

    edit_json(folder / "policy_preprocessor.json", lambda p: enable(p["steps"], True))
    edit_json(folder / "policy_postprocessor.json", lambda p: enable(p["steps"], False))
    noise = d["case0/noise"][0]
    base = policy_of(PI05).infer(request(d), noise=noise)["actions"]
    relative = policy_of(folder).infer(request(d), noise=noise)["actions"]
    state = d["case0/input/observation.state"]
    mask = np.asarray([n != "gripper" for n in names])
    np.testing.assert_allclose(relative, base + np.where(mask, state[:7], 0), rtol=0, atol=1e-6)


def test_blank_cameras_are_masked_and_leave_the_chunk_unchanged(tmp_path):
    d = cases(PI05)
    folder = copy_folder(tmp_path)
    edit_json(folder / "config.json", lambda c: c.update(empty_cameras=1))
    noise = d["case0/noise"][0]
    policy = policy_of(folder)
    response, trace = policy.infer_traced(request(d), noise=noise)
    blank = "observation.images.empty_camera_0"
    assert policy.model.config.image_keys == (*CAMERAS, blank)  # LeRobot appends the cameras a batch lacks
    assert trace.camera_sources[blank] is None and trace.raw_images[blank] is None
    assert not bool(np.asarray(trace.observation.image_masks[blank])[0])
    np.testing.assert_array_equal(np.asarray(trace.observation.images[blank]), -1.0)
    # A masked camera is seen by no token and moves no position, so the chunk is the two-camera one.
    base = policy_of(PI05).infer(request(d), noise=noise)["actions"]
    np.testing.assert_allclose(response["actions"], base, rtol=0, atol=1e-6 * np.abs(base).max())


def test_a_renamed_camera_is_requested_under_its_old_name(tmp_path):
    d = cases(PI05)
    folder = copy_folder(tmp_path)
    rename = {"observation.images.front": CAMERAS[0]}
    edit_json(folder / "policy_preprocessor.json", lambda p: p["steps"][0]["config"].update(rename_map=rename))
    policy = policy_of(folder)
    assert policy.camera_sources == {CAMERAS[0]: "observation.images.front", CAMERAS[1]: CAMERAS[1]}
    obs = request(d)
    obs["observation.images.front"] = obs.pop(CAMERAS[0])
    noise = d["case0/noise"][0]
    np.testing.assert_array_equal(
        policy.infer(obs, noise=noise)["actions"], policy_of(PI05).infer(request(d), noise=noise)["actions"]
    )


def test_the_weights_read_are_lerobots_tensors():
    """The q projection of LeRobot's first layer is the model's (a mapping slip would show here before the chunks)."""
    policy = policy_of(PI05)
    q = read_tensor(PI05 / "model.safetensors", Q_PROJ)
    ours = np.asarray(policy.model.params["PaliGemma"]["llm"]["layers"]["attn"]["q_einsum"]["w"])[1]
    np.testing.assert_array_equal(ours, q.reshape(8, 16, 64).transpose(0, 2, 1))


def test_the_golden_command_takes_lerobot_folders(tmp_path, capsys):
    folder = copy_folder(tmp_path)
    edit_json(folder / "config.json", lambda c: c.update(type="pi052"))
    assert cli_golden.main(folder) == 1  # the LeRobot check ran, and refused the folder in one line
    assert "config.json: type 'pi052' is not served" in capsys.readouterr().out


def test_reliance_re_runs_a_lerobot_folder_with_its_own_preprocessor_and_postprocessor(tmp_path):
    """`cam.reliance`'s re-runs on a folder whose prompt is tokenised by LeRobot's preprocessor and whose actions go
    back through a relative-action postprocessor: the served call's actions come back exactly, and an emptied prompt
    is what serving the request without its task returns."""
    d = cases(PI05)
    folder = copy_folder(tmp_path)

    def enable(steps: list, relative: bool) -> None:
        step = next(s for s in steps if s["registry_name"].startswith("relative" if relative else "absolute"))
        step["config"].update(enabled=True, **({"action_names": [f"j{i}" for i in range(7)]} if relative else {}))

    edit_json(folder / "policy_preprocessor.json", lambda p: enable(p["steps"], True))
    edit_json(folder / "policy_postprocessor.json", lambda p: enable(p["steps"], False))
    policy, noise = policy_of(folder), d["case0/noise"][0]
    response, trace = policy.infer_traced(request(d), noise=noise)
    np.testing.assert_array_equal(policy.resample(trace, trace.observation), response["actions"])
    np.testing.assert_array_equal(policy.served_actions(trace), response["actions"])
    emptied = policy.with_prompt(trace, "")
    assert not np.array_equal(np.asarray(emptied.tokenized_prompt), np.asarray(trace.observation.tokenized_prompt))
    np.testing.assert_array_equal(np.asarray(emptied.state), np.asarray(trace.observation.state))
    without = policy.infer({**request(d), "prompt": ""}, noise=noise)["actions"]
    np.testing.assert_array_equal(policy.resample(trace, emptied), without)
