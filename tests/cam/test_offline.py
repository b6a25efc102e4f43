"""Offline Grad-CAM (`openpi-cam explain`): batched rows against the single-row engine, PolicyRecorder records and our
own run directories as sources, the step layout against the live side channel, resuming, data parallelism over two
forced host devices, and `CAMLogger.resume` after a crash.

Every test uses the real tiny upstream DROID policy with the hand-made well-formed generation swapped into its
traces (the random model never writes `Action: `). All explaining runs use batch size 2 so that they share one
compiled Grad-CAM program per target.
"""

from __future__ import annotations

import contextlib
import json
import os
import pathlib
import subprocess
import sys
import textwrap
from typing import Any

import numpy as np
import pytest
from fixed_generation import FixedGeneration
from openpi_cam.cam.batch_engine import explain_batch, stack_observations
from openpi_cam.cam.engine import CamSkipped, explain
from openpi_cam.cam.explain import (
    SOURCE_KEY,
    ExplainOptions,
    explain_cmd,
    explain_replays,
    iter_policy_records,
    iter_run_steps,
    record_observation,
)
from openpi_cam.cam.reader import load_run
from openpi_cam.cam.wrapper import CAMOptions, wrap_policy_with_cam
from paths import REPO_ROOT

from openpi_cam.cam.logger import CAMLogger, StepRecord
from openpi_cam.serving import RequestContext

REPO = REPO_ROOT
BATCH = 2


def _obs(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "observation/exterior_image_1_left": rng.integers(0, 256, (180, 320, 3), dtype=np.uint8),
        "observation/wrist_image_left": rng.integers(0, 256, (180, 320, 3), dtype=np.uint8),
        "observation/joint_position": rng.uniform(-1, 1, 7),
        "observation/gripper_position": rng.uniform(0, 1, 1),
        "prompt": "pick up the red block",
    }


def _record(folder: pathlib.Path, n: int, obs: dict, outputs: dict) -> None:
    # Upstream's PolicyRecorder layout: flax flatten_dict(sep="/") of {"inputs", "outputs"}, saved as an object array.
    flat = {f"inputs/{k}": v for k, v in obs.items()} | {f"outputs/{k}": v for k, v in outputs.items()}
    np.save(folder / f"step_{n}", np.asarray(flat))


def _records(folder: pathlib.Path, policy: Any, n: int) -> list[dict]:
    folder.mkdir()
    observations = [_obs(i) for i in range(n)]
    for i, obs in enumerate(observations):
        # cam_extra/ values ride along so that the produced run can itself be replayed.
        extra = {f"cam_extra/{k}": v for k, v in obs.items() if "position" in k}
        _record(folder, i, obs | extra, policy.infer(obs))
    return observations


def _new_logger(cam_dir: pathlib.Path) -> CAMLogger:
    return CAMLogger(cam_dir, run_config={}, checkpoint="tiny", options={"target": "action-token"})


@pytest.fixture(scope="module")
def golden_tokens(golden_dir) -> np.ndarray:
    return np.load(golden_dir / "tiny_policy_droid" / "droid_case.npz")["hand/generated_tokens"].astype(np.int32)


@pytest.fixture(scope="module")
def policy(tiny_droid_policy, golden_tokens):
    return FixedGeneration(tiny_droid_policy, golden_tokens)


def test_record_observation_reads_flat_and_nested_keys():
    record = {"inputs/images/cam_high": 1, "inputs/state": 2, "inputs/cam_extra/a/b": 3, "outputs/actions": 4}
    assert record_observation(record, nested=False) == {"images/cam_high": 1, "state": 2, "cam_extra/a/b": 3}
    # cam_extra/ keys stay flat: the side channel's prefix is matched on the flat key.
    assert record_observation(record, nested=True) == {"images": {"cam_high": 1}, "state": 2, "cam_extra/a/b": 3}


