"""`openpi-cam explain SOURCE`: maps computed offline for recorded observations, written as a normal CAM run."""

from __future__ import annotations

import pathlib
import sys
from typing import Literal

import tyro

from openpi_cam.cam.logger import CAMLogger
from openpi_cam.cam.offline import ExplainOptions, Replay, explain_replays, open_source, resume_mismatch
from openpi_cam.cam.runfmt import RUN_JSON, load_run
from openpi_cam.cam.spot_check import DEFAULT_PATCHES
from openpi_cam.cli.options import map_options, parse_action_index
from openpi_cam.errors import InvalidRequest
from openpi_cam.policies import demo_reach  # noqa: F401  (registers the bundled demo_reach config)
from openpi_cam.policies.policy import create_policy
from openpi_cam.viz.progress import progress as progress_bar
from openpi_cam.viz.rerun_sink import write_rrd
from openpi_cam.vocabulary import MAP_KINDS, MapKind, SaveFrames, Target


def main(
    source: tyro.conf.Positional[pathlib.Path],
    checkpoint_dir: pathlib.Path,
    config: str = "pi0_fast_droid",
    out: pathlib.Path = pathlib.Path("cam_runs"),
    resume: pathlib.Path | None = None,
    target: Target = "action-token",
    action_index: str = "0",
    maps: tuple[MapKind, ...] = MAP_KINDS,
    baseline: Literal["mean", "blur"] = "mean",
    occlusion_region: int = 1,
    occlusion_masks: int = 0,
    ig_space: Literal["tokens", "pixels"] = "tokens",
    check_patches: int = DEFAULT_PATCHES,
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
) -> int:
    """Compute maps offline for recorded observations and write a CAM run directory (same format as serving).
    Exit status 3 when a re-run inference returned other actions than the recorded ones.

    Args:
        source: an upstream PolicyRecorder folder (step_N.npy files) or a CAM run directory with raw frames.
        checkpoint_dir: checkpoint folder with `params/` and `assets/<asset_id>/norm_stats.json`.
        config: named policy config (e.g. pi0_fast_droid, pi0_fast_libero, pi0_fast_aloha).
        out: folder in which a new run directory is created; if OUT is itself a run directory, it is resumed.
        resume: a run directory to resume: observations already explained in it are skipped, new steps appended.
        target: which score the maps explain (generations without action tokens: `generated-tokens`).
        action_index: pi0-FAST: which action token (`action-token`); pi0 / pi0.5: `H,D`, dimension D at horizon
            step H (`action`).
        maps: which kinds of map to compute (README, "Which map to trust"); all four by default.
        baseline: the frame IG starts from and occlusion paints with: the frame's mean colour (measured more
            faithful on the demo model) or a Gaussian-blurred copy (sigma 8 px).
        occlusion_region: side of an occlusion region in patches (1: every patch alone, C x (N + 1) re-runs per
            step; a 224 px camera has 256 patches).
        occlusion_masks: 0: every region once; M > 0: M random region masks per camera, scored with the
            Interventional Significance Score (for large grids).
        ig_space: where the IG path runs: between the SigLIP tokens of the baseline frame and the frame, or between
            the frames' pixels, through SigLIP (README, "Map kinds").
        check_patches: each step's spot check paints each map's top patch and this many random patches, a few
            re-runs per camera, and stores the score drops with the maps (README, "Looking at the maps"); 0: none.
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
    """
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
        index, dim_index = parse_action_index(action_index)
        run_options = {
            "target": target,
            "action_index": index,
            "action_dim_index": dim_index,
            "maps": list(maps),
            "baseline": baseline,
            "occlusion_region": occlusion_region,
            "occlusion_masks": occlusion_masks,
            "ig_space": ig_space,
            "check_patches": check_patches,
            "save_frames": save_frames,
        }
        replays, total = open_source(source, nested_keys=nested_keys)
        options = ExplainOptions(
            target,
            index,
            dim_index,
            tuple(maps),
            save_frames,
            batch_size,
            limit,
            map_options(baseline, occlusion_region, occlusion_masks, ig_space),
            check_patches,
        )
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


__all__ = ["Replay", "main"]
