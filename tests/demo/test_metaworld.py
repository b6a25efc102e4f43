"""The Meta-World demo's simulator, data and perturbations (MuJoCo through the `metaworld` extra, rendered headless).
The tests that step the simulator are in the slow tier."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest

from openpi_cam import cli
from openpi_cam.cam.run_format import load_run
from openpi_cam.checkpoints.model_spec import create_demo_policy
from openpi_cam.cli import train_demo
from openpi_cam.cli.demo import main as demo_main
from openpi_cam.cli.train_demo import RecordArgs, read_demonstrations, record_expert
from openpi_cam.demo import bundled, metaworld_data, metaworld_sim, quality, train
from openpi_cam.demo.metaworld_sim import MetaWorldSim, Perturbation
from openpi_cam.demo.run import METAWORLD_CAMERA_SIZE, DemoOptions, run_demo
from openpi_cam.lerobot.dataset import open_dataset
from openpi_cam.policies import demo_metaworld, demo_reach

pytest.importorskip("metaworld", reason='the Meta-World demo needs pip install -e ".[metaworld]"')

GRID = METAWORLD_CAMERA_SIZE // bundled.PATCH_SIZE  # the served model's patch grid per camera


def _grown(mask: np.ndarray, pixels: int = 1) -> np.ndarray:
    """The mask and its neighbours within `pixels`: anti-aliasing blends a geom's edge into the pixels around it."""
    out = mask.copy()
    for dy in range(-pixels, pixels + 1):
        for dx in range(-pixels, pixels + 1):
            out |= np.roll(np.roll(mask, dy, axis=0), dx, axis=1)
    return out


def test_perturbations_parse_and_refuse_in_one_line():
    assert Perturbation.parse("clean") == metaworld_sim.CLEAN
    assert Perturbation.parse("distractors=3").value == 3
    assert Perturbation.parse("prompt=").strength == ""
    assert Perturbation.parse("hue=90").name == "hue=90"
    for bad, says in [
        ("blur=2", "unknown perturbation"),
        ("dim=dark", "needs a number"),
        ("distractors=1.5", "whole number"),
        ("dim=-1", ">= 0"),
        ("clean=1", "no strength"),
    ]:
        with pytest.raises(ValueError, match=says) as e:
            Perturbation.parse(bad)
        assert "\n" not in str(e.value)


def test_a_chunk_repeats_its_episodes_last_action_past_the_end():
    actions = np.arange(10, dtype=np.float32).reshape(5, 2)
    demos = metaworld_data.Demonstrations(
        base_image=np.zeros((5, 2, 2, 3), np.uint8),
        wrist_image=np.zeros((5, 2, 2, 3), np.uint8),
        state=np.zeros((5, 4), np.float32),
        actions=actions,
        episode_index=np.array([0, 0, 0, 1, 1]),
        prompt=np.array(["a"] * 5),
    )
    np.testing.assert_array_equal(demos.chunk(1, 4), actions[[1, 2, 2, 2]])
    np.testing.assert_array_equal(demos.chunk(3, 3), actions[[3, 4, 4]])