def test_batched_rows_equal_the_single_row_engine(policy, golden_tokens):
    """Two rows with different action-token counts, explained in one call, give each row's single-row result."""
    tok = policy.tokenizer
    steps = tok.action_token_steps(golden_tokens)
    assert len(steps) > 4
    short = golden_tokens.copy()
    short[steps[3] :] = 0  # the loop "stopped" after three action tokens (0 = what the decoder leaves)
    assert len(tok.action_token_steps(short)) == 3
    traces = [policy.inner.infer_traced(_obs(i))[1] for i in range(2)]
    obs = stack_observations([t.observation for t in traces])
    generated = np.stack([golden_tokens, short])
    for target, index in (("action-token", 2), ("chunk", 0)):
        rows = explain_batch(policy.model, tok, obs, generated, target=target, action_index=index)
        for b, trace in enumerate(traces):
            one = explain(policy.model, tok, trace.observation, generated[b], target=target, action_index=index)
            got = rows[b]
            assert not isinstance(got, CamSkipped)
            assert (got.token_ids, got.decode_steps, got.positions) == (one.token_ids, one.decode_steps, one.positions)
            assert got.action_indices == one.action_indices and got.cameras == one.cameras
            np.testing.assert_allclose(got.score, one.score, rtol=1e-4, atol=2e-3)
            for c, m in one.maps.items():
                assert got.maps[c].shape == m.shape
                # Measured max |diff| 3e-6 against maps peaking at 5e-3 .. 0.18 (batch shapes change float sums).
                np.testing.assert_allclose(got.maps[c], m, rtol=0, atol=1e-3 * np.abs(m).max())
                norms = one.gradnorm_maps[c]
                np.testing.assert_allclose(got.gradnorm_maps[c], norms, rtol=0, atol=1e-3 * norms.max())
        if target == "chunk":
            assert len(rows[1].decode_steps) == 3 and len(rows[0].decode_steps) == len(steps)
    # A row whose generation lacks the requested action token is answered with the engine's reason, not dropped.
    rows = explain_batch(policy.model, tok, obs, generated, target="action-token", action_index=4)
    assert not isinstance(rows[0], CamSkipped) and rows[0].action_indices == [4]
    assert isinstance(rows[1], CamSkipped) and rows[1].kind == "action_index_out_of_range"


def test_policy_records_become_a_cam_run_and_replay(policy, tmp_path):
    observations = _records(tmp_path / "records", policy, 3)
    cam_logger = _new_logger(tmp_path / "cam")
    options = ExplainOptions(save_frames="both", batch_size=BATCH)
    summary = explain_replays(policy, iter_policy_records(tmp_path / "records", False), options, cam_logger, mesh=None)
    cam_logger.close()
    assert summary["observations"] == 3 and summary["completed"] == 3
    assert summary["actions_compared"] == 3 and summary["actions_mismatched"] == 0
    run = load_run(cam_logger.run_dir)
    assert [(s.seq, s.meta["connection"], s.meta["step"]) for s in run.steps] == [(i, "records", i) for i in range(3)]
    for step, obs in zip(run.steps, observations, strict=True):
        assert step.meta["extra"][SOURCE_KEY] == f"step_{step.seq}.npy"
        np.testing.assert_allclose(step.meta["extra"]["observation/joint_position"], obs["observation/joint_position"])
        assert np.array_equal(step.frames["base_0_rgb"], obs["observation/exterior_image_1_left"])
        assert step.maps["base_0_rgb"].shape == tuple(step.meta["cameras"]["base_0_rgb"]["grid"])
        assert step.meta["cameras"]["base_0_rgb"]["geometry"]["pad_top"] == 49
        assert step.meta["cameras"]["base_0_rgb"]["obs_key"] == "observation/exterior_image_1_left"
    assert run.manifest["counters"]["external"]["completed"] == 3

    # (b) our own run directory, replayed: same frames, prompt and extras, so the same maps; the new steps name their
    # source step file and keep the extras (the new run is replayable in turn).
    logger2 = _new_logger(tmp_path / "cam2")
    explain_replays(policy, iter_run_steps(cam_logger.run_dir), options, logger2, mesh=None)
    logger2.close()
    run2 = load_run(logger2.run_dir)
    assert len(run2.steps) == 3
    for a, b in zip(run.steps, run2.steps, strict=True):
        assert b.meta["extra"][SOURCE_KEY] == f"steps/{a.seq:08d}.npz"
        assert b.meta["extra"]["observation/joint_position"] == a.meta["extra"]["observation/joint_position"]
        assert (b.meta["connection"], b.meta["step"], b.meta["prompt"]) == (
            a.meta["connection"],
            a.meta["step"],
            a.meta["prompt"],
        )
        for c in a.maps:
            np.testing.assert_allclose(a.maps[c], b.maps[c], rtol=1e-4, atol=1e-6)


