"""Offline explanation (`openpi-cam explain`): batched rows against single rows, PolicyRecorder records and our own
run directories as sources, the replay check of the recorded actions (and the command's exit code on a mismatch), the
step layout against the live side channel, resuming, data parallelism over two forced host devices, and
`CAMLogger.resume` after a crash.

Everything runs on the bundled demo policy, whose actions depend on the observation, so a replay that compared the
wrong record's actions cannot pass. Explaining runs use batch size 2 so that they share one compiled program.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import pathlib
import subprocess
import sys
import textwrap
from typing import Any

import lerobot_cases
import numpy as np
import pytest
from cam_support import assert_pairwise_different, demo_obs, policy_part
from one_line import assert_one_line
from paths import REPO_ROOT

from openpi_cam import cli
from openpi_cam.cam.batching import explain_traces
from openpi_cam.cam.faithfulness_run import step_model_inputs
from openpi_cam.cam.logger import CAMLogger
from openpi_cam.cam.offline import (
    SOURCE_KEY,
    ReplayOptions,
    explain_replays,
    iter_policy_records,
    iter_run_steps,
    record_observation,
)
from openpi_cam.cam.run_format import IMAGE_INPUT, StepRecord, load_run
from openpi_cam.cam.side_channel import CAMOptions, wrap_policy_with_cam
from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.cli import explain_run
from openpi_cam.cli.options import ExplainFlags
from openpi_cam.errors import BadFile
from openpi_cam.policies import demo_reach
from openpi_cam.policies.family import ExplainSkipped, Explanation
from openpi_cam.policies.libero import make_libero_example
from openpi_cam.serving import RequestContext
from openpi_cam.vocabulary import ONE_PASS_KINDS as ONE_PASS
from openpi_cam.vocabulary import ExplainOptions

REPO = REPO_ROOT
BATCH = 2
STATE_KEY = "observation/state"
# `openpi-cam explain` arguments that load the bundled demo model.
DEMO_MODEL_ARGS = [
    "--checkpoint-dir",
    str(demo_reach.CHECKPOINT),
    "--config",
    "demo_reach",
    "--paligemma-tokenizer",
    str(demo_reach.PALIGEMMA_TOKENIZER),
    "--fast-tokenizer",
    str(demo_reach.FAST_TOKENIZER),
    "--dtype",
    "float32",
]


def _record(folder: pathlib.Path, n: int, obs: dict, outputs: dict) -> None:
    # Upstream's PolicyRecorder layout: flax flatten_dict(sep="/") of {"inputs", "outputs"}, saved as an object array.
    flat = {f"inputs/{k}": v for k, v in obs.items()} | {f"outputs/{k}": v for k, v in outputs.items()}
    np.save(folder / f"step_{n}", np.asarray(flat))


def _records(folder: pathlib.Path, policy: Any, n: int, *, seed: int = 0, shift: int = 0) -> list[dict]:
    """n demo observations recorded with the actions the policy returns for them; `shift` records each with the
    actions of the observation `shift` places on instead (a recorder that paired requests and responses wrongly)."""
    folder.mkdir()
    observations = [demo_obs(seed + i) for i in range(n)]
    outputs = [policy.infer(policy_part(o)) for o in observations]
    assert_pairwise_different([o["actions"] for o in outputs])
    for i, obs in enumerate(observations):
        # The state rides along as a cam_extra/ value so that the produced run can itself be replayed.
        _record(folder, i, obs | {f"cam_extra/{STATE_KEY}": obs[STATE_KEY]}, outputs[(i + shift) % n])
    return observations


def _new_logger(cam_dir: pathlib.Path) -> CAMLogger:
    return CAMLogger(cam_dir, run_config={}, checkpoint="demo", options={"target": "action-token"})


def _assert_maps_close(got: dict[str, np.ndarray], want: dict[str, np.ndarray], what: str) -> None:
    """One kind's maps (camera -> map) of the same inputs computed in batches of different sizes, i.e. float sums in
    another order. Measured on the demo model: at most 2.7e-5 of the camera's own peak (chunk target, a row padded
    with a shorter generation), 2e-6 for one action token. The bound, 1e-4 of the step's peak over cameras (the
    scale render normalises by; a Grad-CAM map can be all zero after its ReLU), is far below the differences
    between rows."""
    assert set(got) == set(want), what
    scale = max(float(np.abs(m).max()) for m in want.values())
    assert scale > 0, what
    for c, m in want.items():
        assert got[c].shape == m.shape, f"{what} {c}"
        np.testing.assert_allclose(got[c], m, rtol=0, atol=1e-4 * scale, err_msg=f"{what} {c}")


def test_record_observation_reads_flat_and_nested_keys():
    record = {"inputs/images/cam_high": 1, "inputs/state": 2, "inputs/cam_extra/a/b": 3, "outputs/actions": 4}
    assert record_observation(record, nested=False) == {"images/cam_high": 1, "state": 2, "cam_extra/a/b": 3}
    # cam_extra/ keys stay flat: the side channel's prefix is matched on the flat key.
    assert record_observation(record, nested=True) == {"images": {"cam_high": 1}, "state": 2, "cam_extra/a/b": 3}


@pytest.mark.slow
def test_batched_rows_equal_single_rows(demo_policy):
    """Two rows with different observations and action-token counts, explained in one call, give each row's result
    explained alone (rows neither mix nor swap)."""
    explainer = demo_policy.explainer
    traces = [demo_policy.infer_traced(policy_part(demo_obs(10 + i)))[1] for i in range(2)]
    steps = explainer.tokenizer.action_token_steps(traces[1].output)
    assert len(steps) > 4
    short = np.asarray(traces[1].output).copy()
    short[steps[3] :] = 0  # the loop "stopped" after three action tokens (0 = what the decoder leaves)
    traces[1] = dataclasses.replace(traces[1], output=short)
    assert len(explainer.tokenizer.action_token_steps(short)) == 3
    for target, index in (("action-token", 2), ("chunk", 0)):
        request = ExplainOptions(target, index, maps=ONE_PASS)
        rows = explain_traces(explainer, traces, request)
        alone = [explain_traces(explainer, [t], request)[0] for t in traces]
        for b, (got, one) in enumerate(zip(rows, alone, strict=True)):
            assert isinstance(got, Explanation) and isinstance(one, Explanation)
            assert got.target == one.target == target and got.details == one.details and got.cameras == one.cameras
            assert got.score == pytest.approx(one.score, rel=1e-4)
            for kind, maps in one.maps.items():
                _assert_maps_close(got.maps[kind], maps, f"{target} row {b} {kind}")
        # the two rows' maps differ, so a swap of rows could not pass the comparison above
        assert not np.allclose(rows[0].maps["gradnorm"]["base_0_rgb"], rows[1].maps["gradnorm"]["base_0_rgb"])
        if target == "chunk":
            assert len(rows[1].details["decode_steps"]) == 3 and len(rows[0].details["decode_steps"]) == 20
    # A row whose generation lacks the requested action token is answered with the reason, not dropped.
    rows = explain_traces(explainer, traces, ExplainOptions("action-token", 4, maps=ONE_PASS))
    assert isinstance(rows[0], Explanation) and rows[0].details["action_indices"] == [4]
    assert isinstance(rows[1], ExplainSkipped) and rows[1].reason == "action_index_out_of_range"


def test_policy_records_become_a_cam_run_and_replay(demo_policy, tmp_path):
    observations = _records(tmp_path / "records", demo_policy, 3)
    cam_logger = _new_logger(tmp_path / "cam")
    options = ReplayOptions(save_frames="both", batch_size=BATCH, maps=ONE_PASS)
    summary = explain_replays(
        demo_policy, iter_policy_records(tmp_path / "records", False), options, cam_logger, mesh=None
    )
    cam_logger.close()
    # The replay check: each record's actions are the ones the policy returns for that record's observation.
    assert summary["observations"] == 3 and summary["completed"] == 3
    assert summary["actions_compared"] == 3 and summary["actions_mismatched"] == 0
    run = load_run(cam_logger.run_dir)
    assert [(s.seq, s.meta.connection, s.meta.step) for s in run.steps] == [(i, "records", i) for i in range(3)]
    for step, obs in zip(run.steps, observations, strict=True):
        assert step.meta.extra[SOURCE_KEY] == f"step_{step.seq}.npy"
        np.testing.assert_array_equal(step.extra[STATE_KEY], obs[STATE_KEY])  # an array, stored as one
        np.testing.assert_array_equal(step.frames["base_0_rgb"], obs["observation/image"])
        np.testing.assert_array_equal(step.frames["wrist_0_rgb"], obs["observation/wrist_image"])
        assert step.maps_of("gradcam")["base_0_rgb"].shape == step.meta.cameras["base_0_rgb"].grid
        assert step.meta.cameras["base_0_rgb"].obs_key == "observation/image"
        assert step.meta.prompt == obs["prompt"]
    assert run.manifest["counters"]["external"]["completed"] == 3

    # Our own run directory, replayed: same frames, prompt and extras, so the same maps; the new steps name their
    # source step file and keep the extras (the new run is replayable in turn).
    logger2 = _new_logger(tmp_path / "cam2")
    explain_replays(demo_policy, iter_run_steps(cam_logger.run_dir), options, logger2, mesh=None)
    logger2.close()
    run2 = load_run(logger2.run_dir)
    assert len(run2.steps) == 3
    for a, b in zip(run.steps, run2.steps, strict=True):
        assert b.meta.extra[SOURCE_KEY] == f"steps/{a.seq:08d}.npz"
        np.testing.assert_array_equal(b.extra[STATE_KEY], a.extra[STATE_KEY])
        assert (b.meta.connection, b.meta.step, b.meta.prompt) == (
            a.meta.connection,
            a.meta.step,
            a.meta.prompt,
        )
        np.testing.assert_array_equal(b.inputs["output"], a.inputs["output"])
        for kind in ("gradcam", "gradnorm"):
            for c, m in a.maps_of(kind).items():
                np.testing.assert_array_equal(b.maps_of(kind)[c], m)


def test_replay_check_counts_records_whose_actions_are_another_requests(demo_policy, tmp_path):
    """Records paired with the next observation's response (all actions differ): every one is a mismatch."""
    _records(tmp_path / "records", demo_policy, 3, seed=20, shift=1)
    cam_logger = _new_logger(tmp_path / "cam")
    options = ReplayOptions(save_frames="none", batch_size=BATCH, maps=ONE_PASS)
    summary = explain_replays(
        demo_policy, iter_policy_records(tmp_path / "records", False), options, cam_logger, mesh=None
    )
    cam_logger.close()
    assert summary["actions_compared"] == 3 and summary["actions_mismatched"] == 3


