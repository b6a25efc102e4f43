"""`openpi-cam explain SOURCE`: maps computed offline for recorded observations, written as a normal CAM run."""

from __future__ import annotations

import dataclasses
import pathlib
import sys
from collections.abc import Callable
from typing import Literal

import tyro

from openpi_cam.cam.logger import CAMLogger
from openpi_cam.cam.offline import ExplainOptions, Replay, explain_replays, open_source, resume_mismatch
from openpi_cam.cam.run_format import RUN_JSON, load_run
from openpi_cam.cli.options import MapFlags
from openpi_cam.datasets.explain import (
    DatasetJob,
    JobSummary,
    PolicySpec,
    dataset_keys,
    parse_pairs,
    recorded_actions_feature,
    run_local,
)
from openpi_cam.datasets.lerobot import DatasetError, is_lerobot_dataset, parse_episodes
from openpi_cam.datasets.ray_engine import run_ray
from openpi_cam.errors import InvalidRequest
from openpi_cam.policies import demo_reach
from openpi_cam.policies.config import resolve_config
from openpi_cam.policies.family import resolve_target
from openpi_cam.policies.policy import create_policy
from openpi_cam.viz.progress import progress as progress_bar
from openpi_cam.viz.rerun_sink import write_rrd
from openpi_cam.vocabulary import DATASET_ACTIONS, DEFAULT_TARGETS, MAP_KINDS, SaveFrames

_DEFAULT_OUT = pathlib.Path("cam_runs")
_EVERY_KIND = MapFlags(maps=MAP_KINDS)  # offline, every kind by default: there is no robot to keep waiting


