"""Does the failure monitor transfer? Each bundled model's monitor fitted on dev rollouts, shipped, and measured on
rollouts it never saw: other seeds and perturbation strengths, and (multi-task Meta-World) tasks it was not fitted on.

    python benchmarks/monitor_transfer.py --out DIR [--settings reach-pi0_fast ...] [--ship]

Per setting (a bundled model, `SETTINGS`), with the commands a user runs:

1. `openpi-cam demo ... --no-explain --seed S --perturb P... --num-episodes N --record OUT/<split>.lerobot`: closed
   loops recorded with their outcomes, for the splits `dev` (seed `DEV_SEED`, the dev strengths), `test` (the
   setting's test seed, other strengths) and, for multi-task models, `unseen` (the test seeds and strengths on tasks the
   monitor is not fitted on: two the policy was trained on, two it never saw);
2. `openpi-cam explain-dataset OUT/<split>.lerobot --config C --maps gradnorm --every-k 5 --monitor-features
   --no-monitor`: every request frame with its monitor inputs (pooled last-layer features, STAC-single, token entropy);
3. the monitor kinds (`CANDIDATES`) are compared on dev alone, by two folds over its scenes (fit on one half, AUROC
   at the setting's early frame count and over whole episodes on the other) and, for multi-task models, by leaving
   each task out in turn (fit on the others, the held-out tasks' scores pooled: how a monitor carries over to tasks
   it was not fitted on, which is what `unseen` measures); the best mean is fitted on all of dev with `openpi-cam
   monitor fit` and, with `--ship`, copied beside the bundled checkpoint (`<assets>/monitor.json`), where `serve`
   and `explain-dataset` use it by default;
4. the test and unseen recordings explained again on default monitor flags (the shipped monitor), and `openpi-cam
   stats --format json`'s `outcomes.detection` read: the monitor's AUROC from the first N source frames beside
   STAC-single, token entropy and the map figures; the other candidates (fitted on dev) scored on the same frames.

The splits and perturbation strengths below were fixed before anything was measured; nothing is chosen on `test` or
`unseen`. Each change to the protocol after a look at test gets fresh test scenes (`Setting.test_seed`, the rounds of
docs/MONITOR.md): round 1 tested on seed 50000; round 2 (the union and the task folds added) on 60000; round 3 (the
multi-task models' dev enlarged from 3 to 9 scenes per task and perturbation) on 70000; round 4 (the reaching
models' dev enlarged from 32 to 96 scenes per perturbation) on 80000; round 5 (the same dev and choice, their test
enlarged from 8 to 32 scenes per perturbation: 48 episodes put +-0.15 on an AUROC) on 90000; the multi-task models'
round 4 (the `gated` candidate added, their test and unseen splits enlarged from 3 to 6 scenes per task and
perturbation) on 110000; their round 5 (the gated monitor told the instructions the policy was trained on, `monitor
fit --trained-prompts`: a step under any other is flagged from the first call) on 120000. Stages already done are
reused (delete a folder to redo it). Writes OUT/<setting>/report.json and prints markdown tables.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import pathlib
import shutil
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from bench_serving import machine_line

from openpi_cam import cli
from openpi_cam.checkpoints.model_spec import BUNDLED_CONFIGS, MONITOR_FILE, ModelSpec
from openpi_cam.demo import metaworld_sim
from openpi_cam.maps.dataset import open_maps_dataset
from openpi_cam.maps.monitoring import Rollouts, read_rollouts
from openpi_cam.monitor import monitor_file
from openpi_cam.monitor.detection import ScoredEpisode, detection
from openpi_cam.monitor.fit import Episode, FitOptions, fit_monitor, split_episodes

DEV_SEED = 40_000  # disjoint from the demos' (0), evaluations' (10000), the maps bench's and the experts' seeds
REACH_DEV = ("clean", "distractors=2", "hue=45", "shift=32", "dim=0.3", "absent")
REACH_TEST = ("clean", "distractors=1", "hue=60", "shift=24", "dim=0.4", "absent")
MW_DEV = ("clean", "hue=45", "dim=0.75")
MW_TEST = ("clean", "hue=30", "dim=0.7")
SEEN = ("button-press-topdown-v3", "reach-v3", "push-v3", "drawer-close-v3")
UNSEEN = ("door-open-v3", "window-open-v3", *metaworld_sim.HELD_OUT_TASKS)
ALPHA, FEW_SUCCESSES_ALPHA = 0.1, 0.2  # the shipped monitors' false-alarm rate on successful episodes
CHOICE = "choice"  # the dev folds' figure a monitor kind is chosen by
EVERY_K = 5  # the demo robots execute 5 actions a call: every request frame
# The monitors compared on dev: name -> (`monitor fit --kind`, `--temporal`).
CANDIDATES = {
    "stac": ("stac", False),
    "mahalanobis": ("mahalanobis", False),
    "mahalanobis-temporal": ("mahalanobis", True),
    "probe": ("probe", False),
    "probe-temporal": ("probe", True),
    "union": ("union", False),
    "union-temporal": ("union", True),
    "gated": ("gated", False),
    "gated-temporal": ("gated", True),
}


@dataclasses.dataclass(frozen=True)
class Setting:
    """A bundled model and the rollouts its monitor is fitted and measured on."""

    name: str
    model: str  # `model_spec.BUNDLED_CONFIGS` key
    demo: tuple[str, ...]  # the `openpi-cam demo` flags that pick the model (and tasks)
    dev: tuple[str, ...]
    test: tuple[str, ...]
    scenes: int  # scenes per test split; every task and perturbation meets each
    early: int  # the source frames the target reads the AUROC at
    tasks: tuple[str, ...] = ()  # Meta-World: the tasks the monitor is fitted on (empty: the reaching task)
    dev_scenes: int | None = None  # scenes of dev (default: `scenes`)
    test_seed: int = 60_000  # the round's fresh test scenes (module docstring)
    trained: tuple[str, ...] = ()  # the instructions the policy was trained on, told to gated monitors

    def splits(self) -> dict[str, tuple[tuple[str, ...], tuple[str, ...], int, int]]:
        """split -> (perturbations, tasks, seed, scenes)."""
        dev = (self.dev, self.tasks, DEV_SEED, self.dev_scenes or self.scenes)
        out = {"dev": dev, "test": (self.test, self.tasks, self.test_seed, self.scenes)}
        if self.tasks:
            out["unseen"] = (self.test, UNSEEN, self.test_seed, self.scenes)
        return out


def _reach(family: str) -> Setting:
    return Setting(
        f"reach-{family}", family, ("--model", family), REACH_DEV, REACH_TEST, 32, 4, dev_scenes=96, test_seed=90_000
    )


def _metaworld(family: str) -> Setting:
    demo = ("--sim", "metaworld", "--model", family)
    name, model = f"metaworld-mt-{family}", f"metaworld_mt_{family}"
    trained = tuple(p for t in metaworld_sim.TRAINED_TASKS for p in metaworld_sim.TASKS[t].prompts)
    return Setting(
        name, model, demo, MW_DEV, MW_TEST, 6, 32, tasks=SEEN, dev_scenes=9, test_seed=120_000, trained=trained
    )


SETTINGS = (
    _reach("pi0_fast"),
    _reach("pi05"),
    _metaworld("pi05"),
    _metaworld("pi0_fast"),
)


def record(setting: Setting, split: str, out: pathlib.Path) -> None:
    if (out / "meta" / "info.json").is_file():
        return
    perturb, tasks, seed, scenes = setting.splits()[split]
    episodes = scenes * len(perturb) * max(1, len(tasks))
    argv = ["demo", *setting.demo, "--no-explain", "--seed", str(seed), "--num-episodes", str(episodes)]
    argv += ["--perturb", *perturb, *(("--task", *tasks) if tasks else ())]
    cli.main([*argv, "--record", str(out)])


def explain(setting: Setting, source: pathlib.Path, out: pathlib.Path, monitor: str) -> None:
    """`explain-dataset` of every request frame with the monitor inputs; `monitor` "--no-monitor" or "" (default
    flags: the shipped monitor)."""
    if (out / "meta" / "summary.json").is_file():
        return
    argv = ["explain-dataset", str(source), "--out", str(out), "--config", BUNDLED_CONFIGS[setting.model].name]
    argv += ["--maps", "gradnorm", "--every-k", str(EVERY_K), "--monitor-features", "--no-progress"]
    argv += [monitor] if monitor else []
    cli.main([*argv, "--extra", "perturbation=perturbation"])


def scored(
    maps: pathlib.Path, monitors: dict[str, monitor_file.Monitor], only: Sequence[str] | None = None
) -> list[ScoredEpisode]:
    """Each episode of a maps dataset scored by every monitor (offline, over its explained frames in order); `only`:
    the episodes under these instructions alone."""
    rollouts = read_rollouts([maps])
    out = []
    keep = None if only is None else {monitor_file.instruction(p) for p in only}
    for episode in rollouts.episodes:
        if keep is not None and monitor_file.instruction(episode.prompts[0]) not in keep:
            continue
        scores = {name: m.score_steps(episode.matrix(m.inputs), episode.prompts) for name, m in monitors.items()}
        out.append(ScoredEpisode(episode.frames, scores, not episode.success))
    return out


def scene_folds(maps: pathlib.Path, setting: Setting) -> list[int]:
    """Each episode's fold (0 or 1) by the parity of its scene: the demo drives scene seed + i // (P T)."""
    per_scene = len(setting.dev) * max(1, len(setting.tasks))
    return [(episode // per_scene) % 2 for episode in open_maps_dataset(maps).episodes]


def fit(
    maps: Sequence[pathlib.Path],
    kind: str,
    temporal: bool,
    alpha: float,
    out: pathlib.Path,
    trained: Sequence[str] = (),
) -> monitor_file.Monitor:
    """`openpi-cam monitor fit` of one candidate (reused when its file is there); a gated one is told `trained`."""
    flags = ["--kind", kind, "--alpha", str(alpha), *(["--temporal"] if temporal else [])]
    flags += ["--trained-prompts", *trained] if kind == "gated" and trained else []
    if not out.is_file():
        code = cli.main(["monitor", "fit", *map(str, maps), *flags, "--out", str(out)])
        if code:
            raise SystemExit(f"monitor fit {flags} failed ({code})")
    return monitor_file.load(out)


def _aurocs(scored: Sequence[tuple[monitor_file.Monitor, Episode]], early: int) -> dict[str, float]:
    """The AUROC of episodes, each scored by its monitor, at `early` source frames and over whole episodes; one that
    cannot be computed (STAC on one call) counts as 0.5."""
    episodes = [
        ScoredEpisode(e.frames, {"m": m.score_steps(e.matrix(m.inputs), e.prompts)}, not e.success) for m, e in scored
    ]
    out = {}
    for entry in detection(episodes, (early,), resamples=10):
        auroc = entry["figures"]["m"]["auroc"]
        out[str(entry["frames"])] = 0.5 if auroc is None else auroc
    return out


def _split(episodes: Sequence[Episode], keys: Sequence[object], held: object) -> tuple[list[Episode], list[Episode]]:
    """(the episodes whose key is not `held`, those whose key is)."""
    pairs = list(zip(episodes, keys, strict=True))
    return [e for e, k in pairs if k != held], [e for e, k in pairs if k == held]


def choose(setting: Setting, dev_maps: pathlib.Path, rollouts: Rollouts) -> dict[str, dict[str, float]]:
    """Each candidate's AUROC on dev at the setting's early frame count and over whole episodes: over two folds of
    dev's scenes (fit on one half, ranked on the other; the two folds' mean, `scene <N>`), and for multi-task models
    with each task left out in turn (fit on the other tasks; the left-out episodes, each scored by the monitor that
    never saw its task, ranked together, `task <N>`); `CHOICE` is the mean of them all."""
    folds = scene_folds(dev_maps, setting)
    tasks = [e.prompts[0] for e in rollouts.episodes]  # each episode's instruction, as its rows carry it
    out = {}
    for name, (kind, temporal) in CANDIDATES.items():
        options = _options(kind, temporal, rollouts)
        figures: dict[str, float] = {}
        per_fold = []
        for held in (0, 1):
            train, rest = _split(rollouts.episodes, folds, held)
            monitor = fit_monitor(train, options)
            per_fold.append(_aurocs([(monitor, e) for e in rest], setting.early))
        figures |= {f"scene {n}": float(np.mean([f[n] for f in per_fold])) for n in per_fold[0]}
        if setting.tasks:
            scored = []
            for task in sorted(set(tasks)):
                train, rest = _split(rollouts.episodes, tasks, task)
                monitor = fit_monitor(train, options)
                scored += [(monitor, e) for e in rest]
            figures |= {f"task {n}": v for n, v in _aurocs(scored, setting.early).items()}
        out[name] = {**figures, CHOICE: float(np.mean(list(figures.values())))}
    return out


def false_alarm_rate(rollouts: Rollouts) -> float:
    """`ALPHA`, or `FEW_SUCCESSES_ALPHA` where dev's calibration share of successes is too small for it: the split
    conformal threshold at alpha needs ceil((n + 1)(1 - alpha)) <= n calibration episodes, else it never flags."""
    success = [e.success for e in rollouts.episodes]
    n = split_episodes(success, FitOptions().calibration_share, FitOptions().seed)[1].size
    return ALPHA if math.ceil((n + 1) * (1 - ALPHA)) <= n else FEW_SUCCESSES_ALPHA


def _options(kind: str, temporal: bool, rollouts: Rollouts) -> FitOptions:
    """What `monitor fit --kind KIND [--temporal]` fits on these rollouts (its default inputs)."""
    inputs = ("stac",) if kind == "stac" else tuple(rollouts.inputs)
    return FitOptions(kind=kind, inputs=inputs, temporal=temporal, execution_horizon=rollouts.execution_horizon)


def stats_detection(maps: pathlib.Path, folder: pathlib.Path) -> list[dict[str, Any]]:
    out = folder / f"{maps.name}.stats.json"
    if not out.is_file():
        cli.main(["stats", str(maps), "--format", "json", "--out", str(out)])
    return json.loads(out.read_text())["summary"]["outcomes"]["detection"]


def run(setting: Setting, root: pathlib.Path, ship: bool) -> dict[str, Any]:
    folder = root / setting.name
    folder.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    for split in setting.splits():
        record(setting, split, folder / f"{split}.lerobot")
    recorded = time.perf_counter() - t0
    dev_maps = folder / "dev.maps"
    explain(setting, folder / "dev.lerobot", dev_maps, "--no-monitor")
    rollouts = read_rollouts([dev_maps])
    dev = choose(setting, dev_maps, rollouts)
    chosen = max(dev, key=lambda n: dev[n][CHOICE])
    alpha = false_alarm_rate(rollouts)
    fitted = {
        name: fit([dev_maps], kind, temporal, alpha, folder / f"monitor-{name}.json", setting.trained)
        for name, (kind, temporal) in CANDIDATES.items()
    }
    shipped = ModelSpec.demo(setting.model).assets() / MONITOR_FILE
    if ship:
        shutil.copyfile(folder / f"monitor-{chosen}.json", shipped)
    report: dict[str, Any] = {"dev_folds": dev, "chosen": chosen, "alpha": alpha, "early": setting.early, "splits": {}}
    for split in [s for s in setting.splits() if s != "dev"]:
        maps = folder / f"{split}.maps"
        explain(setting, folder / f"{split}.lerobot", maps, "" if shipped.is_file() else "--no-monitor")
        offline = detection(scored(maps, fitted))
        report["splits"][split] = {"stats": stats_detection(maps, folder), "candidates": offline}
    if setting.trained and "unseen" in report["splits"]:
        # the unseen tasks the policy was trained on (SAFE's unseen tasks), apart from those it never was
        subset = detection(scored(folder / "unseen.maps", fitted, setting.trained))
        report["splits"]["unseen, trained tasks"] = {"stats": [], "candidates": subset}
    report["seconds"] = {"record": recorded, "total": time.perf_counter() - t0}
    return report


def _cell(entry: dict[str, Any] | None) -> str:
    if entry is None or entry["auroc"] is None:
        return "-"
    low, high = entry["auroc_ci95"]
    return f"{entry['auroc']:.2f} ({low:.2f}-{high:.2f})"


BASELINES = ("monitor", "stac", "token_entropy")


def table(name: str, report: dict[str, Any]) -> list[str]:
    """Per split: AUROC (95% interval) at each frame count of the shipped monitor, the training-free baselines, the
    map figures (`stats`' names) and every candidate fitted on dev."""
    dev = ", ".join(f"{k} {v[CHOICE]:.2f}" for k, v in report["dev_folds"].items())
    lines = [
        f"### {name} (chosen on dev: {report['chosen']}; dev folds, mean of their figures: {dev})",
        "",
    ]
    lines += ["| split | figure | N=1 | N=4 | N=8 | N=16 | N=32 | episode |", "|---" * 8 + "|"]
    for split, data in report["splits"].items():
        entries = {e["frames"]: e["figures"] for e in data["stats"]}
        offline = {e["frames"]: e["figures"] for e in data["candidates"]}
        # the shipped monitor first, then the training-free baselines, then the map figures
        names = sorted(entries.get(1, ()), key=lambda n: (not n.startswith("monitor"), n not in BASELINES, n))
        rows = [(n, entries) for n in names] + [(n, offline) for n in sorted(offline[1])]
        for figure, source in rows:
            label = figure if source is entries else f"fitted {figure}"
            cells = [_cell(source[n].get(figure)) for n in (1, 4, 8, 16, 32, "episode")]
            lines.append(f"| {split} | {label} | " + " | ".join(cells) + " |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=pathlib.Path, required=True)
    parser.add_argument("--settings", nargs="+", default=[s.name for s in SETTINGS])
    parser.add_argument("--ship", action="store_true", help="copy each chosen monitor beside its bundled model")
    args = parser.parse_args()
    load_before = os.getloadavg()
    for setting in [s for s in SETTINGS if s.name in args.settings]:
        report = run(setting, args.out, args.ship)
        report["machine"] = machine_line(load_before, os.getloadavg())
        (args.out / setting.name / "report.json").write_text(json.dumps(report, indent=2, default=float))
        print("\n".join(table(setting.name, report)), flush=True)
        print(report["machine"], flush=True)


if __name__ == "__main__":
    main()
