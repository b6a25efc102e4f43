"""`openpi-cam explain`: Grad-CAM computed offline for recorded observations, written as a normal CAM run.

Sources:
  * upstream `PolicyRecorder` output: a folder of `step_N.npy` files, each a pickled dict with flattened
    `inputs/...` (the observation as the client sent it) and `outputs/...` (the response) keys;
  * one of our CAM run directories saved with raw frames (`--cam-save-frames raw|both`): each step's client images
    are replayed at their observation keys, with the prompt and whatever the client sent under `cam_extra/` (send
    the non-image observation, e.g. `cam_extra/observation/joint_position`, to make a run replayable).

Inference stays per observation, exactly as served (`Policy.infer_traced`); Grad-CAM is then computed for a whole
chunk of `batch_size` inferences in one model call, sharded over all local devices (`cam.batch_engine`). Every step
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
import sys
import time
from collections.abc import Iterable, Iterator, Mapping
from typing import Annotated, Any, Literal

import numpy as np
import tyro

from openpi_cam.cam.engine import CamSkipped
from openpi_cam.cam.records import EXTRA_PREFIX, SaveFrames, jsonable, split_extra
from openpi_cam.errors import InvalidRequest
from openpi_cam.nested import unflatten_dict

log = logging.getLogger(__name__)

_RECORD_RE = re.compile(r"^step_(\d+)\.npy$")
SOURCE_KEY = "source"  # meta["extra"] key holding the id of the record a step explains
# run.json fields that must match for a resumed run to stay one consistent explanation of one source.
_RESUME_CONFIG_KEYS = ("config", "checkpoint_dir", "dtype", "source")
_RESUME_OPTION_KEYS = ("target", "action_index")


@dataclasses.dataclass(frozen=True)
class Replay:
    """One observation to explain, with a stable id and where it sits in its episode."""

    source: str  # unique within the source (a record file name, a step file path); what resuming skips
    connection: str
    step: int
    obs: dict[str, Any]  # what the policy receives
    extra: dict[str, Any]  # JSON-able values stored in the step's meta["extra"]
    recorded_actions: np.ndarray | None = None  # actions the original inference returned, if known
    timestamp: float | None = None  # the original request time, if known


@dataclasses.dataclass(frozen=True)
class ExplainOptions:
    target: Literal["action-token", "all-action-tokens", "chunk"] = "action-token"
    action_index: int = 0
    save_frames: SaveFrames = "both"
    batch_size: int = 8  # observations per Grad-CAM call (padded to a multiple of the device count)
    limit: int | None = None  # explain at most this many new observations
    progress: bool = False

    def __post_init__(self):
        if self.batch_size < 1 or self.action_index < 0 or (self.limit is not None and self.limit < 0):
            raise ValueError("batch_size >= 1, action_index >= 0 and limit >= 0 are required")


def split_extra_json(obs: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """(what the policy receives, the `cam_extra/` values as JSON), as the side channel splits a live request."""
    obs, extra = split_extra(dict(obs))
    return obs, {k: jsonable(v) for k, v in extra.items()}


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
        record = np.load(path, allow_pickle=True).item()
        obs, extra = split_extra_json(record_observation(record, nested))
        actions = record.get("outputs/actions")
        yield Replay(path.name, "records", n, obs, extra, None if actions is None else np.asarray(actions))


def iter_run_steps(run_dir: pathlib.Path) -> Iterator[Replay]:
    from openpi_cam.cam.reader import load_run

    run = load_run(run_dir, load_arrays=False)
    for step in run.steps:
        meta = step.meta
        frames = step.frames
        obs: dict[str, Any] = {
            info["obs_key"]: frames[c]
            for c, info in meta.get("cameras", {}).items()
            if info.get("obs_key") and c in frames
        }
        if not obs:
            raise ValueError(f"{step.file}: no raw client frames; record the run with --cam-save-frames raw or both")
        # The step's extras were the client's cam_extra/ values: the policy gets them back at their keys, and they
        # stay extras of the new step so that the new run is replayable too. An earlier explain's source id is not
        # an observation.
        extra = {k: v for k, v in (meta.get("extra") or {}).items() if k != SOURCE_KEY}
        obs.update({k: np.asarray(v) for k, v in extra.items()})
        if meta.get("prompt"):
            obs["prompt"] = meta["prompt"]
        source = step.file.relative_to(run.run_dir).as_posix()
        connection = str(meta.get("connection", "replay"))
        yield Replay(source, connection, int(meta.get("step", step.seq)), obs, extra, timestamp=meta.get("timestamp"))


def explained_sources(run_dir: pathlib.Path) -> set[str]:
    """Source ids already explained in a run (complete step files only)."""
    from openpi_cam.cam.reader import load_run

    run = load_run(run_dir, load_arrays=False)
    return {str(s.meta["extra"][SOURCE_KEY]) for s in run.steps if SOURCE_KEY in (s.meta.get("extra") or {})}


def _actions_match(ours: Any, recorded: np.ndarray) -> bool:
    ours = np.asarray(ours)
    return ours.shape == recorded.shape and bool(np.allclose(ours, recorded, rtol=1e-3, atol=1e-3))


def explain_replays(
    policy: Any,
    replays: Iterable[Replay],
    options: ExplainOptions,
    cam_logger: Any,
    *,
    mesh: Any = "auto",
    total: int = 0,
) -> dict[str, Any]:
    """Explains every replay whose source is not yet in `cam_logger`'s run and logs it there (the caller closes the
    logger). `mesh`: "auto" shards over all local devices, None keeps one device; `total`: the number of replays,
    for progress only. Returns a summary of counts; observations the target cannot explain (e.g. no action tokens)
    are counted, not logged, and are tried again on resume."""
    from openpi_cam.cam.batch_engine import data_mesh, explain_batch, replicate_model, stack_observations
    from openpi_cam.cam.records import step_record
    from openpi_cam.viz.progress import progress

    mesh = data_mesh() if mesh == "auto" else mesh
    model = replicate_model(policy.model, mesh)
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

    todo: Iterator[Replay] = pending() if options.limit is None else itertools.islice(pending(), options.limit)
    left = max(0, total - len(done)) if options.limit is None else min(options.limit, max(0, total - len(done)))
    todo = progress(todo, left, "explain", options.progress)
    for chunk in iter(lambda: list(itertools.islice(todo, options.batch_size)), []):
        traces, stamps = [], []
        for r in chunk:
            response, trace = policy.infer_traced(r.obs)  # one request at a time, as served
            stamps.append(time.time() if r.timestamp is None else float(r.timestamp))
            traces.append(trace)
            counts["observations"] += 1
            if r.recorded_actions is not None:
                counts["actions_compared"] += 1
                counts["actions_mismatched"] += not _actions_match(response["actions"], r.recorded_actions)
        t0 = time.perf_counter()
        results = explain_batch(
            model,
            policy.tokenizer,
            stack_observations([t.observation for t in traces]),
            np.stack([np.asarray(t.generated_tokens, np.int32) for t in traces]),
            target=options.target,
            action_index=options.action_index,
            mesh=mesh,
            pad_to=options.batch_size,  # a short last batch reuses the compiled program
        )
        per_row_ms = (time.perf_counter() - t0) * 1000.0 / len(chunk)
        for r, trace, stamp, exp in zip(chunk, traces, stamps, results, strict=True):
            if isinstance(exp, CamSkipped):
                counts[f"skipped_{exp.kind}"] += 1
                if counts[f"skipped_{exp.kind}"] == 1:
                    log.warning("explain: %s: %s (further ones are only counted)", r.source, exp)
                continue
            record = step_record(
                trace,
                exp,
                connection=r.connection,
                step=r.step,
                timestamp=stamp,
                save_frames=options.save_frames,
                extra={**r.extra, SOURCE_KEY: r.source},
                gradcam_ms=per_row_ms,
            )
            counts["completed" if cam_logger.log_step(record) else "not_logged"] += 1
    summary = {k: counts[k] for k in ("observations", "completed", "actions_compared", "actions_mismatched")}
    summary |= {k: v for k, v in counts.items() if k not in summary}
    summary["devices"] = 1 if mesh is None else int(mesh.devices.size)
    cam_logger.set_external_counters(summary)
    return summary


def _resume_mismatch(run_info: Mapping[str, Any], run_config: dict[str, Any], options: dict[str, Any]) -> list[str]:
    """Settings of this invocation that differ from the run being resumed."""
    old_config, old_options = run_info.get("config") or {}, run_info.get("options") or {}
    diffs = [
        f"{k}: {old_config.get(k)!r} != {run_config[k]!r}"
        for k in _RESUME_CONFIG_KEYS
        if old_config.get(k) != run_config[k]
    ]
    return diffs + [
        f"{k}: {old_options.get(k)!r} != {options[k]!r}"
        for k in _RESUME_OPTION_KEYS
        if old_options.get(k) != options[k]
    ]


def explain_cmd(
    source: Annotated[pathlib.Path, tyro.conf.arg(metavar="SOURCE")],
    /,
    checkpoint_dir: pathlib.Path,
    config: str = "pi0_fast_droid",
    out: pathlib.Path = pathlib.Path("cam_runs"),
    resume: pathlib.Path | None = None,
    target: Literal["action-token", "all-action-tokens", "chunk"] = "action-token",
    action_index: int = 0,
    save_frames: SaveFrames = "both",
    batch_size: int = 8,
    limit: int | None = None,
    nested_keys: bool = False,
    paligemma_tokenizer: pathlib.Path | None = None,
    fast_tokenizer: pathlib.Path | None = None,
    dtype: Literal["bfloat16", "float32"] = "bfloat16",
    default_prompt: str | None = None,
    rerun: pathlib.Path | None = None,
    progress: bool = True,
) -> int:
    """Compute Grad-CAM offline for recorded observations and write a CAM run directory (same format as serving).

    Args:
        source: an upstream PolicyRecorder folder (step_N.npy files) or a CAM run directory with raw frames.
        checkpoint_dir: checkpoint folder with `params/` and `assets/<asset_id>/norm_stats.json`.
        config: named policy config (e.g. pi0_fast_droid, pi0_fast_libero, pi0_fast_aloha).
        out: folder in which a new run directory is created; if OUT is itself a run directory, it is resumed.
        resume: a run directory to resume: observations already explained in it are skipped, new steps appended.
        target: which score Grad-CAM explains.
        action_index: which action token for `action-token`.
        save_frames: which camera frames to store next to the maps (`raw`/`both` keep the run re-explainable).
        batch_size: observations explained per Grad-CAM call, split over all local devices.
        limit: explain at most this many observations not yet in the run (resume later for the rest).
        nested_keys: read PolicyRecorder keys `a/b` as nested dicts (ALOHA's `images/...`) instead of flat keys.
        paligemma_tokenizer: PaliGemma SentencePiece model; default: the policy factory's standard location.
        fast_tokenizer: FAST action tokenizer folder; default: the policy factory's standard location.
        dtype: parameter dtype; upstream serves bfloat16.
        default_prompt: prompt used when a record has none.
        rerun: also write the finished run as a Rerun recording (.rrd; needs the `rerun` extra).
        progress: show progress on stderr.
    """
    from openpi_cam.cam.logger import CAMLogger
    from openpi_cam.cam.reader import RUN_JSON
    from openpi_cam.policies.policy import create_policy

    source = pathlib.Path(source)
    if (source / RUN_JSON).is_file():
        replays: Iterator[Replay] = iter_run_steps(source)
        total = sum(1 for _ in (source / "steps").glob("*.npz"))
    elif source.is_dir():
        replays = iter_policy_records(source, nested_keys)
        total = sum(1 for p in source.iterdir() if _RECORD_RE.match(p.name))
    else:
        print(f"openpi-cam explain: {source} is neither a CAM run nor a policy-record folder", file=sys.stderr)
        return 2
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
    }
    cam_options = {"target": target, "action_index": action_index, "save_frames": save_frames}
    try:
        options = ExplainOptions(target, action_index, save_frames, batch_size, limit, progress)
        if resume_dir is not None:
            from openpi_cam.cam.reader import load_run

            if diffs := _resume_mismatch(load_run(resume_dir, load_arrays=False).run_info, run_config, cam_options):
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
        if resume_dir is not None:
            cam_logger = CAMLogger.resume(resume_dir)
        else:
            cam_logger = CAMLogger(out, run_config=run_config, checkpoint=str(checkpoint_dir), options=cam_options)
        try:
            summary = explain_replays(policy, replays, options, cam_logger, total=total)
        finally:
            cam_logger.close()
        if rerun is not None:
            from openpi_cam.viz.rerun_sink import write_rrd

            write_rrd(cam_logger.run_dir, rerun)
    except (FileNotFoundError, ValueError, InvalidRequest, OSError, ImportError) as e:
        print(f"openpi-cam explain: {e}", file=sys.stderr)
        return 1
    print(f"openpi-cam explain: wrote {cam_logger.run_dir}: {summary}", file=sys.stderr)
    return 0 if summary["actions_mismatched"] == 0 else 3
