"""Offline Grad-CAM (`openpi-cam explain`) over upstream PolicyRecorder records and over our own run directories."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest

from openpi_cam.cam.explain import explain_replays, iter_policy_records, iter_run_steps, unflatten
from openpi_cam.cam.reader import load_run
from openpi_cam.cam.wrapper import CAMOptions


class FixedGeneration:
    """The real tiny policy whose traces carry a well-formed generation (the random model emits no action tokens)."""

    def __init__(self, policy: Any, tokens: np.ndarray):
        self.inner, self.tokens = policy, np.asarray(tokens, np.int32)

    model = property(lambda self: self.inner.model)
    tokenizer = property(lambda self: self.inner.tokenizer)
    metadata = property(lambda self: self.inner.metadata)

    def infer(self, obs, context=None):
        return self.inner.infer(obs, context)

    def infer_traced(self, obs):
        response, trace = self.inner.infer_traced(obs)
        return response, dataclasses.replace(trace, generated_tokens=self.tokens)

    def stats(self):
        return self.inner.stats()

    def close(self, timeout=None):
        pass


def _obs(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "observation/exterior_image_1_left": rng.integers(0, 256, (180, 320, 3), dtype=np.uint8),
        "observation/wrist_image_left": rng.integers(0, 256, (180, 320, 3), dtype=np.uint8),
        "observation/joint_position": rng.uniform(-1, 1, 7),
        "observation/gripper_position": rng.uniform(0, 1, 1),
        "prompt": "pick up the red block",
    }


def _record(folder, n: int, obs: dict, outputs: dict) -> None:
    # Upstream's PolicyRecorder layout: flax flatten_dict(sep="/") of {"inputs", "outputs"}, saved as an object array.
    flat = {f"inputs/{k}": v for k, v in obs.items()} | {f"outputs/{k}": v for k, v in outputs.items()}
    np.save(folder / f"step_{n}", np.asarray(flat))


def test_unflatten_nests_every_separator():
    assert unflatten({"images/cam_high": 1, "state": 2, "a/b/c": 3}) == {
        "images": {"cam_high": 1},
        "state": 2,
        "a": {"b": {"c": 3}},
    }


@pytest.fixture(scope="module")
def policy(tiny_droid_policy, golden_dir):
    tokens = np.load(golden_dir / "tiny_policy_droid" / "droid_case.npz")["hand/generated_tokens"]
    return FixedGeneration(tiny_droid_policy, tokens)


def test_policy_records_become_a_cam_run(policy, tmp_path):
    records = tmp_path / "policy_records"
    records.mkdir()
    observations = [_obs(i) for i in range(3)]
    for i, obs in enumerate(observations):
        # cam_extra/ values ride along so that the produced run can itself be replayed below.
        extra = {f"cam_extra/{k}": v for k, v in obs.items() if "position" in k}
        _record(records, i, obs | extra, policy.infer(obs))
    options = CAMOptions(every_k=1, cam_dir=tmp_path / "cam", save_frames="both", queue_size=2)
    run_dir, summary = explain_replays(
        policy, iter_policy_records(records, nested=False), options, run_config={}, checkpoint="tiny"
    )
    assert summary["observations"] == 3 and summary["actions_compared"] == 3 and summary["actions_mismatched"] == 0
    assert summary.get("completed") == 3
    run = load_run(run_dir)
    assert [s.meta["step"] for s in run.steps] == [0, 1, 2]
    for step, obs in zip(run.steps, observations, strict=True):
        assert np.array_equal(step.frames["base_0_rgb"], obs["observation/exterior_image_1_left"])
        assert step.maps["base_0_rgb"].shape == tuple(step.meta["cameras"]["base_0_rgb"]["grid"])
        assert step.meta["cameras"]["base_0_rgb"]["geometry"]["pad_top"] == 49

    # (b) our own run directory, replayed: same frames, same prompt, same maps.
    options2 = dataclasses.replace(options, cam_dir=tmp_path / "cam2")
    run_dir2, summary2 = explain_replays(policy, iter_run_steps(run_dir), options2, run_config={}, checkpoint="tiny")
    assert summary2["completed"] == 3
    for a, b in zip(run.steps, load_run(run_dir2).steps, strict=True):
        for c in a.maps:
            np.testing.assert_allclose(a.maps[c], b.maps[c], rtol=1e-4, atol=1e-6)
