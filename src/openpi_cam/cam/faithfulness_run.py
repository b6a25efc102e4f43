"""How faithful are a run's maps? Every logged step re-scored by the model under interventions (`openpi-cam
faithfulness RUN_DIR`).

A step is rebuilt from what the logger stored (model frames `frame_model/<camera>`, the non-image model inputs and the
raw output under `input/`; docs/FORMAT.md), so the explained score is re-run exactly; the first check of every step
is that the unpainted re-run reproduces the logged score. Then, per map kind and valid camera:

* deletion: paint the map's top-k patches (signed order, highest first) with the baseline frame, re-run, and divide
  the score's drop by the single-patch occlusion optimum of the same step and camera (the largest drop any one patch
  causes alone); k = 1, 2, 4 and the area under the curve (mean over k = 1..K). The same for random orders.
* agreement with occlusion: does the map's peak name the patch whose painting alone drops the score most (top-1),
  and the Spearman correlation of the two maps over patches;
* model randomisation (Adebayo et al. 2018): |Spearman| between the map and the same kind's map from a model whose
  language model (or every weight) is re-initialised, next to a null of |Spearman| between maps of unrelated steps;
* pointing game, mass on target and nuisance mass ratio, for steps whose client sent a ground-truth box
  (`cam_extra/target_box`, x0 y0 x1 y1 in the client image of `cam_extra/target_camera`, default the first camera).

Medians are the headline (per-step ratios are heavy-tailed: a step whose best patch barely moves the score has a tiny
optimum); means come with 95% bootstrap intervals. The report also keeps each step's own figures (`steps`), which
`render` and the HTML report show beside that step's maps; it is saved as RUN_DIR/faithfulness.json
(`run_evidence.REPORT_FILE`). The pure metrics are `cam.faithfulness`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import Any, Literal

import jax
import numpy as np
from jax.sharding import Mesh

from openpi_cam.cam import faithfulness as metrics
from openpi_cam.cam.batching import data_mesh, explain_rows
from openpi_cam.cam.run_evidence import ig_summary
from openpi_cam.cam.run_format import IMAGE_INPUT, CAMRun, CAMStep, StepMeta
from openpi_cam.model.observation import Observation, uint8_to_model
from openpi_cam.policies.family import Explainer, ExplainSkipped, Explanation
from openpi_cam.vocabulary import MAP_KINDS, ExplainOptions, HeadRef, MapOptions

_OBS_INPUTS = ("state", "tokenized_prompt", "tokenized_prompt_mask", "token_ar_mask")
_SAMPLER_INPUTS = ("noise",)

# Wraps the steps with a progress display: (steps, how many) -> the same steps.
Progress = Callable[[Iterator[CAMStep], int], Iterator[CAMStep]]


@dataclasses.dataclass(frozen=True)
class FaithfulnessOptions:
    ks: tuple[int, ...] = (1, 2, 4)  # deletion depths reported
    max_k: int = 16  # the curve (and its AUC) runs k = 1..min(max_k, patches per camera)
    random_orders: int = 8  # random patch orders averaged for the random reference
    randomize: Literal["none", "llm", "all"] = "llm"  # which weights the randomisation test re-initialises
    seed: int = 0  # random orders, bootstrap and the re-initialisation
    max_steps: int | None = None  # evaluate at most this many steps (evenly spread over the run)
    baseline: Literal["run", "mean", "blur"] = "run"  # painting: "run" = the baseline the run's ig/occlusion used
    batch_size: int = 8  # steps per call of the randomised model (padded to a multiple of the device count)

    def __post_init__(self) -> None:
        if not self.ks or min(self.ks) < 1 or max(self.ks) > self.max_k or self.random_orders < 1:
            raise ValueError("deletion depths must lie in [1, max_k] and random_orders >= 1")
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {self.batch_size}")


def step_model_inputs(step: CAMStep) -> tuple[Observation, np.ndarray, dict[str, np.ndarray]]:
    """(observation [B = 1], raw output [1, ...], sampler inputs [1, ...]) of a logged step, as the model saw them.

    Needs the model frames (`--cam.save-frames model|both`) and the `input/` arrays (schema version 2 or later)."""
    inputs, frames, cameras = step.inputs, step.model_frames, step.meta.cameras
    missing = [c for c in cameras if c not in frames] + [k for k in ("output", "state") if k not in inputs]
    if not cameras or missing:
        raise ExplainSkipped("not_replayable", f"step {step.seq} lacks {missing or 'its cameras'} (save model frames)")
    images = {
        c: np.asarray(inputs[IMAGE_INPUT + c] if IMAGE_INPUT + c in inputs else uint8_to_model(frames[c]))[None]
        for c in cameras
    }
    masks = {c: np.asarray([info.valid]) for c, info in cameras.items()}
    fields = {k: np.asarray(inputs[k])[None] if k in inputs else None for k in _OBS_INPUTS}
    obs = Observation(images=images, image_masks=masks, **fields)
    sample_inputs = {k: np.asarray(inputs[k])[None] for k in _SAMPLER_INPUTS if k in inputs}
    return obs, np.asarray(inputs["output"])[None], sample_inputs


def painting_options(step: CAMStep, baseline: str) -> MapOptions:
    """What a step's patches are painted with: the options its ig / occlusion maps were computed with ("run"), or
    the named baseline."""
    logged = step.meta.map_options
    if baseline == "run":
        if logged:
            names = {f.name for f in dataclasses.fields(MapOptions)}
            return MapOptions(**{k: v for k, v in logged.items() if k in names})
        return MapOptions()
    return MapOptions(baseline=baseline)


@dataclasses.dataclass
class _CameraRecord:
    """One (step, camera): what the summary aggregates."""

    step: int
    deletion: metrics.Deletion  # per kind and metrics.RANDOM; `single` is the step's single-patch occlusion map
    maps: dict[str, np.ndarray]
    cells: np.ndarray | None


@dataclasses.dataclass
class _Rescored:
    """A logged step re-run under its deletion masks (one explainer call for all its cameras)."""

    obs: Observation
    outputs: np.ndarray
    sample_inputs: dict[str, np.ndarray]
    kinds: list[str]
    cameras: list[str]  # the valid ones
    grid: tuple[int, int]
    painting: MapOptions
    masks: dict[str, metrics.DeletionMasks]  # camera -> its deletion masks
    scores: dict[str, np.ndarray]  # camera -> [K], in its mask stack's order


@dataclasses.dataclass
class _RandomisationRow:
    """A re-scored step waiting for its explanation by the randomised model."""

    step: CAMStep
    kinds: list[str]
    cameras: list[str]
    request: ExplainOptions
    row: tuple[Observation, np.ndarray, dict[str, np.ndarray]]


@dataclasses.dataclass
class _Evaluation:
    """What evaluating a run gathers, step by step."""

    skipped: dict[str, int] = dataclasses.field(default_factory=dict)  # why -> steps not re-scored
    replay_diffs: list[float] = dataclasses.field(default_factory=list)  # |unpainted re-run - logged score|
    records: dict[str, list[_CameraRecord]] = dataclasses.field(default_factory=dict)  # camera -> its records
    # (kind, camera) -> (the step's map, the randomised model's map), in step order
    randomised: dict[tuple[str, str], list[tuple[np.ndarray, np.ndarray]]] = dataclasses.field(default_factory=dict)
    waiting: list[_RandomisationRow] = dataclasses.field(default_factory=list)  # not yet explained by that model

    def skip(self, why: str) -> None:
        self.skipped[why] = self.skipped.get(why, 0) + 1

    def add(self, step: CAMStep, rescored: _Rescored) -> None:
        """The step's deletion figures per valid camera, and how closely its unpainted re-run met the logged score."""
        logged = step.meta.score
        for c in rescored.cameras:
            scores = np.asarray(rescored.scores[c], np.float64)
            if isinstance(logged, float):
                self.replay_diffs.append(abs(float(scores[0]) - logged))
            maps = {k: metrics.reduce_map(step.maps_of(k)[c]) for k in rescored.kinds}
            deletion = metrics.deletion(rescored.masks[c], scores)
            self.records.setdefault(c, []).append(
                _CameraRecord(step.seq, deletion, maps, _cells(step, c, rescored.grid))
            )


