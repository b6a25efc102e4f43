"""Does the demo's Grad-CAM point at the right thing? Figures from a demo run directory and from fresh inferences.

* success rate of the run's episodes;
* pointing game: share of logged steps whose base-camera map peaks on a patch overlapping the named block's box, next
  to chance (the share of patches overlapping the box, and the box's share of the image area);
* object pointing: share of steps whose peak lies on any block, next to its chance (patches overlapping any block):
  separates "the map finds objects" from "the policy picked the named one";
* model randomisation (Adebayo et al.): Spearman rank correlation between the trained model's maps and those of a
  re-initialised copy explaining the same tokens; low means the maps depend on what the model learned;
* prompt swap: naming another block in the same scene moves the peak onto that block;
* binding probe: does the model prefer the chunk toward the named block over one toward another block (0.5: it
  ignores the colour word);
* camera occlusion: how often the policy heads for the named / any block with the blocks erased from one view.

`python -m openpi_cam.demo.quality RUN_DIR [--samples 30]`
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from openpi_cam.demo import bundled, task

BASE_CAMERA = "base_0_rgb"


def peak_cell(cam_map: np.ndarray) -> tuple[int, int]:
    """(row, col) of the strongest patch; a per-token stack [T, Hp, Wp] is summed over tokens first."""
    m = np.asarray(cam_map, np.float64)
    m = m.sum(axis=0) if m.ndim == 3 else m
    return tuple(int(i) for i in np.unravel_index(int(np.argmax(m)), m.shape))  # type: ignore[return-value]


def cells_overlapping(box: tuple[int, ...], grid: tuple[int, int], image_size: int) -> np.ndarray:
    """Boolean [Hp, Wp]: which patches share at least one pixel with the box (x0, y0, x1, y1), end exclusive."""
    x0, y0, x1, y1 = box
    ph, pw = image_size / grid[0], image_size / grid[1]
    rows = (np.arange(grid[0]) * ph < y1) & ((np.arange(grid[0]) + 1) * ph > y0)
    cols = (np.arange(grid[1]) * pw < x1) & ((np.arange(grid[1]) + 1) * pw > x0)
    return rows[:, None] & cols[None, :]


def peak_in(cam_map: np.ndarray, cells: np.ndarray) -> bool:
    """Does the map's peak fall in `cells` [Hp, Wp]? A map without any positive mass points nowhere: a miss."""
    return bool(np.asarray(cam_map).max() > 0 and cells[peak_cell(cam_map)])


def hits(cam_map: np.ndarray, box: tuple[int, ...], image_size: int) -> bool:
    """Pointing-game hit: the peak lies on a patch overlapping the box."""
    return peak_in(cam_map, cells_overlapping(box, np.shape(cam_map)[-2:], image_size))


def object_pointing(cam_map: np.ndarray, boxes: list[tuple[int, ...]], image_size: int) -> tuple[bool, float]:
    """(does the peak lie on any of the blocks, share of patches overlapping any block)."""
    grid = np.shape(cam_map)[-2:]
    any_block = np.logical_or.reduce([cells_overlapping(b, grid, image_size) for b in boxes])
    return peak_in(cam_map, any_block), float(any_block.mean())


def run_figures(run_dir: Path, image_size: int = task.TaskConfig().image_size) -> dict[str, Any]:
    """Success rate (from the demo's episode file) and the pointing game over every logged step."""
    from openpi_cam.cam.reader import load_run
    from openpi_cam.demo.demo_cmd import EPISODES_FILE

    run = load_run(run_dir)
    hit, cell_chance, area_chance, on_block, block_chance = [], [], [], [], []
    for step in run.steps:
        extra = step.meta.get("extra") or {}
        box = extra.get("target_box")
        maps = step.maps
        if box is None or BASE_CAMERA not in maps:
            continue
        cam_map = maps[BASE_CAMERA]
        hit.append(hits(cam_map, tuple(box), image_size))
        cell_chance.append(cells_overlapping(tuple(box), np.shape(cam_map)[-2:], image_size).mean())
        area_chance.append((box[2] - box[0]) * (box[3] - box[1]) / image_size**2)
        if extra.get("block_boxes") is not None:
            hit_any, chance = object_pointing(cam_map, [tuple(b) for b in extra["block_boxes"]], image_size)
            on_block.append(hit_any)
            block_chance.append(chance)
    episodes_path = Path(run_dir) / EPISODES_FILE
    episodes = json.loads(episodes_path.read_text()) if episodes_path.exists() else []
    return {
        "episodes": len(episodes),
        "success_rate": float(np.mean([e["success"] for e in episodes])) if episodes else float("nan"),
        "steps": len(hit),
        "pointing_game": float(np.mean(hit)) if hit else float("nan"),
        "pointing_chance": float(np.mean(cell_chance)) if hit else float("nan"),
        "pointing_chance_area": float(np.mean(area_chance)) if hit else float("nan"),
        "object_pointing": float(np.mean(on_block)) if on_block else float("nan"),
        "object_pointing_chance": float(np.mean(block_chance)) if on_block else float("nan"),
    }