def test_explained_steps_have_the_side_channel_layout(policy, tmp_path):
    """An offline step carries exactly the fields a live side-channel step carries, with the same values."""
    obs = _obs(7)
    cam = wrap_policy_with_cam(policy, CAMOptions(every_k=1, cam_dir=tmp_path / "live", save_frames="both"))
    cam.infer(obs, RequestContext("c0", 0))
    cam.close(timeout=None)
    live = load_run(cam.run_dir).steps[0]

    folder = tmp_path / "records"
    folder.mkdir()
    _record(folder, 0, obs, {})
    cam_logger = _new_logger(tmp_path / "offline")
    explain_replays(policy, iter_policy_records(folder, False), ExplainOptions(batch_size=BATCH), cam_logger, mesh=None)
    cam_logger.close()
    offline = load_run(cam_logger.run_dir).steps[0]

    assert set(offline.meta) == set(live.meta)
    skip = {"gradcam_ms", "extra", "run_id", "timestamp", "connection", "score"}
    assert {k: v for k, v in offline.meta.items() if k not in skip} == {
        k: v for k, v in live.meta.items() if k not in skip
    }
    assert offline.meta["score"] == pytest.approx(live.meta["score"], abs=2e-3)
    assert set(offline.maps) == set(live.maps) and set(offline.frames) == set(live.frames)
    assert set(offline.model_frames) == set(live.model_frames)
    for c, m in live.maps.items():
        np.testing.assert_allclose(offline.maps[c], m, rtol=0, atol=1e-3 * np.abs(m).max())


def test_resume_explains_only_the_rest(policy, tmp_path):
    _records(tmp_path / "records", policy, 5)
    records = tmp_path / "records"
    first = _new_logger(tmp_path / "cam")
    s1 = explain_replays(
        policy, iter_policy_records(records, False), ExplainOptions(batch_size=BATCH, limit=2), first, mesh=None
    )
    first.close()
    assert s1["completed"] == 2 and len(load_run(first.run_dir).steps) == 2

    resumed = CAMLogger.resume(first.run_dir)
    s2 = explain_replays(
        policy, iter_policy_records(records, False), ExplainOptions(batch_size=BATCH), resumed, mesh=None
    )
    resumed.close()
    assert s2["completed"] == 3 and s2["already_explained"] == 2 and s2["observations"] == 3

    run = load_run(first.run_dir)
    assert [s.seq for s in run.steps] == [0, 1, 2, 3, 4]
    sources = [s.meta["extra"][SOURCE_KEY] for s in run.steps]
    assert sorted(sources) == [f"step_{i}.npy" for i in range(5)]
    assert [s.meta["step"] for s in run.steps] == [0, 1, 2, 3, 4]
    manifest = json.loads((first.run_dir / "manifest.json").read_text())
    assert manifest["closed"] and manifest["num_steps"] == 5 and len(manifest["resumed_at"]) == 1
    assert [e["seq"] for e in manifest["steps"]] == [0, 1, 2, 3, 4]
    assert manifest["counters"]["logger"]["steps_logged"] == 5
    lines = (first.run_dir / "index.jsonl").read_text().splitlines()
    assert [json.loads(line)["seq"] for line in lines] == [0, 1, 2, 3, 4]

    # Nothing left: a third pass explains nothing and writes nothing.
    again = CAMLogger.resume(first.run_dir)
    s3 = explain_replays(
        policy, iter_policy_records(records, False), ExplainOptions(batch_size=BATCH), again, mesh=None
    )
    again.close()
    assert s3["observations"] == 0 and s3["already_explained"] == 5
    assert len(load_run(first.run_dir).steps) == 5