def _rescore(step: CAMStep, explainer: Explainer, opts: FaithfulnessOptions, mesh: Mesh | None) -> _Rescored:
    """Re-runs a logged step's score under the deletion masks of each valid camera's maps (`ExplainSkipped` when
    the step cannot be rebuilt)."""
    obs, outputs, sample_inputs = step_model_inputs(step)
    kinds = [k for k in step.map_kinds if k in MAP_KINDS]
    cameras = step.meta.valid_cameras()
    grid = tuple(np.shape(step.maps_of(kinds[0])[cameras[0]])[-2:])
    plans = {
        c: metrics.deletion_masks(
            {k: metrics.patch_order(step.maps_of(k)[c]) for k in kinds},
            grid,
            k_max=opts.max_k,
            random_orders=opts.random_orders,
            seed=opts.seed,
        )
        for c in cameras
    }
    painting = painting_options(step, opts.baseline)
    masks = {c: plan.masks for c, plan in plans.items()}
    with jax.set_mesh(mesh) if mesh is not None else contextlib.nullcontext():
        scores = explainer.rescore(
            obs, outputs, sample_inputs, explained=step.meta.explained(), masks=masks, options=painting
        )
    return _Rescored(
        obs=obs,
        outputs=outputs,
        sample_inputs=sample_inputs,
        kinds=kinds,
        cameras=cameras,
        grid=grid,
        painting=painting,
        masks=plans,
        scores=scores,
    )


