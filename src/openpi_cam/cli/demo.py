"""`openpi-cam demo`: the whole system on the bundled tiny model, on CPU, in about a minute."""

from __future__ import annotations

import tyro

from openpi_cam.cam.faithfulness_run import format_report
from openpi_cam.demo.run import DemoOptions, run_demo
from openpi_cam.vocabulary import MAP_KIND_INFO

DEFAULT = DemoOptions()


def main(opts: tyro.conf.OmitArgPrefixes[DemoOptions] = DEFAULT) -> int:
    """Run the bundled model end to end: server + side channel + simulated robot + rendered reports + figures.

    Args:
        opts: what to run (every flag below).
    """
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
        print(f"  {MAP_KIND_INFO[kind].label:>36}: {f['pointing_game']:.0%} (chance {f['pointing_chance']:.0%})")
    if result.faithfulness is not None:
        print()
        print(format_report(result.faithfulness))
        print()
    print(f"run directory: {result.run_dir}")
    for kind, report in result.reports.items():
        print(f"open the {MAP_KIND_INFO[kind].label} report: {report}")
    return 0