def test_explain_cmd_refuses_to_resume_a_run_with_other_settings(tmp_path, tiny_policy_files, capsys):
    records = tmp_path / "records"
    records.mkdir()
    _record(records, 0, _obs(0), {})
    cam_logger = CAMLogger(
        tmp_path / "cam",
        run_config={"config": "pi0_fast_droid", "checkpoint_dir": str(tiny_policy_files.checkpoint.resolve())},
        checkpoint="x",
        options={"target": "chunk", "action_index": 0},
    )
    cam_logger.close()
    rc = explain_cmd(records, checkpoint_dir=tiny_policy_files.checkpoint, out=cam_logger.run_dir, dtype="float32")
    assert rc == 2
    err = capsys.readouterr().err
    assert "cannot resume" in err and "target: 'chunk' != 'action-token'" in err
    assert load_run(cam_logger.run_dir).steps == []


def _record_for(i: int) -> StepRecord:
    maps = {"base_0_rgb": np.full((4, 4), float(i), np.float32)}
    return StepRecord("c0", i, 1.0 + i, maps, meta={"target": "chunk"})


def test_logger_resume_after_a_crash_continues_seq_and_repairs_the_index(tmp_path):
    cam_logger = CAMLogger(tmp_path, run_config={"a": 1}, checkpoint="ck", options={}, manifest_every=100)
    for i in range(3):
        assert cam_logger.log_step(_record_for(i))
    run_dir = cam_logger.run_dir
    # A kill -9 mid-append: no final manifest, index cut short, a stray temporary file, an unreadable last step.
    os.close(cam_logger._index_fd)
    index = run_dir / "index.jsonl"
    index.write_bytes(index.read_bytes()[:-7])
    (run_dir / "steps" / "00000003.npz").write_bytes(b"not a zip")
    (run_dir / "steps" / "00000004.npz.123-ab.tmp").write_bytes(b"partial")
    assert not (run_dir / "manifest.json").exists()
    run_json = (run_dir / "run.json").read_text()

    resumed = CAMLogger.resume(run_dir, max_steps=5)
    assert resumed.run_id == run_dir.name and resumed.counters["steps_logged"] == 3
    assert resumed.log_step(_record_for(10))  # seq 4: the unreadable 00000003.npz is never overwritten
    assert resumed.log_step(_record_for(11))
    assert not resumed.log_step(_record_for(12))  # max_steps counts the whole run
    resumed.close()

    assert (run_dir / "steps" / "00000003.npz").read_bytes() == b"not a zip"
    assert (run_dir / "run.json").read_text() == run_json
    run = load_run(run_dir)
    assert [s.seq for s in run.steps] == [0, 1, 2, 4, 5]
    assert [s.meta["step"] for s in run.steps] == [0, 1, 2, 10, 11]
    assert all(s.meta["run_id"] == run_dir.name for s in run.steps)
    manifest = json.loads((run_dir / "manifest.json").read_text())
    assert [e["seq"] for e in manifest["steps"]] == [0, 1, 2, 4, 5] and manifest["closed"]
    assert manifest["counters"]["logger"]["steps_skipped_cap"] == 1
    # The cut line stays unparseable, but the next line starts on its own line.
    parsed = []
    for line in index.read_text().splitlines():
        with contextlib.suppress(ValueError):
            parsed.append(json.loads(line)["seq"])
    assert parsed == [0, 1, 4, 5]