def test_task_weights_set_how_often_each_tasks_frames_are_drawn():
    """`train_demo --task-weights push-v3=3`: push's frames drawn three times as often as the others', frame for frame
    (a task's share grows with its frames too); the unweighted draw is the uniform one the shipped models trained on."""
    reach, push, button = (metaworld_sim.TASKS[t].prompts for t in ("reach-v3", "push-v3", metaworld_sim.TASK))
    prompts = [reach[0]] * 20 + [push[1]] * 10 + [button[2]] * 10  # frames: reach 50%, push 25%, button 25%
    n = len(prompts)
    demos = metaworld_data.Demonstrations(
        base_image=np.zeros((n, 2, 2, 3), np.uint8),
        wrist_image=np.zeros((n, 2, 2, 3), np.uint8),
        state=np.arange(n, dtype=np.float32)[:, None].repeat(4, 1),
        actions=np.zeros((n, 4), np.float32),
        episode_index=np.arange(n) // 5,
        prompt=np.array(prompts),
    )
    weighted = demos.weighted(train_demo.parse_task_weights(["push-v3=3"]))
    expected = {"reach-v3": 20 / 60, "push-v3": 30 / 60, metaworld_sim.TASK: 10 / 60}
    assert weighted.task_shares() == pytest.approx(expected)
    assert demos.task_shares() == pytest.approx({"reach-v3": 0.5, "push-v3": 0.25, metaworld_sim.TASK: 0.25})
    draws = 30_000
    rows = [int(s.state[0]) for s in weighted.samples(np.random.default_rng(0), draws, 2)]
    tasks = weighted.tasks()[rows]
    for name, share in expected.items():
        # Binomial: the drawn share within 4 standard errors (<= 0.012 at these shares and draws) of the expected.
        assert abs(np.mean(tasks == name) - share) < 4 * np.sqrt(share * (1 - share) / draws)
    # Unweighted, the rows are the uniform draw the recipe has always made: same generator, same rows.
    uniform = [int(s.state[0]) for s in demos.samples(np.random.default_rng(0), 50, 2)]
    assert uniform == np.random.default_rng(0).integers(n, size=50).tolist()
    with pytest.raises(ValueError, match="no episodes of drawer-close-v3"):
        demos.weighted({"drawer-close-v3": 2.0})
    for bad, says in [("push-v3", "TASK=WEIGHT"), ("pull-v3=2", "TASK=WEIGHT"), ("push-v3=0", "positive"),
                      ("push-v3=x", "positive"), ("push-v3=nan", "positive")]:  # fmt: skip
        with pytest.raises(ValueError, match=says) as e:
            train_demo.parse_task_weights([bad])
        assert "\n" not in str(e.value)


@pytest.mark.slow
def test_the_expert_presses_the_button_and_the_state_hides_it():
    with MetaWorldSim(3) as sim:
        first = sim.frame()
        while not sim.success and sim.steps < metaworld_sim.MAX_STEPS:
            sim.step(sim.expert_action())
        assert sim.success, "the scripted expert solves the task (61-73 steps in docs/DEMO_NOTES.md)"
        assert sim.steps <= 100
    size = metaworld_sim.IMAGE_SIZE
    assert first.base_image.shape == first.wrist_image.shape == (size, size, 3)
    assert first.state.shape == (metaworld_sim.STATE_DIM,)
    assert first.prompt == "press the button"
    # The box is in view at the size the model reads: at least 8 x 8 pixels of the fixed camera.
    x0, y0, x1, y1 = first.target_box
    assert x1 - x0 >= 8 and y1 - y0 >= 8 and first.target_mask.sum() >= 64
    assert first.target_mask[y0:y1, x0:x1].sum() == first.target_mask.sum()


@pytest.mark.slow
def test_scenes_follow_the_seed():
    with MetaWorldSim(1) as a, MetaWorldSim(1) as b, MetaWorldSim(2) as c:
        np.testing.assert_array_equal(a.frame().base_image, b.frame().base_image)
        assert a.frame().target_box != c.frame().target_box


