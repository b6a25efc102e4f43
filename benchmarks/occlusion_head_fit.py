"""Held-out agreement of fitted occlusion heads with occlusion, beside each input kind alone, over several split seeds:
the figures docs/MAP_KINDS.md reports for the `occlusion-head` kind.

`openpi-cam head fit` holds out one seeded share of the episodes; on ~100 frames that is ~25 frames, so one split's
figures move by several points with the seed. This script fits one head per seed (`maps.head_fit`: the same
examples, split, training and evaluation as the command) and prints, per camera, the mean over seeds of the head's and
each input's held-out top-1 agreement and median Spearman correlation with occlusion, and the position prior's (the
fitting episodes' mean occlusion map), with their range, and the same for the fitting episodes (how far the head
over-fits). Deletion is not measured here (it needs the model): explain
frames with the kind and run `openpi-cam faithfulness`.

    openpi-cam demo --no-explain --num-episodes 40 --seed 20000 --perturb clean distractors=2 hue=45 shift=32 \\
        --record R
    openpi-cam explain-dataset R --maps gradcam gradnorm lrp ig occlusion --every-k 5 --check-patches 0 --out R.maps
    python benchmarks/occlusion_head_fit.py R.maps --inputs gradcam gradnorm lrp --seeds 0 1 2 3 4 5 6 7
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from openpi_cam.maps.head_fit import (
    HeadFitOptions,
    evaluate,
    head_from,
    position_prior,
    read_examples,
    split,
    train,
)


def _stats(values: list[float | None], percent: bool = False) -> str:
    x = np.asarray([v for v in values if v is not None], np.float64)
    if not x.size:
        return "-"
    if percent:
        return f"{x.mean():.0%} [{x.min():.0%}, {x.max():.0%}]"
    return f"{x.mean():+.2f} [{x.min():+.2f}, {x.max():+.2f}]"


def _table(per_seed: list[dict[str, Any]], title: str) -> list[str]:
    width = max(len(c) for c in per_seed[0]["by_camera"]) + 2
    lines = [title, f"{'camera':<{width}}{'map':<18}{'top-1, mean [range]':>24}{'Spearman median, mean [range]':>32}"]
    for camera in per_seed[0]["by_camera"]:
        if not per_seed[0]["by_camera"][camera]["head"]["examples"]:
            continue  # never valid (pi0.5's blank right wrist)
        names = ["head", "prior", *per_seed[0]["by_camera"][camera]["inputs"]]
        for i, name in enumerate(names):

            def pick(figures: dict[str, Any], name: str = name, camera: str = camera) -> dict[str, Any]:
                per_camera = figures["by_camera"][camera]
                return per_camera[name] if name in ("head", "prior") else per_camera["inputs"][name]

            top1 = _stats([pick(f)["top1"] for f in per_seed], percent=True)
            rho = _stats([pick(f)["spearman_median"] for f in per_seed])
            label = {"head": "head", "prior": "position prior"}.get(name, f"{name} alone")
            lines.append(f"{camera if i == 0 else '':<{width}}{label:<18}{top1:>24}{rho:>32}")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("maps", nargs="+", type=Path, help="maps datasets of one policy (input kinds and occlusion)")
    parser.add_argument("--inputs", nargs="+", default=list(HeadFitOptions.inputs))
    parser.add_argument("--seeds", nargs="+", type=int, default=list(range(8)))
    parser.add_argument("--hidden", type=int, default=HeadFitOptions.hidden)
    parser.add_argument("--holdout", type=float, default=HeadFitOptions.holdout)
    parser.add_argument("--temperature", type=float, default=HeadFitOptions.temperature)
    parser.add_argument("--mse-weight", type=float, default=HeadFitOptions.mse_weight)
    args = parser.parse_args()
    base = HeadFitOptions(
        inputs=tuple(args.inputs),
        hidden=args.hidden,
        holdout=args.holdout,
        temperature=args.temperature,
        mse_weight=args.mse_weight,
    )
    t0 = time.perf_counter()
    examples = read_examples(args.maps, base.inputs)
    held_out, fitting = [], []
    for seed in args.seeds:
        options = dataclasses.replace(base, seed=seed)
        fit_rows, held_rows = split(examples, options.holdout, seed)
        weights, _ = train(examples.subset(fit_rows), options)
        head = head_from(examples, weights, {})
        prior = position_prior(examples.subset(fit_rows))
        held_out.append(evaluate(head, examples.subset(held_rows), prior))
        fitting.append(evaluate(head, examples.subset(fit_rows), prior))
    seconds = time.perf_counter() - t0
    per_camera = ", ".join(f"{c} {int(np.sum(examples.camera == i))}" for i, c in enumerate(examples.cameras))
    print(
        f"{examples.model.get('config')} ({examples.family}), {examples.target_name} maps of {len(examples.episodes)} "
        f"episodes ({per_camera}); inputs {' '.join(base.inputs)}, hidden {base.hidden}, weight decay "
        f"{base.weight_decay}, {len(args.seeds)} seeds, holdout {base.holdout}"
    )
    print(
        f"machine: {platform.machine()} {os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}; {seconds:.0f} s"
    )
    print("\n".join(_table(held_out, "\nheld-out episodes (agreement with occlusion)")))
    print("\n".join(_table(fitting, "\nfitting episodes")))


if __name__ == "__main__":
    main()
