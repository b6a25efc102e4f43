"""`openpi-cam explain-dataset DATASET`: a LeRobot dataset (v2.1 or v3.0) into a maps dataset, on this machine or a
Ray cluster (README, "Explaining a LeRobot dataset")."""

from __future__ import annotations

import dataclasses
import pathlib
import sys
from typing import Annotated, Literal

import tyro

from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.cli.options import BUNDLED_MODEL, EVERY_KIND, ExplainFlags
from openpi_cam.errors import InvalidRequest
from openpi_cam.lerobot.dataset import DatasetError, parse_episodes
from openpi_cam.maps.explain import (
    DatasetJob,
    JobSummary,
    dataset_keys,
    parse_pairs,
    recorded_actions_feature,
    run_local,
)
from openpi_cam.maps.ray_engine import run_ray
from openpi_cam.viz.progress import Reporter
from openpi_cam.vocabulary import DATASET_ACTIONS

COMMAND = "explain-dataset"


def main(
    source: tyro.conf.Positional[pathlib.Path],
    model: tyro.conf.OmitArgPrefixes[ModelSpec] = BUNDLED_MODEL,
    out: pathlib.Path | None = None,
    explanation: tyro.conf.OmitArgPrefixes[ExplainFlags] = EVERY_KIND,
    batch_size: int = 8,
    keys: tuple[str, ...] = (),
    extra: tuple[str, ...] = (),
    episodes: str | None = None,
    every_k: Annotated[int, tyro.conf.arg(aliases=("--every",))] = 1,
    engine: Literal["local", "ray"] = "local",
    workers: int = 1,
    ray_address: str | None = None,
    keep_going: bool = False,
    outcome: str | None = None,
    monitor: pathlib.Path | None = None,
    no_monitor: tyro.conf.FlagCreatePairsOff[bool] = False,
    monitor_features: bool = False,
    sample_spread: int = 0,
    execution_horizon: int | None = None,
    progress: bool = True,
) -> int:
    """Serve every selected frame of a LeRobot dataset to the policy as a robot would send it, explain it, and write
    one parquet shard of maps per episode (a maps dataset: docs/FORMAT.md). Exit status 1 with one line on bad input
    or bad data.

    Args:
        source: a LeRobot dataset folder (holds meta/info.json; layouts v2.1 and v3.0).
        model: the model to explain with (default: the bundled demo model; no `--default-prompt`: every frame's task
            is its prompt).
        out: the maps dataset to write or add to (default: `SOURCE_NAME.maps` in the current folder).
        explanation: what the maps explain and which kinds each frame carries (all four by default); `--target
            dataset-actions` (pi0-FAST) explains the recorded chunk instead of the model's own.
        batch_size: frames explained per model call, split over all local devices.
        keys: `OBS_KEY=FEATURE` pairs feeding the policy's observation key from a dataset feature, overriding the
            config's declared mapping key by key.
        extra: `FEATURE=NAME` pairs carrying a dataset feature into each row as `extra/NAME`
            (`observation.target_box=target_box` gives the pointing figures).
        episodes: which episodes, e.g. `0,3,7-9` (default: all).
        every_k: explain every k-th frame of each episode.
        engine: `local` (this machine's devices) or `ray` (a Ray Data actor pool; the `ray` extra).
        workers: Ray actors, each with its own model (one GPU each where the cluster has GPUs).
        ray_address: an existing Ray cluster's address (default: start a local Ray instance).
        keep_going: skip an episode with bad data (counted and named in the summary) instead of stopping.
        outcome: the feature whose truth in any frame of an episode makes it a success (default: `next.success`,
            as `lerobot-eval --eval.recording=true` records it, where the dataset has it); each row then carries its
            episode's length, success and return (`next.reward` summed), and `stats` tells failures from successes.
        monitor: a failure monitor file (`openpi-cam monitor fit`): each row gets its frame's `monitor/score` and
            `monitor/flag` (the episode flagged by then), scored over the episode's explained frames in order, as
            `serve --monitor` scores a connection's calls. Every row carries `monitor/stac` and (pi0-FAST)
            `monitor/token_entropy` with or without one. Default: a demo model's own `<assets>/monitor.json`, as
            `serve` uses it.
        no_monitor: score with no monitor, even a demo model's own.
        monitor_features: also write each row's pooled last-layer features (`monitor/features/<name>`, float32), what
            `openpi-cam monitor fit` fits a probe or a Mahalanobis monitor on.
        sample_spread: also draw this many action chunks per frame (the served one and N - 1 from other noises) and
            write how far they spread (`monitor/sample_spread`), a monitor input (pi0 / pi0.5; it costs N - 1 more
            samples a frame). Default: none, or the monitor's count where it reads the spread.
        execution_horizon: the actions the robot executed per call: `monitor/stac` compares a frame's chunk with the
            previous explained frame's when that lies this many frames before (explain with `--every-k` equal to
            it). Default: the monitor's, else 5 (the demo robots').
        progress: show progress on stderr.
    """
    try:
        if workers < 1:
            raise ValueError(f"--workers must be >= 1, got {workers}")
        if engine == "local" and (workers != 1 or ray_address is not None):
            raise ValueError("--workers and --ray-address run the Ray engine: add --engine ray")
        if model.default_prompt is not None:
            raise ValueError("--default-prompt: every frame of a LeRobot dataset has its task, which is its prompt")
        spec = model.resolved()
        overrides = parse_pairs(keys, "--keys")
        mapping, nested = dataset_keys(spec, overrides)
        options, recorded = explanation.options(model=spec), None
        if options.target == DATASET_ACTIONS:
            recorded = recorded_actions_feature(spec, overrides)
            if recorded is None:
                raise ValueError(
                    f"--target {DATASET_ACTIONS}: the model declares no recorded actions; name the feature with --keys "
                    "actions=FEATURE"
                )
            options = dataclasses.replace(options, target="chunk")
        job = DatasetJob(
            source=source,
            out=out if out is not None else pathlib.Path(f"{source.resolve().name}.maps"),
            model=spec,
            options=options,
            batch_size=batch_size,
            recorded_actions=recorded,
            keys=mapping,
            extra=parse_pairs(extra, "--extra"),
            episodes=parse_episodes(episodes),
            every=every_k,
            nested_keys=nested,
            keep_going=keep_going,
            outcome=outcome,
            monitor=model.chosen_monitor(monitor, no_monitor),
            monitor_features=monitor_features,
            sample_spread=sample_spread,
            execution_horizon=execution_horizon,
        )

        show = Reporter("episodes", progress)
        summary: JobSummary
        if engine == "ray":
            summary = run_ray(job, workers=workers, address=ray_address, progress=show)
        else:
            summary = run_local(job, progress=show)
    except (DatasetError, FileNotFoundError, KeyError, ValueError, InvalidRequest, OSError, ImportError) as e:
        print(f"openpi-cam {COMMAND}: {e}", file=sys.stderr)
        return 1
    print(f"openpi-cam {COMMAND}: wrote {job.out}: {summary.line()}", file=sys.stderr)
    for episode, why in sorted(summary.episodes_skipped.items()):
        print(f"openpi-cam {COMMAND}: skipped episode {episode}: {why}", file=sys.stderr)
    return 0
