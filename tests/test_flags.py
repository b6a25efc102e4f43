"""No command takes a flag and ignores it. Every flag of every command is read from the command's own tyro parser
(each `openpi-cam` command, `python -m openpi_cam.cli.train_demo` and `python -m openpi_cam.demo.train`), and each
must have a case here (`test_every_flag_has_a_case`: a new flag without one fails):

- `Changes`: the command run with the flag's arguments added to a base command line gives another output than the
  base, in what the case's probe reads of it (a file's bytes, a recorded option, a printed line, a response).
  Commands that compile a model run the flags of a group together, once (`Run.together`): each probe then reads a
  part of the output that only its own flag changes. For options that no output of a normal run reflects at once
  (queue sizes, drain times, batch sizes), the probe reads the value the run records, which is the object the
  command's components were built from.
- `Refused`: the command refuses the flag in that combination (the other flags leave it nothing to do): a non-zero
  exit, one line naming the flag, no traceback.
- `Fixed`: the parser accepts one value only, its default: nothing given can be ignored.
- `Covered`: only a failure no real request can cause shows the flag (serve's `--debug`), and the named test of the
  server shows it with a policy that raises.
- `Delegates`: `train_demo`'s `--args.*` are `demo.train`'s flags, handed over unchanged: given all at once, they
  train the very model `demo.train` trains with them.

The commands run in process (serve in a child process, since it serves until stopped), on the bundled demo models,
the side channel's run of them and the demo dataset. The fast tier runs the refusals and the commands that compile
nothing (stats, render, export, and explain-run up to its first step); the commands that compile a model run in the
slow tier, in one run per group of flags."""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import io
import json
import shutil
import signal
import subprocess
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tyro
from command_inputs import DEMO_DATASET, TARGET_BOX
from demo_inputs import demo_observation
from heads import planted_head, random_maps
from paths import GOLDEN_DIR, REPO_ROOT
from real_clients import http_get
from serve_process import free_port, wait_healthy

from openpi_cam import cli
from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.cli import train_demo
from openpi_cam.demo import metaworld_data, metaworld_sim, train
from openpi_cam.monitor import monitor_file
from openpi_cam.monitor.fit import Episode, FitOptions, fit_monitor
from openpi_cam.monitor.signals import STAC
from openpi_cam.policies import demo_metaworld, demo_reach
from openpi_cam.serving import msgpack_numpy
from openpi_cam.vocabulary import MAP_KIND_INFO

# ---------------------------------------------------------------------------------------------------- the parsers


def _parsers() -> dict[str, Callable[..., Any]]:
    """Command -> the callable tyro parses its flags from."""
    import importlib

    parsers = {}
    for name, (module, _) in cli.COMMANDS.items():
        loaded = importlib.import_module(module)
        if hasattr(loaded, "main"):  # `explain` routes to explain-run or explain-dataset, whose flags are theirs
            parsers[name] = loaded.main
    return parsers | {"train_demo": train_demo.main, "demo.train": train.TrainArgs}


# How each command runs in process: argv -> exit status (`openpi-cam` commands raise SystemExit).
def _run_in_process(command: str, argv: list[str]) -> int:
    if command == "demo.train":
        return train.main(argv)
    if command == "train_demo":
        return int(tyro.cli(train_demo.main, args=argv))
    cli.main([*command.split(" "), *argv])
    return 0


def _parser(parsed: Callable[..., Any]) -> Any:
    """tyro's argparse parser for `parsed`."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # get_parser is the one way to read the parser
        return tyro.extras.get_parser(parsed)


def flags_of(parsed: Callable[..., Any]) -> set[str]:
    """The flags tyro's parser takes for `parsed`, each by its own name (`--no-X` and earlier spellings are the same
    flag); positional arguments are not flags."""
    names = set()
    for action in _parser(parsed)._actions:
        options = [o for o in action.option_strings if not o.startswith(("--no-", "--cam.no-"))]
        if not options or "--help" in options:
            continue
        own = [o for o in options if o[2:] == action.dest or action.dest.endswith("." + o[2:])]
        names.add((own or options)[0])
    return names


# ----------------------------------------------------------------------------------------------------- the cases


@dataclasses.dataclass(frozen=True)
class Run:
    """A base command line: the command, its arguments, and whether its cases' flags are added all at once."""

    command: str
    args: tuple[str, ...] = ()
    together: bool = False
    slow: bool = False
    fails: bool = False  # the base command line ends in an error (what the flag changes)


@dataclasses.dataclass(frozen=True)
class Changes:
    run: Run
    args: tuple[str, ...]
    probe: Callable[[Output], Any]


@dataclasses.dataclass(frozen=True)
class Refused:
    command: str
    args: tuple[str, ...]
    slow: bool = False


@dataclasses.dataclass(frozen=True)
class Fixed:
    """The flag's only accepted value is its default."""


@dataclasses.dataclass(frozen=True)
class Covered:
    test: str  # a test node id that shows the flag's effect
    why: str


Case = Changes | Refused | Fixed | Covered


