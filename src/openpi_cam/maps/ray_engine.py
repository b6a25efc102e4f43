"""`openpi-cam explain-dataset DATASET_DIR --engine ray --workers N`: the dataset explanation on a Ray cluster.

Ray Data holds the episodes still to do (one block each) and runs `map_batches` over them with a fixed pool of
actors: each actor loads its own copy of the model once (`EpisodeExplainer`), takes one episode at a time, explains it
and writes its shard itself, and hands back a small summary row. The driver only plans (which episodes, the maps
dataset's info.json), gathers the rows and writes meta/summary.json. Rows, shards and info.json are the local engine's
(`maps.explain.run_local`): the same `EpisodeExplainer` makes them.

Exactly once: an episode's shard has a fixed path and is written atomically (`maps.dataset`), so an episode
that is done again (a retried task after its actor died, a resumed job) replaces its shard instead of adding rows, and
a worker killed while writing leaves only a hidden temporary file that readers never list.

Retries: Ray Data's actor pools restart a dead actor (`max_restarts=-1`) and resubmit the tasks it held
(`max_task_retries=-1`) unless told otherwise; the engine relies on those defaults, since Ray 2.60 deprecates passing
Ray remote arguments through `map_batches`. An actor that fails while loading the model fails the job at once
(`DataContext.max_consecutive_actor_init_deaths`, 0 by default): a model that does not load is not retried N times.

On a cluster every node needs this package installed, the source dataset readable and the output folder writable at
the same path (shared storage), since the actors read and write them directly.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import os
import socket
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import Any

import numpy as np

from openpi_cam.lerobot.dataset import DatasetError, LeRobotDataset, open_dataset
from openpi_cam.maps import dataset as fmt
from openpi_cam.maps.explain import (
    DatasetJob,
    EpisodeExplainer,
    EpisodeResult,
    JobSummary,
    check_features,
    job_info,
    prepare_output,
    selected_episodes,
)
from openpi_cam.vocabulary import DEFAULT_TARGETS

log = logging.getLogger(__name__)

EPISODE = "episode"
EPISODE_RECORD = "episode_record"  # the attribute of the per-episode debug log record holding its figures
_ROW_DTYPES = {EPISODE: np.int64, "finished_at": np.float64}  # the rest of a summary row: strings


def planned(dataset: LeRobotDataset, job: DatasetJob) -> tuple[DatasetJob, fmt.MapsInfo]:
    """The job with its target resolved, and the maps dataset's info.json, made on the driver without loading the
    model.

    `job_info` needs the model's patch grid, family and cameras (`ModelSpec.facts`: parameter shapes and configs, no
    array data), so the driver, which may be a small head node without an accelerator, never holds the weights. A
    target left to the family's default is resolved here, as the loaded policy resolves it. Every actor checks that
    the info its loaded model gives is this one before it writes a shard (`_ExplainEpisodes`)."""
    facts = job.model.facts()
    family = facts.family
    job = dataclasses.replace(
        job, options=dataclasses.replace(job.options, target=job.options.target or DEFAULT_TARGETS[family])
    )
    return job, job_info(dataset, job, family=family, grid=facts.grid, camera_sources=facts.camera_sources)


class _ExplainEpisodes:
    """The actor of the pool: one loaded model, episodes in, one summary row per episode out (shards on disk)."""

    def __init__(self, job: DatasetJob, info: fmt.MapsInfo) -> None:
        self.worker = EpisodeExplainer(job)
        if self.worker.info != info:
            mine, planned = dataclasses.asdict(self.worker.info), dataclasses.asdict(info)
            diffs = sorted(k for k in planned if planned[k] != mine[k])
            raise RuntimeError(
                f"the loaded model gives another maps-dataset info than the planned one (differs in {diffs})"
            )
        self.name = f"{socket.gethostname()}:{os.getpid()}"

    def __call__(self, batch: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        rows = [self._one(int(episode)) for episode in batch[EPISODE]]
        return {k: np.asarray([r[k] for r in rows], dtype=_ROW_DTYPES.get(k, object)) for k in rows[0]}

    def _one(self, episode: int) -> dict[str, Any]:
        try:
            result = self.worker.explain(episode)
        except DatasetError as e:
            # Bad data is the driver's call (skip with --keep-going, else stop the job): hand it back, don't raise,
            # so that Ray neither retries it nor wraps the message.
            error, counts, seconds = str(e), {}, {}
        else:
            self.worker.write(result)
            error, counts, seconds = "", dict(result.counts), result.seconds
        return {
            EPISODE: episode,
            "worker": self.name,
            "error": error,
            "counts": json.dumps(counts),
            "seconds": json.dumps(seconds),
            "finished_at": time.time(),  # the worker's clock: compare only with the same worker's times
        }


def _actor_resources(ray: Any) -> dict[str, float]:
    """One GPU per actor where the cluster has GPUs (JAX then sees just that one), else one CPU."""
    if ray.cluster_resources().get("GPU", 0) > 0:
        return {"num_gpus": 1}
    return {"num_cpus": 1}


def run_ray(
    job: DatasetJob,
    *,
    workers: int,
    address: str | None = None,
    progress: Callable[[Iterable[int], int], Iterable[int]] | None = None,
) -> JobSummary:
    """Explains the job's episodes on a pool of `workers` Ray actors, each with its own loaded model.

    `address`: a running cluster to join (`ray start --head` prints it; "auto" finds a local one). None: a Ray
    instance in this process, started here with `max(workers, 2)` CPUs and shut down at the end. If this process is
    already connected to Ray, that connection is used and left open. `progress` wraps the episodes as they finish.
    """
    import ray  # optional dependency: the `ray` extra

    if workers < 1:
        raise ValueError(f"--workers must be >= 1, got {workers}")
    dataset = open_dataset(job.source)
    check_features(dataset, job)
    selected = selected_episodes(dataset, job)
    job, info = planned(dataset, job)
    done = prepare_output(job, info)
    todo = [e for e in selected if e not in done]
    summary = JobSummary(engine="ray", workers=workers, episodes_already_written=len(selected) - len(todo))

    started_here = not ray.is_initialized()
    if started_here:
        if address is None:
            ray.init(num_cpus=max(workers, 2), include_dashboard=False, log_to_driver=False)
        else:
            ray.init(address=address, log_to_driver=False)
    try:
        if todo:
            rows = _run_pool(ray, job, info, todo, workers)
            finished = (_gather(summary, row, job) for row in rows)
            for _ in finished if progress is None else progress(finished, len(todo)):
                pass
    finally:
        if started_here:
            ray.shutdown()
    fmt.write_json(job.out / fmt.SUMMARY_JSON, summary.as_json())
    return summary


def _run_pool(ray: Any, job: DatasetJob, info: fmt.MapsInfo, todo: list[int], workers: int) -> Iterator[dict]:
    # One block per episode and one episode per call: an episode is the unit of work and of retry, and a free actor
    # takes the next episode instead of one queued behind another actor's long episode.
    episodes = ray.data.from_items([{EPISODE: e} for e in todo], override_num_blocks=len(todo))
    results = episodes.map_batches(
        _ExplainEpisodes,
        fn_constructor_args=(job, info),
        batch_size=1,
        batch_format="numpy",
        compute=ray.data.ActorPoolStrategy(size=workers, max_tasks_in_flight_per_actor=1),
        **_actor_resources(ray),
    )
    return results.iter_rows()


def _gather(summary: JobSummary, row: Mapping[str, Any], job: DatasetJob) -> int:
    episode = int(row[EPISODE])
    if row["error"]:
        if not job.keep_going:
            raise DatasetError(str(row["error"]))
        summary.episodes_skipped[episode] = str(row["error"])
        log.warning("explain: skipping episode %d: %s", episode, row["error"])
        return episode
    result = EpisodeResult(episode, [], collections.Counter(json.loads(row["counts"])), json.loads(row["seconds"]))
    summary.add(result)
    # Which worker did an episode and what it cost, as the episode arrives (for debugging a cluster, and for
    # benchmarks/bench_dataset.py, which leaves each worker's compiling first episode out of its steady figures).
    record = {
        EPISODE: episode,
        "worker": str(row["worker"]),
        "counts": dict(result.counts),
        "seconds": result.seconds,
        "finished_at": float(row["finished_at"]),
    }
    log.debug("explain: episode %d by %s", episode, row["worker"], extra={EPISODE_RECORD: record})
    return episode
