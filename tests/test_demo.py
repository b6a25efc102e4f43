"""The bundled demo: task, simulator, shipped tokenizers and checkpoint, and a short end-to-end demo run."""

from __future__ import annotations

import numpy as np
import pytest

from openpi_cam.demo import bundled, quality, sim, task


def test_task_is_deterministic_per_seed():
    a, b, c = task.make_dataset(7, 16), task.make_dataset(7, 16), task.make_dataset(8, 16)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    assert not np.array_equal(a["base_image"], c["base_image"])


def test_observation_shows_the_named_block_inside_its_box():
    rng = np.random.default_rng(3)
    for _ in range(20):
        scene = task.random_scene(rng)
        sample = task.observe(scene, task.random_start(rng, scene))
        color = scene.target_block.color
        assert sample.prompt == f"reach the {color} block"
        x0, y0, x1, y1 = sample.target_box
        is_color = np.all(sample.base_image == task.COLORS[color], axis=-1)
        ys, xs = np.nonzero(is_color)
        # Every pixel of that colour lies in the box and the block fills most of it (the marker may cover a few).
        assert xs.min() >= x0 and xs.max() < x1 and ys.min() >= y0 and ys.max() < y1
        assert is_color.sum() >= 0.8 * (x1 - x0) * (y1 - y0)
        assert len({b.color for b in scene.blocks}) == len(scene.blocks)


def test_expert_chunks_reach_the_target_in_the_simulator():
    for seed in range(25):
        episode = sim.new_episode(seed)
        assert not episode.success
        for _ in range(6):
            if episode.execute(episode.observe().actions, 5):
                break
        assert episode.success, f"seed {seed}: expert ended at {episode.state}, goal {episode.goal}"


def test_moving_away_from_the_target_fails():
    episode = sim.new_episode(0)
    away = -np.sign(episode.goal - episode.state) * 0.1
    assert not episode.execute(np.tile(away, (10, 1)))
    assert episode.steps == 10


def _shipped_tokenizer_rows(seed: int, n: int):
    """The shipped tokenizers and, per task sample, (normalised actions, tokenize() output) as in training."""
    from openpi_cam.normalize import load_checkpoint_norm_stats
    from openpi_cam.tokenizers.pi0_fast import Pi0FastTokenizer
    from openpi_cam.transforms import Normalize

    tok = Pi0FastTokenizer.from_files(bundled.PALIGEMMA_TOKENIZER, bundled.FAST_TOKENIZER, max_len=56)
    normalize = Normalize(load_checkpoint_norm_stats(bundled.CHECKPOINT, bundled.ASSET_ID), use_quantiles=True)
    data = task.make_dataset(seed, n)
    rows = []
    for prompt, state, actions in zip(data["prompt"], data["state"], data["actions"], strict=True):
        norm = normalize({"state": state.astype(np.float64), "actions": actions.astype(np.float64)})
        rows.append((norm["actions"], tok.tokenize(str(prompt), norm["state"], norm["actions"])))
    return tok, rows


def test_shipped_tokenizers_load_and_round_trip():
    tok, rows = _shipped_tokenizer_rows(11, 40)
    sp = tok.paligemma
    assert [sp.pad_id(), sp.eos_id(), sp.bos_id(), sp.unk_id()] == [0, 1, 2, 3]
    # PaliGemma's layout: FAST id f lands on <loc{255 - f}>, the last 128 pieces are skipped.
    assert sp.id_to_piece(int(tok.fast_to_paligemma([0])[0])) == "<loc0255>"
    assert sp.id_to_piece(sp.vocab_size() - 1) == "<seg127>"
    for actions, (tokens, mask, ar, loss) in rows:
        assert mask.sum() < len(mask), "training sequence does not fit max_token_len"
        np.testing.assert_array_equal(loss, (ar == 1) & mask)  # loss on the postfix only, as upstream
        decoded = tok.extract_actions(tokens[(ar == 1) & mask], 10, 2)
        np.testing.assert_allclose(decoded, actions, atol=0.15)


def test_expert_postfix_fits_the_decoding_cap():
    _, rows = _shipped_tokenizer_rows(12, 40)
    lengths = {int(((ar == 1) & mask).sum()) for _, (_, mask, ar, _) in rows}
    # The shipped FAST fit has no merges (its 97-id budget is below the 256 byte symbols): 20 ids per chunk.
    assert lengths == {27}
    assert max(lengths) <= bundled.MAX_DECODING_STEPS


def test_shipped_checkpoint_loads_through_the_normal_loader():
    from openpi_cam.model.checkpoint import load_params
    from openpi_cam.model.pi0_fast import Pi0FAST

    params = load_params(bundled.CHECKPOINT / "params")
    model = Pi0FAST.from_params(params, action_dim=2, action_horizon=10, max_token_len=56, dtype="float32")
    assert model.camera_grid == (8, 8)
    assert model.config.image_resolution == (64, 64)
    assert model.config.gemma.vocab_size == bundled.create_demo_policy().tokenizer.vocab_size


def test_pointing_game_geometry():
    box = (10, 20, 22, 32)  # x0, y0, x1, y1 in a 64 px image with 8 px patches
    overlap = quality.cells_overlapping(box, (8, 8), 64)
    assert overlap.sum() == 4 and overlap[2:4, 1:3].all()
    cam = np.zeros((8, 8))
    cam[3, 2] = 1.0
    assert quality.hits(cam, box, 64)
    cam[0, 7] = 2.0
    assert not quality.hits(cam, box, 64)
    assert not quality.hits(np.zeros((8, 8)), (0, 0, 8, 8), 64)  # no mass: points nowhere, even at cell (0, 0)


def test_object_pointing_counts_any_block_and_its_chance():
    boxes = [(10, 20, 22, 32), (40, 0, 48, 8)]  # 4 cells + 1 cell of 64
    cam = np.zeros((8, 8))
    cam[0, 5] = 1.0  # on the second block only
    assert quality.object_pointing(cam, boxes, 64) == (True, 5 / 64)
    assert not quality.hits(cam, boxes[0], 64)
    cam[7, 7] = 2.0
    assert quality.object_pointing(cam, boxes, 64)[0] is False
    assert quality.object_pointing(np.zeros((8, 8)), boxes, 64)[0] is False


@pytest.mark.slow
def test_short_demo_run_is_readable(tmp_path):
    from openpi_cam.cam.reader import load_run
    from openpi_cam.demo.demo_cmd import demo

    assert demo(out=tmp_path, episodes=1, max_calls=2, render=False) == 0
    (run_dir,) = [p for p in tmp_path.iterdir() if p.is_dir()]
    run = load_run(run_dir)
    assert 1 <= len(run.steps) <= 2
    for step in run.steps:
        assert len(step.meta["extra"]["target_box"]) == 4
        assert np.shape(step.maps["base_0_rgb"])[-2:] == (8, 8)
    figures = quality.run_figures(run_dir)
    assert figures["episodes"] == 1 and figures["steps"] == len(run.steps)
    assert 0.0 <= figures["object_pointing"] <= 1.0 and figures["object_pointing_chance"] > 0
