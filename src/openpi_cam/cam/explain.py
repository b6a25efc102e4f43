"""`openpi-cam explain`: Grad-CAM computed offline for recorded observations, written as a normal CAM run.

Sources:
  * upstream `PolicyRecorder` output: a folder of `step_N.npy` files, each a pickled dict with flattened
    `inputs/...` (the observation as the client sent it) and `outputs/...` (the response) keys;
  * one of our CAM run directories saved with raw frames (`--cam-save-frames raw|both`): each step's client images
    are replayed at their observation keys, with the prompt and whatever the client sent under `cam_extra/` (send
    the non-image observation, e.g. `cam_extra/observation/joint_position`, to make a run replayable).
Each observation runs through the same `Policy.infer_traced` + CAM wrapper path as the server, so the output is
indistinguishable from a live run; replayed actions are compared with recorded ones where those exist.
"""

from __future__ import annotations

import dataclasses
import pathlib
import re
import sys
import time
from collections.abc import Iterator, Mapping
from typing import Annotated, Any, Literal

import numpy as np
import tyro

from openpi_cam.errors import InvalidRequest

_RECORD_RE = re.compile(r"^step_(\d+)\.npy$")


@dataclasses.dataclass(frozen=True)
class Replay:
    """One observation to explain, and the actions the original inference returned (None if unknown)."""

    connection: str
    obs: dict[str, Any]
    recorded_actions: np.ndarray | None


def unflatten(flat: Mapping[str, Any], sep: str = "/") -> dict[str, Any]:
    """Nested dicts from `sep`-joined keys (what flax's flatten_dict produced)."""
    out: dict[str, Any] = {}
    for key, value in flat.items():
        node = out
        *parents, leaf = key.split(sep)
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = value
    return out


def record_observation(record: Mapping[str, Any], nested: bool) -> dict[str, Any]:
    """The client observation of a PolicyRecorder record.

    Flattening loses whether `a/b` was one key (DROID/LIBERO clients send `observation/...` keys) or a nested dict
    (ALOHA's `images/cam_high`); `nested` picks the reading.
    """
    flat = {k[len("inputs/") :]: v for k, v in record.items() if k.startswith("inputs/")}
    return unflatten(flat) if nested else flat


def iter_policy_records(folder: pathlib.Path, nested: bool) -> Iterator[Replay]:
    files = sorted((int(m.group(1)), p) for p in folder.iterdir() if (m := _RECORD_RE.match(p.name)) and p.is_file())
    if not files:
        raise FileNotFoundError(f"no step_N.npy policy records in {folder}")
    for _, path in files:
        # Upstream stores each record as a pickled object array: only open records from a source you trust.
        record = np.load(path, allow_pickle=True).item()
        actions = record.get("outputs/actions")
        yield Replay("records", record_observation(record, nested), None if actions is None else np.asarray(actions))


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
        obs.update({k: np.asarray(v) for k, v in (meta.get("extra") or {}).items()})
        if meta.get("prompt"):
            obs["prompt"] = meta["prompt"]
        yield Replay(str(meta.get("connection", "replay")), obs, None)


def explain_replays(
    policy: Any, replays: Iterator[Replay], options: Any, *, run_config: dict[str, Any], checkpoint: str
) -> tuple[pathlib.Path, dict[str, Any]]:
    """Runs every replay through the CAM wrapper, one at a time so that none is dropped; returns the run directory
    and a summary (steps, wrapper counters, action mismatches against recorded actions)."""
    from openpi_cam.cam.wrapper import wrap_policy_with_cam
    from openpi_cam.serving import RequestContext

    cam = wrap_policy_with_cam(policy, options, run_config=run_config, checkpoint=checkpoint)
    if cam.run_dir is None:
        raise OSError(f"cannot create a CAM run directory under {options.cam_dir}")
    counts: dict[str, int] = {}
    mismatches, compared, total = 0, 0, 0
    try:
        for replay in replays:
            index = counts.get(replay.connection, 0)
            counts[replay.connection] = index + 1
            while cam.stats()["gradcam"]["queued"]:  # keep the bounded queue from dropping a job
                time.sleep(0.01)
            response = cam.infer(replay.obs, RequestContext(replay.connection, index))
            total += 1
            if replay.recorded_actions is not None:
                compared += 1
                ours = np.asarray(response["actions"])
                if ours.shape != replay.recorded_actions.shape or not np.allclose(
                    ours, replay.recorded_actions, rtol=1e-3, atol=1e-3
                ):
                    mismatches += 1
    finally:
        cam.close(timeout=None)
    gradcam = cam.stats()["gradcam"]
    summary = {"observations": total, "actions_compared": compared, "actions_mismatched": mismatches, **gradcam}
    return cam.run_dir, summary


