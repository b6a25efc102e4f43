"""`openpi-cam explain-run SOURCE`: maps computed offline for recorded observations (a CAM run saved with raw frames,
or upstream's PolicyRecorder records), written as a normal CAM run."""

from __future__ import annotations

import pathlib
import sys
from typing import Annotated

import tyro

from openpi_cam.cam.logger import CAMLogger
from openpi_cam.cam.offline import ReplayOptions, explain_replays, open_source
from openpi_cam.cam.records import resume_mismatch
from openpi_cam.cam.run_format import RUN_JSON, load_run
from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.cli.options import BUNDLED_MODEL, EVERY_KIND, ExplainFlags
from openpi_cam.errors import InvalidRequest
from openpi_cam.policies.family import resolve_target
from openpi_cam.viz.progress import Reporter
from openpi_cam.viz.rerun_sink import write_rrd
from openpi_cam.vocabulary import SaveFrames

COMMAND = "explain-run"
DEFAULT_OUT = pathlib.Path("cam_runs")
# Exit status when a replayed inference returned other actions than the recorded ones.
ACTIONS_DIFFER = 3


def main(
    source: tyro.conf.Positional[pathlib.Path],
    model: tyro.conf.OmitArgPrefixes[ModelSpec] = BUNDLED_MODEL,
    out: pathlib.Path = DEFAULT_OUT,
    resume: pathlib.Path | None = None,
    explanation: tyro.conf.OmitArgPrefixes[ExplainFlags] = EVERY_KIND,
    save_frames: SaveFrames = "both",
    batch_size: int = 8,
    max_steps: Annotated[int | None, tyro.conf.arg(aliases=("--limit",))] = None,
    nested_keys: bool = False,
    rerun: pathlib.Path | None = None,
    progress: bool = True,
) -> int:
    """Replay recorded observations through the policy, one at a time as served, and write their maps as a CAM run
    directory (the format `serve` writes). Exit status 3 when a replayed inference returned other actions (or another
    raw output) than the recorded one.

    Args:
        source: a CAM run directory saved with raw frames (`serve --cam.save-frames raw|both`), or an upstream
            PolicyRecorder folder (step_N.npy files).
        model: the model to replay with; default for a CAM run: the model it records (any flag given replaces that
            field), else the bundled demo model.
        out: the folder in which a new run directory is created (if OUT is itself a run directory, it is resumed).
        resume: a run directory to resume: observations already explained in it are skipped, new steps appended.
        explanation: what the maps explain and which kinds each step carries (all four by default).
        save_frames: which camera frames to store next to the maps (`raw`/`both` keep the run replayable).
        batch_size: observations explained per model call, split over all local devices.
        max_steps: explain at most this many observations not yet in the run (resume later for the rest).
        nested_keys: read PolicyRecorder keys `a/b` as nested dicts (ALOHA's `images/...`) instead of flat keys;
            refused for a model whose robot reads flat keys (every config but ALOHA's).
        rerun: also write the finished run as a Rerun recording (.rrd; needs the `rerun` extra).
        progress: show progress on stderr.
    """
    if nested_keys and (source / RUN_JSON).is_file():
        print(f"openpi-cam {COMMAND}: --nested-keys reads PolicyRecorder records; {source} is a run", file=sys.stderr)
        return 2
    resume_dir = resume if resume is not None else (out if (out / RUN_JSON).is_file() else None)
    if resume_dir is not None and not (resume_dir / RUN_JSON).is_file():
        print(f"openpi-cam {COMMAND}: --resume {resume_dir} is not a CAM run directory", file=sys.stderr)
        return 2
    try:
        replays, total = open_source(source, nested_keys=nested_keys)
        stop_at_action_end = False
        if (source / RUN_JSON).is_file():  # a run records the model it was served with, and how it decoded
            recorded = load_run(source, load_arrays=False).run_info.get("config") or {}
            model = ModelSpec.from_json(recorded).overridden_by(model)
            stop_at_action_end = bool(recorded.get("stop_at_action_end", False))
        if nested_keys and not model.dataset_keys()[1]:  # its robot finds `a/b` keys flat or nested alike
            name = model.resolved().config or "a LeRobot policy"
            print(f"openpi-cam {COMMAND}: --nested-keys: {name} reads flat keys (ALOHA's nest)", file=sys.stderr)
            return 2
        policy = model.create(stop_at_action_end=stop_at_action_end)
        try:
            target = resolve_target(policy.explainer, explanation.target)
        except ValueError as e:  # a target this family cannot explain: refused before a run is created
            print(f"openpi-cam {COMMAND}: --target {e}", file=sys.stderr)
            return 2
        # The run records the target it explains: the family's default when none was named.
        options = explanation.options(target, model).extended(
            ReplayOptions, save_frames=save_frames, batch_size=batch_size, max_steps=max_steps
        )
        run_config = {"command": COMMAND, **model.resolved().to_json(), "source": str(source.resolve())}
        run_options = {**options.to_json(), "save_frames": save_frames, "batch_size": batch_size}
        if resume_dir is not None:
            run_info = load_run(resume_dir, load_arrays=False, skip_unreadable=True).run_info
            old_config, old_options = run_info.get("config") or {}, run_info.get("options") or {}
            diffs = resume_mismatch(old_config, old_options, model, options)
            if old_config.get("source") != run_config["source"]:
                diffs.insert(0, f"source: {old_config.get('source')!r} != {run_config['source']!r}")
            if diffs:
                print(
                    f"openpi-cam {COMMAND}: --resume {resume_dir}: cannot resume, settings differ: {diffs}",
                    file=sys.stderr,
                )
                return 2
            cam_logger = CAMLogger.resume(resume_dir)
        else:
            cam_logger = CAMLogger(out, run_config=run_config, checkpoint=str(model.checkpoint), options=run_options)

        try:
            summary = explain_replays(
                policy, replays, options, cam_logger, total=total, progress=Reporter(COMMAND, progress)
            )
        finally:
            cam_logger.close()
        if rerun is not None:
            write_rrd(cam_logger.run_dir, rerun)
    except (FileNotFoundError, KeyError, ValueError, InvalidRequest, OSError, ImportError) as e:
        print(f"openpi-cam {COMMAND}: {e}", file=sys.stderr)
        return 1
    print(f"openpi-cam {COMMAND}: wrote {cam_logger.run_dir}: {summary}", file=sys.stderr)
    return 0 if summary["actions_mismatched"] == 0 else ACTIONS_DIFFER
