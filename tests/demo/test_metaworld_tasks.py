"""The multi-task Meta-World models: the task switch, what the prompt does to the actions, and pi0-FAST's decoding
budget on a four-dimensional chunk. The bundled multi-task pi0.5 and pi0-FAST serve (float32, CPU)."""

from __future__ import annotations

import numpy as np
import pytest

from openpi_cam.checkpoints.model_spec import BUNDLED_ASSETS, create_demo_policy
from openpi_cam.demo import bundled, metaworld_data, metaworld_sim
from openpi_cam.demo.data import load_normalize
from openpi_cam.demo.run import METAWORLD_CAMERA_SIZE, DemoOptions, run_demo
from openpi_cam.policies import demo_metaworld, demo_reach
from openpi_cam.tokenizers.pi0_fast import Pi0FastTokenizer

pytest.importorskip("metaworld", reason='the Meta-World demo needs pip install -e ".[metaworld]"')

MODELS = ("metaworld_mt_pi05", "metaworld_mt_pi0_fast")


@pytest.fixture(scope="module")
def policies():
    return {m: create_demo_policy(m) for m in MODELS}


@pytest.fixture(scope="module")
def button_frame():
    with metaworld_sim.MetaWorldSim(3, image_size=METAWORLD_CAMERA_SIZE) as sim:
        return sim.frame()


def test_task_names_and_groups_expand_and_an_unknown_task_is_refused_in_one_line():
    assert DemoOptions(sim="metaworld", task=("all",)).tasks == metaworld_sim.TRAINED_TASKS
    both = DemoOptions(sim="metaworld", task=("reach-v3", "held-out", "reach-v3")).tasks
    assert both == ("reach-v3", *metaworld_sim.HELD_OUT_TASKS)
    assert not set(metaworld_sim.TRAINED_TASKS) & set(metaworld_sim.HELD_OUT_TASKS)
    with pytest.raises(ValueError, match="--task pick-the-lock: not a Meta-World task") as e:
        DemoOptions(sim="metaworld", task=("pick-the-lock",))
    assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="needs --sim metaworld"):
        DemoOptions(task=("reach-v3",))


@pytest.mark.parametrize("model", MODELS)
def test_another_tasks_prompt_changes_the_chunk_on_the_same_frame(policies, button_frame, model):
    """The same frame and noise under the button's prompt and the door's: the policy reads the prompt (a one-task
    model ignores it), and the same prompt gives the same chunk again (so the difference is the prompt's)."""
    policy = policies[model]
    obs = bundled.policy_input(bundled.client_observation(button_frame))
    noise = np.random.default_rng(0).standard_normal((demo_metaworld.ACTION_HORIZON, 32)).astype(np.float32)

    def chunk(prompt: str) -> np.ndarray:  # pi0-FAST decodes greedily; pi0.5 from the fixed noise
        return np.asarray(policy.infer({**obs, "prompt": prompt}, noise=noise if "pi05" in model else None)["actions"])

    button, again, door = chunk("press the button"), chunk("press the button"), chunk("open the door")
    np.testing.assert_array_equal(button, again)
    assert button.shape == door.shape == (demo_metaworld.ACTION_HORIZON, metaworld_sim.ACTION_DIM)
    # Actions lie in [-1, 1]; a tenth of that range between the two chunks is far above float32 rounding.
    assert np.abs(button - door).max() > 0.1


def test_pi0_fast_decodes_the_longest_expert_chunk_within_its_budget(policies, button_frame):
    """The decoding budget covers the longest postfix of the expert's chunks (`Action: `, the FAST ids, `|`, EOS)
    with a margin, and a served generation on a Meta-World frame ends inside it with a chunk that decodes."""
    config = demo_metaworld.DEMO_METAWORLD_MT_PI0_FAST_CONFIG
    assets = BUNDLED_ASSETS["metaworld_mt_pi0_fast"]
    tokenizer = Pi0FastTokenizer.from_files(
        assets / demo_reach.PALIGEMMA_TOKENIZER.name, assets / demo_reach.FAST_TOKENIZER.name, max_len=512
    )
    normalize = load_normalize(assets, demo_metaworld.MT_ASSET_ID)
    longest = 0
    for task in metaworld_sim.TRAINED_TASKS:
        steps = list(metaworld_data.expert_episode(7, 0.0, task=task, image_size=METAWORLD_CAMERA_SIZE))
        actions = np.stack([s.frame[metaworld_data.ACTION_FEATURE] for s in steps])
        state = steps[0].frame[metaworld_data.STATE_FEATURE]
        for start in range(0, len(steps), 7):
            chunk = actions[np.minimum(np.arange(start, start + config.action_horizon), len(steps) - 1)]
            norm = normalize({"state": state.astype(np.float64), "actions": chunk.astype(np.float64)})
            row = tokenizer.tokenize(steps[0].prompt, norm["state"], norm["actions"])
            longest = max(longest, int(np.asarray(row[3]).sum()))  # the loss mask covers the postfix
            total = int(np.asarray(row[1]).sum())
            assert total <= config.max_token_len, f"a training sequence of {total} tokens > {config.max_token_len}"
    assert longest + 8 <= config.max_decoding_steps, (
        f"postfix {longest} leaves no margin in {config.max_decoding_steps}"
    )
    assert longest > demo_reach.MAX_DECODING_STEPS, (
        "a four-dimensional chunk needs more than the reaching demo's budget"
    )
    response, trace = policies["metaworld_mt_pi0_fast"].infer_traced(
        bundled.policy_input(bundled.client_observation(button_frame))
    )
    generated = np.asarray(trace.output)
    assert generated.shape == (config.max_decoding_steps,) and trace.malformed_reason is None
    assert np.asarray(response["actions"]).shape == (config.action_horizon, metaworld_sim.ACTION_DIM)


@pytest.mark.slow
def test_the_demo_drives_the_tasks_it_is_given_in_turn(tmp_path):
    """`--task reach-v3 drawer-close-v3`: episode i drives task i mod 2 in scene seed + i // 2, with that task's
    instruction, through the server."""
    opts = DemoOptions(
        out=tmp_path, sim="metaworld", task=("reach-v3", "drawer-close-v3"), num_episodes=4, max_calls=1, explain=False
    )
    episodes = run_demo(opts).episodes
    assert [e["task"] for e in episodes] == ["reach-v3", "drawer-close-v3"] * 2
    assert [e["seed"] for e in episodes] == [0, 0, 1, 1]
    assert [e["prompt"] for e in episodes] == [metaworld_sim.TASKS[e["task"]].prompt for e in episodes]
    assert all(e["steps"] == opts.execute for e in episodes)