@pytest.mark.slow
def test_a_narrower_fixed_camera_shows_the_small_targets_larger():
    """`fovy=25` against Meta-World's 45 degrees: the reach goal and the puck cover (tan 22.5 / tan 12.5)^2, about
    3.5 times the fixed camera's pixels (measured 3-4 over scenes: pixel edges); the expert's episode and the wrist
    camera are the same."""
    for task in ("reach-v3", "push-v3"):
        with (
            MetaWorldSim(3, task=task, image_size=96) as wide,
            MetaWorldSim(3, task=task, image_size=96, fovy=25) as narrow,
        ):
            a, b = wide.frame(), narrow.frame()
        np.testing.assert_array_equal(a.wrist_image, b.wrist_image)
        np.testing.assert_array_equal(a.state, b.state)
        assert 2.5 < b.target_mask.sum() / a.target_mask.sum() < 5, (task, a.target_mask.sum(), b.target_mask.sum())
    steps = list(metaworld_data.expert_episode(3, 0.3, task="reach-v3", image_size=32, fovy=25))
    same = list(metaworld_data.expert_episode(3, 0.3, task="reach-v3", image_size=32))
    assert [s.frame[metaworld_data.ACTION_FEATURE].tolist() for s in steps] == [
        s.frame[metaworld_data.ACTION_FEATURE].tolist() for s in same
    ]
    assert all(
        (s.frame[metaworld_data.BASE_FEATURE] != t.frame[metaworld_data.BASE_FEATURE]).any()
        for s, t in zip(steps, same, strict=True)
    )


@pytest.mark.slow
def test_the_wrist_view_is_any_camera_of_the_scene():
    """`wrist_camera` changes the wrist frames alone: the fixed camera, the state and the expert's actions stay; a
    camera the scene lacks is refused in one line that names it and the scene's cameras."""
    with (
        MetaWorldSim(3, task="reach-v3", image_size=32) as shipped,
        MetaWorldSim(3, task="reach-v3", image_size=32, wrist_camera="behindGripper") as behind,
    ):
        a, b = shipped.frame(), behind.frame()
    np.testing.assert_array_equal(a.base_image, b.base_image)
    np.testing.assert_array_equal(a.state, b.state)
    assert (a.wrist_image != b.wrist_image).mean() > 0.5
    steps = list(metaworld_data.expert_episode(3, 0.3, task="reach-v3", image_size=32, wrist_camera="behindGripper"))
    same = list(metaworld_data.expert_episode(3, 0.3, task="reach-v3", image_size=32))
    features = (metaworld_data.ACTION_FEATURE, metaworld_data.BASE_FEATURE)
    for s, t in zip(steps, same, strict=True):
        assert all(np.array_equal(s.frame[f], t.frame[f]) for f in features)
        assert (s.frame[metaworld_data.WRIST_FEATURE] != t.frame[metaworld_data.WRIST_FEATURE]).any()
    with pytest.raises(ValueError, match=r"no camera 'wrist'.*behindGripper") as e:
        MetaWorldSim(3, task="reach-v3", image_size=32, wrist_camera="wrist")
    assert "\n" not in str(e.value)


@pytest.mark.slow
def test_a_hue_turn_touches_only_the_box_and_the_mask_is_where_it_is():
    with MetaWorldSim(4) as clean, MetaWorldSim(4, Perturbation.parse("hue=120")) as turned:
        before, after = clean.frame(), turned.frame()
    np.testing.assert_array_equal(before.target_mask, after.target_mask)
    changed = np.any(before.base_image != after.base_image, axis=-1)
    # The yellow top and the red button turn; the black base (about half of the box's pixels in this view) cannot.
    assert changed[before.target_mask].mean() > 0.25
    assert not changed[~_grown(before.target_mask)].any()


@pytest.mark.slow
def test_dim_shift_and_distractors_change_the_scene_as_stated():
    with MetaWorldSim(5) as sim:
        clean = sim.frame()
    with MetaWorldSim(5, Perturbation.parse("dim=0.3")) as sim:
        dim = sim.frame()
    # Lit surfaces scale with the light; the emissive and ambient-free parts keep some brightness.
    assert dim.base_image.mean() < 0.7 * clean.base_image.mean()
    with MetaWorldSim(5, Perturbation.parse("shift=0.15")) as sim:
        shifted = sim.frame()
    # Moving the camera along its image's x axis moves the scene the other way in the image.
    assert shifted.target_box[0] < clean.target_box[0] - 3
    with MetaWorldSim(5, Perturbation.parse("distractors=3")) as sim:
        crowded = sim.frame()
        while not sim.success and sim.steps < metaworld_sim.MAX_STEPS:
            sim.step(sim.expert_action())
        assert sim.success, "distractors leave the task's own state and the expert's solution as they were"
    np.testing.assert_array_equal(crowded.state, clean.state)
    changed = np.any(crowded.base_image != clean.base_image, axis=-1)
    assert changed[~_grown(clean.target_mask)].sum() >= 3 * 4  # three cubes of at least a few pixels each
    with MetaWorldSim(5, Perturbation.parse("prompt=")) as sim:
        assert sim.frame().prompt == ""


