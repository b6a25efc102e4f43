"""`openpi-cam demo`: the whole system on the bundled tiny model, on CPU, in about a minute."""

from __future__ import annotations

import pathlib
from typing import Literal

from openpi_cam.cam.faithfulness_run import format_report
from openpi_cam.demo.run import DemoOptions, run_demo
from openpi_cam.viz.stats import MAP_LABELS
from openpi_cam.vocabulary import MAP_KINDS, MapKind, Target


def main(
    out: pathlib.Path = pathlib.Path("demo_runs"),
    episodes: int = 3,
    max_calls: int = 6,
    execute: int = 5,
    seed: int = 0,
    target: Target = "chunk",
    render: bool = True,
    videos: bool = False,
    model: Literal["pi0_fast", "pi05"] = "pi0_fast",
    assets: pathlib.Path | None = None,
    maps: tuple[MapKind, ...] = MAP_KINDS,
    faithfulness: bool = True,
    baseline: Literal["mean", "blur"] = "mean",
    ig_space: Literal["tokens", "pixels"] = "tokens",
) -> int:
    """Run the bundled model end to end: server + side channel + simulated robot + rendered reports + figures.

    Args:
        out: directory for the CAM run (a new run directory is created inside).
        episodes: simulated reaching episodes to drive.
        max_calls: inference calls per episode at most.
        execute: actions of each returned chunk the robot executes before asking again.
        seed: first episode seed (episode i uses seed + i).
        target: what the maps explain for each inference.
        render: write overlays and the HTML report of each map kind after the run.
        videos: also write MP4/GIF videos (needs the viz extra).
        model: which bundled model serves: the tiny pi0-FAST (default) or the tiny pi0.5 trained on the same task.
        assets: directory holding the model (checkpoint/) and its tokenizers (default: the bundled ones of `model`).
        maps: which map kinds the side channel computes (all four by default, to compare them).
        faithfulness: re-score every step afterwards and print how faithful each map kind is.
        baseline: the frame `ig` starts from and `occlusion` (and the faithfulness deletion) paints with.
        ig_space: where the `ig` path runs: between the SigLIP tokens of the baseline frame and the frame, or between
            the frames' pixels (through SigLIP).
    """
    opts = DemoOptions(
        out,
        episodes,
        max_calls,
        execute,
        seed,
        target,
        render,
        videos,
        model,
        assets,
        maps,
        faithfulness,
        baseline,
        ig_space,
    )
    try:
        result = run_demo(opts)
    except OSError as e:
        print(f"openpi-cam demo: {e}")
        return 1
    wins = sum(r["success"] for r in result.episodes)
    print(f"\nopenpi-cam demo: {wins}/{len(result.episodes)} episodes reached their block in {result.seconds:.0f}s")
    figures = result.figures
    print(f"pointing game over {figures['steps']} steps (the base camera's map peaks on the named block):")
    for kind, f in figures["maps"].items():
        if not f["steps"]:
            continue
        print(f"  {MAP_LABELS[kind]:>36}: {f['pointing_game']:.0%} (chance {f['pointing_chance']:.0%})")
    if result.faithfulness is not None:
        print()
        print(format_report(result.faithfulness))
        print()
    print(f"run directory: {result.run_dir}")
    for kind, report in result.reports.items():
        print(f"open the {MAP_LABELS[kind]} report: {report}")
    return 0