@dataclasses.dataclass
class Output:
    """What a command left: its exit status, what it printed, the files under its folder, and (serve) what its
    clients saw."""

    code: int
    out: str
    err: str
    root: Path
    seen: dict[str, Any] = dataclasses.field(default_factory=dict)

    def files(self, pattern: str = "**/*") -> dict[str, str]:
        """Relative path -> digest of the content, of every file matching `pattern` (links followed)."""
        return {
            str(p.relative_to(self.root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(self.root.glob(pattern))
            if p.is_file()
        }

    def paths(self, pattern: str = "**/*") -> list[str]:
        return sorted(self.files(pattern))

    def json(self, pattern: str) -> Any:
        (path,) = sorted(self.root.glob(pattern))
        return json.loads(path.read_text())


# Probes: what of an output a flag changes.
def printed(o: Output) -> str:
    return o.out


def reported(o: Output) -> str:
    return o.err


def paths(pattern: str = "**/*") -> Callable[[Output], list[str]]:
    return lambda o: o.paths(pattern)


def contents(pattern: str) -> Callable[[Output], list[str]]:
    """The files' contents, whatever their names."""
    return lambda o: sorted(o.files(pattern).values())


def recorded(pattern: str, *keys: str) -> Callable[[Output], Any]:
    """A value of the JSON file matching `pattern` (`keys` indexing into it)."""

    def probe(o: Output) -> Any:
        value = o.json(pattern)
        for key in keys:
            value = value[key]
        return value

    return probe


def seen(key: str) -> Callable[[Output], Any]:
    return lambda o: o.seen[key]


def exit_status(o: Output) -> int:
    return o.code


# ------------------------------------------------------------------------------------------------------- stats

STATS = Run("stats", ("{run}",))
STATS_CASES: dict[str, tuple[Case, ...]] = {
    "--format": (Changes(STATS, ("--format", "json"), printed),),
    "--out": (Changes(STATS, ("--out", "{scratch}/stats.csv"), paths()),),
    "--kind": (Changes(STATS, ("--kind", "gradcam"), printed),),
}

# ------------------------------------------------------------------------------------------------------ render

RENDER = Run("render", ("{run}",))
RENDER_DATASET = Run("render", ("{maps}", "--no-videos"))
PANELS = "run/render-*/**/*.png"
RENDER_CASES: dict[str, tuple[Case, ...]] = {
    "--out": (Changes(RENDER, ("--out", "{scratch}/drawn"), paths()),),
    "--kind": (Changes(RENDER, ("--kind", "gradcam"), paths()),),
    "--norm": (Changes(RENDER, ("--norm", "run"), contents(PANELS)),),
    "--alpha": (Changes(RENDER, ("--alpha", "0.9"), contents(PANELS)),),
    "--tile-height": (Changes(RENDER, ("--tile-height", "120"), contents(PANELS)),),
    "--fps": (Changes(RENDER, ("--fps", "2"), contents("run/render-*/**/*.mp4")),),
    "--videos": (Changes(RENDER, ("--no-videos",), paths()),),
    "--html": (Changes(RENDER, ("--no-html",), paths()),),
    "--progress": (Changes(RENDER, ("--no-progress",), reported),),
    "--rerun": (Changes(RENDER, ("--rerun", "{scratch}/run.rrd"), paths()),),
    "--episodes": (
        Changes(RENDER_DATASET, ("--episodes", "1"), paths("maps/render-*/**/*")),
        Refused("render", ("{run}", "--episodes", "0")),
    ),
}

# ------------------------------------------------------------------------------------------------------ export

EXPORT = Run("export", ("--out", "{scratch}/lerobot"))
EXPORT_PI05 = Run("export", ("--out", "{scratch}/lerobot", "--config", demo_reach.DEMO_PI05_CONFIG.name))
WEIGHTS = "lerobot/model.safetensors"
EXPORT_CASES: dict[str, tuple[Case, ...]] = {
    "--out": (Changes(EXPORT, ("--out", "{scratch}/elsewhere"), paths()),),
    "--to": (Fixed(),),
    # Another checkpoint of the same config: the bundled pi0.5's weights with other statistics in its assets/.
    "--checkpoint-dir": (
        Changes(
            EXPORT_PI05, ("--checkpoint-dir", "{restated}/checkpoint"), contents("lerobot/*processor*.safetensors")
        ),
    ),
    "--config": (Changes(EXPORT, ("--config", demo_metaworld.DEMO_METAWORLD_CONFIG.name), contents(WEIGHTS)),),
    "--paligemma-tokenizer": (
        Changes(
            EXPORT,
            ("--paligemma-tokenizer", "{golden}/tiny_policy_pi05_droid/paligemma_tokenizer_tiny.model"),
            contents("lerobot/tokenizer/*"),
        ),
    ),
    "--fast-tokenizer": (Refused("export", ("--out", "{scratch}/x", "--fast-tokenizer", "{demo}/fast_tokenizer")),),
    "--dtype": (Changes(EXPORT, ("--dtype", "bfloat16"), contents(WEIGHTS)),),
    "--default-prompt": (Refused("export", ("--out", "{scratch}/x", "--default-prompt", "reach the red block")),),
}

# ------------------------------------------------------------------------------------------------- explain-run

# Up to its first step: the run is created, with the model and options it records, and nothing is compiled.
EXPLAIN_RUN = Run("explain-run", ("{run}", "--out", "{scratch}/runs", "--max-steps", "0"))
# One step explained (compiled: slow), one kind, no spot check.
EXPLAIN_STEP = Run(
    "explain-run",
    ("{run}", "--out", "{scratch}/runs", "--max-steps", "1", "--maps", "gradnorm", "--check-patches", "0"),
    slow=True,
)
RUN_CONFIG = "runs/*/run.json"


def run_option(key: str) -> Callable[[Output], Any]:
    return recorded(RUN_CONFIG, "options", key)


def run_model(key: str) -> Callable[[Output], Any]:
    return recorded(RUN_CONFIG, "config", key)


def step_files(o: Output) -> list[str]:
    return o.paths("runs/*/steps/*.npz")


# One step explained with the kinds the added options shape (compiled: slow): each of those flags alone changes the
# maps of the kind that reads it. Alone, since a kind's two options move the same maps.
EXPLAIN_KINDS = Run(
    "explain-run",
    ("{run}", "--out", "{scratch}/runs", "--max-steps", "1", "--maps", "smoothgrad", "rise", "--check-patches", "0"),
    slow=True,
)


def step_maps(kind: str) -> Callable[[Output], dict[str, Any]]:
    """The `kind` maps of every step written, per step file and camera."""

    def probe(o: Output) -> dict[str, Any]:
        prefix, maps = MAP_KIND_INFO[kind].prefix, {}
        for path in sorted(o.root.glob("runs/*/steps/*.npz")):
            with np.load(path, allow_pickle=False) as npz:
                maps |= {f"{path.name} {k}": npz[k].tolist() for k in npz.files if k.startswith(prefix)}
        return maps

    return probe


def step_checks(o: Output) -> list[Any]:
    """The spot check of every step written (its meta's `check`)."""
    checks = []
    for path in sorted(o.root.glob("runs/*/steps/*.npz")):
        with np.load(path, allow_pickle=False) as npz:
            checks.append(json.loads(str(npz["meta"][()])).get("check"))
    return checks


# The model flags of the commands that load one: each case names another model than the base's, and the probe reads
# the model the command records (a run's or maps dataset's own record of what made it).
def model_cases(run: Run, probe: Callable[[str], Callable[[Output], Any]]) -> dict[str, tuple[Case, ...]]:
    # A model of another family than pi0-FAST has no FAST tokenizer to read: refused.
    pi05_fast = (*run.args, "--config", demo_reach.DEMO_PI05_CONFIG.name, "--fast-tokenizer", "{demo}/fast_tokenizer")
    return {
        "--checkpoint-dir": (
            Changes(
                run, ("--checkpoint-dir", "{democopy}/checkpoint", "--config", "demo_reach"), probe("checkpoint_dir")
            ),
        ),
        "--config": (Changes(run, ("--config", demo_reach.DEMO_PI05_CONFIG.name), probe("config")),),
        "--paligemma-tokenizer": (
            Changes(
                run, ("--paligemma-tokenizer", "{democopy}/paligemma_tokenizer.model"), probe("paligemma_tokenizer")
            ),
        ),
        "--fast-tokenizer": (
            Changes(run, ("--fast-tokenizer", "{democopy}/fast_tokenizer"), probe("fast_tokenizer")),
            Refused(run.command, pi05_fast, slow=run.slow),
        ),
        "--dtype": (Changes(run, ("--dtype", "bfloat16"), probe("dtype")),),
        "--default-prompt": (Changes(run, ("--default-prompt", "reach the red block"), probe("default_prompt")),),
    }


EXPLAIN_RUN_CASES: dict[str, tuple[Case, ...]] = {
    "--out": (Changes(EXPLAIN_RUN, ("--out", "{scratch}/other"), paths()),),
    "--resume": (
        Refused("explain-run", ("{run}", "--out", "{scratch}/runs", "--max-steps", "0", "--resume", "{run}")),
    ),
    "--save-frames": (Changes(EXPLAIN_RUN, ("--save-frames", "model"), run_option("save_frames")),),
    "--batch-size": (Changes(EXPLAIN_RUN, ("--batch-size", "3"), run_option("batch_size")),),
    "--max-steps": (Changes(EXPLAIN_STEP, ("--max-steps", "2"), step_files),),
    # Only ALOHA's robot reads nested observation dicts (the others find `a/b` keys either way), and a run's steps
    # keep their own keys: no combination at hand where the flag has an effect, both refused.
    "--nested-keys": (
        Refused("explain-run", ("{records}", "--out", "{scratch}/runs", "--max-steps", "0", "--nested-keys")),
        Refused("explain-run", ("{run}", "--out", "{scratch}/runs", "--max-steps", "0", "--nested-keys")),
    ),
    "--rerun": (Changes(EXPLAIN_RUN, ("--rerun", "{scratch}/run.rrd"), paths()),),
    "--progress": (Changes(EXPLAIN_STEP, ("--no-progress",), reported),),
    **model_cases(EXPLAIN_RUN, run_model),
    "--target": (Changes(EXPLAIN_RUN, ("--target", "chunk"), run_option("target")),),
    "--action-index": (Changes(EXPLAIN_RUN, ("--action-index", "2"), run_option("action_index")),),
    "--maps": (
        Changes(EXPLAIN_RUN, ("--maps", "gradnorm"), run_option("maps")),
        Changes(EXPLAIN_RUN, ("--maps", "lrp"), run_option("maps")),  # the relevance kind, asked for by name only
    ),
    "--baseline": (Changes(EXPLAIN_RUN, ("--baseline", "blur"), run_option("baseline")),),
    "--occlusion-region": (Changes(EXPLAIN_RUN, ("--occlusion-region", "2"), run_option("occlusion_region")),),
    "--occlusion-masks": (Changes(EXPLAIN_RUN, ("--occlusion-masks", "8"), run_option("occlusion_masks")),),
    "--ig-space": (Changes(EXPLAIN_RUN, ("--ig-space", "pixels"), run_option("ig_space")),),
    "--smoothgrad-samples": (Changes(EXPLAIN_KINDS, ("--smoothgrad-samples", "4"), step_maps("smoothgrad")),),
    "--smoothgrad-sigma": (Changes(EXPLAIN_KINDS, ("--smoothgrad-sigma", "0.25"), step_maps("smoothgrad")),),
    "--rise-masks": (Changes(EXPLAIN_KINDS, ("--rise-masks", "32"), step_maps("rise")),),
    "--rise-keep-prob": (Changes(EXPLAIN_KINDS, ("--rise-keep-prob", "0.5"), step_maps("rise")),),
    "--check-patches": (Changes(EXPLAIN_STEP, ("--check-patches", "2"), step_checks),),
    "--reliance": (Changes(EXPLAIN_RUN, ("--reliance",), run_option("reliance")),),
    # The head `occlusion-head` applies, recorded by its SHA-256 (a planted head: the demo pi0-FAST's, action-token).
    "--head": (
        Changes(EXPLAIN_RUN, ("--maps", "occlusion-head", "--head", "{head}"), run_option("occlusion_head")),
        Refused("explain-run", ("{run}", "--out", "{scratch}/runs", "--max-steps", "0", "--head", "{head}")),
    ),
}

# --------------------------------------------------------------------------------------------- explain-dataset

# One frame of each of two episodes, one kind, every flag of the group at once, on Ray (compiled: slow).
EXPLAIN_DATASET = Run(
    "explain-dataset",
    (
        str(DEMO_DATASET),
        "--out",
        "{scratch}/maps",
        "--episodes",
        "0,1",
        "--every-k",
        "100",
        "--maps",
        "gradnorm",
        "--check-patches",
        "0",
        "--batch-size",
        "2",
    ),
    together=True,
    slow=True,
)
# The flags whose probes other flags of the group would move too, each alone.
EXPLAIN_DATASET_ALONE = dataclasses.replace(EXPLAIN_DATASET, together=False)


def maps_info(*keys: str) -> Callable[[Output], Any]:
    return recorded("*/meta/info.json", *keys)


def maps_rows(column: str) -> Callable[[Output], Any]:
    """A column of every shard written (None where a shard has no such column)."""

    def probe(o: Output) -> Any:
        import pyarrow.parquet as pq

        tables = [pq.read_table(p) for p in sorted(o.root.glob("*/data/*/*.parquet"))]
        return [t.column(column).to_pylist() if column in t.column_names else None for t in tables]

    return probe


def top_folders(o: Output) -> list[str]:
    return sorted({p.split("/")[0] for p in o.paths()})


EXPLAIN_DATASET_CASES: dict[str, tuple[Case, ...]] = {
    "--out": (Changes(EXPLAIN_DATASET, ("--out", "{scratch}/other.maps"), top_folders),),
    "--batch-size": (Changes(EXPLAIN_DATASET, ("--batch-size", "1"), maps_info("options", "batch_size")),),
    "--keys": (Changes(EXPLAIN_DATASET, ("--keys", "observation/image=observation.images.wrist"), maps_info("keys")),),
    "--extra": (Changes(EXPLAIN_DATASET, ("--extra", TARGET_BOX), maps_info("extra")),),
    "--episodes": (Changes(EXPLAIN_DATASET, ("--episodes", "2"), maps_rows("episode_index")),),
    "--every-k": (Changes(EXPLAIN_DATASET, ("--every-k", "3"), maps_info("every")),),
    "--engine": (Changes(EXPLAIN_DATASET, ("--engine", "ray"), recorded("*/meta/summary.json", "engine")),),
    "--workers": (
        Changes(EXPLAIN_DATASET, ("--workers", "2"), recorded("*/meta/summary.json", "workers")),
        Refused("explain-dataset", (str(DEMO_DATASET), "--workers", "2", "--no-progress")),
    ),
    "--ray-address": (Refused("explain-dataset", (str(DEMO_DATASET), "--ray-address", "auto", "--no-progress")),),
    # A dataset whose episode 2 has a cut video: the job stops on it, or skips it and writes the others.
    "--keep-going": (
        Changes(
            Run(
                "explain-dataset",
                ("{cutvideo}", *EXPLAIN_DATASET.args[1:4], "1,2", *EXPLAIN_DATASET.args[5:]),
                slow=True,
                fails=True,
            ),
            ("--keep-going",),
            exit_status,
        ),
    ),
    "--outcome": (Changes(EXPLAIN_DATASET, ("--outcome", "observation.target_box"), maps_info("outcome")),),
    "--progress": (Changes(EXPLAIN_DATASET_ALONE, ("--no-progress",), reported),),
    **{
        flag: cases
        for flag, cases in model_cases(EXPLAIN_DATASET, lambda key: maps_info("model", key)).items()
        if flag not in ("--config", "--default-prompt")
    },
    "--config": (Changes(EXPLAIN_DATASET_ALONE, ("--config", demo_reach.DEMO_PI05_CONFIG.name), maps_info("family")),),
    "--default-prompt": (
        Refused("explain-dataset", (str(DEMO_DATASET), "--default-prompt", "reach", "--no-progress")),
    ),
    "--target": (Changes(EXPLAIN_DATASET, ("--target", "chunk"), maps_info("target")),),
    "--action-index": (Changes(EXPLAIN_DATASET, ("--action-index", "1"), maps_info("options", "action_index")),),
    "--maps": (Changes(EXPLAIN_DATASET, ("--maps", "gradcam"), maps_info("kinds")),),
    "--baseline": (Changes(EXPLAIN_DATASET, ("--baseline", "blur"), maps_info("options", "baseline")),),
    "--occlusion-region": (
        Changes(EXPLAIN_DATASET, ("--occlusion-region", "2"), maps_info("options", "occlusion_region")),
    ),
    "--occlusion-masks": (
        Changes(EXPLAIN_DATASET, ("--occlusion-masks", "8"), maps_info("options", "occlusion_masks")),
    ),
    "--ig-space": (Changes(EXPLAIN_DATASET, ("--ig-space", "pixels"), maps_info("options", "ig_space")),),
    "--smoothgrad-samples": (
        Changes(EXPLAIN_DATASET, ("--smoothgrad-samples", "4"), maps_info("options", "smoothgrad_samples")),
    ),
    "--smoothgrad-sigma": (
        Changes(EXPLAIN_DATASET, ("--smoothgrad-sigma", "0.25"), maps_info("options", "smoothgrad_sigma")),
    ),
    "--rise-masks": (Changes(EXPLAIN_DATASET, ("--rise-masks", "32"), maps_info("options", "rise_masks")),),
    "--rise-keep-prob": (
        Changes(EXPLAIN_DATASET, ("--rise-keep-prob", "0.5"), maps_info("options", "rise_keep_prob")),
    ),
    "--check-patches": (Changes(EXPLAIN_DATASET, ("--check-patches", "1"), maps_rows("check")),),
    "--reliance": (Changes(EXPLAIN_DATASET, ("--reliance",), maps_rows("reliance")),),
    # One frame per episode: no STAC, so the STAC monitor scores nothing, but every row carries its episode's flag.
    "--monitor": (Changes(EXPLAIN_DATASET, ("--monitor", "{monitor}"), maps_rows("monitor/flag")),),
    "--monitor-features": (Changes(EXPLAIN_DATASET, ("--monitor-features",), maps_rows("monitor/features/prompt")),),
    "--head": (
        Changes(
            EXPLAIN_DATASET_ALONE,
            ("--maps", "gradnorm", "occlusion-head", "--head", "{head}"),
            maps_info("options", "occlusion_head"),
        ),
        Refused("explain-dataset", (str(DEMO_DATASET), "--head", "{head}", "--no-progress")),
    ),
    "--execution-horizon": (
        Changes(EXPLAIN_DATASET, ("--execution-horizon", "3"), maps_info("execution_horizon")),
        Refused("explain-dataset", (str(DEMO_DATASET), "--execution-horizon", "0", "--no-progress")),
    ),
    # pi0.5 draws other chunks of a frame from other noises; pi0-FAST, greedy, has none to draw.
    "--sample-spread": (
        Changes(
            EXPLAIN_DATASET_ALONE,
            ("--config", demo_reach.DEMO_PI05_CONFIG.name, "--sample-spread", "2"),
            maps_rows("monitor/sample_spread"),
        ),
        Refused("explain-dataset", (str(DEMO_DATASET), "--sample-spread", "2", "--no-progress")),
    ),
}

# ------------------------------------------------------------------------------------------------ faithfulness

# The run's two steps re-scored: the flags of the group at once (compiled: slow).
FAITHFULNESS = Run("faithfulness", ("{run}", "--out", "{scratch}/report.json"), together=True, slow=True)
FAITHFULNESS_ALONE = dataclasses.replace(FAITHFULNESS, together=False)
# A maps dataset's frames served again: the model flags, each alone (another model serves other actions).
FAITHFULNESS_MAPS = Run(
    "faithfulness",
    ("{maps}", "--max-steps", "2", "--randomize", "none", "--random-orders", "1", "--out", "{scratch}/report.json"),
    slow=True,
)


def report(*keys: str) -> Callable[[Output], Any]:
    return recorded("*.json", *keys)


def served_again(o: Output) -> Any:
    """The exit status and what serving the frames again gave."""
    reports = sorted(o.root.glob("*.json"))
    return o.code, json.loads(reports[0].read_text()).get("maps_dataset") if reports else None


FAITHFULNESS_CASES: dict[str, tuple[Case, ...]] = {
    "--randomize": (Changes(FAITHFULNESS, ("--randomize", "all"), report("options", "randomize")),),
    "--baseline": (Changes(FAITHFULNESS, ("--baseline", "blur"), report("options", "baseline")),),
    "--max-steps": (Changes(FAITHFULNESS, ("--max-steps", "1"), report("steps_evaluated")),),
    "--random-orders": (Changes(FAITHFULNESS, ("--random-orders", "2"), report("options", "random_orders")),),
    "--batch-size": (
        Changes(FAITHFULNESS, ("--batch-size", "1"), report("options", "batch_size")),
        Refused("faithfulness", ("{run}", "--randomize", "none", "--batch-size", "4")),
    ),
    "--out": (Changes(FAITHFULNESS, ("--out", "{scratch}/elsewhere.json"), paths("*.json")),),
    "--progress": (Changes(FAITHFULNESS_ALONE, ("--no-progress",), reported),),
    "--checkpoint-dir": (
        Changes(
            FAITHFULNESS_MAPS, ("--checkpoint-dir", "{restated}/checkpoint", "--config", "demo_reach"), served_again
        ),
    ),
    "--config": (Changes(FAITHFULNESS_MAPS, ("--config", demo_reach.DEMO_PI05_CONFIG.name), served_again),),
    "--paligemma-tokenizer": (
        Changes(
            FAITHFULNESS_MAPS,
            ("--paligemma-tokenizer", "{golden}/tiny_policy_droid/paligemma_tokenizer_tiny.model"),
            served_again,
        ),
    ),
    "--fast-tokenizer": (
        Changes(FAITHFULNESS_MAPS, ("--fast-tokenizer", "{golden}/tiny_policy_droid/fast_tokenizer"), served_again),
        Refused(
            "faithfulness",
            (
                "{run}",
                "--config",
                demo_reach.DEMO_PI05_CONFIG.name,
                "--fast-tokenizer",
                "{demo}/fast_tokenizer",
                "--randomize",
                "none",
                "--max-steps",
                "1",
            ),
            slow=True,
        ),
    ),
    "--dtype": (Changes(FAITHFULNESS_MAPS, ("--dtype", "bfloat16"), served_again),),
    "--default-prompt": (Refused("faithfulness", ("{run}", "--default-prompt", "reach the red block")),),
}

# ------------------------------------------------------------------------------------------------------- serve

# Served in a child process with the side channel on: one request, a prompt-less one, a second connection and an
# oversized message from a client, then SIGTERM (`serve_session`). The flags of the group at once (slow).
SERVE = Run(
    "serve",
    (
        "--host",
        "127.0.0.1",
        "--port",
        "{port}",
        "--cam.every-k",
        "1",
        "--cam.dir",
        "{scratch}/cam",
        "--batch-window-ms",
        "5",
        "--max-batch",
        "2",
        "--record",
        "{scratch}/rec",
    ),
    together=True,
    slow=True,
)
SERVE_OFF = ("--no-warm-up",)  # in process, refused before it would listen


def cam_option(key: str) -> Callable[[Output], Any]:
    return recorded("cam*/*/run.json", "options", key)


def cam_model(key: str) -> Callable[[Output], Any]:
    return recorded("cam*/*/run.json", "config", key)


def serving_line(o: Output) -> str:
    """Where it said it listens."""
    return next(line.split("serving on ")[1] for line in o.err.splitlines() if "serving on " in line)


def cam_folders(o: Output) -> list[str]:
    return sorted({p.split("/")[0] for p in o.paths("cam*/*/run.json")})


def record_folders(o: Output) -> list[str]:
    return sorted({p.split("/")[0] for p in o.paths("rec*/meta/info.json")})


def drain_logged(o: Output) -> list[str]:
    """How long the server said it lets the policy drain (its log lines without their time stamps)."""
    return [line.split("closing the policy", 1)[1] for line in o.err.splitlines() if "closing the policy" in line]


def side_channel_off(flag: str, value: str | None) -> Refused:
    return Refused("serve", (*SERVE_OFF, flag, *(() if value is None else (value,))))


# Each side-channel flag: recorded in the run it makes (the options its side channel was built with), and refused
# with the side channel off.
CAM_FLAGS = {
    "--cam.target": ("chunk", "target"),
    "--cam.action-index": ("2", "action_index"),
    "--cam.maps": ("gradnorm", "maps"),
    "--cam.baseline": ("blur", "baseline"),
    "--cam.occlusion-region": ("2", "occlusion_region"),
    "--cam.occlusion-masks": ("8", "occlusion_masks"),
    "--cam.ig-space": ("pixels", "ig_space"),
    "--cam.smoothgrad-samples": ("4", "smoothgrad_samples"),
    "--cam.smoothgrad-sigma": ("0.25", "smoothgrad_sigma"),
    "--cam.rise-masks": ("32", "rise_masks"),
    "--cam.rise-keep-prob": ("0.5", "rise_keep_prob"),
    "--cam.check-patches": ("1", "check_patches"),
    "--cam.reliance": (None, "reliance"),
    "--cam.save-frames": ("both", "save_frames"),
    "--cam.queue-size": ("3", "queue_size"),
    "--cam.per-connection": ("1", "per_connection"),
    "--cam.settle-ms": ("2.5", "settle_ms"),
    "--cam.device": ("0", "device"),
    "--cam.max-steps": ("5", "max_steps"),
    "--cam.max-mb": ("1.5", "max_mb"),
    "--cam.max-extra-value-kb": ("2", "max_extra_value_kb"),
    "--cam.max-extra-kb": ("4", "max_extra_kb"),
    "--cam.stats-window": ("5", "stats_window"),
    # port 9 (discard): no viewer there, so the stream stops and serving goes on (tests/cam/test_rerun_live.py)
    "--cam.rerun": ("rerun+http://127.0.0.1:9/proxy", "rerun"),
}
SERVE_CASES: dict[str, tuple[Case, ...]] = {
    "--port": (Changes(SERVE, ("--port", "{port}"), serving_line),),
    "--host": (Changes(SERVE, ("--host", "localhost"), serving_line),),
    "--api-key": (Changes(SERVE, ("--api-key", "k3y"), seen("stats_without_key")),),
    "--max-message-mb": (Changes(SERVE, ("--max-message-mb", "1"), seen("oversized")),),
    "--max-connections": (Changes(SERVE, ("--max-connections", "1"), seen("second_connection")),),
    # Less room for requests than one message may take: the limits are refused once the model has loaded.
    "--max-buffered-mb": (Refused("serve", (*SERVE_OFF, "--max-buffered-mb", "1")),),
    "--debug": (
        Covered(
            "tests/serving/test_hardening.py::test_unexpected_errors_are_reported_short_unless_debug",
            "the served policies answer every request a client can send, or refuse it as invalid",
        ),
    ),
    "--stop-at-action-end": (Changes(SERVE, ("--stop-at-action-end",), cam_model("stop_at_action_end")),),
    "--warm-up": (Changes(SERVE, ("--no-warm-up",), lambda o: "warmed up" in o.err),),
    "--batch-window-ms": (
        Changes(SERVE, ("--batch-window-ms", "7"), lambda o: o.seen["stats"]["batching"]["window_ms"]),
    ),
    "--max-batch": (
        Changes(SERVE, ("--max-batch", "4"), lambda o: o.seen["stats"]["batching"]["max_batch"]),
        Refused("serve", (*SERVE_OFF, "--max-batch", "4")),
    ),
    "--record": (Changes(SERVE, ("--record", "{scratch}/rec2"), record_folders),),
    "--record-fps": (
        Changes(SERVE, ("--record-fps", "7"), recorded("rec*/meta/info.json", "fps")),
        Refused("serve", (*SERVE_OFF, "--record-fps", "7")),
    ),
    "--checkpoint-dir": (
        Changes(
            SERVE, ("--checkpoint-dir", "{democopy}/checkpoint", "--config", "demo_reach"), cam_model("checkpoint_dir")
        ),
    ),
    # The bundled configs other than the default are other families (or need a checkpoint): refused or elsewhere.
    "--config": (Refused("serve", (*SERVE_OFF, "--config", "pi0_fast_droid")),),
    "--paligemma-tokenizer": (
        Changes(
            SERVE, ("--paligemma-tokenizer", "{democopy}/paligemma_tokenizer.model"), cam_model("paligemma_tokenizer")
        ),
    ),
    "--fast-tokenizer": (
        Changes(SERVE, ("--fast-tokenizer", "{democopy}/fast_tokenizer"), cam_model("fast_tokenizer")),
        Refused(
            "serve",
            (*SERVE_OFF, "--config", demo_reach.DEMO_PI05_CONFIG.name, "--fast-tokenizer", "{demo}/fast_tokenizer"),
        ),
    ),
    "--dtype": (Changes(SERVE, ("--dtype", "bfloat16"), cam_model("dtype")),),
    "--default-prompt": (Changes(SERVE, ("--default-prompt", "reach the red block"), seen("without_prompt")),),
    "--cam.every-k": (Changes(SERVE, ("--cam.every-k", "2"), cam_option("every_k")),),
    "--monitor": (
        Changes(SERVE, ("--monitor", "{monitor}"), lambda o: o.seen["stats"]["policy"].get("monitor")),
        Refused("serve", (*SERVE_OFF, "--monitor", "{scratch}/none.json")),
    ),
    # With `occlusion-head` among the maps (the other flags of the group name theirs): the head the run records.
    "--cam.head": (
        Changes(
            dataclasses.replace(SERVE, together=False),
            ("--cam.maps", "gradnorm", "occlusion-head", "--cam.head", "{head}"),
            cam_option("occlusion_head"),
        ),
        Refused("serve", (*SERVE_OFF, "--cam.head", "{head}")),
    ),
    # The response's keys: the monitor's is added only when asked for.
    "--cam.monitor-response": (
        Changes(SERVE, ("--cam.monitor-response",), seen("response_keys")),
        Refused("serve", (*SERVE_OFF, "--no-monitor", "--cam.monitor-response")),  # the bundled model's own is off
    ),
    "--cam.dir": (Changes(SERVE, ("--cam.dir", "{scratch}/cam2"), cam_folders), side_channel_off("--cam.dir", "x")),
    # The server's own: how long it lets the served policy drain on SIGTERM, with the side channel on or off (off,
    # under its earlier spelling `--cam.drain-timeout`).
    "--drain-timeout": (
        Changes(SERVE, ("--drain-timeout", "7"), drain_logged),
        Changes(
            Run("serve", ("--host", "127.0.0.1", "--port", "{port}", "--no-warm-up"), slow=True),
            ("--cam.drain-timeout", "7"),
            drain_logged,
        ),
        Refused("serve", (*SERVE_OFF, "--drain-timeout", "-1")),
    ),
    **{
        flag: (
            Changes(SERVE, (flag,) if value is None else (flag, value), cam_option(key)),
            side_channel_off(flag, value),
        )
        for flag, (value, key) in CAM_FLAGS.items()
    },
}

# -------------------------------------------------------------------------------------------------------- demo

DEMO_ARGS = ("--num-episodes", "1", "--max-calls", "1")
# Driven without explanation, recorded (the episodes' seeds, perturbations, calls and steps are the record's): the
# flags of the group at once (slow).
DEMO_DRIVE = Run("demo", ("--no-explain", *DEMO_ARGS, "--record", "{scratch}/rec"), together=True, slow=True)
DEMO_DRIVE_ALONE = dataclasses.replace(DEMO_DRIVE, together=False)
# Explained with one cheap kind, no faithfulness, no videos: the flags of the group at once (slow).
DEMO_EXPLAIN = Run(
    "demo", (*DEMO_ARGS, "--maps", "gradnorm", "--no-faithfulness", "--no-videos"), together=True, slow=True
)
DEMO_EXPLAIN_ALONE = dataclasses.replace(DEMO_EXPLAIN, together=False)
NO_EXPLAIN = ("--no-explain", *DEMO_ARGS)
# Meta-World driven by a stand-in for the multi-task pi0.5 (`{mt05}`: the one-task pi0.5's weights and statistics
# under the multi-task robot's asset id), so that no case needs the multi-task models' own assets.
MT05 = ("--sim", "metaworld", "--model", "pi05", "--assets", "{mt05}")
DEMO_METAWORLD = Run("demo", (*NO_EXPLAIN, "--record", "{scratch}/rec", *MT05), slow=True)


def episodes(key: str) -> Callable[[Output], Any]:
    return lambda o: [e[key] for e in o.json("rec/meta/demo_episodes.json")["episodes"]]


def executed_per_call(o: Output) -> list[float]:
    """Actions executed per call of the episodes that never reached their block (each call executes the same
    number of actions)."""
    return [e["steps"] / e["calls"] for e in o.json("rec/meta/demo_episodes.json")["episodes"] if not e["success"]]


def demo_option(key: str) -> Callable[[Output], Any]:
    return recorded("*/*/run.json", "options", key)


def recorded_actions(o: Output) -> list[list[float]]:
    import pyarrow.parquet as pq

    return [pq.read_table(p, columns=["action"]).column(0).to_pylist() for p in sorted(o.root.glob("rec/data/*/*"))]


DEMO_CASES: dict[str, tuple[Case, ...]] = {
    "--record": (Changes(Run("demo", NO_EXPLAIN, slow=True), ("--record", "{scratch}/rec"), paths()),),
    "--num-episodes": (Changes(DEMO_DRIVE, ("--num-episodes", "2"), lambda o: len(episodes("seed")(o))),),
    "--max-calls": (Changes(DEMO_DRIVE, ("--max-calls", "2"), lambda o: max(episodes("calls")(o))),),
    "--execute": (Changes(DEMO_DRIVE, ("--execute", "3"), executed_per_call),),
    "--seed": (Changes(DEMO_DRIVE, ("--seed", "5"), episodes("seed")),),
    "--perturb": (Changes(DEMO_DRIVE, ("--perturb", "hue=45", "dim=0.5"), episodes("perturbation")),),
    "--model": (
        Changes(DEMO_DRIVE_ALONE, ("--model", "pi05"), recorded_actions),
        # Meta-World's family: pi0-FAST (the default) cannot serve the pi0.5 weights that pi0.5 serves.
        Changes(Run("demo", (*NO_EXPLAIN, *MT05[:2], *MT05[4:]), slow=True, fails=True), MT05[2:4], exit_status),
    ),
    "--sim": (
        Changes(
            Run("demo", (*NO_EXPLAIN, "--record", "{scratch}/rec", "--model", "pi05"), slow=True),
            ("--sim", "metaworld", "--assets", "{mt05}"),
            recorded("rec/meta/info.json", "robot_type"),
        ),
    ),
    "--task": (
        Changes(DEMO_METAWORLD, ("--task", "reach-v3"), episodes("task")),
        Refused("demo", ("--task", "reach-v3")),
    ),
    "--explain": (Changes(DEMO_EXPLAIN_ALONE, ("--no-explain",), lambda o: o.paths("*/*/run.json")),),
    "--out": (
        Changes(
            DEMO_EXPLAIN,
            ("--out", "{scratch}/elsewhere"),
            lambda o: sorted({p.split("/")[0] for p in o.paths("*/*/run.json")}),
        ),
        Refused("demo", (*NO_EXPLAIN, "--out", "{scratch}/x")),
    ),
    "--target": (
        Changes(DEMO_EXPLAIN, ("--target", "action-token"), demo_option("target")),
        Refused("demo", (*NO_EXPLAIN, "--target", "action-token")),
    ),
    "--maps": (
        Changes(DEMO_EXPLAIN, ("--maps", "gradnorm", "ig"), demo_option("maps")),
        Refused("demo", (*NO_EXPLAIN, "--maps", "ig")),
    ),
    "--baseline": (
        Changes(DEMO_EXPLAIN, ("--baseline", "blur"), demo_option("baseline")),
        Refused("demo", (*NO_EXPLAIN, "--baseline", "blur")),
    ),
    "--ig-space": (
        Changes(DEMO_EXPLAIN, ("--ig-space", "pixels"), demo_option("ig_space")),
        Refused("demo", (*NO_EXPLAIN, "--ig-space", "pixels")),
    ),
    "--faithfulness": (
        Changes(DEMO_EXPLAIN, ("--faithfulness",), lambda o: o.paths("*/*/faithfulness.json")),
        Refused("demo", (*NO_EXPLAIN, "--no-faithfulness")),
    ),
    "--videos": (
        Changes(DEMO_EXPLAIN, ("--videos",), lambda o: o.paths("*/*/render-*/**/*.mp4")),
        Refused("demo", (*NO_EXPLAIN, "--no-videos")),
        Refused("demo", (*DEMO_ARGS, "--no-render", "--no-videos")),
    ),
    "--render": (
        Changes(DEMO_EXPLAIN_ALONE, ("--no-render",), lambda o: o.paths("*/*/render-*/index.html")),
        Refused("demo", (*NO_EXPLAIN, "--no-render")),
    ),
    "--assets": (
        Changes(DEMO_EXPLAIN, ("--assets", "{democopy}"), recorded("*/*/run.json", "config", "checkpoint_dir")),
    ),
    # The demo explains the chunk: a head planted for it.
    "--head": (
        Changes(
            DEMO_EXPLAIN_ALONE,
            ("--maps", "gradnorm", "occlusion-head", "--head", "{chunkhead}"),
            demo_option("occlusion_head"),
        ),
        Refused("demo", (*NO_EXPLAIN, "--head", "{chunkhead}")),
    ),
}

# ------------------------------------------------------------------------------------------------- monitor fit

# Fitted on the bundled pi0-FAST's labelled rollouts (`{featured}`); numbers only, no model: the flags of a group at
# once. The rollouts are made once, by the demo and explain-dataset (compiled: slow).
FEATURED = ("{featured}", "--out", "{scratch}/monitor.json")
MONITOR_FIT = Run("monitor fit", FEATURED, together=True, slow=True)
MONITOR_FIT_ALONE = dataclasses.replace(MONITOR_FIT, together=False)
MAHALANOBIS_FIT = Run("monitor fit", (*FEATURED, "--kind", "mahalanobis"), slow=True)
# Refused before any dataset is read: a flag another kind reads.
NOTHING = ("nothing.maps", "--out", "{scratch}/monitor.json")


# The flags a gated monitor alone reads: a gated fit needs STAC values that vary among the training successes, and
# these rollouts' successes end within a call or two; that test fits one on a copy with seeded STAC values.
GATED_FIT_TEST = (
    "tests/datasets/test_monitor_rollouts.py::test_monitor_fit_gated_records_the_instructions_it_trusts_its_probe_on"
)
GATED_FIT_WHY = "a gated fit on these rollouts is refused (their STAC does not vary among successes)"


def fitted(*keys: str) -> Callable[[Output], Any]:
    return recorded("*.json", *keys)


MONITOR_FIT_CASES: dict[str, tuple[Case, ...]] = {
    "--out": (Changes(MONITOR_FIT, ("--out", "{scratch}/other.json"), paths("*.json")),),
    "--kind": (Changes(MONITOR_FIT_ALONE, ("--kind", "mahalanobis"), fitted("kind")),),
    "--inputs": (
        Changes(
            MONITOR_FIT,
            ("--inputs", "features/prompt", "stac"),
            lambda o: [i["name"] for i in o.json("*.json")["inputs"]],
        ),
    ),
    # Wider inputs than --max-dims: the projection keeps that many directions (by default, one fewer than the
    # training steps).
    "--max-dims": (
        Changes(MONITOR_FIT, ("--max-dims", "4"), lambda o: len(o.json("*.json")["basis"]["components"])),
        Refused("monitor fit", (*NOTHING, "--kind", "stac", "--max-dims", "4")),
    ),
    "--alpha": (Changes(MONITOR_FIT, ("--alpha", "0.25"), fitted("alpha")),),
    # The successful episodes held out to set the threshold: a fifth of them is fewer than the default half.
    "--calibration-share": (
        Changes(MONITOR_FIT, ("--calibration-share", "0.2"), fitted("fit", "calibration_episodes")),
    ),
    "--seed": (Changes(MONITOR_FIT, ("--seed", "3"), fitted("fit", "seed")),),
    "--l2": (
        Changes(MONITOR_FIT, ("--l2", "0.5"), fitted("fit", "l2")),
        Refused("monitor fit", (*NOTHING, "--kind", "mahalanobis", "--l2", "0.5")),
    ),
    "--temporal": (
        Changes(MONITOR_FIT, ("--temporal",), fitted("temporal")),
        Refused("monitor fit", (*NOTHING, "--kind", "stac", "--temporal")),
    ),
    "--shrinkage": (
        Changes(MAHALANOBIS_FIT, ("--shrinkage", "0.5"), fitted("fit", "shrinkage")),
        Refused("monitor fit", (*NOTHING, "--shrinkage", "0.5")),
    ),
    "--trained-on": (
        Covered(GATED_FIT_TEST, GATED_FIT_WHY),
        Refused("monitor fit", (*NOTHING, "--trained-on", "training.lerobot")),
    ),
    "--trained-prompts": (
        Covered(GATED_FIT_TEST, GATED_FIT_WHY),
        Refused("monitor fit", (*NOTHING, "--kind", "union", "--trained-prompts", "open the door")),
    ),
}

# --------------------------------------------------------------------------------------------------- head fit

# Fitted on a small maps dataset of random maps (`{headmaps}`, no model): the flags of the group at once, each probe
# reading what the head file records of its flag (the held-out share as the maps it held out).
HEAD_FIT = Run(
    "head fit",
    ("{headmaps}", "--out", "{scratch}/head.json", "--inputs", "gradnorm", "lrp", "--steps", "20"),
    together=True,
)


def head_option(key: str) -> Callable[[Output], Any]:
    return recorded("*.json", "fit", "options", key)


HEAD_FIT_CASES: dict[str, tuple[Case, ...]] = {
    "--out": (Changes(HEAD_FIT, ("--out", "{scratch}/other.json"), paths("*.json")),),
    "--inputs": (Changes(HEAD_FIT, ("--inputs", "lrp"), recorded("*.json", "inputs")),),
    "--hidden": (Changes(HEAD_FIT, ("--hidden", "0"), recorded("*.json", "hidden")),),
    "--seed": (Changes(HEAD_FIT, ("--seed", "1"), head_option("seed")),),
    "--holdout": (
        Changes(HEAD_FIT, ("--holdout", "0.5"), recorded("*.json", "fit", "examples", "held_out")),
        Refused("head fit", ("{headmaps}", "--out", "{scratch}/head.json", "--holdout", "1.5")),
    ),
    "--steps": (Changes(HEAD_FIT, ("--steps", "10"), head_option("steps")),),
    "--learning-rate": (Changes(HEAD_FIT, ("--learning-rate", "0.05"), head_option("learning_rate")),),
    "--temperature": (Changes(HEAD_FIT, ("--temperature", "0.3"), head_option("temperature")),),
    "--mse-weight": (Changes(HEAD_FIT, ("--mse-weight", "0.5"), head_option("mse_weight")),),
    "--weight-decay": (Changes(HEAD_FIT, ("--weight-decay", "0.1"), head_option("weight_decay")),),
}

# ---------------------------------------------------------------------------------------------------- training

# A tiny model, six steps (a learning rate shows from the third loss on: the first update's warmup rate is 0), no
# evaluation: one flag at a time, or (`TRAIN`) the flags whose probes read apart at once.
TRAIN_ARGS = ("--out", "{scratch}/model", "--steps", "6", "--finetune-steps", "0", "--eval-episodes", "0",
              "--probe-every", "0", "--log-every", "1", "--width", "16", "--depth", "1", "--vit-width", "16",
              "--batch-size", "2")  # fmt: skip
TRAIN = Run("demo.train", TRAIN_ARGS, together=True, slow=True)
TRAIN_ALONE = Run("demo.train", TRAIN_ARGS, slow=True)
TRAIN_FINETUNE = Run("demo.train", (*TRAIN_ARGS, "--finetune-steps", "6"), slow=True)


def losses(o: Output) -> list[str]:
    """The printed losses."""
    return [line.split(" loss ")[1].split()[0] for line in o.out.splitlines() if " loss " in line]


def logged_steps(phase: str) -> Callable[[Output], list[str]]:
    return lambda o: [
        line.split()[2] for line in o.out.splitlines() if line.startswith(f"{phase} step ") and " loss " in line
    ]


def param_shapes(path: str) -> Callable[[Output], Any]:
    def probe(o: Output) -> Any:
        from openpi_cam.model.checkpoint import read_param_shapes

        (params,) = sorted(o.root.glob("*/checkpoint/params"))
        return {k: v for k, v in read_param_shapes(params).items() if path in k}

    return probe


def log_period(o: Output) -> int:
    import math

    steps = [int(s.split("/")[0]) for s in logged_steps("main")(o)]
    return math.gcd(*steps)


TRAIN_CASES: dict[str, tuple[Case, ...]] = {
    "--model": (Changes(TRAIN_ALONE, ("--model", "pi05"), lambda o: o.paths("*/fast_tokenizer/*")),),
    "--out": (
        Changes(TRAIN, ("--out", "{scratch}/elsewhere"), lambda o: sorted({p.split("/")[0] for p in o.paths()})),
    ),
    "--steps": (Changes(TRAIN, ("--steps", "7"), lambda o: {s.split("/")[1] for s in logged_steps("main")(o)}),),
    "--batch-size": (Changes(TRAIN_ALONE, ("--batch-size", "3"), losses),),
    "--lr": (Changes(TRAIN_ALONE, ("--lr", "0.02"), losses),),
    "--warmup": (Changes(TRAIN_ALONE, ("--warmup", "1"), losses),),
    "--seed": (Changes(TRAIN_ALONE, ("--seed", "1"), losses),),
    "--width": (Changes(TRAIN, ("--width", "32"), param_shapes("llm/embedder")),),
    "--depth": (Changes(TRAIN, ("--depth", "2"), param_shapes("llm/layers")),),
    "--vit-width": (Changes(TRAIN, ("--vit-width", "32"), param_shapes("img/embedding")),),
    "--patch-size": (Changes(TRAIN, ("--patch-size", "8"), param_shapes("img/pos_embedding")),),
    "--contrast-pairs": (Changes(TRAIN_ALONE, ("--no-contrast-pairs",), losses),),
    "--decode-offset": (
        Changes(TRAIN_ALONE, ("--decode-offset", "1"), losses),
        Refused("demo.train", (*TRAIN_ARGS, "--model", "pi05", "--decode-offset", "1")),
    ),
    "--finetune-steps": (Changes(TRAIN, ("--finetune-steps", "2"), logged_steps("finetune")),),
    "--finetune-lr": (
        Changes(TRAIN_FINETUNE, ("--finetune-lr", "0.02"), losses),
        Refused("demo.train", (*TRAIN_ARGS, "--finetune-lr", "0.02")),
    ),
    "--finetune-warmup": (
        Changes(TRAIN_FINETUNE, ("--finetune-warmup", "1"), losses),
        Refused("demo.train", (*TRAIN_ARGS, "--finetune-warmup", "1")),
    ),
    "--init-from": (Changes(TRAIN_ALONE, ("--init-from", "{trained}/checkpoint/params"), losses),),
    "--eval-episodes": (Changes(TRAIN, ("--eval-episodes", "1"), lambda o: "success_rate" in o.out),),
    "--log-every": (Changes(TRAIN, ("--log-every", "2"), log_period),),
    "--probe-every": (Changes(TRAIN, ("--probe-every", "1"), lambda o: "binding probe" in o.out),),
    "--save-every": (
        Changes(TRAIN, ("--save-every", "3"), lambda o: [s for s in o.out.splitlines() if "state saved" in s]),
    ),
    # What resuming continues to: tests/demo/test_train_state.py (runs stopped by SIGTERM and SIGKILL).
    "--resume": (Refused("demo.train", (*TRAIN_ARGS, "--resume")),),
}


@dataclasses.dataclass(frozen=True)
class Delegates:
    """`train_demo --sim reach` hands its `--args.*` to `demo.train` unchanged: with every one of them given, it trains
    the model `demo.train` trains with the same flags (whose own cases show each flag changes the training)."""


# train_demo: the reaching task's base, Meta-World's (two expert episodes recorded, then the same tiny training).
def _args_flags(args: tuple[str, ...]) -> tuple[str, ...]:
    """`demo.train`'s flags as `train_demo` spells them (`--args.` before each)."""
    return tuple(("--args." + a[2:]) if a.startswith("--") else a for a in args)


# Meta-World trains without the binding probe: its default is kept (it never runs in six steps).
TRAIN_DEMO_ARGS = _args_flags(
    tuple(a for pair in zip(TRAIN_ARGS[::2], TRAIN_ARGS[1::2], strict=True) if pair[0] != "--probe-every" for a in pair)
)
TRAIN_DEMO = Run("train_demo", TRAIN_DEMO_ARGS, slow=True)
# Two episodes of one task (its three phrasings cycled), recorded at the multi-task robot's size.
METAWORLD = ("--sim", "metaworld", "--data", "{scratch}/expert", "--record.episodes", "2", "--record.tasks",
             metaworld_sim.TASK)  # fmt: skip
TRAIN_METAWORLD = Run("train_demo", (*METAWORLD, *TRAIN_DEMO_ARGS), slow=True)
TRAIN_METAWORLD_PI05 = Run("train_demo", (*METAWORLD, *TRAIN_DEMO_ARGS, "--args.model", "pi05"), slow=True)
# Two tasks' episodes, for a weight to shift the draws between.
TRAIN_METAWORLD_TWO_TASKS = Run("train_demo", (*METAWORLD, "reach-v3", *TRAIN_DEMO_ARGS), slow=True)
EXPERT_CAMERA = recorded("expert/meta/info.json", "features", metaworld_data.BASE_FEATURE, "shape")


def expert_states(episode: int | None) -> Callable[[Output], Any]:
    """The recorded states of one episode (None: all) of the expert's dataset."""

    def probe(o: Output) -> Any:
        import pyarrow.parquet as pq

        table = pq.read_table(sorted(o.root.glob("expert/data/*/*.parquet"))[0])
        rows = table.to_pydict()
        keep = [i for i, e in enumerate(rows["episode_index"]) if episode is None or e == episode]
        return [rows["observation.state"][i] for i in keep]

    return probe


def expert_wrist(o: Output) -> str:
    """A digest of the expert's recorded wrist frames (their encoded bytes, in order)."""
    import pyarrow.parquet as pq

    digest = hashlib.sha256()
    for path in sorted(o.root.glob("expert/data/*/*.parquet")):
        for image in pq.read_table(path, columns=[metaworld_data.WRIST_FEATURE]).column(0).to_pylist():
            digest.update(image["bytes"])
    return digest.hexdigest()


def expert_tasks(o: Output) -> list[str]:
    """The instructions of the expert's episodes."""
    import pyarrow.parquet as pq

    (path,) = sorted(o.root.glob("expert/meta/tasks.parquet"))
    return sorted(str(v) for column in pq.read_table(path).to_pydict().values() for v in column)


TRAIN_DEMO_CASES: dict[str, tuple[Case, ...]] = {
    **{"--args." + flag[2:]: (Delegates(),) for flag in TRAIN_CASES},
    "--sim": (
        Changes(TRAIN_DEMO, METAWORLD, paths()),
        # Button press alone: the one-task pi0.5 at the one-task robot's size.
        Changes(TRAIN_METAWORLD_PI05, ("--sim", "metaworld-button"), EXPERT_CAMERA),
    ),
    "--data": (
        Changes(TRAIN_METAWORLD, ("--data", "{scratch}/other"), top_folders),
        Refused("train_demo", ("--data", "{scratch}/expert")),
        # A second folder is read, never recorded into: one that holds no dataset is refused before anything runs.
        Refused("train_demo", ("--sim", "metaworld", "--data", "{scratch}/expert", "{scratch}/absent")),
    ),
    "--record.episodes": (
        Changes(TRAIN_METAWORLD, ("--record.episodes", "3"), recorded("expert/meta/info.json", "total_episodes")),
        Refused("train_demo", ("--record.episodes", "3")),
    ),
    "--record.seed": (Changes(TRAIN_METAWORLD, ("--record.seed", "7"), expert_states(0)),),
    "--record.noise": (Changes(TRAIN_METAWORLD, ("--record.noise", "0.1"), expert_states(None)),),
    "--record.clean-every": (Changes(TRAIN_METAWORLD, ("--record.clean-every", "1"), expert_states(None)),),
    "--record.tasks": (Changes(TRAIN_METAWORLD, ("--record.tasks", "reach-v3"), expert_tasks),),
    "--record.image-size": (Changes(TRAIN_METAWORLD, ("--record.image-size", "32"), EXPERT_CAMERA),),
    "--record.phrasings": (Changes(TRAIN_METAWORLD, ("--record.phrasings", "1"), expert_tasks),),
    "--record.wrist-camera": (
        Changes(TRAIN_METAWORLD, ("--record.wrist-camera", "behindGripper"), expert_wrist),
        Refused("train_demo", ("--record.wrist-camera", "behindGripper")),  # the reaching task has no such cameras
        Refused("train_demo", ("--sim", "metaworld", "--data", "{scratch}/expert", "--record.wrist-camera", "wrist")),
    ),
    "--task-weights": (
        Changes(TRAIN_METAWORLD_TWO_TASKS, ("--task-weights", "reach-v3=4"), losses),
        Refused("train_demo", ("--task-weights", "reach-v3=2")),  # the reaching task has no Meta-World tasks
        Refused("train_demo", ("--sim", "metaworld", "--data", "{scratch}/expert", "--task-weights", "reach=2")),
        # A task the recorded episodes do not show: refused once they are read, before any training.
        Refused("train_demo", (*METAWORLD, "--task-weights", "reach-v3=2"), slow=True),
    ),
}

CASES: dict[str, dict[str, tuple[Any, ...]]] = {
    "serve": SERVE_CASES,
    "demo": DEMO_CASES,
    "golden": {},
    "explain-run": EXPLAIN_RUN_CASES,
    "explain-dataset": EXPLAIN_DATASET_CASES,
    "faithfulness": FAITHFULNESS_CASES,
    "render": RENDER_CASES,
    "stats": STATS_CASES,
    "rebuild-manifest": {},
    "export": EXPORT_CASES,
    "monitor fit": MONITOR_FIT_CASES,
    "head fit": HEAD_FIT_CASES,
    "train_demo": TRAIN_DEMO_CASES,
    "demo.train": TRAIN_CASES,
}


# ------------------------------------------------------------------------------------------------ running them


def _linked_copy(src: Path, dst: Path) -> Path:
    """`src` at `dst` as real folders of links to its files (a checkpoint somewhere else: another path, same bytes)."""
    for path in sorted(src.rglob("*")):
        target = dst / path.relative_to(src)
        if path.is_dir():
            target.mkdir(parents=True, exist_ok=True)
        else:
            target.parent.mkdir(parents=True, exist_ok=True)
            target.symlink_to(path.resolve())
    return dst


def _restated(src: Path, dst: Path) -> Path:
    """A linked copy of a bundled model whose norm stats are shifted: the same weights, other statistics."""
    copy = _linked_copy(src, dst)
    (stats,) = copy.glob("checkpoint/assets/*/norm_stats.json")
    data = json.loads(stats.read_text())
    for entry in data["norm_stats"].values():
        entry["mean"] = [v + 0.5 for v in entry["mean"]]
        for q in ("q01", "q99"):
            if entry.get(q) is not None:
                entry[q] = [v + 0.5 for v in entry[q]]
    stats.unlink()
    stats.write_text(json.dumps(data))
    return copy


class Runner:
    """Runs each command line once (a case's base is shared by every case of it) in a folder of its own, which is
    the command's working directory and holds copies of the inputs its arguments name."""

    def __init__(self, tmp: pytest.TempPathFactory, request: pytest.FixtureRequest) -> None:
        self._tmp, self._request = tmp, request
        self._outputs: dict[tuple[str, tuple[str, ...]], Output] = {}
        self._shared: dict[str, Path] = {}

    def output(self, command: str, args: tuple[str, ...], *, serving: bool = False) -> Output:
        key = (command, args)
        if key not in self._outputs:
            root = self._tmp.mktemp(command.replace(".", "_").replace(" ", "_"))
            argv = [self._place(a, root) for a in args]
            self._outputs[key] = serve_session(argv, root) if serving else in_process(command, argv, root)
        return self._outputs[key]

    def _place(self, arg: str, root: Path) -> str:
        per_run = {
            "{scratch}": lambda: root,
            "{run}": lambda: shutil.copytree(self._request.getfixturevalue("served_run_dir"), root / "run"),
            "{maps}": lambda: shutil.copytree(self._request.getfixturevalue("demo_maps_dir"), root / "maps"),
            "{port}": lambda: free_port(),
        }
        for name, make in per_run.items():
            if name in arg:
                done = root / "run" if name == "{run}" and (root / "run").exists() else None
                done = root / "maps" if name == "{maps}" and (root / "maps").exists() else done
                arg = arg.replace(name, str(done or make()))
        for name in (
            "{demo}",
            "{pi05}",
            "{golden}",
            "{democopy}",
            "{restated}",
            "{restated05}",
            "{records}",
            "{cutvideo}",
            "{trained}",
            "{mt05}",
            "{monitor}",
            "{featured}",
            "{head}",
            "{chunkhead}",
            "{headmaps}",
        ):
            if name in arg:
                arg = arg.replace(name, str(self._shared_input(name)))
        return arg

    def _shared_input(self, name: str) -> Path:
        if name not in self._shared:
            folder = self._tmp.mktemp("input")
            self._shared[name] = {
                "{demo}": lambda: demo_reach.ASSETS,
                "{pi05}": lambda: demo_reach.ASSETS_PI05,
                "{golden}": lambda: GOLDEN_DIR,
                "{democopy}": lambda: _linked_copy(demo_reach.ASSETS, folder / "demo"),
                "{restated}": lambda: _restated(demo_reach.ASSETS, folder / "demo"),
                "{restated05}": lambda: _restated(demo_reach.ASSETS_PI05, folder / "demo_pi05"),
                "{records}": lambda: _policy_records(folder / "records"),
                "{cutvideo}": lambda: _cut_video(folder / "cut"),
                "{trained}": lambda: self._trained(folder),
                "{mt05}": lambda: _multitask_stand_in(demo_metaworld.ASSETS_METAWORLD, folder / "mt05"),
                "{monitor}": lambda: _stac_monitor(folder / "stac_monitor.json"),
                "{featured}": lambda: _featured_rollouts(folder),
                "{head}": lambda: Path(planted_head(folder / "head.json", ModelSpec(), "action-token").path),
                "{chunkhead}": lambda: Path(planted_head(folder / "head.json", ModelSpec(), "chunk").path),
                "{headmaps}": lambda: random_maps(folder / "random.maps"),
            }[name]()
        return self._shared[name]

    def _trained(self, folder: Path) -> Path:
        out = folder / "trained"
        argv = [a.replace("{scratch}/model", str(out)) for a in TRAIN_ARGS]
        assert train.main(argv) == 0
        return out


def _multitask_stand_in(src: Path, dst: Path) -> Path:
    """A linked copy of the one-task Meta-World pi0.5 whose statistics sit under the multi-task robot's asset id:
    a folder the multi-task pi0.5's config serves (the same robot, state and actions)."""
    copy = _linked_copy(src, dst)
    assets = copy / "checkpoint" / "assets"
    (assets / demo_metaworld.ASSET_ID).rename(assets / demo_metaworld.MT_ASSET_ID)
    return copy


def _stac_monitor(path: Path) -> Path:
    """A STAC monitor (STAC-single is its score; any model gives it) with its threshold set on made-up successful
    episodes. It names no execution horizon, so a command's own (`--execution-horizon`) stands beside it."""
    episodes = [Episode({STAC: np.array([np.nan, 0.1 * k, 0.2 * k])}, True) for k in range(1, 5)]
    return monitor_file.save(fit_monitor(episodes, FitOptions(kind="stac")), path)


def _featured_rollouts(folder: Path) -> Path:
    """The bundled pi0-FAST's recorded rollouts, clean and with the named block absent (successes and failures),
    explained every 5th frame (the calls) with the monitor's features: what `monitor fit` fits on."""
    rollouts, maps = folder / "rollouts", folder / "featured.maps"
    cli.main(["demo", "--no-explain", "--num-episodes", "6", "--max-calls", "3", "--perturb", "clean", "absent",
              "--record", str(rollouts)])  # fmt: skip
    cli.main(["explain-dataset", str(rollouts), "--out", str(maps), "--every-k", "5", "--maps", "gradnorm",
              "--check-patches", "0", "--monitor-features", "--no-progress"])  # fmt: skip
    return maps


def _policy_records(folder: Path) -> Path:
    """An upstream PolicyRecorder folder of two demo requests (pickled dicts of `inputs/...` and `outputs/...`)."""
    folder.mkdir()
    for n in range(2):
        record = {f"inputs/{k}": v for k, v in demo_observation(n).items()} | {"outputs/actions": np.zeros((10, 2))}
        np.save(folder / f"step_{n}", np.asarray(record))
    return folder


def _cut_video(dst: Path) -> Path:
    from shared_copies import writable_copy

    source = writable_copy(DEMO_DATASET.with_name("demo_reach_v21_video"), dst)
    broken = source / "videos/chunk-000/observation.images.base/episode_000002.mp4"
    broken.write_bytes(broken.read_bytes()[: broken.stat().st_size // 3])
    return source


def _text_stream() -> io.TextIOWrapper:
    # A text stream with a binary buffer beneath, as the real ones have (`stats` writes parquet and CSV bytes to it).
    return io.TextIOWrapper(io.BytesIO(), encoding="utf-8", write_through=True)


def _written(stream: io.TextIOWrapper) -> str:
    stream.flush()
    return stream.buffer.getvalue().decode("utf-8", errors="replace")  # type: ignore[attr-defined]


def in_process(command: str, argv: list[str], root: Path) -> Output:
    out, err = _text_stream(), _text_stream()
    with contextlib.chdir(root), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = _run_in_process(command, argv)
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
            if isinstance(e.code, str):
                print(e.code, file=sys.stderr)
    return Output(code, _written(out), _written(err), root)


def _value(argv: list[str], flag: str) -> str | None:
    """The last value given to `flag` (as the parser takes it)."""
    values = [argv[i + 1] for i, a in enumerate(argv[:-1]) if a == flag]
    return values[-1] if values else None


def serve_session(argv: list[str], root: Path) -> Output:
    """`serve ARGV` in a child process: once it answers, a client asks for /stats with and without the API key,
    sends a request and a prompt-less one, opens a second connection while the first is open and sends an oversized
    message; then SIGTERM. What the client saw is `Output.seen`."""
    from websockets.exceptions import ConnectionClosed, InvalidHandshake
    from websockets.sync.client import connect

    port, key = int(_value(argv, "--port")), _value(argv, "--api-key")
    headers = {"Authorization": f"Api-Key {key}"} if key else {}
    log = root / "serve.log"
    seen: dict[str, Any] = {}
    with log.open("w") as sink:
        proc = subprocess.Popen(
            [sys.executable, "-m", "openpi_cam", "serve", *argv], stdout=sink, stderr=subprocess.STDOUT, cwd=root
        )
    try:
        wait_healthy(proc, port, log)
        base = f"http://127.0.0.1:{port}"
        seen["stats_without_key"] = http_get(f"{base}/stats")[0]
        seen["stats"] = json.loads(http_get(f"{base}/stats", headers=headers)[1])

        def reply(ws: Any, obs: dict[str, Any]) -> Any:
            ws.send(msgpack_numpy.packb(obs))
            frame = ws.recv(timeout=300)
            if isinstance(frame, str):  # an error is sent as text
                return frame
            response = msgpack_numpy.unpackb(frame)
            seen.setdefault("response_keys", sorted(response))
            return np.asarray(response["actions"]).round(4).tolist()

        url = f"ws://127.0.0.1:{port}"
        with connect(url, additional_headers=headers, max_size=None, open_timeout=60) as ws:
            ws.recv(timeout=60)  # the metadata
            seen["actions"] = reply(ws, demo_observation(0))
            without = {k: v for k, v in demo_observation(0).items() if k != "prompt"}
            seen["without_prompt"] = "refused" if isinstance(reply(ws, without), str) else "served"
            try:
                with connect(url, additional_headers=headers, open_timeout=60) as second:
                    second.recv(timeout=60)
                    seen["second_connection"] = "admitted"
            except ConnectionClosed as e:
                seen["second_connection"] = f"closed {e.rcvd.code if e.rcvd else None}"
            except InvalidHandshake as e:  # refused before the websocket opened
                seen["second_connection"] = f"refused {type(e).__name__}"
            try:
                ws.send(bytes(3 << 19))  # 1.5 MB
                answer = ws.recv(timeout=300)
                seen["oversized"] = "answered" if answer else "empty"
            except ConnectionClosed as e:
                seen["oversized"] = f"closed {e.rcvd.code if e.rcvd else None}"
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(180)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return Output(proc.returncode, "", log.read_text(), root, seen)


@pytest.fixture(scope="module")
def runner(tmp_path_factory, request) -> Runner:
    return Runner(tmp_path_factory, request)


# ------------------------------------------------------------------------------------------------------ the tests


def test_every_flag_has_a_case():
    """The parsers' flags and the cases' flags are the same, command by command: a flag added without a case (or a
    case left for a removed flag) fails here."""
    for command, parsed in _parsers().items():
        flags = flags_of(parsed)
        cases = set(CASES[command])
        assert flags == cases, (
            f"{command}: flags without a case {sorted(flags - cases)}, cases of no flag {sorted(cases - flags)}"
        )
        assert all(CASES[command][flag] for flag in flags), f"{command}: a flag with an empty list of cases"


def test_every_flag_says_what_it_does():
    """Each flag's `--help` has text of its own: none is bare, and no two flags of a command share one text (a
    comment above several fields gives tyro's help of each the same block, which then describes only the first)."""
    for command, parsed in _parsers().items():
        by_text: dict[str, list[str]] = {}
        for action in _parser(parsed)._actions:
            if not action.option_strings or "--help" in action.option_strings:
                continue
            text = (action.help or "").split("(default:")[0].split("(required)")[0].strip()
            by_text.setdefault(text, []).append(action.option_strings[0])
        assert "" not in by_text, f"{command}: flags without help {by_text.get('')}"
        shared = {text[:60]: flags for text, flags in by_text.items() if len(flags) > 1}
        assert not shared, f"{command}: flags sharing one help text {shared}"


def _params() -> list:
    params = []
    for command, by_flag in CASES.items():
        for flag, cases in by_flag.items():
            for i, case in enumerate(cases):
                slow = getattr(case, "slow", False) or getattr(getattr(case, "run", None), "slow", False)
                slow = slow or isinstance(case, Delegates)
                marks = [pytest.mark.slow] if slow else []
                params.append(pytest.param(command, flag, case, id=f"{command}:{flag}:{i}", marks=marks))
    return params


def _with_group(case: Changes) -> tuple[str, ...]:
    """The arguments a case's run is made with: its own, or every case's of its group (`Run.together`)."""
    if not case.run.together:
        return case.args
    together = [
        c.args
        for cases in CASES[case.run.command].values()
        for c in cases
        if isinstance(c, Changes) and c.run == case.run
    ]
    return tuple(a for args in together for a in args)


@pytest.mark.parametrize(("command", "flag", "case"), _params())
def test_a_flag_changes_the_output_or_is_refused(command, flag, case, runner):
    serving = command == "serve"
    if isinstance(case, Changes):
        base = runner.output(command, case.run.args, serving=serving)
        given = runner.output(command, case.run.args + _with_group(case), serving=serving)
        for output in (base, given):
            assert "Traceback" not in output.err, output.err
        assert (base.code != 0) == case.run.fails, f"{command} {' '.join(case.run.args)}: {base.out}{base.err}"
        before, after = case.probe(base), case.probe(given)
        assert before != after, f"{command} {flag}: the output read by the probe did not change ({after!r})"
    elif isinstance(case, Refused):
        output = runner.output(command, case.args)
        text = output.out + output.err
        assert output.code not in (0, None), f"{command} {' '.join(case.args)} was not refused:\n{text}"
        assert "Traceback" not in text, text
        spelled = {flag, flag.replace("--", "--no-", 1), flag.replace("--args.", "--args.no-")}
        named = [line for line in text.splitlines() if any(s in line for s in spelled)]
        assert len(named) == 1, f"{command} {' '.join(case.args)}: not one line naming {flag}:\n{text}"
    elif isinstance(case, Fixed):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            parser = tyro.extras.get_parser(_parsers()[command])
        (action,) = [a for a in parser._actions if flag in a.option_strings]
        assert action.choices is not None and len(tuple(action.choices)) == 1, action.choices
    elif isinstance(case, Covered):
        path, _, name = case.test.partition("::")
        assert f"def {name}(" in (REPO_ROOT / path).read_text(), case.test
    else:  # Delegates: train_demo --sim reach with every --args.* flag trains what demo.train trains with them
        flags = [
            a for c in TRAIN_CASES.values() for c in c if isinstance(c, Changes) and c.run == TRAIN for a in c.args
        ]
        ours = runner.output("train_demo", _args_flags((*TRAIN_ARGS, *flags)))
        theirs = runner.output("demo.train", (*TRAIN_ARGS, *flags))
        assert ours.code == theirs.code == 0, ours.out + ours.err
        assert ours.files("model/checkpoint/**/*") == theirs.files("model/checkpoint/**/*")
