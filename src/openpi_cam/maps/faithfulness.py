"""How faithful a maps dataset's maps are (`openpi-cam faithfulness MAPS_DATASET`).

The faithfulness report re-scores logged steps under interventions (`cam.faithfulness_run`), which needs each step's
exact model inputs. A maps dataset stores maps, not model inputs, so `max_steps` frames spread evenly over it are
served again from the source dataset (the same frames, prompt and noise rule as when they were explained), checked
against the actions the row recorded, and logged as a CAM run with the maps the dataset holds for them. The run is
then evaluated like any other, and the report is saved beside the maps.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import pathlib
import shutil
import time
from typing import Any

import numpy as np

from openpi_cam.cam.logger import CAMLogger
from openpi_cam.cam.records import step_record
from openpi_cam.cam.run_evidence import REPORT_FILE
from openpi_cam.cam.run_format import SpotCheck
from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.maps import dataset as fmt
from openpi_cam.maps.explain import DatasetJob, EpisodeExplainer
from openpi_cam.policies.family import Explanation
from openpi_cam.policies.policy import Policy
from openpi_cam.vocabulary import ExplainOptions

RUN_DIR = "meta/faithfulness_run"  # the CAM run of the evaluated frames, inside the maps dataset
REPORT_PATH = f"meta/{REPORT_FILE}"  # a maps dataset's report, beside its info.json
# The re-served chunk must be the explained one: float32 replays of the same program agree to rounding.
ACTIONS_ATOL = 1e-4


def evenly(indices: list[int], limit: int | None) -> list[int]:
    """At most `limit` of `indices`, spread evenly over them (all of them when `limit` is None)."""
    if limit is None or limit >= len(indices):
        return list(indices)
    picks = np.linspace(0, len(indices) - 1, max(limit, 1)).round().astype(int)
    return [indices[i] for i in dict.fromkeys(picks.tolist())]


def job_of(maps: fmt.MapsDataset, model: ModelSpec) -> DatasetJob:
    """The job that made a maps dataset, as far as serving its frames again needs it (no spot checks: the rows hold
    theirs)."""
    info = maps.info
    options = dataclasses.replace(ExplainOptions.from_json(info.options), target=info.target, check_patches=0)
    return DatasetJob(
        source=pathlib.Path(info.source),
        out=maps.root,
        model=model,
        options=options,
        keys=info.keys,
        extra=info.extra,
        every=info.every,
        nested_keys=info.nested_keys,
    )


def _explanation(row: dict[str, Any], maps: fmt.MapsDataset) -> Explanation:
    by_kind: dict[str, dict[str, np.ndarray]] = {}
    for kind in maps.kinds:
        for camera in maps.cameras:
            values = row.get(fmt.map_column(kind, camera))
            if values is not None:
                hp, wp = maps.grid(camera)
                flat = np.asarray(values, np.float32)
                shape = (hp, wp) if flat.size == hp * wp else (-1, hp, wp)
                by_kind.setdefault(kind, {})[camera] = flat.reshape(shape)
    return Explanation(
        target=row["target"],
        maps=by_kind,
        score=row["score"],
        cameras=json.loads(row[fmt.CAMERAS_COLUMN]),
        details=json.loads(row["details"]),
    )


def build_run(
    maps: fmt.MapsDataset, policy: Policy, model: ModelSpec, *, max_steps: int | None
) -> tuple[pathlib.Path, collections.Counter[str]]:
    """Serves `max_steps` rows of the maps dataset again and logs them with their maps as a CAM run (replacing an
    earlier one). Returns the run directory and counts (rows evaluated, actions that did not match)."""
    job = job_of(maps, model)
    worker = EpisodeExplainer(dataclasses.replace(job, episodes=tuple(maps.episodes)), policy, mesh=None)
    table = maps.table(columns=["index", "episode_index", "frame_index"]).to_pydict()
    chosen = set(evenly(table["index"], max_steps))
    by_episode: dict[int, set[int]] = collections.defaultdict(set)
    for index, episode, frame in zip(table["index"], table["episode_index"], table["frame_index"], strict=True):
        if index in chosen:
            by_episode[episode].add(frame)
    parent = maps.root / RUN_DIR
    shutil.rmtree(parent, ignore_errors=True)  # an earlier evaluation's run is replaced
    run_config = {**model.resolved().to_json(), "source": str(maps.root)}
    logger = CAMLogger(parent, run_config=run_config, checkpoint=str(model.checkpoint), options=job.options.to_json())
    counts: collections.Counter[str] = collections.Counter()
    try:
        for episode, frames in sorted(by_episode.items()):
            rows = {r["frame_index"]: r for r in maps.rows(episode)}
            for frame, response, trace in worker.served(episode, frames):
                row = rows[int(frame["frame_index"])]
                served = np.asarray(response["actions"], np.float32).reshape(-1)
                if served.shape != (len(row["actions"]),) or not np.allclose(served, row["actions"], atol=ACTIONS_ATOL):
                    counts["actions_mismatched"] += 1
                    continue
                extra = {name: np.asarray(row[fmt.extra_column(name)]) for name in job.extra.values()}
                record = step_record(
                    trace,
                    _explanation(row, maps),
                    connection=f"episode_{episode:06d}",
                    step=int(frame["frame_index"]),
                    timestamp=time.time(),
                    save_frames="both",
                    extra={**extra, "index": int(row["index"])},
                    explain_ms=float(row["explain_ms"] or 0.0),
                    check=None if row["check"] is None else SpotCheck.from_json(json.loads(row["check"])),
                )
                counts["rows"] += logger.log_step(record)
    finally:
        logger.close()
    return logger.run_dir, counts