@pytest.mark.slow
def test_the_bundled_model_presses_the_button_served_with_the_side_channel(tmp_path):
    """`openpi-cam demo --sim metaworld` at toy length: the demo's default model (the multi-task pi0-FAST, cameras at
    `METAWORLD_CAMERA_SIZE`) served over the websocket, every call explained and logged with the box the simulator
    sees, and the episode solved (the button succeeds in most clean episodes: docs/DEMO_NOTES.md; this seed is one
    it solves)."""
    result = run_demo(
        DemoOptions(out=tmp_path, sim="metaworld", num_episodes=1, seed=0, render=False, faithfulness=False)
    )
    (episode,) = result.episodes
    assert episode["success"] and episode["perturbation"] == "clean"
    run = load_run(result.run_dir)
    assert len(run.steps) == episode["calls"] and not run.problems
    for step in run.steps:
        assert step.meta.target == "chunk"
        maps = step.maps_of("occlusion")  # the default kind
        assert len(maps) == 2 and all(m.shape == (GRID, GRID) for m in maps.values())  # base and wrist
        x0, y0, x1, y1 = step.extra["target_box"]
        assert 0 <= x0 < x1 <= METAWORLD_CAMERA_SIZE and 0 <= y0 < y1 <= METAWORLD_CAMERA_SIZE
    assert result.figures["steps"] == len(run.steps)


@pytest.mark.slow
def test_the_training_command_records_the_expert_as_lerobot_and_trains_a_servable_model(tmp_path):
    """`python -m openpi_cam.cli.train_demo --sim metaworld-button` at toy size: the expert's episodes recorded as a
    LeRobot v3.0 dataset, read back frame for frame as the expert produced them, and a model trained on them that
    serves."""
    data, out = tmp_path / "expert", tmp_path / "model"
    record_expert(
        data, RecordArgs(episodes=2, tasks=(metaworld_sim.TASK,), seed=7, clean_every=2, image_size=64, phrasings=1)
    )
    steps = [s for e in range(2) for s in metaworld_data.expert_episode(7 + e, 0.3 * (e % 2))]
    demos = read_demonstrations([data])
    assert len(demos) == len(steps) and list(np.unique(demos.episode_index)) == [0, 1]
    np.testing.assert_array_equal(demos.actions, np.stack([s.frame[metaworld_data.ACTION_FEATURE] for s in steps]))
    np.testing.assert_array_equal(demos.base_image, np.stack([s.frame[metaworld_data.BASE_FEATURE] for s in steps]))
    assert set(demos.prompt) == {"press the button"}
    # A second dataset (`--data A B`) continues the episode numbering: its episode 0 is the third, and the last chunk
    # of the first dataset's last episode repeats that episode's last action instead of running into the next.
    more = tmp_path / "more"
    record_expert(more, RecordArgs(episodes=1, tasks=(metaworld_sim.TASK,), seed=9, image_size=64, phrasings=1))
    both = read_demonstrations([data, more])
    extra = list(metaworld_data.expert_episode(9, 0.0))
    assert len(both) == len(steps) + len(extra) and list(np.unique(both.episode_index)) == [0, 1, 2]
    np.testing.assert_array_equal(both.episode_index[len(steps) :], 2)
    last = both.chunk(len(steps) - 1, 3)
    np.testing.assert_array_equal(last, np.repeat(demos.actions[-1:], 3, axis=0))
    np.testing.assert_array_equal(
        both.actions[len(steps) :], np.stack([s.frame[metaworld_data.ACTION_FEATURE] for s in extra])
    )
    args = train.TrainArgs(model="pi05", out=out, steps=2, batch_size=4, log_every=1, eval_episodes=0)
    assert train_demo.main(args, sim="metaworld-button", data=(data, more)) == 0
    policy = create_demo_policy("metaworld", assets=out)
    with MetaWorldSim(0) as sim:
        obs = bundled.policy_input(bundled.client_observation(sim.frame()))
    actions = policy.infer(obs)["actions"]
    assert actions.shape == (demo_metaworld.ACTION_HORIZON, metaworld_sim.ACTION_DIM) and np.isfinite(actions).all()