def main(
    source: tyro.conf.Positional[pathlib.Path],
    checkpoint_dir: pathlib.Path | None = None,
    config: str | None = None,
    out: pathlib.Path = _DEFAULT_OUT,
    resume: pathlib.Path | None = None,
    explanation: tyro.conf.OmitArgPrefixes[MapFlags] = _EVERY_KIND,
    save_frames: SaveFrames = "both",
    batch_size: int = 8,
    limit: int | None = None,
    nested_keys: bool = False,
    paligemma_tokenizer: pathlib.Path | None = None,
    fast_tokenizer: pathlib.Path | None = None,
    dtype: str = "bfloat16",
    default_prompt: str | None = None,
    rerun: pathlib.Path | None = None,
    progress: bool = True,
    keys: tuple[str, ...] = (),
    extra: tuple[str, ...] = (),
    episodes: str | None = None,
    every: int = 1,
    engine: Literal["local", "ray"] = "local",
    workers: int = 1,
    ray_address: str | None = None,
    keep_going: bool = False,
) -> int:
    """Compute maps offline for recorded observations and write a CAM run directory (same format as serving).
    Exit status 3 when a re-run inference returned other actions than the recorded ones.

    Args:
        source: a LeRobot dataset (v2.1 or v3.0; written as a maps dataset, README "Explaining a LeRobot
            dataset"), an upstream PolicyRecorder folder (step_N.npy files) or a CAM run directory with raw frames.
        checkpoint_dir: checkpoint folder with `params/` and `assets/<asset_id>/norm_stats.json`; default: the
            bundled demo model (config `demo_reach`).
        config: named policy config (e.g. pi0_fast_droid, pi05_libero); default pi0_fast_droid for a checkpoint.
        out: for a LeRobot dataset, the maps dataset to write or add to (default `SOURCE_NAME.maps` in the current
            folder); otherwise the folder in which a new run directory is created (if OUT is itself a run
            directory, it is resumed).
        resume: a run directory to resume: observations already explained in it are skipped, new steps appended.
        explanation: what the maps explain and which kinds each step carries (all four by default).
        save_frames: which camera frames to store next to the maps (`raw`/`both` keep the run re-explainable).
        batch_size: observations explained per model call, split over all local devices.
        limit: explain at most this many observations not yet in the run (resume later for the rest).
        nested_keys: read PolicyRecorder keys `a/b` as nested dicts (ALOHA's `images/...`) instead of flat keys.
        paligemma_tokenizer: PaliGemma SentencePiece model; default: the policy factory's standard location.
        fast_tokenizer: FAST action tokenizer folder; default: the policy factory's standard location.
        dtype: parameter dtype (bfloat16 or float32); upstream serves bfloat16.
        default_prompt: prompt used when a record has none.
        rerun: also write the finished run as a Rerun recording (.rrd; needs the `rerun` extra).
        progress: show progress on stderr.
        keys: LeRobot datasets: `OBS_KEY=FEATURE` pairs feeding the policy's observation key from a dataset
            feature, overriding the config's declared mapping key by key.
        extra: LeRobot datasets: `FEATURE=NAME` pairs carrying a dataset feature into each row as `extra/NAME`
            (`observation.target_box=target_box` gives the pointing figures).
        episodes: LeRobot datasets: which episodes, e.g. `0,3,7-9` (default: all).
        every: LeRobot datasets: explain every N-th frame of each episode.
        engine: LeRobot datasets: `local` (this machine's devices) or `ray` (a Ray Data actor pool; the `ray` extra).
        workers: Ray actors, each with its own model (one GPU each where the cluster has GPUs).
        ray_address: an existing Ray cluster's address (default: start a local Ray instance).
        keep_going: LeRobot datasets: skip an episode with bad data (counted and named in the summary) instead of
            stopping.
    """
    if is_lerobot_dataset(source):
        return _explain_dataset(
            source,
            checkpoint_dir=checkpoint_dir,
            config=config,
            out=out if out != _DEFAULT_OUT else None,
            options_of=lambda: explanation.explain_options("none", batch_size, limit),
            paligemma_tokenizer=paligemma_tokenizer,
            fast_tokenizer=fast_tokenizer,
            dtype=dtype,
            default_prompt=default_prompt,
            keys=keys,
            extra=extra,
            episodes=episodes,
            every=every,
            engine=engine,
            workers=workers,
            ray_address=ray_address,
            keep_going=keep_going,
            progress=progress,
        )
    if checkpoint_dir is None:
        checkpoint_dir, config = demo_reach.CHECKPOINT, config or demo_reach.DEMO_CONFIG.name
        paligemma_tokenizer = paligemma_tokenizer or demo_reach.PALIGEMMA_TOKENIZER
        fast_tokenizer = fast_tokenizer or demo_reach.FAST_TOKENIZER
    config = config or "pi0_fast_droid"
    resume_dir = resume if resume is not None else (out if (out / RUN_JSON).is_file() else None)
    if resume_dir is not None and not (resume_dir / RUN_JSON).is_file():
        print(f"openpi-cam explain: --resume {resume_dir} is not a CAM run directory", file=sys.stderr)
        return 2
    run_config = {
        "command": "explain",
        "config": config,
        "checkpoint_dir": str(pathlib.Path(checkpoint_dir).resolve()),
        "dtype": dtype,
        "source": str(source.resolve()),
        "paligemma_tokenizer": None if paligemma_tokenizer is None else str(paligemma_tokenizer.resolve()),
        "fast_tokenizer": None if fast_tokenizer is None else str(fast_tokenizer.resolve()),
    }
    try:
        replays, total = open_source(source, nested_keys=nested_keys)
        # The run records the target it explains: the config's family's default when none was named.
        explanation = dataclasses.replace(
            explanation, target=explanation.target or DEFAULT_TARGETS[resolve_config(config).family]
        )
        run_options = {**explanation.recorded(), "save_frames": save_frames}
        options = explanation.explain_options(save_frames, batch_size, limit)
        if resume_dir is not None:
            run_info = load_run(resume_dir, load_arrays=False).run_info
            if diffs := resume_mismatch(run_info, run_config, run_options):
                print(f"openpi-cam explain: cannot resume {resume_dir}, settings differ: {diffs}", file=sys.stderr)
                return 2
        policy = create_policy(
            config,
            checkpoint_dir,
            paligemma_tokenizer=paligemma_tokenizer,
            fast_tokenizer=fast_tokenizer,
            dtype=dtype,
            default_prompt=default_prompt,
        )
        try:
            resolve_target(policy.explainer, explanation.target)
        except ValueError as e:  # a target this family cannot explain: refused before a run is created
            print(f"openpi-cam explain: --target {e}", file=sys.stderr)
            return 2
        if resume_dir is not None:
            cam_logger = CAMLogger.resume(resume_dir)
        else:
            cam_logger = CAMLogger(out, run_config=run_config, checkpoint=str(checkpoint_dir), options=run_options)

        def show(items: object, n: int) -> object:
            return progress_bar(items, n, "explain", progress)  # type: ignore[arg-type]

        try:
            summary = explain_replays(policy, replays, options, cam_logger, total=total, progress=show)  # type: ignore[arg-type]
        finally:
            cam_logger.close()
        if rerun is not None:
            write_rrd(cam_logger.run_dir, rerun)
    except (FileNotFoundError, KeyError, ValueError, InvalidRequest, OSError, ImportError) as e:
        print(f"openpi-cam explain: {e}", file=sys.stderr)
        return 1
    print(f"openpi-cam explain: wrote {cam_logger.run_dir}: {summary}", file=sys.stderr)
    return 0 if summary["actions_mismatched"] == 0 else 3


