"""`openpi-cam demo`: the whole system on a bundled tiny model, on CPU, in about a minute (the reaching task) or a
few (Meta-World, `--sim metaworld`)."""

from __future__ import annotations

import contextlib
import json
import pathlib

import tyro

from openpi_cam.cam.faithfulness_run import format_report
from openpi_cam.cam.outcomes import wilson_interval
from openpi_cam.demo.recorded import recorded_episodes_file
from openpi_cam.demo.run import ROLLOUT_FPS, ROLLOUT_FPS_METAWORLD, DemoOptions, UnfitModel, run_demo
from openpi_cam.lerobot.dataset import DatasetError
from openpi_cam.lerobot.rollouts import RolloutRecorder
from openpi_cam.policies import demo_metaworld, demo_reach
from openpi_cam.vocabulary import MAP_KIND_INFO

DEFAULT = DemoOptions()


def main(opts: tyro.conf.OmitArgPrefixes[DemoOptions] = DEFAULT, record: pathlib.Path | None = None) -> int:
    """Run a bundled model end to end: server + side channel + simulated robot + rendered reports + figures.

    Args:
        opts: what to run (every flag below).
        record: also record every episode as a LeRobot v3.0 dataset in this new folder, as `lerobot-eval
            --eval.recording=true` records evaluation rollouts: per executed action the cameras (AV1 video), the
            state, the action, the target's box in the base camera (`observation.target_box`: the named block, or
            Meta-World's button box), the perturbation's index
            (`perturbation`) and `next.reward` / `next.success` / `next.done`; `meta/demo_episodes.json` names each
            episode's perturbation, seed and outcome.
    """
    if ignored := opts.ignored():
        print(f"openpi-cam demo: {', '.join(ignored)}: {'; '.join(dict.fromkeys(ignored.values()))}")
        return 2
    if record is not None and record.exists() and (not record.is_dir() or any(record.iterdir())):
        print(f"openpi-cam demo: --record {record} exists and is not an empty folder")
        return 1
    if record is not None and any(p.kind == "prompt" and not p.strength for p in opts.perturbations):
        print("openpi-cam demo: --record cannot record an empty prompt (a LeRobot task is non-empty): prompt=TEXT")
        return 1
    metaworld = opts.sim == "metaworld"
    fps, robot = (ROLLOUT_FPS_METAWORLD, demo_metaworld.ASSET_ID) if metaworld else (ROLLOUT_FPS, demo_reach.ASSET_ID)
    recorder = None if record is None else RolloutRecorder(record, fps=fps, robot_type=robot)
    try:
        with recorder or contextlib.nullcontext():
            result = run_demo(opts, sink=recorder)
    except (OSError, DatasetError, ImportError, UnfitModel) as e:
        print(f"openpi-cam demo: {e}")
        return 1
    if record is not None:
        episodes = [{"episode_index": i, **e} for i, e in enumerate(result.episodes)]
        rollouts = {"perturbations": list(opts.perturb), "episodes": episodes}
        recorded_episodes_file(record).write_text(json.dumps(rollouts, indent=2))
    wins = sum(r["success"] for r in result.episodes)
    goal = "succeeded at their task" if metaworld else "reached their block"
    print(f"\nopenpi-cam demo: {wins}/{len(result.episodes)} episodes {goal} in {result.seconds:.0f}s")
    if metaworld or len(opts.perturb) > 1 or opts.perturbations[0].kind != "clean":
        tasks = opts.tasks if metaworld else (None,)
        for task in tasks:
            for name in opts.perturb:
                group = [r for r in result.episodes if r["perturbation"] == name and r.get("task") == task]
                outcomes = [r["success"] for r in group]
                low, high = wilson_interval(sum(outcomes), len(outcomes))
                label = name if task is None else f"{task} {name}"
                print(f"  {label:>40}: {sum(outcomes)}/{len(outcomes)} (95% interval {low:.0%}-{high:.0%})")
    figures = result.figures
    flags = figures.get("monitor_flags")
    if flags is not None and len(flags) == len(result.episodes):
        failed = [f for f, r in zip(flags, result.episodes, strict=True) if not r["success"]]
        succeeded = [f for f, r in zip(flags, result.episodes, strict=True) if r["success"]]
        print(
            f"failure monitor (the model's own, every call scored): flagged {sum(failed)}/{len(failed)} failed and "
            f"{sum(succeeded)}/{len(succeeded)} successful episodes"
        )
    if figures["steps"]:
        target = "the task's target" if metaworld else "the named block"
        print(f"pointing game over {figures['steps']} steps (the base camera's map peaks on {target}):")
    for kind, f in figures["maps"].items():
        if not f["steps"]:
            continue
        print(f"  {MAP_KIND_INFO[kind].label:>36}: {f['pointing_game']:.0%} (chance {f['pointing_chance']:.0%})")
    if result.faithfulness is not None:
        print()
        print(format_report(result.faithfulness))
        print()
    if result.run_dir is not None:
        print(f"run directory: {result.run_dir}")
    for kind, report in result.reports.items():
        print(f"open the {MAP_KIND_INFO[kind].label} report: {report}")
    if record is not None:
        print(f"recorded {len(result.episodes)} episodes as a LeRobot dataset: {record}")
    return 0
