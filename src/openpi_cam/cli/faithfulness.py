"""`openpi-cam faithfulness RUN_DIR`: how faithful each map kind of a run is, re-scored by the model itself."""

from __future__ import annotations

import pathlib
import sys
from collections.abc import Callable
from typing import Literal

import tyro

from openpi_cam.cam.faithfulness_run import FaithfulnessOptions, evaluate_run, format_report
from openpi_cam.cam.run_evidence import REPORT_FILE
from openpi_cam.cam.run_format import dumps, load_run
from openpi_cam.cli.options import DeletionBaseline
from openpi_cam.datasets.explain import PolicySpec
from openpi_cam.datasets.faithfulness import REPORT_FILE as DATASET_REPORT_FILE
from openpi_cam.datasets.faithfulness import build_run
from openpi_cam.datasets.maps_dataset import is_maps_dataset, open_maps_dataset
from openpi_cam.errors import InvalidRequest
from openpi_cam.policies import demo_reach
from openpi_cam.policies.policy import Policy, create_policy
from openpi_cam.viz.progress import progress as progress_bar

# Frames of a maps dataset evaluated unless --max-steps says otherwise: each is served again and re-scored.
DEFAULT_DATASET_STEPS = 64


def load_policy(
    run_config: dict,
    *,
    config: str | None,
    checkpoint_dir: pathlib.Path | None,
    paligemma_tokenizer: pathlib.Path | None,
    fast_tokenizer: pathlib.Path | None,
    dtype: str | None,
) -> Policy:
    """The policy that served (or explained) a run: the bundled demo model when the run names a demo config and no
    checkpoint is given, else `create_policy` with the run's recorded settings, each overridable."""
    config = config or run_config.get("config")
    if config is None:
        raise ValueError("the run does not record its policy config; pass --config")
    checkpoint = checkpoint_dir or run_config.get("checkpoint_dir")
    if config in demo_reach.DEMO_MODELS and checkpoint is None:
        return demo_reach.create_demo_policy(model=demo_reach.DEMO_MODELS[config])
    if checkpoint is None:
        raise ValueError("the run does not record its checkpoint; pass --checkpoint-dir")
    return create_policy(
        config,
        checkpoint,
        paligemma_tokenizer=paligemma_tokenizer or run_config.get("paligemma_tokenizer"),
        fast_tokenizer=fast_tokenizer or run_config.get("fast_tokenizer"),
        dtype=dtype or run_config.get("dtype") or "bfloat16",
    )