def _randomisation_row(
    step: CAMStep, rescored: _Rescored, targets: Sequence[str], head: HeadRef | None
) -> _RandomisationRow:
    """The randomised model's request for a step: its own target where that model explains it, else the chunk;
    `head`: the run's occlusion head (the kind's map of the randomised model is that head on its input maps)."""
    action_index, action_dim_index = _request_indices(step.meta)
    request = ExplainOptions(
        step.meta.target if step.meta.target in targets else "chunk",
        action_index=action_index,
        action_dim_index=action_dim_index,
        maps=tuple(rescored.kinds),
        map_options=rescored.painting,
        occlusion_head=head,
    )
    row = (rescored.obs, rescored.outputs[0], {k: v[0] for k, v in rescored.sample_inputs.items()})
    return _RandomisationRow(step, rescored.kinds, rescored.cameras, request, row)


def _cells(step: CAMStep, camera: str, grid: tuple[int, int]) -> np.ndarray | None:
    frame = step.model_frames.get(camera)
    return metrics.target_cells(step.meta, camera, grid, None if frame is None else frame.shape[:2], step.extra)


def _evenly(steps: Sequence[CAMStep], limit: int | None) -> list[CAMStep]:
    if limit is None or limit >= len(steps):
        return list(steps)
    picks = np.unique(np.linspace(0, len(steps) - 1, limit).round().astype(int))
    return [steps[i] for i in picks]


def _summary(values: Iterable[float], seed: int) -> dict[str, float | int | None]:
    x = np.asarray([v for v in values if v is not None and math.isfinite(v)], np.float64)
    if x.size == 0:
        return {"n": 0, "median": None, "mean": None, "ci95": None}
    mean, low, high = metrics.bootstrap_mean_ci(x, seed=seed)
    return {"n": int(x.size), "median": float(np.median(x)), "mean": mean, "ci95": [low, high]}


def evaluate_run(
    run: CAMRun,
    explainer: Explainer,
    opts: FaithfulnessOptions = FaithfulnessOptions(),
    *,
    progress: Progress | None = None,
    mesh: Mesh | Literal["auto"] | None = "auto",
) -> dict[str, Any]:
    """The faithfulness report of a run (JSON data: a number that is not finite, such as a deletion fraction where no
    patch lowers the score, is None): per map kind and camera, deletion, agreement with occlusion, randomisation and
    pointing figures, plus what was skipped and why.

    Work is spread over the local devices as in offline explanation (`mesh`: "auto" = all of them, None = one): each
    step's painted variants are split over them, and the randomised model explains `opts.batch_size` steps per call
    (fewer when the run has fewer), their rows sharded."""
    mesh = data_mesh() if mesh == "auto" else mesh
    explainer = explainer.on_mesh(mesh)
    random_explainer = None
    if opts.randomize != "none":
        random_explainer = explainer.randomized(opts.randomize, opts.seed).on_mesh(mesh)
    steps = _evenly([s for s in run.steps if s.meta.map_kinds], opts.max_steps)
    head = ExplainOptions.from_json(run.run_info.get("options") or {}).occlusion_head
    # Rows per randomised call, the same for every call of this run (one program); a run shorter than a batch pads
    # to its own length rather than to rows it never fills.
    rows_per_call = max(1, min(opts.batch_size, len(steps)))
    evaluation = _Evaluation()
    for step in iter(steps) if progress is None else progress(iter(steps), len(steps)):
        try:
            rescored = _rescore(step, explainer, opts, mesh)
        except ExplainSkipped as e:
            evaluation.skip(e.reason)
            continue
        evaluation.add(step, rescored)
        if random_explainer is not None:
            evaluation.waiting.append(_randomisation_row(step, rescored, random_explainer.targets, head))
            if len(evaluation.waiting) == rows_per_call:
                _explain_randomised(random_explainer, evaluation, mesh, rows_per_call)
    if random_explainer is not None:
        _explain_randomised(random_explainer, evaluation, mesh, rows_per_call)
    report = _report(run, evaluation, opts)
    report["devices"] = 1 if mesh is None else int(mesh.devices.size)
    return _json_safe(report)


