"""Do the demo's maps point at the right thing? Figures from a demo run directory and from fresh inferences.

The run's figures are reported for every map kind it logged; the fresh inferences', for the two kinds one gradient
gives (Grad-CAM and the per-token gradient norm, `ONE_PASS_KINDS`).

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

import jax
import numpy as np

from openpi_cam.cam.batching import explain_traces
from openpi_cam.cam.faithfulness import box_cells, box_visible, spearman
from openpi_cam.cam.run_format import CAMRun, load_run
from openpi_cam.checkpoints import model_spec
from openpi_cam.demo import bundled, task
from openpi_cam.demo.data import Batches, load_normalize
from openpi_cam.demo.recorded import EPISODES_FILE
from openpi_cam.model.pi0_fast import Pi0FAST, init_params
from openpi_cam.monitor.stream import FLAG
from openpi_cam.policies import demo_reach
from openpi_cam.policies.family import Explainer, Explanation
from openpi_cam.policies.pi0_fast_family import FastExplainer
from openpi_cam.policies.policy import InferenceTrace, Policy
from openpi_cam.vocabulary import MAP_KINDS, ONE_PASS_KINDS, ExplainOptions

BASE_CAMERA = "base_0_rgb"


def peak_cell(cam_map: np.ndarray) -> tuple[int, int]:
    """(row, col) of the strongest patch; a per-token stack [T, Hp, Wp] is summed over tokens first."""
    m = np.asarray(cam_map, np.float64)
    m = m.sum(axis=0) if m.ndim == 3 else m
    return tuple(int(i) for i in np.unravel_index(int(np.argmax(m)), m.shape))  # type: ignore[return-value]


def cells_overlapping(box: tuple[int, ...], grid: tuple[int, int], image_size: int) -> np.ndarray:
    """Boolean [Hp, Wp]: which patches share at least one pixel with the box (x0, y0, x1, y1), end exclusive."""
    return box_cells(box, grid, image_size)


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
    """Success rate (from the demo's episode file) and, per map kind the run carries, the pointing game over every
    logged step whose target is in view (a hidden target, an empty box, is not scored); cameras of `image_size` px."""
    run = load_run(run_dir)
    labelled = [s for s in run.steps if s.extra.get("target_box") is not None and box_visible(s.extra["target_box"])]
    per_kind = {}
    for kind in (k for k in MAP_KINDS if any(k in s.map_kinds for s in run.steps)):
        hit, cell_chance, area_chance, on_block, block_chance = [], [], [], [], []
        for step in labelled:
            extra = step.extra
            box = tuple(extra["target_box"])
            cam_map = step.maps_of(kind).get(BASE_CAMERA)
            if cam_map is None:
                continue
            hit.append(hits(cam_map, box, image_size))
            cell_chance.append(cells_overlapping(box, np.shape(cam_map)[-2:], image_size).mean())
            area_chance.append((box[2] - box[0]) * (box[3] - box[1]) / image_size**2)
            if extra.get("block_boxes") is not None:
                hit_any, chance = object_pointing(cam_map, [tuple(b) for b in extra["block_boxes"]], image_size)
                on_block.append(hit_any)
                block_chance.append(chance)
        per_kind[kind] = {
            "steps": len(hit),
            "pointing_game": _mean(hit),
            "pointing_chance": _mean(cell_chance),
            "pointing_chance_area": _mean(area_chance),
            "object_pointing": _mean(on_block),
            "object_pointing_chance": _mean(block_chance),
        }
    episodes_path = Path(run_dir) / EPISODES_FILE
    episodes = json.loads(episodes_path.read_text()) if episodes_path.exists() else []
    return {
        "episodes": len(episodes),
        "success_rate": success_rate(episodes),
        "steps": len(labelled),
        "maps": per_kind,
        "monitor_flags": monitor_flags(run),
    }


def monitor_flags(run: CAMRun) -> list[bool] | None:
    """Per connection (an episode of the demo), in the order they began, whether the failure monitor flagged it by
    its last logged step; None where the run's steps carry no monitor."""
    flagged: dict[str, bool] = {}
    for step in sorted(run.steps, key=lambda s: s.seq):
        flag = step.monitor.get(FLAG)
        if flag is None:
            return None
        flagged[step.meta.connection] = flagged.get(step.meta.connection, False) or bool(flag)
    return list(flagged.values()) if flagged else None


def success_rate(episodes: list[dict[str, Any]]) -> float:
    return _mean([e["success"] for e in episodes])


def _mean(values: list[Any]) -> float:
    return float(np.mean(values)) if len(values) else float("nan")


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


def occlusion_figures(policy: Policy, samples: int = 40, seed: int = 4321) -> dict[str, dict[str, float]]:
    """Which camera drives the policy? Per occlusion (the blocks erased from no view, from the base view, from the wrist
    view; the end-effector marker stays), the share of fresh rollout starts whose executed chunk heads for the named
    block, and for any block. A causal counterpart to the maps: a camera the policy does not use cannot be where a
    map's peak means anything."""
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


def _explain(explainer: Explainer, trace: InferenceTrace, target: str) -> Explanation | None:
    request = ExplainOptions(target, maps=ONE_PASS_KINDS)  # type: ignore[arg-type]
    (explanation,) = explain_traces(explainer, [trace], request)
    return explanation if isinstance(explanation, Explanation) and explanation.target == target else None


def _trace(policy: Policy, obs: dict[str, Any]) -> InferenceTrace:
    return policy.infer_traced(bundled.policy_input(obs))[1]


def map_figures(
    policy: Policy, samples: int = 30, seed: int = 1234, target: str = "chunk"
) -> dict[str, dict[str, Any]]:
    """Per map kind, on `samples` fresh scenes: pointing game, object pointing, the randomisation check (against a
    copy of the model re-initialised with `seed`) and the prompt swap."""
    explainer = policy.explainer
    model = explainer.model
    random_explainer = FastExplainer(
        Pi0FAST(model.config, init_params(model.config, jax.random.key(seed))), explainer.tokenizer
    )
    rng = np.random.default_rng(seed)
    size = task.TaskConfig().image_size
    fields = ("rho", "kept", "chance", "moved", "on_block", "block_chance")
    figures = {k: {field: [] for field in fields} for k in ONE_PASS_KINDS}  # the kinds `_explain` computes
    scenes = 0
    while scenes < samples:
        scene = task.random_scene(rng)
        state = task.random_start(rng, scene)
        obs = bundled.client_observation(task.observe(scene, state))
        trace = _trace(policy, obs)
        trained = _explain(explainer, trace, target)
        if trained is None:
            continue
        randomised = _explain(random_explainer, trace, target)
        other = scene.with_target(next(b.color for i, b in enumerate(scene.blocks) if i != scene.target))
        swapped = _explain(explainer, _trace(policy, bundled.client_observation(task.observe(other, state))), target)
        for kind, f in figures.items():
            own = trained.maps[kind][BASE_CAMERA]
            f["rho"].append(spearman(own, randomised.maps[kind][BASE_CAMERA]) if randomised else float("nan"))
            f["kept"].append(hits(own, scene.target_block.box, size))
            f["chance"].append(cells_overlapping(scene.target_block.box, np.shape(own)[-2:], size).mean())
            hit_any, chance = object_pointing(own, [b.box for b in scene.blocks], size)
            f["on_block"].append(hit_any)
            f["block_chance"].append(chance)
            if swapped is not None:
                f["moved"].append(hits(swapped.maps[kind][BASE_CAMERA], other.target_block.box, size))
        scenes += 1
    maps = {}
    for kind, f in figures.items():
        finite = [r for r in f["rho"] if np.isfinite(r)]
        maps[kind] = {
            "pointing_game_fresh": _mean(f["kept"]),
            "pointing_chance_fresh": _mean(f["chance"]),
            "object_pointing_fresh": _mean(f["on_block"]),
            "object_pointing_chance": _mean(f["block_chance"]),
            "randomisation_spearman_mean": _mean(finite),
            "randomisation_spearman_abs_mean": _mean(np.abs(finite).tolist()),
            "prompt_swap_peak_moves": _mean(f["moved"]),
            "prompt_swap_samples": len(f["moved"]),
        }
    return maps


def offline_figures(
    samples: int = 30, seed: int = 1234, target: str = "chunk", assets: Path = demo_reach.ASSETS
) -> dict[str, Any]:
    """The map figures, the binding probe and camera occlusion, on fresh scenes."""
    policy = model_spec.create_demo_policy(assets=assets)
    batches = Batches(assets, load_normalize(assets), 1, seed)

    def loss(pairs: list[task.Sample]) -> np.ndarray:  # at the positions the decoder serves the action tokens at
        return np.asarray(policy.model.compute_loss(batches.batch(pairs).obs, decode_offset=1))

    return {
        "samples": samples,
        "target": target,
        "maps": map_figures(policy, samples, seed, target),
        "binding_probe": binding_probe(loss),
        "occlusion": occlusion_figures(policy, samples, seed),
    }


@dataclasses.dataclass(frozen=True)
class Args:
    run_dir: Path | None = None  # a demo run directory; None: only the offline figures
    samples: int = 30
    seed: int = 1234
    target: str = "chunk"  # what the maps explain in the offline checks (as `openpi-cam demo --target`)
    assets: Path = demo_reach.ASSETS  # the model judged offline (as `openpi-cam demo --assets`; a training run's --out)


def main(args: Args) -> dict[str, Any]:
    figures: dict[str, Any] = {}
    if args.run_dir is not None:
        figures["run"] = run_figures(args.run_dir)
    if args.samples:
        figures["offline"] = offline_figures(args.samples, args.seed, args.target, args.assets)
    print(json.dumps(figures, indent=2))
    return figures


if __name__ == "__main__":
    import tyro

    main(tyro.cli(Args))