def main(
    run_dir: tyro.conf.Positional[pathlib.Path],
    checkpoint_dir: pathlib.Path | None = None,
    config: str | None = None,
    paligemma_tokenizer: pathlib.Path | None = None,
    fast_tokenizer: pathlib.Path | None = None,
    dtype: Literal["bfloat16", "float32"] | None = None,
    randomize: Literal["none", "llm", "all"] = "llm",
    baseline: DeletionBaseline = "run",
    max_steps: int | None = None,
    random_orders: int = 8,
    batch_size: int = 8,
    json_out: pathlib.Path | None = None,
    progress: bool = True,
) -> int:
    """Re-score every logged step of RUN_DIR under interventions and report, per map kind and camera, how faithful
    the maps are: deletion (k = 1, 2, 4, AUC) normalised by the single-patch occlusion optimum next to a random
    order, top-1 agreement with occlusion, model randomisation against its null, and the pointing game where the
    client sent ground-truth boxes. Needs steps logged with model frames (`serve --cam.save-frames model|both`).

    Args:
        run_dir: a CAM run directory.
        checkpoint_dir: the checkpoint that served the run; default: the one the run records (or the bundled demo).
        config: policy config; default: the one the run records.
        paligemma_tokenizer: PaliGemma SentencePiece model; default: the run's, else the standard location.
        fast_tokenizer: FAST tokenizer folder; default: the run's, else the standard location.
        dtype: parameter dtype; default: the run's.
        randomize: which weights the randomisation test re-initialises (`llm`: the language model and action
            expert, SigLIP kept; `all`; `none` skips the test).
        baseline: what deletion paints with: the baseline the run's ig / occlusion maps used (`run`), or one named.
        max_steps: evaluate at most this many steps, evenly spread over the run.
        random_orders: random patch orders averaged for the random reference.
        batch_size: steps per call of the randomised model (sharded over all local devices, like `explain`).
        json_out: where to write the full report (every figure with its 95% bootstrap interval, and each step's
            own figures) as JSON; default RUN_DIR/faithfulness.json, where `render` finds it and shows each map's
            figures beside it.
        progress: show progress on stderr.
    """
    if is_maps_dataset(run_dir):
        return _maps_dataset_main(
            run_dir,
            checkpoint_dir=checkpoint_dir,
            config=config,
            paligemma_tokenizer=paligemma_tokenizer,
            fast_tokenizer=fast_tokenizer,
            dtype=dtype,
            opts_of=lambda: FaithfulnessOptions(
                randomize=randomize,
                baseline=baseline,
                max_steps=None,
                random_orders=random_orders,
                batch_size=batch_size,
            ),
            max_steps=max_steps,
            json_out=json_out,
            progress=progress,
        )
    try:
        run = load_run(run_dir)
        policy = load_policy(
            run.run_info.get("config") or {},
            config=config,
            checkpoint_dir=checkpoint_dir,
            paligemma_tokenizer=paligemma_tokenizer,
            fast_tokenizer=fast_tokenizer,
            dtype=dtype,
        )
        opts = FaithfulnessOptions(
            randomize=randomize,
            baseline=baseline,
            max_steps=max_steps,
            random_orders=random_orders,
            batch_size=batch_size,
        )

        def show(items, n):
            return progress_bar(items, n, "faithfulness", progress)

        report = evaluate_run(run, policy.explainer, opts, progress=show)
    except (FileNotFoundError, KeyError, ValueError, InvalidRequest, OSError) as e:
        print(f"openpi-cam faithfulness: {e}", file=sys.stderr)
        return 1
    print(format_report(report))
    out = pathlib.Path(run_dir) / REPORT_FILE if json_out is None else json_out
    try:
        out.write_text(dumps(report, indent=2))
    except OSError as e:
        print(f"openpi-cam faithfulness: could not save the report to {out}: {e}", file=sys.stderr)
        return 1
    print(f"saved the report to {out}", file=sys.stderr)
    if report["steps_evaluated"] == 0:
        print("openpi-cam faithfulness: no step could be re-scored", file=sys.stderr)
        return 1
    return 0


__all__ = ["main"]


def _maps_dataset_main(
    root: pathlib.Path,
    *,
    checkpoint_dir: pathlib.Path | None,
    config: str | None,
    paligemma_tokenizer: pathlib.Path | None,
    fast_tokenizer: pathlib.Path | None,
    dtype: str | None,
    opts_of: Callable[[], FaithfulnessOptions],
    max_steps: int | None,
    json_out: pathlib.Path | None,
    progress: bool,
) -> int:
    """Faithfulness of a maps dataset: `max_steps` frames (default 64) spread over it, served again and re-scored."""
    try:
        maps = open_maps_dataset(root)
        info = maps.info
        bundled_checkpoints = {
            str(assets / demo_reach.CHECKPOINT.name) for assets in demo_reach.DEFAULT_ASSETS.values()
        }
        bundled = checkpoint_dir is None and info["checkpoint"] in bundled_checkpoints
        spec = PolicySpec(
            config=config or info["config"],
            checkpoint_dir=None if bundled else str(checkpoint_dir or info["checkpoint"]),
            paligemma_tokenizer=None if paligemma_tokenizer is None else str(paligemma_tokenizer),
            fast_tokenizer=None if fast_tokenizer is None else str(fast_tokenizer),
            dtype=dtype or info["dtype"],
        )
        policy = spec.create()
        run_dir, counts = build_run(
            maps, policy, spec, max_steps=DEFAULT_DATASET_STEPS if max_steps is None else max_steps
        )

        def show(items, n):
            return progress_bar(items, n, "faithfulness", progress)

        report = evaluate_run(load_run(run_dir), policy.explainer, opts_of(), progress=show)
        report["maps_dataset"] = {"root": str(root), "rows_served_again": counts["rows"], **dict(counts)}
    except (FileNotFoundError, KeyError, ValueError, InvalidRequest, OSError) as e:
        print(f"openpi-cam faithfulness: {e}", file=sys.stderr)
        return 1
    print(format_report(report))
    out = root / DATASET_REPORT_FILE if json_out is None else json_out
    out.write_text(dumps(report, indent=2))
    print(f"saved the report to {out}", file=sys.stderr)
    if counts["actions_mismatched"]:
        print(
            f"openpi-cam faithfulness: {counts['actions_mismatched']} frames served other actions than when they were "
            "explained and were left out (another checkpoint or dtype?)",
            file=sys.stderr,
        )
    return 0 if report["steps_evaluated"] else 1
