"""`openpi-cam faithfulness RUN_DIR`: how faithful each map kind of a run is, re-scored by the model itself."""

from __future__ import annotations

import dataclasses
import pathlib
import sys
from collections.abc import Mapping
from typing import Annotated, Any, Literal

import tyro

from openpi_cam.cam.faithfulness_run import FaithfulnessOptions, evaluate_run, format_report
from openpi_cam.cam.run_evidence import REPORT_FILE
from openpi_cam.cam.run_format import dumps, load_run
from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.cli.options import BUNDLED_MODEL, DeletionBaseline
from openpi_cam.errors import InvalidRequest
from openpi_cam.maps.dataset import is_maps_dataset, open_maps_dataset
from openpi_cam.maps.faithfulness import REPORT_PATH as DATASET_REPORT_PATH
from openpi_cam.maps.faithfulness import build_run
from openpi_cam.viz.progress import Reporter

# Frames of a maps dataset evaluated unless --max-steps says otherwise: each is served again and re-scored.
DEFAULT_DATASET_STEPS = 64


def run_model(recorded: Mapping[str, Any], flags: ModelSpec) -> ModelSpec:
    """The model that served (or explained) a run or maps dataset, as it records it, with each field the command line
    gives replacing the recorded one."""
    if not recorded.get("config") and flags.config is None:
        raise ValueError("the run does not record its policy config; pass --config")
    return ModelSpec.from_json(recorded).overridden_by(flags)


def main(
    run_dir: tyro.conf.Positional[pathlib.Path],
    model: tyro.conf.OmitArgPrefixes[ModelSpec] = BUNDLED_MODEL,
    randomize: Literal["none", "llm", "all"] = "llm",
    baseline: DeletionBaseline = "run",
    max_steps: int | None = None,
    random_orders: int = 8,
    batch_size: int = 8,
    out: Annotated[pathlib.Path | None, tyro.conf.arg(aliases=("--json-out",))] = None,
    progress: bool = True,
) -> int:
    """Re-score every logged step of RUN_DIR under interventions and report, per map kind and camera, how faithful
    the maps are: deletion (k = 1, 2, 4, AUC) normalised by the single-patch occlusion optimum next to a random
    order, top-1 agreement with occlusion, model randomisation against its null, and the pointing game where the
    client sent ground-truth boxes. Needs steps logged with model frames (`serve --cam.save-frames model|both`).

    Args:
        run_dir: a CAM run directory, or a maps dataset (`max_steps` of its frames, default 64, served again).
        model: the model that made the run; default: the one the run records (each flag given replaces its field;
            no `--default-prompt`: every step has its prompt).
        randomize: which weights the randomisation test re-initialises (`llm`: the language model and action
            expert, SigLIP kept; `all`; `none` skips the test).
        baseline: what deletion paints with: the baseline the run's ig / occlusion maps used (`run`), or one named.
        max_steps: evaluate at most this many steps, evenly spread over the run (a maps dataset: default 64).
        random_orders: random patch orders averaged for the random reference.
        batch_size: steps per call of the randomised model (sharded over all local devices, like `explain`).
        out: where to write the full report (every figure with its 95% bootstrap interval, and each step's
            own figures) as JSON; default RUN_DIR/faithfulness.json, where `render` finds it and shows each map's
            figures beside it.
        progress: show progress on stderr.
    """
    if model.default_prompt is not None:
        print("openpi-cam faithfulness: --default-prompt: every step re-scored has its prompt (a run's steps their "
              "model inputs, a maps dataset's frames their tasks)", file=sys.stderr)  # fmt: skip
        return 2
    if randomize == "none" and batch_size != FaithfulnessOptions.batch_size:
        print("openpi-cam faithfulness: --batch-size sizes the randomised model's calls: --randomize none makes none",
              file=sys.stderr)  # fmt: skip
        return 2
    opts = FaithfulnessOptions(
        randomize=randomize, baseline=baseline, max_steps=None, random_orders=random_orders, batch_size=batch_size
    )

    show = Reporter("faithfulness", progress)

    mismatched = 0
    try:
        if is_maps_dataset(run_dir):  # frames served again and logged as a run inside the maps dataset
            maps = open_maps_dataset(run_dir)
            spec = run_model(maps.info.model, model)
            policy = spec.create()
            steps = DEFAULT_DATASET_STEPS if max_steps is None else max_steps
            evaluated_dir, counts = build_run(maps, policy, spec, max_steps=steps)
            report = evaluate_run(load_run(evaluated_dir), policy.explainer, opts, progress=show)
            report["maps_dataset"] = {"root": str(run_dir), "rows_served_again": counts["rows"], **dict(counts)}
            default_out, mismatched = pathlib.Path(run_dir) / DATASET_REPORT_PATH, counts["actions_mismatched"]
        else:
            run = load_run(run_dir)
            policy = run_model(run.run_info.get("config") or {}, model).create()
            opts = dataclasses.replace(opts, max_steps=max_steps)
            report = evaluate_run(run, policy.explainer, opts, progress=show)
            default_out = pathlib.Path(run_dir) / REPORT_FILE
    except (FileNotFoundError, KeyError, ValueError, InvalidRequest, OSError) as e:
        print(f"openpi-cam faithfulness: {e}", file=sys.stderr)
        return 1
    print(format_report(report))
    out = default_out if out is None else out
    try:
        out.write_text(dumps(report, indent=2))
    except OSError as e:
        print(f"openpi-cam faithfulness: could not save the report to {out}: {e}", file=sys.stderr)
        return 1
    print(f"saved the report to {out}", file=sys.stderr)
    if mismatched:
        print(
            f"openpi-cam faithfulness: {mismatched} frames served other actions than when they were explained and "
            "were left out (another checkpoint or dtype?)",
            file=sys.stderr,
        )
    if report["steps_evaluated"] == 0:
        print("openpi-cam faithfulness: no step could be re-scored", file=sys.stderr)
        return 1
    return 0