def _explain_randomised(explainer: Explainer, evaluation: _Evaluation, mesh: Mesh | None, batch_size: int) -> None:
    """Explains the waiting steps with the randomised model, one call per request (padded to `batch_size` rows, so
    every call reuses one program), and pairs each map with the step's own, in step order; empties the queue."""
    waiting = evaluation.waiting
    results: dict[int, Explanation | ExplainSkipped] = {}
    by_request: dict[ExplainOptions, list[int]] = {}
    for i, w in enumerate(waiting):
        by_request.setdefault(w.request, []).append(i)
    for request, members in by_request.items():
        rows = [waiting[i].row for i in members]
        for i, result in zip(
            members, explain_rows(explainer, rows, request, mesh=mesh, pad_to=batch_size), strict=True
        ):
            results[i] = result
    for i, w in enumerate(waiting):
        other = results[i]
        if isinstance(other, ExplainSkipped):
            continue
        for k in w.kinds:
            for c in w.cameras:
                evaluation.randomised.setdefault((k, c), []).append((w.step.maps_of(k)[c], other.maps[k][c]))
    waiting.clear()


def _request_indices(meta: StepMeta) -> tuple[int, int]:
    """(action_index, action_dim_index) of the request that explained a step."""
    if meta.action_index is not None:  # pi0 / pi0.5: (h, d)
        return meta.action_index
    indices = meta.action_indices or (0,)
    return indices[0], 0


def _kind_entry(
    kind: str,
    records: Sequence[_CameraRecord],
    randomised: Sequence[tuple[np.ndarray, np.ndarray]],
    opts: FaithfulnessOptions,
) -> dict[str, Any]:
    """One camera's figures for one map kind (or metrics.RANDOM) over its records."""
    seed = opts.seed
    usable = [r for r in records if r.deletion.optimum > 0]
    scored = [r.deletion for r in usable if kind in r.deletion.curves]
    entry: dict[str, Any] = {
        f"deletion_k{k}": _summary((float(d.at_k(kind, [k])[0]) for d in scored), seed) for k in opts.ks
    }
    entry["deletion_auc"] = _summary((d.auc(kind) for d in scored), seed)
    if kind == metrics.RANDOM:
        return entry
    with_map = [r for r in usable if kind in r.maps]
    top1 = (float(metrics.top1_agreement(r.maps[kind], r.deletion.single)) for r in with_map)
    entry["top1_occlusion"] = _summary(top1, seed)
    entry["spearman_occlusion"] = _summary((metrics.spearman(r.maps[kind], r.deletion.single) for r in with_map), seed)
    if len(randomised) >= 2:
        ours, theirs = [a for a, _ in randomised], [b for _, b in randomised]
        entry["randomisation_abs_spearman"] = _summary(metrics.randomisation_abs_spearman(ours, theirs), seed)
        entry["null_abs_spearman"] = _summary(metrics.null_abs_spearman(ours), seed)
    boxed = [r for r in records if r.cells is not None and kind in r.maps]
    if boxed:
        entry["pointing"] = _summary((float(metrics.pointing_hit(r.maps[kind], r.cells)) for r in boxed), seed)
        entry["pointing_chance"] = float(np.mean([metrics.pointing_chance(r.cells) for r in boxed]))
        entry["mass_on_target"] = _summary((metrics.mass_on_target(r.maps[kind], r.cells) for r in boxed), seed)
        ratios = (metrics.nuisance_mass_ratio(r.maps[kind], r.cells) for r in boxed)
        entry["nuisance_mass_ratio"] = _summary(ratios, seed)
    return entry


