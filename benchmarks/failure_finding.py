"""Do the maps find the failures? The demo's failing rollouts, explained and measured, per model family.

    python benchmarks/failure_finding.py --out /tmp/failures [--per-perturbation 40] [--sim metaworld]

For each bundled model of the reaching task (pi0-FAST, pi0.5), or the multi-task Meta-World pi0.5 on the demo's
button task with `--sim metaworld` (perturbed by `METAWORLD_PERTURB` instead, with `--sim metaworld --model pi05` in
the first command and its config in the second; the one-task button pi0.5 these strengths were chosen on is no
longer one the demo drives), with the commands a user runs:

1. `openpi-cam demo --model M --no-explain --num-episodes 6N --perturb clean distractors=2 hue=45 shift=32 dim=0.3
   absent --record OUT/M.lerobot`: N closed-loop episodes per perturbation through the websocket server, recorded
   as a LeRobot v3.0 dataset with lerobot-eval's outcome features (the same N scenes under every perturbation);
2. `openpi-cam explain-dataset OUT/M.lerobot --maps gradnorm occlusion --every-k 5 --reliance --extra
   observation.target_box=target_box perturbation=perturbation`: every request frame (the robot asks every 5 steps)
   explained, with camera and prompt reliance, the named block's box carried for the nuisance mass;
3. the views of each map kind (`maps.views.compute_views`, what `stats --format json` prints).

Printed as markdown: success per perturbation with Wilson intervals; per map kind, each episode figure's ROC AUC for
finding the failures (whole episodes, with the episode length beside it, and from each episode's first request
only), its precision at the number of failures; camera and prompt reliance in successes vs failures; how nuisance
mass goes with success (episode-level point-biserial r, and across the perturbations). Steps already done (an
existing recording or maps dataset) are reused.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import time

import numpy as np
from bench_serving import machine_line
from PIL import Image

from openpi_cam import cli
from openpi_cam.cam.outcomes import roc_auc, wilson_interval
from openpi_cam.checkpoints.model_spec import BUNDLED_CONFIGS
from openpi_cam.demo.recorded import recorded_episodes_file
from openpi_cam.maps.dataset import EPISODE_SUCCESS, MapsDataset, is_maps_dataset, open_maps_dataset
from openpi_cam.maps.views import DatasetViews, compute_views, displayable, normalised

PERTURB = ("clean", "distractors=2", "hue=45", "shift=32", "dim=0.3", "absent")
# Meta-World's strengths, chosen (8 episodes each) so that the policy fails some of the time: hue 30 and 60 gave 8/8
# and 0/8, dim 0.8 and 0.7 gave 7/8 and 2/8, a 5 cm camera shift 3/8; five distractor cubes 8/8.
METAWORLD_PERTURB = ("clean", "hue=45", "dim=0.75", "shift=0.05", "distractors=5", "prompt=open the drawer")
KINDS = ("gradnorm", "occlusion")
LABELS = {"pi0_fast": "pi0-FAST", "pi05": "pi0.5", "metaworld_mt_pi05": "Meta-World multi-task pi0.5"}


def record(model: str, out: pathlib.Path, per: int) -> None:
    if out.exists():
        return
    sim = ["--sim", "metaworld", "--model", "pi05"] if model == "metaworld_mt_pi05" else ["--model", model]
    argv = ["demo", *sim, "--no-explain", "--num-episodes", str(per * len(PERTURB))]
    cli.main([*argv, "--perturb", *PERTURB, "--record", str(out)])


def explain(model: str, source: pathlib.Path, out: pathlib.Path) -> float:
    if is_maps_dataset(out) and (out / "meta" / "summary.json").is_file():
        return math.nan
    t0 = time.perf_counter()
    argv = ["explain-dataset", str(source), "--out", str(out), "--config", BUNDLED_CONFIGS[model].name]
    argv += ["--maps", *KINDS, "--check-patches", "0", "--every-k", "5", "--reliance", "--no-progress"]
    cli.main([*argv, "--extra", "observation.target_box=target_box", "perturbation=perturbation"])
    return time.perf_counter() - t0


def _f(x: float | None, digits: int = 2) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def success_table(rollouts: dict[str, dict]) -> list[str]:
    lines = ["| perturbation | " + " | ".join(LABELS[m] for m in rollouts) + " |", "|---" * (len(rollouts) + 1) + "|"]
    for name in PERTURB:
        cells = []
        for data in rollouts.values():
            wins = [e["success"] for e in data["episodes"] if e["perturbation"] == name]
            low, high = wilson_interval(sum(wins), len(wins))
            cells.append(f"{sum(wins)}/{len(wins)} ({low:.0%}-{high:.0%})")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def finding_table(views: dict[str, DatasetViews]) -> list[str]:
    """One row per episode figure, per model and map kind: whole-episode AUROC (95%), precision at #failures, the
    first request's AUROC."""
    head = "| figure | " + " | ".join(f"{LABELS[m]} {k}" for m, k in views) + " |"
    lines = [head, "|---" * (len(views) + 1) + "|"]
    names = list(dict.fromkeys(n for v in views.values() for n in v.outcomes["failure_finding"]))
    for name in names:
        cells = []
        for v in views.values():
            f = v.outcomes["failure_finding"].get(name)
            e = v.outcomes["early_warning"]["figures"].get(name)
            if f is None or f["auroc"] is None:
                cells.append("-")
                continue
            low, high = f["auroc_ci95"]
            early = "" if e is None or e["auroc"] is None else f"; first request {_f(e['auroc'])}"
            cells.append(f"{_f(f['auroc'])} ({_f(low)}-{_f(high)}), P@F {_f(f['precision_at_failures'])}{early}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


WITHIN = ("length", "entropy", "distance", "base_0_rgb/mean_nuisance_mass", "prompt/mean_reliance_score")


def within_table(views: dict[str, DatasetViews], perturbation_of: dict[str, dict[int, int]]) -> list[str]:
    """The same AUROCs inside each perturbation that both succeeds and fails at least 5 times: whether a figure
    finds the failures, rather than the perturbations that cause most of them."""
    lines = ["| model | map | perturbation | failures | " + " | ".join(WITHIN) + " |", "|---" * (len(WITHIN) + 4) + "|"]
    for (model, kind), v in views.items():
        figures = {e["episode_index"]: e for e in v.episodes}
        for p, name in enumerate(PERTURB):
            chosen = [e for e, q in perturbation_of[model].items() if q == p and e in figures]
            failed = np.array([not figures[e]["success"] for e in chosen])
            if failed.sum() < 5 or (~failed).sum() < 5:
                continue
            values = {name: [_figure(figures[e], name) for e in chosen] for name in WITHIN}
            cells = [_f(roc_auc(failed, values[name])) for name in WITHIN]
            lines.append(
                f"| {LABELS[model]} | {kind} | {name} | {failed.sum()}/{len(chosen)} | " + " | ".join(cells) + " |"
            )
    return lines


def _figure(episode: dict, name: str) -> float:
    """An episode figure of `outcome_views` from the ranking's entry of the episode."""
    if name in ("length", "entropy", "distance"):
        value = episode[name]
    elif name.startswith("prompt/"):
        value = episode["prompt"][name.split("/", 1)[1]]
    else:
        camera, key = name.split("/", 1)
        value = episode["cameras"][camera][key]
    return math.nan if value is None else float(value)


def reliance_table(views: dict[str, DatasetViews]) -> list[str]:
    lines = ["| model | what | successes: score drop / action change | failures: score drop / action change |"]
    lines.append("|---|---|---|---|")
    for (model, kind), v in views.items():
        if kind != KINDS[0]:
            continue
        groups = v.outcomes["by_outcome"]
        for what in [*v.cameras, "prompt"]:
            cells = []
            for name in ("success", "failure"):
                entry = groups[name]["prompt"] if what == "prompt" else groups[name]["cameras"][what]
                if entry["mean_reliance_score"] is None:
                    break
                cells.append(f"{_f(entry['mean_reliance_score'])} / {_f(entry['mean_reliance_actions'], 3)}")
            if len(cells) == 2:
                lines.append(f"| {LABELS[model]} | {what} | {cells[0]} | {cells[1]} |")
    return lines


def nuisance_lines(views: dict[str, DatasetViews], perturbation_of: dict[str, dict[int, int]]) -> list[str]:
    """Point-biserial r between an episode's success and its mean nuisance mass (base camera), and Pearson r across
    the perturbations between success rate and mean nuisance mass."""
    lines = ["| model | map | episodes | r(success, nuisance) per episode | r across the 6 perturbations |"]
    lines.append("|---|---|---|---|---|")
    for (model, kind), v in views.items():
        camera = v.cameras[0]
        eps = [e for e in v.episodes if e["cameras"][camera]["mean_nuisance_mass"] is not None]
        success = np.array([float(e["success"]) for e in eps])
        nuisance = np.array([e["cameras"][camera]["mean_nuisance_mass"] for e in eps])
        r_episode = float(np.corrcoef(success, nuisance)[0, 1])
        which = np.array([perturbation_of[model][e["episode_index"]] for e in eps])
        rates = [success[which == p].mean() for p in range(len(PERTURB))]
        means = [nuisance[which == p].mean() for p in range(len(PERTURB))]
        r_condition = float(np.corrcoef(rates, means)[0, 1])
        lines.append(f"| {LABELS[model]} | {kind} | {len(eps)} | {r_episode:+.2f} | {r_condition:+.2f} |")
    return lines


def outcome_maps(ds: MapsDataset, kind: str, perturbation_of: dict[int, int], png: pathlib.Path) -> list[str]:
    """Per perturbation, each camera's mean map (every frame's map normalised to sum 1, as the views' prior; unlike
    the prior, a frame without positive mass counts, as zeros) over the frames of failed and of successful episodes,
    side by side: a PNG (a row per perturbation; per camera, failures
    then successes, each map scaled to its own maximum) and the frames behind each mean."""
    table = ds.table(columns=["episode_index", EPISODE_SUCCESS]).to_pydict()
    episode, success = np.array(table["episode_index"]), np.array(table[EPISODE_SUCCESS], bool)
    which = np.array([perturbation_of[e] for e in episode])
    cameras = [c for c in ds.cameras if ds.maps(kind, c).any()]
    maps = {c: normalised(displayable(ds.maps(kind, c)))[0] for c in cameras}
    lines = ["| perturbation | " + " | ".join(f"{c}: failed / successful frames" for c in cameras) + " |"]
    lines.append("|---" * (len(cameras) + 1) + "|")
    cell, gap = 64, 8
    rows = []
    for p, name in enumerate(PERTURB):
        row, counts = [], []
        for c in cameras:
            for failed in (True, False):
                use = (which == p) & (success != failed)
                mean = maps[c][use].mean(axis=0) if use.any() else np.zeros(ds.grid(c))
                scaled = mean / mean.max() if mean.max() > 0 else mean
                # nearest-neighbour to one cell size whatever the grid (4 x 4 for the demo, 6 x 6 at 96 px)
                up = Image.fromarray((scaled * 255).astype(np.uint8)).resize((cell, cell), Image.Resampling.NEAREST)
                row += [np.asarray(up), np.full((cell, gap), 128, np.uint8)]
                counts.append(int(use.sum()))
        rows += [np.concatenate(row, axis=1), np.full((gap, sum(r.shape[1] for r in row)), 128, np.uint8)]
        cells = [f"{counts[2 * i]} / {counts[2 * i + 1]}" for i in range(len(cameras))]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    Image.fromarray(np.concatenate(rows, axis=0)).save(png)
    return [f"mean {kind} maps of failed / successful episodes per perturbation: {png}", *lines]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=pathlib.Path, required=True)
    parser.add_argument("--per-perturbation", type=int, default=40)
    parser.add_argument("--sim", choices=["reach", "metaworld"], default="reach")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if args.sim == "metaworld":
        global PERTURB
        PERTURB = METAWORLD_PERTURB
    models = ["metaworld_mt_pi05"] if args.sim == "metaworld" else ["pi0_fast", "pi05"]
    load_before = os.getloadavg()
    rollouts, views, perturbation_of, seconds, outcome_lines = {}, {}, {}, {}, {}
    for model in models:
        source, maps = args.out / f"{model}.lerobot", args.out / f"{model}.maps"
        record(model, source, args.per_perturbation)
        seconds[model] = explain(model, source, maps)
        rollouts[model] = json.loads(recorded_episodes_file(source).read_text())
        ds = open_maps_dataset(maps)
        table = ds.table(columns=["episode_index", "extra/perturbation"]).to_pydict()
        perturbation_of[model] = {
            e: int(p[0]) for e, p in zip(table["episode_index"], table["extra/perturbation"], strict=True)
        }
        for kind in KINDS:
            views[(model, kind)] = compute_views(ds, kind)
            outcome_lines[(model, kind)] = outcome_maps(
                ds, kind, perturbation_of[model], args.out / f"{model}_{kind}_outcome_maps.png"
            )
    print(machine_line(load_before, os.getloadavg()))
    print("explain-dataset seconds: " + ", ".join(f"{LABELS[m]} {_f(s, 0)}" for m, s in seconds.items()))
    for lines in (
        success_table(rollouts),
        finding_table(views),
        within_table(views, perturbation_of),
        reliance_table(views),
        nuisance_lines(views, perturbation_of),
        *outcome_lines.values(),
    ):
        print()
        print("\n".join(lines))


if __name__ == "__main__":
    main()
