"""How the options of the `rise` and `smoothgrad` kinds trade agreement with exhaustive occlusion against cost, on the
steps of a run that carries occlusion maps (e.g. `openpi-cam demo --out DIR --num-episodes 30 --max-calls 1 --seed
2000 --no-render --no-faithfulness`): what chose `MapOptions.rise_masks` and `smoothgrad_sigma`.

Per step and valid camera, against the step's logged exhaustive 1 x 1 occlusion map (each patch's single-patch drop):
top-1 agreement, Spearman, and deletion k = 1 (the single-patch drop of the map's top patch over the best single
patch's drop: `openpi-cam faithfulness`'s figure, read off the occlusion map instead of re-run).

* rise: `--masks-max` random masks per camera and keep probability (`--keep`), re-scored once per step by the model
  (`Explainer.rescore`, the painting the run's maps used); the maps of the first N masks for each N of `--masks`
  (nested, so the N compare like for like), under three estimators of the same masks: `iss` (mean score with the
  patch kept minus with it painted: `attribution.iss_map`, what the kind uses), `centred` (the scores' covariance
  with the patch being kept over keep (1 - keep)) and `paper` (RISE's own normalisation, sum_i score_i kept_i /
  (N keep)). Timed: the `rise` kind alone at each N through the explainer, per step.
* smoothgrad: the kind at each `--sigmas` level with `--samples` noisy copies, and the gradient norm (sigma 0).

    python benchmarks/kind_options.py DIR/<run> --max-steps 30
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

from openpi_cam.cam import faithfulness as fm
from openpi_cam.cam.faithfulness_run import painting_options, step_model_inputs
from openpi_cam.cam.run_format import load_run
from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.model.attribution import iss_map, random_region_masks
from openpi_cam.vocabulary import ExplainOptions


def estimators(masks: np.ndarray, scores: np.ndarray, keep: float) -> dict[str, np.ndarray]:
    """The three estimators of a patch's effect from random masks (True = painted) and their scores [M]."""
    kept = 1.0 - masks.astype(np.float64)  # [M, Hp, Wp]
    n = len(scores)
    centred = np.einsum("m,mhw->hw", scores - scores.mean(), kept) / (n * keep * (1 - keep))
    return {
        "iss": iss_map(masks, scores.mean() - scores),  # drops against the masks' mean: the same differences
        "centred": centred,
        "paper": np.einsum("m,mhw->hw", scores, kept) / (n * keep),
    }


def figures(cam_map: np.ndarray, occlusion: np.ndarray) -> tuple[float, float, float]:
    """(top-1 = occlusion, Spearman with it, deletion k = 1 read off the occlusion map)."""
    top = fm.patch_order(cam_map)[0]
    best = occlusion.max()
    ratio = occlusion.ravel()[top] / best if best > 0 else np.nan
    return float(fm.top1_agreement(cam_map, occlusion)), fm.spearman(cam_map, occlusion), float(ratio)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--max-steps", type=int, default=30)
    parser.add_argument("--masks", type=int, nargs="+", default=[16, 32, 64, 128])
    parser.add_argument("--keep", type=float, nargs="+", default=[0.5, 0.75])
    parser.add_argument("--sigmas", type=float, nargs="+", default=[0.1, 0.25, 0.5, 1.0])
    parser.add_argument("--samples", type=int, default=16)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-timing", action="store_true")
    args = parser.parse_args()

    run = load_run(args.run_dir)
    policy = ModelSpec.from_json(run.run_info["config"]).create()
    explainer = policy.explainer
    steps = [s for s in run.steps if "occlusion" in s.map_kinds][: args.max_steps]
    masks_max = max(args.masks)
    rows: dict[tuple, list[tuple[float, float, float]]] = {}
    times: dict[int, list[float]] = {n: [] for n in args.masks}
    for step in steps:
        obs, outputs, sample_inputs = step_model_inputs(step)
        painting = painting_options(step, "run")
        cameras = step.meta.valid_cameras()
        occlusion = {c: fm.reduce_map(step.maps_of("occlusion")[c]) for c in cameras}
        grid = occlusion[cameras[0]].shape
        for keep in args.keep:
            drawn = random_region_masks(grid, 1, masks_max, keep, args.seed)
            stack = np.concatenate([np.zeros((1, *grid), bool), drawn])
            per_camera = dict.fromkeys(cameras, stack)
            scores = explainer.rescore(obs, outputs, sample_inputs, step.meta.explained(), per_camera, painting)
            for c in cameras:
                s = np.asarray(scores[c], np.float64)[1:]
                for n in args.masks:
                    for name, m in estimators(drawn[:n], s[:n], keep).items():
                        rows.setdefault(("rise", name, keep, n, c), []).append(figures(m, occlusion[c]))
        index, dim_index = step.meta.action_index or ((step.meta.action_indices or (0,))[0], 0)
        request = ExplainOptions(step.meta.target, action_index=index, action_dim_index=dim_index)
        for sigma in (0.0, *args.sigmas):
            options = dataclasses.replace(painting, smoothgrad_samples=args.samples, smoothgrad_sigma=sigma)
            kinds = ("gradnorm",) if sigma == 0 else ("smoothgrad",)
            asked = dataclasses.replace(request, maps=kinds, map_options=options)
            [e] = explainer.explain(obs, outputs, asked, sample_inputs)
            for c in cameras:
                rows.setdefault(("smoothgrad", kinds[0], sigma, args.samples, c), []).append(
                    figures(e.maps[kinds[0]][c], occlusion[c])
                )
        if not args.no_timing:
            for n in args.masks:
                options = dataclasses.replace(painting, rise_masks=n)
                rise = dataclasses.replace(request, maps=("rise",), map_options=options)
                explainer.explain(obs, outputs, rise, sample_inputs)  # compiled for this N before it is timed
                t0 = time.perf_counter()
                explainer.explain(obs, outputs, rise, sample_inputs)
                times[n].append(time.perf_counter() - t0)

    load = "load average {:.1f} {:.1f} {:.1f}".format(*os.getloadavg())
    print(f"{args.run_dir}, {len(steps)} steps, {platform.machine()}, {os.cpu_count()} CPU cores, {load}")
    print(f"{'kind':>10} {'estimator':>9} {'option':>6} {'N':>4} {'camera':>18} {'top-1':>6} {'rho':>6} {'del k=1':>8}")
    for (kind, name, option, n, c), values in rows.items():
        top1, rho, ratio = (np.asarray(v, np.float64) for v in zip(*values, strict=True))
        print(
            f"{kind:>10} {name:>9} {option:6.2f} {n:4d} {c:>18} {np.mean(top1):6.0%} {np.nanmean(rho):6.2f} "
            f"{np.nanmedian(ratio):8.2f}"
        )
    for n, values in times.items():
        if values:
            print(f"rise, {n} masks per camera: median {statistics.median(values) * 1e3:.1f} ms per explained step")


if __name__ == "__main__":
    main()