@pytest.mark.slow
def test_the_demo_records_its_meta_world_episodes_as_lerobot_eval_does(tmp_path, capsys):
    """`openpi-cam demo --sim metaworld --record DIR`: every executed action a frame of a LeRobot v3.0 dataset at
    Meta-World's control rate, the episode's outcome in `next.*` on its last frame, its perturbation's index on every
    frame, and the box's bounding box the simulator saw."""
    out = tmp_path / "rec"
    argv = ["demo", "--sim", "metaworld", "--no-explain", "--num-episodes", "2", "--max-calls", "2"]
    cli.main([*argv, "--perturb", "clean", "hue=45", "--record", str(out)])  # exits non-zero on a refusal
    rollouts = json.loads((out / "meta" / quality.EPISODES_FILE).read_text())
    assert [e["perturbation"] for e in rollouts["episodes"]] == ["clean", "hue=45"]
    ds = open_dataset(out)
    assert ds.fps == metaworld_data.FPS and ds.episodes == [0, 1]
    assert json.loads(ds.info_path.read_text())["robot_type"] == demo_metaworld.ASSET_ID
    for i, outcome in enumerate(rollouts["episodes"]):
        frames = list(ds.frames(i))
        assert len(frames) == outcome["steps"] <= 2 * DemoOptions.execute
        assert [bool(f["next.done"]) for f in frames] == [False] * (len(frames) - 1) + [True]
        assert [bool(f["next.success"]) for f in frames] == [False] * (len(frames) - 1) + [outcome["success"]]
        assert {int(f["perturbation"]) for f in frames} == {i} and {f["task"] for f in frames} == {outcome["prompt"]}
        for f in frames:
            x0, y0, x1, y1 = np.asarray(f[demo_reach.LEROBOT_TARGET_BOX])
            assert 0 <= x0 < x1 <= METAWORLD_CAMERA_SIZE and 0 <= y0 < y1 <= METAWORLD_CAMERA_SIZE
            assert f[metaworld_data.BASE_FEATURE].shape == (METAWORLD_CAMERA_SIZE, METAWORLD_CAMERA_SIZE, 3)


def test_the_demo_refuses_in_one_line_without_the_extra_or_with_an_empty_prompt_to_record(
    tmp_path, monkeypatch, capsys
):
    perturbed = DemoOptions(out=tmp_path, sim="metaworld", perturb=("clean", "prompt="))
    assert demo_main(perturbed, record=tmp_path / "rec") == 1
    out = capsys.readouterr().out.strip()
    assert "cannot record an empty prompt" in out and "\n" not in out
    monkeypatch.setitem(sys.modules, "metaworld.env_dict", None)  # as if the extra were not installed
    assert demo_main(DemoOptions(out=tmp_path, sim="metaworld")) == 1
    out = capsys.readouterr().out.strip()
    assert 'pip install -e ".[metaworld]"' in out and "\n" not in out
    assert not any(tmp_path.iterdir()), "refused before any run directory or dataset was made"