def _explain_dataset(
    source: pathlib.Path,
    *,
    checkpoint_dir: pathlib.Path | None,
    config: str | None,
    out: pathlib.Path | None,
    options_of: Callable[[], ExplainOptions],
    paligemma_tokenizer: pathlib.Path | None,
    fast_tokenizer: pathlib.Path | None,
    dtype: str,
    default_prompt: str | None,
    keys: tuple[str, ...],
    extra: tuple[str, ...],
    episodes: str | None,
    every: int,
    engine: str,
    workers: int,
    ray_address: str | None,
    keep_going: bool,
    progress: bool,
) -> int:
    """A LeRobot dataset into a maps dataset; exit status 1 with one line on bad input or bad data."""
    if checkpoint_dir is None:
        spec = PolicySpec(config=config or demo_reach.DEMO_CONFIG.name, dtype="float32", default_prompt=default_prompt)
    else:
        spec = PolicySpec(
            config=config or "pi0_fast_droid",
            checkpoint_dir=str(pathlib.Path(checkpoint_dir).resolve()),
            paligemma_tokenizer=None if paligemma_tokenizer is None else str(paligemma_tokenizer.resolve()),
            fast_tokenizer=None if fast_tokenizer is None else str(fast_tokenizer.resolve()),
            dtype=dtype,
            default_prompt=default_prompt,
        )
    try:
        if workers < 1:
            raise ValueError(f"--workers must be >= 1, got {workers}")
        overrides = parse_pairs(keys, "--keys")
        mapping, nested = dataset_keys(spec.config, overrides)
        options, recorded = options_of(), None
        if options.target == DATASET_ACTIONS:
            recorded = recorded_actions_feature(spec.config, overrides)
            if recorded is None:
                raise ValueError(
                    f"--target {DATASET_ACTIONS}: config {spec.config!r} declares no recorded actions; name the "
                    "feature with --keys actions=FEATURE"
                )
            options = dataclasses.replace(options, target="chunk")
        job = DatasetJob(
            source=source,
            out=out if out is not None else pathlib.Path(f"{source.resolve().name}.maps"),
            policy=spec,
            options=options,
            recorded_actions=recorded,
            keys=mapping,
            extra=parse_pairs(extra, "--extra"),
            episodes=parse_episodes(episodes),
            every=every,
            nested_keys=nested,
            keep_going=keep_going,
        )

        def show(items: object, n: int) -> object:
            return progress_bar(items, n, "episodes", progress)  # type: ignore[arg-type]

        summary: JobSummary
        if engine == "ray":
            summary = run_ray(job, workers=workers, address=ray_address)
        else:
            summary = run_local(job, progress=show)  # type: ignore[arg-type]
    except (DatasetError, FileNotFoundError, KeyError, ValueError, InvalidRequest, OSError, ImportError) as e:
        print(f"openpi-cam explain: {e}", file=sys.stderr)
        return 1
    print(f"openpi-cam explain: wrote {job.out}: {summary.line()}", file=sys.stderr)
    for episode, why in sorted(summary.episodes_skipped.items()):
        print(f"openpi-cam explain: skipped episode {episode}: {why}", file=sys.stderr)
    return 0


__all__ = ["Replay", "main"]