def _report(run: CAMRun, evaluation: _Evaluation, opts: FaithfulnessOptions) -> dict[str, Any]:
    cameras: dict[str, Any] = {}
    for c, recs in evaluation.records.items():
        kinds = list(dict.fromkeys(k for r in recs for k in r.maps))
        per_kind = {
            k: _kind_entry(k, recs, evaluation.randomised.get((k, c), []), opts) for k in [*kinds, metrics.RANDOM]
        }
        positive = sum(r.deletion.optimum > 0 for r in recs)
        cameras[c] = {"steps": len(recs), "steps_with_positive_optimum": positive, "kinds": per_kind}
    return {
        "ig_completeness": ig_summary(run),
        "run_dir": str(run.run_dir),
        "run_id": run.run_info.get("run_id", run.run_dir.name),
        "options": dataclasses.asdict(opts),
        "steps_evaluated": max((len(r) for r in evaluation.records.values()), default=0),
        "skipped": evaluation.skipped,
        "score_replay_max_abs_diff": max(evaluation.replay_diffs, default=None),
        "cameras": cameras,
        "steps": _per_step(evaluation.records),
    }


def _per_step(records: Mapping[str, list[_CameraRecord]]) -> dict[str, dict[str, Any]]:
    """Each evaluated step's own figures by seq (a string: JSON keys) and camera: the best single patch's drop, and
    per kind (and "random", the mean over random orders) the drop of painting its top patch alone as a fraction of
    that best drop, with whether its top patch is the best one. Both are None where no patch lowers the score
    (nothing to normalise by)."""
    steps: dict[str, dict[str, Any]] = {}
    for c, recs in records.items():
        for r in recs:
            scored = r.deletion.optimum > 0
            steps.setdefault(str(r.step), {})[c] = {
                "optimum": r.deletion.optimum,
                "deletion_k1": {k: float(curve[0]) for k, curve in r.deletion.curves.items()},
                "top1_occlusion": {
                    k: bool(metrics.top1_agreement(m, r.deletion.single)) if scored else None for k, m in r.maps.items()
                },
            }
    return steps


def _json_safe(value: Any) -> Any:
    """The report with every non-finite number as None: JSON has no NaN, and a reader must not meet one."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def _fmt(summary: Mapping[str, Any] | None, stat: str = "median") -> str:
    """A summary's median (or "mean", or "share": the mean as a percentage), "-" when nothing was measured."""
    if not summary or summary.get("median") is None:
        return "-"
    if stat == "share":
        return f"{summary['mean']:.0%}"
    return f"{summary[stat]:.2f}"


def format_report(report: Mapping[str, Any]) -> str:
    """A plain-text table per camera: deletion medians (drop / single-patch optimum), top-1 agreement with
    occlusion, randomisation against its null, and pointing where the run has ground-truth boxes."""
    lines = [
        f"faithfulness of {report['run_dir']}: {report['steps_evaluated']} steps re-scored"
        + (f", skipped {report['skipped']}" if report["skipped"] else ""),
        f"unpainted re-run vs logged score: max |diff| {report['score_replay_max_abs_diff']}",
        *(
            [
                f"IG completeness over {ig['steps']} steps: relative error max {ig['max_relative_error']:.2%}, median "
                f"{ig['median_relative_error']:.3%}; quadrature points (points: steps) {ig['quadrature_points']}"
            ]
            if (ig := report.get("ig_completeness"))
            else []
        ),
        "deletion = score drop after painting the map's top-k patches / the best single patch's drop (median; "
        "occlusion's own map is 1.00 at k=1); rand |rho| = |Spearman| with the map of a re-initialised model "
        "(lower is better; null = unrelated steps); rho occl = Spearman with the occlusion map (median)",
    ]
    for camera, cam in report["cameras"].items():
        ks = report["options"]["ks"]
        columns = [
            "kind",
            *[f"del k={k}" for k in ks],
            "del AUC",
            "top-1 = occl",
            "rho occl",
            "rand |rho| (null)",
            "pointing",
        ]
        head = " | ".join(columns)
        lines += ["", f"camera {camera} ({cam['steps_with_positive_optimum']}/{cam['steps']} steps scored)", head]
        for kind, e in cam["kinds"].items():
            rand = "-"
            if e.get("randomisation_abs_spearman"):
                rand = f"{_fmt(e['randomisation_abs_spearman'], 'mean')} ({_fmt(e['null_abs_spearman'], 'mean')})"
            point = "-"
            if e.get("pointing"):
                point = f"{_fmt(e['pointing'], 'share')} (chance {e['pointing_chance']:.0%})"
            cells = [kind, *[_fmt(e[f"deletion_k{k}"]) for k in ks], _fmt(e["deletion_auc"])]
            if kind == "random":
                cells += ["-", "-", rand, point]
            else:
                cells += [_fmt(e.get("top1_occlusion"), "share"), _fmt(e.get("spearman_occlusion")), rand, point]
            lines.append(" | ".join(cells))
    return "\n".join(lines)