def binding_pairs(samples: int, seed: int) -> tuple[list[task.Sample], list[task.Sample]]:
    """Rollout starts in fresh scenes, each twice: as the expert sees it (the chunk heads for the named block) and with
    the chunk heading for another block instead; prompt and images are the same in both."""
    rng = np.random.default_rng(seed)
    named, other = [], []
    for _ in range(samples):
        scene = task.random_scene(rng)
        state = task.random_start(rng, scene)
        sample = task.observe(scene, state)
        distractor = scene.blocks[task.other_block(rng, scene)]
        goal = task.block_center(distractor, task.TaskConfig().image_size)
        named.append(sample)
        other.append(dataclasses.replace(sample, actions=task.expert_chunk(state, goal)))
    return named, other


def binding_probe(
    example_losses: Callable[[list[task.Sample]], np.ndarray], samples: int = 96, seed: int = 999
) -> float:
    """Share of scenes where the model finds the chunk toward the *named* block likelier (lower teacher-forced loss)
    than the chunk toward another block, given the same prompt and images. 0.5 is a policy that ignores the colour
    word (it may still head for *a* block); 1.0 binds the word to the block. No decoding, so it is cheap enough to log
    during training; `example_losses` maps samples to per-example training losses."""
    named, other = binding_pairs(samples, seed)
    return float(np.mean(np.asarray(example_losses(named)) < np.asarray(example_losses(other))))


def heads_for(
    actions: np.ndarray, state: np.ndarray, goal: np.ndarray, *, execute: int = 5, tolerance: float = 20.0
) -> bool:
    """Does the executed part of a chunk (its first `execute` steps, as the demo robot runs it) point at `goal` within
    `tolerance` degrees?"""
    move = np.asarray(actions, np.float64)[:execute].sum(0)
    want = np.asarray(goal, np.float64) - np.asarray(state, np.float64)
    norm = np.linalg.norm(move) * np.linalg.norm(want)
    return bool(norm > 0 and np.degrees(np.arccos(np.clip(move @ want / norm, -1.0, 1.0))) <= tolerance)


OCCLUSIONS = ("none", "base", "wrist")


def occlusion_figures(policy: Any, samples: int = 40, seed: int = 4321) -> dict[str, dict[str, float]]:
    """Which camera drives the policy? Per occlusion (the blocks erased from no view, from the base view, from the wrist
    view; the end-effector marker stays), the share of fresh rollout starts whose executed chunk heads for the named
    block, and for any block. A causal counterpart to the maps: a camera the policy does not use cannot be where its
    Grad-CAM peak means anything."""
    rng = np.random.default_rng(seed)
    size = task.TaskConfig().image_size
    empty = task.Scene(blocks=(), target=0)
    named = {k: [] for k in OCCLUSIONS}
    any_block = {k: [] for k in OCCLUSIONS}
    for _ in range(samples):
        scene = task.random_scene(rng)
        state = task.random_start(rng, scene)
        sample = task.observe(scene, state)
        for occlusion in OCCLUSIONS:
            shown = sample
            if occlusion == "base":
                shown = dataclasses.replace(sample, base_image=task.render_base(empty, state))
            elif occlusion == "wrist":
                shown = dataclasses.replace(sample, wrist_image=task.render_wrist(empty, state))
            actions = policy.infer(bundled.policy_input(bundled.client_observation(shown)))["actions"]
            heads = [heads_for(actions, state, task.block_center(b, size)) for b in scene.blocks]
            named[occlusion].append(heads[scene.target])
            any_block[occlusion].append(any(heads))
    return {
        k: {"heads_for_named_block": float(np.mean(named[k])), "heads_for_any_block": float(np.mean(any_block[k]))}
        for k in OCCLUSIONS
    }