def explain_cmd(
    source: Annotated[pathlib.Path, tyro.conf.arg(metavar="SOURCE")],
    /,
    checkpoint_dir: pathlib.Path,
    config: str = "pi0_fast_droid",
    out: pathlib.Path = pathlib.Path("cam_runs"),
    target: Literal["action-token", "all-action-tokens", "chunk"] = "action-token",
    action_index: int = 0,
    save_frames: Literal["none", "raw", "model", "both"] = "both",
    nested_keys: bool = False,
    paligemma_tokenizer: pathlib.Path | None = None,
    fast_tokenizer: pathlib.Path | None = None,
    dtype: Literal["bfloat16", "float32"] = "bfloat16",
    default_prompt: str | None = None,
) -> int:
    """Compute Grad-CAM offline for recorded observations and write a CAM run directory (same format as serving).

    Args:
        source: an upstream PolicyRecorder folder (step_N.npy files) or a CAM run directory with raw frames.
        checkpoint_dir: checkpoint folder with `params/` and `assets/<asset_id>/norm_stats.json`.
        config: named policy config (e.g. pi0_fast_droid, pi0_fast_libero, pi0_fast_aloha).
        out: folder in which the new run directory is created.
        target: which score Grad-CAM explains.
        action_index: which action token for `action-token`.
        save_frames: which camera frames to store next to the maps.
        nested_keys: read PolicyRecorder keys `a/b` as nested dicts (ALOHA's `images/...`) instead of flat keys.
        paligemma_tokenizer: PaliGemma SentencePiece model; default: the policy factory's standard location.
        fast_tokenizer: FAST action tokenizer folder; default: the policy factory's standard location.
        dtype: parameter dtype; upstream serves bfloat16.
        default_prompt: prompt used when a record has none.
    """
    from openpi_cam.cam.wrapper import CAMOptions
    from openpi_cam.policies.policy import create_policy

    source = pathlib.Path(source)
    if (source / "run.json").is_file():
        replays = iter_run_steps(source)
    elif source.is_dir():
        replays = iter_policy_records(source, nested_keys)
    else:
        print(f"openpi-cam explain: {source} is neither a CAM run nor a policy-record folder", file=sys.stderr)
        return 2
    try:
        policy = create_policy(
            config,
            checkpoint_dir,
            paligemma_tokenizer=paligemma_tokenizer,
            fast_tokenizer=fast_tokenizer,
            dtype=dtype,
            default_prompt=default_prompt,
        )
        options = CAMOptions(
            every_k=1, cam_dir=out, save_frames=save_frames, target=target, action_index=action_index, queue_size=2
        )
        run_config = {"config": config, "checkpoint_dir": str(checkpoint_dir), "dtype": dtype, "source": str(source)}
        run_dir, summary = explain_replays(
            policy, replays, options, run_config=run_config, checkpoint=str(checkpoint_dir)
        )
    except (FileNotFoundError, ValueError, InvalidRequest, OSError) as e:
        print(f"openpi-cam explain: {e}", file=sys.stderr)
        return 1
    print(f"openpi-cam explain: wrote {run_dir}: {summary}", file=sys.stderr)
    return 0 if summary["actions_mismatched"] == 0 else 3