def _explain_argv(source: pathlib.Path, out: pathlib.Path) -> list[str]:
    return ["explain", str(source), *DEMO_MODEL_ARGS, "--out", str(out), "--batch-size", "1", "--no-progress"]


@pytest.mark.slow
def test_explain_command_exit_codes_follow_the_replay_check(demo_policy, tmp_path):
    """`openpi-cam explain` exits 3 when a re-run inference returns other actions than recorded, 0 when they agree.
    The mismatching case runs as a user would (`python -m openpi_cam`, a fresh process)."""
    _records(tmp_path / "bad", demo_policy, 2, seed=33, shift=1)
    env = os.environ | {"PYTHONPATH": os.pathsep.join([str(REPO / "src"), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run(
        [sys.executable, "-m", "openpi_cam", *_explain_argv(tmp_path / "bad", tmp_path / "out_bad")],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
        cwd=tmp_path,
    )
    assert proc.returncode == 3, proc.stderr[-3000:]
    (bad_run,) = (tmp_path / "out_bad").iterdir()
    assert len(load_run(bad_run).steps) == 2  # the maps are written all the same
    assert "'actions_mismatched': 2" in proc.stderr

    _records(tmp_path / "good", demo_policy, 2, seed=33)
    cli.main(_explain_argv(tmp_path / "good", tmp_path / "out_good"))  # exit 0: no SystemExit
    (good_run,) = (tmp_path / "out_good").iterdir()
    summary = load_run(good_run).manifest["counters"]["external"]
    assert summary["actions_compared"] == 2 and summary["actions_mismatched"] == 0


def test_explained_steps_have_the_side_channel_layout(demo_policy, tmp_path):
    """An offline step carries exactly the fields a live side-channel step carries, with the same values."""
    obs = demo_obs(7)
    live = CAMOptions(maps=ONE_PASS, every_k=1, dir=tmp_path / "live", save_frames="both")
    cam = wrap_policy_with_cam(demo_policy, live)
    cam.infer(obs, RequestContext("c0", 0))
    cam.close(timeout=None)
    live = load_run(cam.run_dir).steps[0]

    folder = tmp_path / "records"
    folder.mkdir()
    _record(folder, 0, obs, {})
    cam_logger = _new_logger(tmp_path / "offline")
    explain_replays(
        demo_policy,
        iter_policy_records(folder, False),
        ReplayOptions(batch_size=BATCH, maps=ONE_PASS),
        cam_logger,
        mesh=None,
    )
    cam_logger.close()
    offline = load_run(cam_logger.run_dir).steps[0]

    offline_json, live_json = offline.meta.to_json(), live.meta.to_json()  # every field, as stored
    assert set(offline_json) == set(live_json)
    skip = {"explain_ms", "extra", "run_id", "timestamp", "connection", "score"}
    assert {k: v for k, v in offline_json.items() if k not in skip} == {
        k: v for k, v in live_json.items() if k not in skip
    }
    assert offline.meta.extra == live.meta.extra | {SOURCE_KEY: "step_0.npy"}
    assert offline.meta.score == pytest.approx(live.meta.score, rel=1e-4)
    assert offline.map_kinds == live.map_kinds and set(offline.frames) == set(live.frames)
    assert set(offline.model_frames) == set(live.model_frames) and set(offline.inputs) == set(live.inputs)
    for name, value in live.inputs.items():
        np.testing.assert_array_equal(offline.inputs[name], value)
    for kind in live.map_kinds:
        _assert_maps_close(offline.maps_of(kind), live.maps_of(kind), kind)


def test_resume_explains_only_the_rest(demo_policy, tmp_path):
    _records(tmp_path / "records", demo_policy, 5, seed=40)
    records = tmp_path / "records"
    first = _new_logger(tmp_path / "cam")
    s1 = explain_replays(
        demo_policy,
        iter_policy_records(records, False),
        ReplayOptions(batch_size=BATCH, max_steps=2, maps=ONE_PASS),
        first,
        mesh=None,
    )
    first.close()
    assert s1["completed"] == 2 and len(load_run(first.run_dir).steps) == 2

    resumed = CAMLogger.resume(first.run_dir)
    s2 = explain_replays(
        demo_policy,
        iter_policy_records(records, False),
        ReplayOptions(batch_size=BATCH, maps=ONE_PASS),
        resumed,
        mesh=None,
    )
    resumed.close()
    assert s2["completed"] == 3 and s2["already_explained"] == 2 and s2["observations"] == 3
    assert s2["actions_compared"] == 3 and s2["actions_mismatched"] == 0

    run = load_run(first.run_dir)
    assert [s.seq for s in run.steps] == [0, 1, 2, 3, 4]
    sources = [s.meta.extra[SOURCE_KEY] for s in run.steps]
    assert sources == [f"step_{i}.npy" for i in range(5)]
    assert [s.meta.step for s in run.steps] == [0, 1, 2, 3, 4]
    manifest = json.loads((first.run_dir / "manifest.json").read_text())
    assert manifest["closed"] and manifest["num_steps"] == 5 and len(manifest["resumed_at"]) == 1
    assert [e["seq"] for e in manifest["steps"]] == [0, 1, 2, 3, 4]
    assert manifest["counters"]["logger"]["steps_logged"] == 5
    lines = (first.run_dir / "index.jsonl").read_text().splitlines()
    assert [json.loads(line)["seq"] for line in lines] == [0, 1, 2, 3, 4]

    # Nothing left: a third pass explains nothing and writes nothing.
    again = CAMLogger.resume(first.run_dir)
    s3 = explain_replays(
        demo_policy,
        iter_policy_records(records, False),
        ReplayOptions(batch_size=BATCH, maps=ONE_PASS),
        again,
        mesh=None,
    )
    again.close()
    assert s3["observations"] == 0 and s3["already_explained"] == 5
    assert len(load_run(first.run_dir).steps) == 5


def test_explain_command_refuses_to_resume_a_run_with_other_settings(tmp_path, capsys):
    records = tmp_path / "records"
    records.mkdir()
    _record(records, 0, demo_obs(0), {})
    cam_logger = CAMLogger(
        tmp_path / "cam",
        run_config={"config": "demo_reach", "checkpoint_dir": str(demo_reach.CHECKPOINT.resolve())},
        checkpoint="x",
        options={"target": "chunk", "action_index": 0},
    )
    cam_logger.close()
    model = ModelSpec(checkpoint_dir=demo_reach.CHECKPOINT, config="demo_reach", dtype="float32")
    rc = explain_run.main(records, model=model, out=cam_logger.run_dir, progress=False)
    assert rc == 2
    err = capsys.readouterr().err
    assert "cannot resume" in err and "target: 'chunk' != 'action-token'" in err
    assert load_run(cam_logger.run_dir).steps == []


def _record_for(i: int) -> StepRecord:
    maps = {"gradcam": {"base_0_rgb": np.full((4, 4), float(i), np.float32)}}
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
    with pytest.raises(BadFile) as refused:  # read as a run, the unreadable step is named
        load_run(run_dir)
    assert_one_line(refused.value, "00000003.npz", "not a readable step file")
    run = load_run(run_dir, skip_unreadable=True)
    (problem,) = run.problems
    assert problem.startswith("steps/00000003.npz: not a readable step file (") and "\n" not in problem
    assert [s.seq for s in run.steps] == [0, 1, 2, 4, 5]
    assert [s.meta.step for s in run.steps] == [0, 1, 2, 10, 11]
    assert all(s.meta.run_id == run_dir.name for s in run.steps)
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
    import sys
    sys.path[:0] = sys.argv[2:4]
    import jax, numpy as np
    from cam_support import demo_obs, policy_part
    from openpi_cam.cam.batching import data_mesh, explain_traces, shard_batch
    from openpi_cam.model.observation import stack_observations
    from openpi_cam.checkpoints import model_spec
    from openpi_cam.vocabulary import ExplainOptions

    policy = model_spec.create_demo_policy()
    traces = [policy.infer_traced(policy_part(demo_obs(50 + i)))[1] for i in range(3)]  # 3 rows on 2 devices
    mesh = data_mesh()
    sharded, rows = shard_batch(stack_observations([t.observation for t in traces]), mesh)
    out = {"devices": len(jax.devices()), "padded_rows": rows, "state_devices": len(sharded.state.sharding.device_set)}
    request = ExplainOptions("action-token", 2, maps=("gradcam", "gradnorm"))
    for name, m in (("spmd", mesh), ("single", None)):
        for b, e in enumerate(explain_traces(policy.explainer.on_mesh(m), traces, request, mesh=m)):
            out.update({f"{name}/{b}/{k}/{c}": v for k, maps in e.maps.items() for c, v in maps.items()})
            out[f"{name}/{b}/score"] = np.float64(e.score)
    np.savez(sys.argv[1], **out)
    """
)


@pytest.mark.slow
def test_data_parallel_over_two_host_devices_matches_one_device(tmp_path):
    result = tmp_path / "dp.npz"
    env = os.environ | {
        "XLA_FLAGS": "--xla_force_host_platform_device_count=2",
        "JAX_PLATFORMS": "cpu",
        "PYTHONPATH": os.pathsep.join([str(REPO / "src"), os.environ.get("PYTHONPATH", "")]),
    }
    proc = subprocess.run(
        [
            sys.executable,
            "-c",
            _DATA_PARALLEL,
            str(result),
            str(pathlib.Path(__file__).parent),
            str(REPO / "tests" / "support"),
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        cwd=REPO,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = np.load(result)
    assert int(out["devices"]) == 2 and int(out["state_devices"]) == 2 and int(out["padded_rows"]) == 4
    keys = [k.split("/", 1)[1] for k in out.files if k.startswith("single/")]
    assert len(keys) == 3 * (2 * 2 + 1)  # 3 rows x (2 kinds x 2 cameras + score)
    cameras = ("base_0_rgb", "wrist_0_rgb")
    for b in range(3):
        # Measured: scores 2e-7 relative, maps 5e-6 of their peak (a sharded batch of 4 against one of 3).
        assert float(out[f"spmd/{b}/score"]) == pytest.approx(float(out[f"single/{b}/score"]), rel=1e-5)
        for kind in ("gradcam", "gradnorm"):
            spmd = {c: out[f"spmd/{b}/{kind}/{c}"] for c in cameras}
            single = {c: out[f"single/{b}/{kind}/{c}"] for c in cameras}
            _assert_maps_close(spmd, single, f"row {b} {kind}")
    rows = [out[f"single/{b}/gradnorm/base_0_rgb"] for b in range(3)]
    assert not np.allclose(rows[0], rows[1]) and not np.allclose(rows[1], rows[2])  # rows cannot be swapped unseen


def _served_run(policy: Any, observations: list[dict], cam_dir: pathlib.Path, run_config: dict) -> pathlib.Path:
    """A run the side channel wrote while serving `observations` (raw frames kept), with their responses."""
    cam = wrap_policy_with_cam(policy, CAMOptions(every_k=1, dir=cam_dir, save_frames="both", maps=("gradnorm",),
                                                  check_patches=0), run_config=run_config)  # fmt: skip
    actions = [cam.infer(obs, RequestContext("robot", i))["actions"] for i, obs in enumerate(observations)]
    cam.close(timeout=None)
    assert_pairwise_different(actions)  # identity below means the replay served each request's own actions
    return cam.run_dir


REPLAYED_FAMILIES = [
    pytest.param("pi0_fast", id="pi0_fast"),
    pytest.param("pi0_fast_stop", id="pi0_fast_stop_at_action_end"),
    pytest.param("pi05", id="pi05"),
    pytest.param("pi0", id="pi0", marks=pytest.mark.slow),
    pytest.param("lerobot", id="lerobot_pi05"),
]


@pytest.mark.parametrize("family", REPLAYED_FAMILIES)
def test_a_served_run_replays_through_explain_run_with_its_own_actions(family, demo_policy, golden_dir, tmp_path):
    """`explain-run RUN_DIR` of a run `serve` wrote with raw frames: every step is served again with the model the run
    records (with its decoding flag), the client's other inputs (the state) and the step's noise, and returns the very
    output it recorded (exit 0, every step compared). pi0.5 and pi0 draw their noise at random: a replay that drew its
    own would mismatch."""
    if family == "pi0":  # upstream's tiny pi0 LIBERO policy
        root = golden_dir / "tiny_policy_pi0_libero"
        model = ModelSpec(root / "checkpoint", "pi0_libero", root / "paligemma_tokenizer_tiny.model", dtype="float32")
        policy = model.create()
        observations = [make_libero_example(seed=seed) for seed in (3, 4, 5)]
    elif family == "lerobot":  # LeRobot's own tiny pi0.5 folder, its cases' 120 x 160 and 96 x 96 frames resized
        model = ModelSpec(golden_dir / "lerobot_pi05_tiny")
        policy = model.create()
        golden = lerobot_cases.cases(golden_dir / "lerobot_pi05_tiny")
        # its three single frames as a LeRobot client sends them (uint8 [H, W, 3] frames, its feature names)
        observations = [lerobot_cases.request(golden, case, uint8=True) for case in ("case0", "case1", "case2")]
    elif family == "pi0_fast_stop":  # `serve --stop-at-action-end`: its outputs end at "|", before the EOS
        model = ModelSpec.demo("pi0_fast")
        policy = model.create(stop_at_action_end=True)
        observations = [policy_part(demo_obs(seed)) for seed in (3, 4, 5)]
    else:
        model = ModelSpec.demo(family)
        policy = demo_policy if family == "pi0_fast" else model.create()
        observations = [policy_part(demo_obs(seed)) for seed in (3, 4, 5)]
    run_config = model.resolved().to_json() | {"stop_at_action_end": family == "pi0_fast_stop"}  # as serve records
    run_dir = _served_run(policy, observations, tmp_path / "served", run_config)
    steps = load_run(run_dir).steps
    assert set(steps[0].client_inputs) == set(_numeric_keys(observations[0]))
    # Only a LeRobot policy's float-resized images need their own copy: an OpenPI image is its uint8 frame exactly.
    stored = {k for step in steps for k in step.inputs if k.startswith(IMAGE_INPUT)}
    assert bool(stored) == (family == "lerobot"), stored
    for step, obs in zip(steps, observations, strict=True):  # the model's images, rebuilt from the step exactly
        trace = policy.infer_traced(obs, noise=step.inputs.get("noise"))[1]
        rebuilt = step_model_inputs(step)[0].images
        for camera, image in trace.observation.images.items():
            np.testing.assert_array_equal(rebuilt[camera], np.asarray(image), err_msg=camera)
    rc = explain_run.main(run_dir, out=tmp_path / "replayed", explanation=ExplainFlags(maps=("gradnorm",)),
                          progress=False)  # fmt: skip
    assert rc == 0
    (replayed,) = (tmp_path / "replayed").iterdir()
    counters = load_run(replayed).manifest["counters"]["external"]
    assert counters["actions_compared"] == len(observations) and counters["actions_mismatched"] == 0


def _numeric_keys(obs: dict) -> list[str]:
    return [
        k
        for k, v in obs.items()
        if k not in ("prompt", "task") and np.asarray(v).dtype.kind in "biuf" and np.ndim(v) < 3
    ]