def test_logger_resume_rejects_a_directory_that_is_not_a_run(tmp_path):
    with pytest.raises(FileNotFoundError):
        CAMLogger.resume(tmp_path)


_DATA_PARALLEL = textwrap.dedent(
    """
    import dataclasses, pathlib, sys
    import jax, numpy as np
    from openpi_cam.cam.batch_engine import data_mesh, explain_batch, replicate_model, shard_batch, stack_observations
    from openpi_cam.policies.policy import create_policy

    root = pathlib.Path(sys.argv[1])
    policy = create_policy("pi0_fast_droid", root / "checkpoint", dtype="float32",
                           paligemma_tokenizer=root / "paligemma_tokenizer_tiny.model",
                           fast_tokenizer=root / "fast_tokenizer")
    tokens = np.load(root / "droid_case.npz")["hand/generated_tokens"].astype(np.int32)
    rng = np.random.default_rng(0)
    traces = []
    for _ in range(3):  # 3 rows over 2 devices: one padding row
        obs = {"observation/exterior_image_1_left": rng.integers(0, 256, (180, 320, 3), dtype=np.uint8),
               "observation/wrist_image_left": rng.integers(0, 256, (180, 320, 3), dtype=np.uint8),
               "observation/joint_position": rng.uniform(-1, 1, 7),
               "observation/gripper_position": rng.uniform(0, 1, 1),
               "prompt": "pick up the red block"}
        traces.append(policy.infer_traced(obs)[1])
    batch = stack_observations([t.observation for t in traces])
    generated = np.stack([tokens] * 3)
    mesh = data_mesh()
    sharded, rows = shard_batch(batch, mesh)
    out = {"devices": len(jax.devices()), "padded_rows": rows,
           "state_devices": len(sharded.state.sharding.device_set)}
    for name, m in (("spmd", mesh), ("single", None)):
        model = replicate_model(policy.model, m)
        for b, e in enumerate(explain_batch(model, policy.tokenizer, batch, generated, target="action-token", mesh=m)):
            out.update({f"{name}/{b}/{c}": v for c, v in e.maps.items()})
            out[f"{name}/{b}/score"] = np.float64(e.score)
    np.savez(sys.argv[2], **out)
    """
)


def test_data_parallel_over_two_host_devices_matches_one_device(golden_dir, tmp_path):
    script, result = tmp_path / "dp.py", tmp_path / "dp.npz"
    script.write_text(_DATA_PARALLEL)
    env = os.environ | {"XLA_FLAGS": "--xla_force_host_platform_device_count=2", "JAX_PLATFORMS": "cpu"}
    proc = subprocess.run(
        [sys.executable, str(script), str(golden_dir / "tiny_policy_droid"), str(result)],
        env=env,
        capture_output=True,
        text=True,
        timeout=900,
        cwd=REPO,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = np.load(result)
    assert int(out["devices"]) == 2 and int(out["state_devices"]) == 2 and int(out["padded_rows"]) == 4
    keys = [k.split("/", 1)[1] for k in out.files if k.startswith("single/")]
    assert len(keys) == 3 * 4  # 3 rows x (3 DROID model cameras, one of them masked + score)
    for k in keys:
        spmd, single = out[f"spmd/{k}"], out[f"single/{k}"]
        if k.endswith("score"):
            # Measured |diff| 3.5e-5; README's logit tolerance is 2e-3.
            assert abs(float(spmd) - float(single)) < 2e-3
        else:
            # Measured max |diff| 9e-7 on maps peaking at 5e-3 .. 3e-2 (1.8e-4 of the max).
            assert spmd.shape == single.shape and (np.abs(single).max() > 0 or "base_1" in k)
            np.testing.assert_allclose(spmd, single, rtol=0, atol=1e-3 * np.abs(single).max())