def _explain(model: Any, policy: Any, obs: dict[str, Any], target: str):
    from openpi_cam.cam.engine import CamSkipped, explain

    _, trace = policy.infer_traced(bundled.policy_input(obs))
    try:
        return trace, explain(model, policy.tokenizer, trace.observation, trace.generated_tokens, target=target)
    except CamSkipped:
        return trace, None


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.stats import spearmanr

    a, b = np.ravel(a), np.ravel(b)
    if np.ptp(a) == 0 or np.ptp(b) == 0:
        return float("nan")
    return float(spearmanr(a, b).statistic)


def offline_figures(samples: int = 30, seed: int = 1234, target: str = "chunk") -> dict[str, Any]:
    """Randomisation check, prompt swap, binding probe and camera occlusion on fresh scenes."""
    import jax

    from openpi_cam.model.pi0_fast import Pi0FAST, init_params

    policy = bundled.create_demo_policy()
    model = policy.model
    random_model = Pi0FAST(model.config, init_params(model.config, jax.random.key(seed)))
    rng = np.random.default_rng(seed)
    size = task.TaskConfig().image_size
    rhos, kept, moved, on_block, block_chance, swaps = [], [], [], [], [], 0
    while swaps < samples:
        scene = task.random_scene(rng)
        state = task.random_start(rng, scene)
        obs = bundled.client_observation(task.observe(scene, state))
        trace, trained = _explain(model, policy, obs, target)
        if trained is None:
            continue
        from openpi_cam.cam.engine import explain

        randomised = explain(random_model, policy.tokenizer, trace.observation, trace.generated_tokens, target=target)
        rhos.append(spearman(trained.maps[BASE_CAMERA], randomised.maps[BASE_CAMERA]))
        kept.append(hits(trained.maps[BASE_CAMERA], scene.target_block.box, size))
        hit_any, chance = object_pointing(trained.maps[BASE_CAMERA], [b.box for b in scene.blocks], size)
        on_block.append(hit_any)
        block_chance.append(chance)
        other = scene.with_target(next(b.color for i, b in enumerate(scene.blocks) if i != scene.target))
        _, swapped = _explain(model, policy, bundled.client_observation(task.observe(other, state)), target)
        if swapped is not None:
            moved.append(hits(swapped.maps[BASE_CAMERA], other.target_block.box, size))
        swaps += 1
    finite = [r for r in rhos if np.isfinite(r)]
    from openpi_cam.demo.train import Batches, load_normalize

    batches = Batches(bundled.ASSETS, load_normalize(bundled.ASSETS), 1, seed)
    # At the positions the decoder serves the action tokens at.
    probe = binding_probe(lambda samples: np.asarray(model.compute_loss(batches.observation(samples), decode_offset=1)))
    return {
        "binding_probe": probe,
        "occlusion": occlusion_figures(policy, samples, seed),
        "samples": swaps,
        "pointing_game_fresh": float(np.mean(kept)),
        "object_pointing_fresh": float(np.mean(on_block)),
        "object_pointing_chance": float(np.mean(block_chance)),
        "randomisation_spearman_mean": float(np.mean(finite)) if finite else float("nan"),
        "randomisation_spearman_abs_mean": float(np.mean(np.abs(finite))) if finite else float("nan"),
        "prompt_swap_peak_moves": float(np.mean(moved)) if moved else float("nan"),
        "prompt_swap_samples": len(moved),
    }


@dataclasses.dataclass(frozen=True)
class Args:
    run_dir: Path | None = None  # a demo run directory; None: only the offline figures
    samples: int = 30
    seed: int = 1234
    target: str = "chunk"  # what Grad-CAM explains in the offline checks (as `openpi-cam demo --target`)


def main(args: Args) -> dict[str, Any]:
    figures: dict[str, Any] = {}
    if args.run_dir is not None:
        figures["run"] = run_figures(args.run_dir)
    if args.samples:
        figures["offline"] = offline_figures(args.samples, args.seed, args.target)
    print(json.dumps(figures, indent=2))
    return figures


if __name__ == "__main__":
    import tyro

    main(tyro.cli(Args))
