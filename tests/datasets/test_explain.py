"""LeRobot datasets into a maps dataset (`openpi-cam explain DATASET_DIR`, local engine): every frame of the three
LeRobot-written demo datasets explained once and joinable on `index`, the gradient-norm maps pointing at the named
block, a job killed mid-episode resuming without writing a frame twice, and bad data skipped with `--keep-going`
without losing what was written.

The bundled demo policy's actions depend on the observation (its frames and prompt), so rows that were explained from
the wrong frame cannot match the reference run.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pyarrow as pa
import pytest
from datasets_support import model_job, pointing, truncated_video_copy
from paths import LEROBOT_DIR, REPO_ROOT
from shared_copies import edit_json, writable_copy

from openpi_cam import cli
from openpi_cam.checkpoints import model_spec
from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.lerobot.dataset import DatasetError, open_dataset, parse_episodes
from openpi_cam.maps import dataset as fmt
from openpi_cam.maps.explain import DatasetJob, dataset_keys, run_local
from openpi_cam.vocabulary import ExplainOptions

DATASETS = ("demo_reach_v30_video", "demo_reach_v30_image", "demo_reach_v21_video")
KINDS = ("gradcam", "gradnorm")
# One set of options for every run here, so that all of them share the compiled programs.
OPTIONS = ExplainOptions(target="action-token", maps=KINDS, check_patches=2)
BATCH = 4
BOX = {"observation.target_box": "target_box"}


def _job(source, out, **kw) -> DatasetJob:
    return model_job(source, out, OPTIONS, batch_size=BATCH, extra=BOX, **kw)


@pytest.fixture(scope="module")
def explained(tmp_path_factory, demo_policy):
    """Each demo dataset explained whole by the local engine: name -> (maps dataset, summary)."""
    out = {}
    for name in DATASETS:
        root = tmp_path_factory.mktemp("maps") / name
        summary = run_local(_job(LEROBOT_DIR / name, root), policy=demo_policy)
        out[name] = (fmt.open_maps_dataset(root), summary)
    return out


@pytest.mark.parametrize("name", DATASETS)
def test_every_frame_is_explained_once_and_joins_the_source(explained, name):
    maps, summary = explained[name]
    reference = np.load(LEROBOT_DIR / f"{name}.lerobot_frames.npz")
    ref_index = sorted(int(k.split("/")[1]) for k in reference.files if k.startswith("episode_index/"))
    table = maps.table().to_pydict()
    assert table["index"] == ref_index, "one row per frame, in index order, none twice"
    assert summary.counts["explained"] == len(ref_index) and not summary.episodes_skipped
    for i, index in enumerate(table["index"]):
        assert table["episode_index"][i] == int(reference[f"episode_index/{index}"])
        assert table["frame_index"][i] == int(reference[f"frame_index/{index}"])
        assert table["task"][i] == str(reference[f"task/{index}"])
        assert table["extra/target_box"][i] == pytest.approx(reference[f"observation.target_box/{index}"].tolist())
    grid = maps.grid("base_0_rgb")
    for kind in KINDS:
        for camera in maps.cameras:
            stack = maps.maps(kind, camera)
            assert stack.shape == (len(ref_index), *grid) and np.isfinite(stack).all()
    # The model's actions differ between frames of an episode: rows are not copies of one explanation per episode.
    actions = np.asarray(table["actions"])
    assert len({a.tobytes() for a in actions.round(4)}) > len(set(table["episode_index"]))
    info = maps.info
    assert info.source_version == open_dataset(LEROBOT_DIR / name).version
    assert info.grids == {c: list(grid) for c in maps.cameras}
    # The spot check ran on every frame and its figures are columns.
    assert all(v is not None for v in table[fmt.check_column("gradnorm", "base_0_rgb")])
    assert all(len(v) == OPTIONS.check_patches for v in table[fmt.check_column(fmt.CHECK_RANDOM, "base_0_rgb")])


def test_gradient_norm_maps_point_at_the_named_block(explained):
    # Live demo runs (docs/MAP_KINDS.md) point at the named block on most steps against a chance of ~0.2; the
    # AV1-compressed frames (mean error 2.7 of 255) must not change that: each dataset at least 3x chance and the
    # video datasets within 10 points of the lossless image dataset (one frame in 55 is ~2 points).
    rates = {name: pointing(explained[name][0], "base_0_rgb") for name in DATASETS}
    for name, (hit, chance) in rates.items():
        assert hit >= 3 * chance, f"{name}: pointing {hit:.2f} vs chance {chance:.2f}"
    lossless = rates["demo_reach_v30_image"][0]
    for name in ("demo_reach_v30_video", "demo_reach_v21_video"):
        assert abs(rates[name][0] - lossless) <= 0.10, rates


def test_adding_to_a_maps_dataset_skips_written_episodes_and_refuses_other_settings(explained, tmp_path, demo_policy):
    maps, _ = explained["demo_reach_v21_video"]
    copy = tmp_path / "copy"
    shutil.copytree(maps.root, copy)
    before = {p: p.stat().st_mtime_ns for p in copy.glob("data/*/*.parquet")}
    summary = run_local(_job(LEROBOT_DIR / "demo_reach_v21_video", copy), policy=demo_policy)
    assert summary.episodes_written == 0 and summary.episodes_already_written == len(before)
    assert {p: p.stat().st_mtime_ns for p in copy.glob("data/*/*.parquet")} == before
    other = dataclasses.replace(_job(LEROBOT_DIR / "demo_reach_v21_video", copy), every=2)
    with pytest.raises(ValueError, match="every"):
        run_local(other, policy=demo_policy)


def test_a_killed_job_resumes_without_writing_a_frame_twice(explained, tmp_path):
    """The command in a subprocess, killed (SIGKILL) once its first shard is written, then run again: the second run
    explains only the missing episodes, and the result equals an uninterrupted run frame for frame."""
    source, out = LEROBOT_DIR / "demo_reach_v21_video", tmp_path / "killed.maps"
    # Every episode of the dataset: with compiled programs cached an episode takes a fraction of a second, and the kill
    # must still find some left to do.
    episodes = len(open_dataset(source).episodes)
    args = [
        sys.executable, "-m", "openpi_cam", "explain", str(source), "--out", str(out), "--maps", *KINDS,
        "--episodes", f"0-{episodes - 1}", "--batch-size", "4", "--check-patches", "2",
        "--extra", "observation.target_box=target_box", "--no-progress",
    ]  # fmt: skip
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    proc = subprocess.Popen(args, cwd=REPO_ROOT, env=env, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 600
    while not list(out.glob("data/*/*.parquet")):
        assert proc.poll() is None, proc.stderr.read()
        assert time.monotonic() < deadline, "no shard written in 10 minutes"
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    first = sorted(out.glob("data/*/*.parquet"))
    assert 1 <= len(first) < episodes, "the kill must land mid-job for this test to say anything"
    done = subprocess.run(args, cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr
    assert f"({len(first)} already written" in done.stderr
    resumed = fmt.open_maps_dataset(out).table().to_pydict()
    reference = pa.concat_tables([explained["demo_reach_v21_video"][0].table(e) for e in range(episodes)]).to_pydict()
    assert resumed["index"] == reference["index"]
    assert not [p for p in out.rglob("*") if p.is_file() and p.suffix == ".tmp"]
    # Same program, same inputs: the maps agree to float32 rounding of a differently scheduled process (measured
    # identical; 1e-5 of each map's scale allows for another thread count).
    for kind in KINDS:
        for camera in ("base_0_rgb", "wrist_0_rgb"):
            a, b = np.asarray(resumed[f"{kind}/{camera}"]), np.asarray(reference[f"{kind}/{camera}"])
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-5 * float(np.abs(b).max()))


def test_bad_episode_is_skipped_with_keep_going_and_nothing_written_is_lost(tmp_path, demo_policy):
    source = truncated_video_copy(tmp_path / "demo_reach_v21_video")
    out = tmp_path / "out"
    job = _job(source, out, episodes=parse_episodes("0-3"))
    with pytest.raises(DatasetError) as err:
        run_local(job, policy=demo_policy)
    assert "episode_000002.mp4" in str(err.value) and "episode 2" in str(err.value)
    written = sorted(p.name for p in out.glob("data/*/*.parquet"))
    assert written == ["episode_000000.parquet", "episode_000001.parquet"], "episodes before the bad one are kept"
    summary = run_local(dataclasses.replace(job, keep_going=True), policy=demo_policy)
    assert list(summary.episodes_skipped) == [2] and "episode_000002.mp4" in summary.episodes_skipped[2]
    assert summary.episodes_written == 1 and summary.episodes_already_written == 2
    assert fmt.open_maps_dataset(out).episodes == [0, 1, 3]
    saved = json.loads((out / fmt.SUMMARY_JSON).read_text())
    assert list(saved["episodes_skipped"]) == ["2"]


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (["--keys", "observation/image=observation.images.top"], "'observation.images.top' (--keys observation/image)"),
        (["--extra", "observation.box=box"], "'observation.box' (--extra observation.box)"),
        (["--episodes", "3-x"], "--episodes takes indices"),
        (["--episodes", "40"], "episodes [40] are not in the dataset"),
        (["--keys", "observation/image"], "--keys takes KEY=VALUE pairs"),
        (
            ["--target", "dataset-actions", "--keys", "actions=observation.nothing"],
            "'observation.nothing' (--target dataset-actions",
        ),
    ],
)
def test_bad_arguments_get_one_line_naming_the_problem(tmp_path, capsys, change, expected):
    with pytest.raises(SystemExit) as exit_:
        cli.main(["explain", str(LEROBOT_DIR / "demo_reach_v30_image"), "--out", str(tmp_path / "o"), *change])
    assert exit_.value.code == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and expected in err[0] and "Traceback" not in err[0], err


def test_unknown_codebase_version_is_refused_by_name(tmp_path, capsys):
    source = writable_copy(LEROBOT_DIR / "demo_reach_v30_image", tmp_path / "demo_reach_v30_image")
    edit_json(source / "meta/info.json", lambda info: info.update(codebase_version="v9.9"))
    with pytest.raises(SystemExit) as exit_:
        cli.main(["explain", str(source), "--out", str(tmp_path / "o")])
    assert exit_.value.code == 1
    err = capsys.readouterr().err
    assert "v9.9" in err and "info.json" in err and "Traceback" not in err


def _negated_actions_copy(tmp_path):
    """The image dataset with every recorded action negated: demonstrations of moving away from the named block."""
    import pyarrow.parquet as pq

    source = writable_copy(LEROBOT_DIR / "demo_reach_v30_image", tmp_path / "demo_reach_v30_image")
    for path in source.glob("data/*/*.parquet"):
        table = pq.read_table(path)
        column = table.column("action").combine_chunks()
        values = pa.array(-np.asarray(column.flatten(), np.float32))
        negated = (
            type(column).from_arrays(values, column.type.list_size)
            if pa.types.is_fixed_size_list(column.type)
            else pa.ListArray.from_arrays(column.offsets, values)
        )
        pq.write_table(table.set_column(table.schema.get_field_index("action"), "action", negated), path)
    return source


def test_dataset_actions_target_explains_the_recorded_chunk(tmp_path, demo_policy):
    """`--target dataset-actions` (pi0-FAST): the explained tokens are the recorded chunk's FAST action tokens as
    training tokenises them (recomputed here from the parquet), and the expert's chunks score a higher
    log-probability than the same chunks negated (the demo model learned the expert)."""
    keys, nested = dataset_keys(ModelSpec(), {})
    options = ExplainOptions(target="chunk", maps=KINDS, check_patches=0)

    def run(source, out):
        job = DatasetJob(
            source,
            out,
            ModelSpec(),
            options,
            keys,
            batch_size=BATCH,
            episodes=(0, 1),
            nested_keys=nested,
            recorded_actions="action",
        )
        run_local(job, policy=demo_policy)
        return fmt.open_maps_dataset(out)

    maps = run(LEROBOT_DIR / "demo_reach_v30_image", tmp_path / "expert")
    assert maps.info.target == "dataset-actions"
    rows = list(maps.rows())
    assert {r["target"] for r in rows} == {"dataset-actions"}
    dataset = open_dataset(LEROBOT_DIR / "demo_reach_v30_image")
    for episode in (0, 1):
        frames = list(dataset.frames(episode))
        recorded = np.stack([f["action"] for f in frames])
        for row in (r for r in rows if r["episode_index"] == episode):
            t = row["frame_index"]
            chunk = recorded[np.minimum(np.arange(t, t + 10), len(frames) - 1)]
            obs = {k: frames[t][f] for k, f in keys.items()} | {"prompt": frames[t]["task"]}
            inputs = demo_policy.training_inputs(obs, chunk)
            postfix = np.asarray(inputs["tokenized_prompt"])[np.asarray(inputs["token_loss_mask"], bool)].tolist()
            explained = json.loads(row["details"])["token_ids"]
            assert explained and all(token in postfix for token in explained)
            assert postfix[5 : 5 + len(explained)] == explained, "the action tokens follow 'Action: ' (5 tokens)"
    negated = run(_negated_actions_copy(tmp_path), tmp_path / "negated")
    expert_scores = np.asarray(maps.table(columns=["score"]).column(0))
    negated_scores = np.asarray(negated.table(columns=["score"]).column(0))
    assert expert_scores.shape == negated_scores.shape
    assert np.median(expert_scores - negated_scores) > 1.0, (expert_scores, negated_scores)


def test_faithfulness_of_a_maps_dataset_serves_its_frames_again(explained, tmp_path, capsys):
    """`openpi-cam faithfulness MAPS_DATASET`: frames spread over the dataset are served again from the source (the
    actions must be the recorded ones: the same frames reached the model), logged with the dataset's own maps and
    re-scored; the pointing game uses the carried `target_box`."""
    maps, _ = explained["demo_reach_v30_image"]
    root = tmp_path / "maps"
    shutil.copytree(maps.root, root)
    code = cli.main(["faithfulness", str(root), "--max-steps", "6", "--randomize", "none", "--no-progress"])
    assert code is None or code == 0, capsys.readouterr().err
    report = json.loads((root / "meta/faithfulness.json").read_text())
    assert report["maps_dataset"]["rows_served_again"] == 6 and report["maps_dataset"].get("actions_mismatched", 0) == 0
    assert report["steps_evaluated"] == 6
    base = report["cameras"]["base_0_rgb"]
    assert base["steps"] == 6
    gradnorm = base["kinds"]["gradnorm"]
    # The dataset's own gradient-norm maps were evaluated against the re-scored model: on these frames they point
    # at the named block (the pointing test above) and their top patch removes more than a random order's.
    assert gradnorm["pointing"]["n"] == 6 and gradnorm["pointing"]["mean"] > gradnorm["pointing_chance"]
    assert gradnorm["deletion_k1"]["median"] > base["kinds"]["random"]["deletion_k1"]["median"]


def test_flow_matching_families_refuse_dataset_actions(tmp_path):
    from openpi_cam.maps.explain import EpisodeExplainer

    options = ExplainOptions(target="chunk", maps=KINDS)
    model = ModelSpec(config="demo_reach_pi05")
    job = model_job(LEROBOT_DIR / "demo_reach_v30_image", tmp_path / "o", options, model, recorded_actions="action")
    with pytest.raises(ValueError, match="pi05 has no likelihood of a given chunk"):
        EpisodeExplainer(job, model_spec.create_demo_policy(model="pi05"))
    assert not (tmp_path / "o").exists(), "refused before anything is written"
