"""Replay: maps computed for recorded observations, written as a normal CAM run (`openpi-cam explain-run`).

Sources:
  * upstream `PolicyRecorder` output: a folder of `step_N.npy` files, each a pickled dict with flattened
    `inputs/...` (the observation as the client sent it) and `outputs/...` (the response) keys;
  * one of our CAM run directories saved with raw frames (`--cam.save-frames raw|both`): each step's client images
    are replayed at their observation keys with the client's other numeric values (`client/`), its prompt and its
    `cam_extra/` values, and a flow-matching policy's noise, so the replay serves the very output the step recorded.

Inference stays per observation, exactly as served (`Policy.infer_traced`); the maps are then computed for a whole
chunk of `batch_size` inferences in one model call, sharded over all local devices (`cam.batching`). Every step
records its source id in `meta["extra"]["source"]`, so a run can be resumed: sources already in it are skipped and
new steps are appended with the following seqs.
"""

from __future__ import annotations

import collections
import dataclasses
import itertools
import logging
import pathlib
import re
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import Any, Literal

import numpy as np
from jax.sharding import Mesh

from openpi_cam.cam.batching import data_mesh, explain_batch
from openpi_cam.cam.logger import CAMLogger
from openpi_cam.cam.records import split_extra, step_record
from openpi_cam.cam.run_format import RUN_JSON, load_run
from openpi_cam.errors import BadFile, reading
from openpi_cam.nested import unflatten_dict
from openpi_cam.policies.family import ExplainSkipped
from openpi_cam.policies.policy import Policy
from openpi_cam.vocabulary import EXTRA_PREFIX, ExplainOptions, SaveFrames

log = logging.getLogger(__name__)

_RECORD_RE = re.compile(r"^step_(\d+)\.npy$")
SOURCE_KEY = "source"  # meta["extra"] key holding the id of the record a step explains

# Wraps the replays with a progress display: (replays, how many) -> the same replays.
Progress = Callable[[Iterator["Replay"], int], Iterator["Replay"]]


@dataclasses.dataclass(frozen=True)
class Replay:
    """One observation to explain, with a stable id and where it sits in its episode."""

    source: str  # unique within the source (a record file name, a step file path); what resuming skips
    connection: str
    step: int
    obs: dict[str, Any]  # what the policy receives
    extra: dict[str, Any]  # the `cam_extra/` values stored with the step (numeric arrays as arrays)
    recorded_actions: np.ndarray | None = None  # actions the original inference returned, if known
    timestamp: float | None = None  # the original request time, if known
    # the model's raw output of the original inference (a CAM step's `input/output`), if known
    recorded_output: np.ndarray | None = None
    noise: np.ndarray | None = None  # a flow-matching policy's noise of the original inference, if known


@dataclasses.dataclass(frozen=True)
class ReplayOptions(ExplainOptions):
    """The explanation options of a replay, and how it runs."""

    save_frames: SaveFrames = "both"
    batch_size: int = 8  # observations per explainer call (padded to a multiple of the device count)
    max_steps: int | None = None  # explain at most this many new observations

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.batch_size < 1 or (self.max_steps is not None and self.max_steps < 0):
            raise ValueError("batch_size >= 1 and max_steps >= 0 are required")


def record_observation(record: Mapping[str, Any], nested: bool) -> dict[str, Any]:
    """The client observation of a PolicyRecorder record.

    Flattening loses whether `a/b` was one key (DROID/LIBERO clients send `observation/...` keys) or a nested dict
    (ALOHA's `images/cam_high`); `nested` picks the reading. `cam_extra/` keys always stay flat.
    """
    flat = {k[len("inputs/") :]: v for k, v in record.items() if k.startswith("inputs/")}
    if not nested:
        return flat
    extra = {k: v for k, v in flat.items() if k.startswith(EXTRA_PREFIX)}
    return unflatten_dict({k: v for k, v in flat.items() if k not in extra}) | extra


def iter_policy_records(folder: pathlib.Path, nested: bool) -> Iterator[Replay]:
    files = sorted((int(m.group(1)), p) for p in folder.iterdir() if (m := _RECORD_RE.match(p.name)) and p.is_file())
    if not files:
        raise FileNotFoundError(f"no step_N.npy policy records in {folder}")
    for n, path in files:
        # Upstream stores each record as a pickled object array: only open records from a source you trust.
        with reading(path, "policy record"):
            record = np.load(path, allow_pickle=True).item()
        if not isinstance(record, dict):
            raise BadFile(f"{path}: holds a {type(record).__name__}, not a policy record's dict")
        obs, extra = split_extra(record_observation(record, nested))
        actions = record.get("outputs/actions")
        yield Replay(path.name, "records", n, obs, extra, None if actions is None else np.asarray(actions))


