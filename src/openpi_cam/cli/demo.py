"""`openpi-cam demo`: the whole system on a bundled tiny model, on CPU, in about a minute (the reaching task) or a
few (Meta-World, `--sim metaworld`)."""

from __future__ import annotations

import math

import tyro

from openpi_cam.cam.faithfulness_run import format_report
from openpi_cam.demo.run import DemoOptions, run_demo
from openpi_cam.vocabulary import MAP_KIND_INFO

DEFAULT = DemoOptions()
Z95 = 1.959964  # the standard normal's 97.5% quantile


def wilson_interval(successes: int, n: int) -> tuple[float, float]:
    """The 95% Wilson score interval of a success rate (sound at 0 or n successes, unlike the normal one)."""
    if n == 0:
        return 0.0, 1.0
    p, z2 = successes / n, Z95**2
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = Z95 * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def main(opts: tyro.conf.OmitArgPrefixes[DemoOptions] = DEFAULT) -> int:
    """Run a bundled model end to end: server + side channel + simulated robot + rendered reports + figures.

    Args:
        opts: what to run (every flag below).
    """
    try:
        result = run_demo(opts)
    except OSError as e:
        print(f"openpi-cam demo: {e}")
        return 1
    wins = sum(r["success"] for r in result.episodes)
    goal = "pressed the button" if opts.sim == "metaworld" else "reached their block"
    print(f"\nopenpi-cam demo: {wins}/{len(result.episodes)} episodes {goal} in {result.seconds:.0f}s")
    if opts.sim == "metaworld":
        print("success per perturbation (95% Wilson interval):")
        for name in dict.fromkeys(r["perturbation"] for r in result.episodes):
            outcomes = [r["success"] for r in result.episodes if r["perturbation"] == name]
            low, high = wilson_interval(sum(outcomes), len(outcomes))
            print(f"  {name:>20}: {sum(outcomes)}/{len(outcomes)} ({low:.0%}-{high:.0%})")
    figures = result.figures
    print(f"pointing game over {figures['steps']} steps (the base camera's map peaks on the target):")
    for kind, f in figures["maps"].items():
        if not f["steps"]:
            continue
        print(f"  {MAP_KIND_INFO[kind].label:>36}: {f['pointing_game']:.0%} (chance {f['pointing_chance']:.0%})")
    if result.faithfulness is not None:
        print()
        print(format_report(result.faithfulness))
        print()
    print(f"run directory: {result.run_dir}")
    for kind, report in result.reports.items():
        print(f"open the {MAP_KIND_INFO[kind].label} report: {report}")
    return 0