def iter_run_steps(run_dir: pathlib.Path) -> Iterator[Replay]:
    run = load_run(run_dir, load_arrays=False)
    for step in run.steps:
        meta = step.meta
        frames = step.frames
        obs: dict[str, Any] = {
            info.obs_key: frames[c] for c, info in meta.cameras.items() if info.obs_key and c in frames
        }
        if not obs:
            raise ValueError(f"{step.file}: no raw client frames; record the run with --cam.save-frames raw or both")
        # The step's extras were the client's cam_extra/ values: the policy gets them back at their keys, and they
        # stay extras of the new step so that the new run is replayable too. An earlier explain's source id is not
        # an observation.
        extra = {k: v for k, v in step.extra.items() if k != SOURCE_KEY}
        obs.update(step.client_inputs)
        obs.update({k: np.asarray(v) for k, v in extra.items() if k not in obs})
        if meta.prompt:
            obs["prompt"] = meta.prompt
        source = step.file.relative_to(run.run_dir).as_posix()
        connection = "replay" if meta.connection is None else meta.connection
        index = step.seq if meta.step is None else meta.step
        inputs = step.inputs
        yield Replay(
            source,
            connection,
            index,
            obs,
            extra,
            timestamp=meta.timestamp,
            recorded_output=inputs.get("output"),
            noise=inputs.get("noise"),
        )


def explained_sources(run_dir: pathlib.Path) -> set[str]:
    """Source ids already explained in a run (complete step files only)."""
    run = load_run(run_dir, load_arrays=False, skip_unreadable=True)
    return {str(s.meta.extra[SOURCE_KEY]) for s in run.steps if SOURCE_KEY in s.meta.extra}


def _actions_match(ours: Any, recorded: np.ndarray) -> bool:
    ours = np.asarray(ours)
    return ours.shape == recorded.shape and bool(np.allclose(ours, recorded, rtol=1e-3, atol=1e-3))


def explain_replays(
    policy: Policy,
    replays: Iterable[Replay],
    options: ReplayOptions,
    cam_logger: CAMLogger,
    *,
    mesh: Mesh | Literal["auto"] | None = "auto",
    total: int = 0,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Explains every replay whose source is not yet in `cam_logger`'s run and logs it there (the caller closes the
    logger). `mesh`: "auto" shards over all local devices, None keeps one device; `total`: the number of replays,
    for `progress` only. Returns a summary of counts; observations that cannot be explained are counted, not logged,
    and are tried again on resume."""
    mesh = data_mesh() if mesh == "auto" else mesh
    explainer = policy.explainer.on_mesh(mesh)
    done = explained_sources(cam_logger.run_dir)
    counts: collections.Counter[str] = collections.Counter()

    def pending() -> Iterator[Replay]:
        seen: set[str] = set()
        for r in replays:
            if r.source in done or r.source in seen:
                counts["already_explained" if r.source in done else "duplicate_source"] += 1
                continue
            seen.add(r.source)
            yield r

    todo: Iterator[Replay] = pending() if options.max_steps is None else itertools.islice(pending(), options.max_steps)
    left = max(0, total - len(done)) if options.max_steps is None else min(options.max_steps, max(0, total - len(done)))
    if progress is not None:
        todo = progress(todo, left)
    for chunk in iter(lambda: list(itertools.islice(todo, options.batch_size)), []):
        traces, stamps = [], []
        for r in chunk:
            response, trace = policy.infer_traced(r.obs, noise=r.noise)  # one request at a time, as served
            stamps.append(time.time() if r.timestamp is None else float(r.timestamp))
            traces.append(trace)
            counts["observations"] += 1
            # What the original call returned: its actions (policy records) or the model's raw output (CAM steps).
            for ours, recorded in ((response["actions"], r.recorded_actions), (trace.output, r.recorded_output)):
                if recorded is not None:
                    counts["actions_compared"] += 1
                    counts["actions_mismatched"] += not _actions_match(ours, recorded)
        # a short last batch is padded to batch_size so that it reuses the compiled program
        done_rows = explain_batch(
            explainer, traces, options, [r.step for r in chunk], mesh=mesh, pad_to=options.batch_size, policy=policy
        )
        for r, trace, stamp, explained in zip(chunk, traces, stamps, done_rows, strict=True):
            if isinstance(explained.result, ExplainSkipped):
                counts[f"skipped_{explained.result.reason}"] += 1
                if counts[f"skipped_{explained.result.reason}"] == 1:
                    log.warning("explain: %s: %s (further ones are only counted)", r.source, explained.result)
                continue
            counts["explained_malformed"] += trace.malformed_reason is not None
            if explained.check is not None and explained.check.skipped is not None:
                counts[f"check_skipped_{explained.check.skipped}"] += 1
            record = step_record(
                trace,
                explained.result,
                connection=r.connection,
                step=r.step,
                timestamp=stamp,
                save_frames=options.save_frames,
                extra={**r.extra, SOURCE_KEY: r.source},
                explain_ms=explained.explain_ms,
                check=explained.check,
                reliance=explained.reliance,
            )
            counts["completed" if cam_logger.log_step(record) else "not_logged"] += 1
    summary = {k: counts[k] for k in ("observations", "completed", "actions_compared", "actions_mismatched")}
    summary |= {k: v for k, v in counts.items() if k not in summary}
    summary["devices"] = 1 if mesh is None else int(mesh.devices.size)
    cam_logger.set_external_counters(summary)
    return summary


def open_source(source: pathlib.Path, *, nested_keys: bool = False) -> tuple[Iterator[Replay], int]:
    """The replays of a CAM run directory (with raw frames) or an upstream PolicyRecorder folder, and their number."""
    if (source / RUN_JSON).is_file():
        return iter_run_steps(source), sum(1 for _ in (source / "steps").glob("*.npz"))
    if source.is_dir():
        return iter_policy_records(source, nested_keys), sum(1 for p in source.iterdir() if _RECORD_RE.match(p.name))
    raise FileNotFoundError(f"{source} is neither a CAM run nor a policy-record folder")
