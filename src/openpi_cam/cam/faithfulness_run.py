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
(`REPORT_FILE`). The pure metrics are `cam.faithfulness`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import pathlib
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from typing import Any, Literal

import jax
import numpy as np
from jax.sharding import Mesh

from openpi_cam.cam import faithfulness as fm
from openpi_cam.cam.batching import data_mesh, explain_rows
from openpi_cam.cam.runfmt import CAMRun, CAMStep, read_json
from openpi_cam.model.observation import Observation
from openpi_cam.policies.family import Explainer, ExplainRequest, ExplainSkipped, Explanation
from openpi_cam.vocabulary import MAP_KINDS, MapOptions

_OBS_INPUTS = ("state", "tokenized_prompt", "tokenized_prompt_mask", "token_ar_mask")
_SAMPLER_INPUTS = ("noise",)

# Where a run's faithfulness report lives: beside its steps, where `render` looks for it.
REPORT_FILE = "faithfulness.json"

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

    Needs the model frames (`--cam-save-frames model|both`) and the `input/` arrays (schema version 2 or later)."""
    inputs, frames, cameras = step.inputs, step.model_frames, step.meta.get("cameras") or {}
    missing = [c for c in cameras if c not in frames] + [k for k in ("output", "state") if k not in inputs]
    if not cameras or missing:
        raise ExplainSkipped("not_replayable", f"step {step.seq} lacks {missing or 'its cameras'} (save model frames)")
    images = {c: (np.asarray(frames[c], np.float32) / 255.0 * 2.0 - 1.0)[None] for c in cameras}
    masks = {c: np.asarray([bool(info.get("valid", True))]) for c, info in cameras.items()}
    fields = {k: np.asarray(inputs[k])[None] if k in inputs else None for k in _OBS_INPUTS}
    obs = Observation(images=images, image_masks=masks, **fields)
    sample_inputs = {k: np.asarray(inputs[k])[None] for k in _SAMPLER_INPUTS if k in inputs}
    return obs, np.asarray(inputs["output"])[None], sample_inputs


def painting_options(step: CAMStep, baseline: str) -> MapOptions:
    """What a step's patches are painted with: the options its ig / occlusion maps were computed with ("run"), or
    the named baseline."""
    logged = step.meta.get("map_options")
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
    optimum: float
    occlusion: np.ndarray  # [Hp, Wp] single-patch drops
    deletion: dict[str, np.ndarray]  # kind (and "random") -> drop_k / optimum, k = 1..K
    maps: dict[str, np.ndarray]
    cells: np.ndarray | None


def _masks(order_by_kind: Mapping[str, np.ndarray], grid: tuple[int, int], k_max: int, orders: int, seed: int):
    """[reference, N single patches, per kind top-k (k = 1..K), per random order top-k] and where each block is."""
    n = grid[0] * grid[1]
    blocks = {"single": fm.single_patch_masks(grid)}  # row 0: nothing painted
    for kind, order in order_by_kind.items():
        blocks[kind] = fm.top_k_masks(order, grid)[1 : k_max + 1]
    rng = np.random.default_rng(seed)
    randoms = [fm.top_k_masks(rng.permutation(n), grid)[1 : k_max + 1] for _ in range(orders)]
    blocks["random"] = np.concatenate(randoms)
    where, start = {}, 0
    for name, block in blocks.items():
        where[name] = slice(start, start + len(block))
        start += len(block)
    return np.concatenate(list(blocks.values())), where


def _cells(step: CAMStep, camera: str, grid: tuple[int, int]) -> np.ndarray | None:
    frame = step.model_frames.get(camera)
    return fm.target_cells(step.meta, camera, grid, None if frame is None else frame.shape[:2], step.extra)


def _evenly(steps: Sequence[CAMStep], limit: int | None) -> list[CAMStep]:
    if limit is None or limit >= len(steps):
        return list(steps)
    picks = np.unique(np.linspace(0, len(steps) - 1, limit).round().astype(int))
    return [steps[i] for i in picks]


def _summary(values: Iterable[float], seed: int) -> dict[str, float | int | None]:
    x = np.asarray([v for v in values if v is not None and math.isfinite(v)], np.float64)
    if x.size == 0:
        return {"n": 0, "median": None, "mean": None, "ci95": None}
    mean, low, high = fm.bootstrap_mean_ci(x, seed=seed)
    return {"n": int(x.size), "median": float(np.median(x)), "mean": mean, "ci95": [low, high]}


def evaluate_run(
    run: CAMRun,
    explainer: Explainer,
    opts: FaithfulnessOptions = FaithfulnessOptions(),
    *,
    progress: Progress | None = None,
    mesh: Mesh | Literal["auto"] | None = "auto",
) -> dict[str, Any]:
    """The faithfulness report of a run (JSON-able): per map kind and camera, deletion, agreement with occlusion,
    randomisation and pointing figures, plus what was skipped and why.

    Work is spread over the local devices as in offline explanation (`mesh`: "auto" = all of them, None = one): each
    step's painted variants are split over them, and the randomised model explains `opts.batch_size` steps per call,
    their rows sharded."""
    mesh = data_mesh() if mesh == "auto" else mesh
    explainer = explainer.on_mesh(mesh)
    steps = _evenly([s for s in run.steps if s.meta.get("map_kinds")], opts.max_steps)
    skipped: dict[str, int] = {}
    replay_diffs: list[float] = []
    records: dict[str, list[_CameraRecord]] = {}
    random_explainer = None
    if opts.randomize != "none":
        random_explainer = explainer.randomized(opts.randomize, opts.seed).on_mesh(mesh)
    randomised: dict[tuple[str, str], list[tuple[np.ndarray, np.ndarray]]] = {}
    waiting: list[_RandomisationRow] = []
    iterator: Iterator[CAMStep] = iter(steps)
    if progress is not None:
        iterator = progress(iterator, len(steps))
    for step in iterator:
        try:
            obs, outputs, sample_inputs = step_model_inputs(step)
            kinds = [k for k in step.map_kinds if k in MAP_KINDS]
            cameras = [c for c, info in step.meta["cameras"].items() if info.get("valid", True)]
            grid = tuple(np.shape(step.maps_of(kinds[0])[cameras[0]])[-2:])
            k_max = min(opts.max_k, grid[0] * grid[1])
            per_camera, where = {}, {}
            for c in cameras:
                order = {k: fm.patch_order(step.maps_of(k)[c]) for k in kinds}
                per_camera[c], where = _masks(order, grid, k_max, opts.random_orders, opts.seed)
            painting = painting_options(step, opts.baseline)
            with jax.set_mesh(mesh) if mesh is not None else contextlib.nullcontext():
                scores = explainer.rescore(obs, outputs, sample_inputs, step.meta, per_camera, painting)
        except ExplainSkipped as e:
            skipped[e.kind] = skipped.get(e.kind, 0) + 1
            continue
        logged = step.meta.get("score")
        for c in cameras:
            s = np.asarray(scores[c], np.float64)
            if isinstance(logged, (int, float)):
                replay_diffs.append(abs(float(s[0]) - float(logged)))
            drops = s[0] - s
            single = drops[where["single"]][1:].reshape(grid)
            optimum = float(single.max())
            deletion = {k: drops[where[k]] / optimum if optimum > 0 else None for k in kinds}
            random = drops[where["random"]].reshape(opts.random_orders, k_max).mean(axis=0)
            deletion["random"] = random / optimum if optimum > 0 else None
            maps = {k: fm.reduce_map(step.maps_of(k)[c]) for k in kinds}
            records.setdefault(c, []).append(
                _CameraRecord(step.seq, optimum, single, deletion, maps, _cells(step, c, grid))
            )
        if random_explainer is not None:
            request = ExplainRequest(
                step.meta["target"] if step.meta["target"] in random_explainer.targets else "chunk",
                *_request_indices(step.meta),
                kinds=tuple(kinds),
                options=painting,
            )
            row = (obs, outputs[0], {k: v[0] for k, v in sample_inputs.items()})
            waiting.append(_RandomisationRow(step, kinds, cameras, request, row))
            if len(waiting) == opts.batch_size:
                _explain_randomised(random_explainer, waiting, randomised, mesh, opts.batch_size)
    if random_explainer is not None:
        _explain_randomised(random_explainer, waiting, randomised, mesh, opts.batch_size)
    report = _report(run, records, randomised, skipped, replay_diffs, opts)
    report["devices"] = 1 if mesh is None else int(mesh.devices.size)
    return report


@dataclasses.dataclass
class _RandomisationRow:
    """A re-scored step waiting for its explanation by the randomised model."""

    step: CAMStep
    kinds: list[str]
    cameras: list[str]
    request: ExplainRequest
    row: tuple[Observation, np.ndarray, dict[str, np.ndarray]]


def _explain_randomised(
    explainer: Explainer,
    waiting: list[_RandomisationRow],
    randomised: dict[tuple[str, str], list[tuple[np.ndarray, np.ndarray]]],
    mesh: Mesh | None,
    batch_size: int,
) -> None:
    """Explains the waiting steps with the randomised model, one call per request (padded to `batch_size` rows, so
    every call reuses one program), and pairs each map with the step's own, in step order; empties `waiting`."""
    results: dict[int, Explanation | ExplainSkipped] = {}
    by_request: dict[ExplainRequest, list[int]] = {}
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
                randomised.setdefault((k, c), []).append((w.step.maps_of(k)[c], other.maps[k][c]))
    waiting.clear()


def _request_indices(meta: Mapping[str, Any]) -> tuple[int, int]:
    index = meta.get("action_index")
    if isinstance(index, list):  # pi0 / pi0.5: [h, d]
        return int(index[0]), int(index[1])
    indices = meta.get("action_indices") or [0]
    return int(indices[0]), 0


def _report(run, records, randomised, skipped, replay_diffs, opts) -> dict[str, Any]:
    seed = opts.seed
    cameras: dict[str, Any] = {}
    for c, recs in records.items():
        kinds = list(dict.fromkeys(k for r in recs for k in r.maps))
        usable = [r for r in recs if r.optimum > 0]
        per_kind: dict[str, Any] = {}
        for kind in [*kinds, "random"]:
            curves = [r.deletion[kind] for r in usable if r.deletion.get(kind) is not None]
            entry: dict[str, Any] = {
                f"deletion_k{k}": _summary((curve[k - 1] for curve in curves), seed) for k in opts.ks
            }
            entry["deletion_auc"] = _summary((float(np.mean(curve)) for curve in curves), seed)
            if kind != "random":
                with_map = [r for r in usable if kind in r.maps]
                top1 = (float(fm.top1_agreement(r.maps[kind], r.occlusion)) for r in with_map)
                entry["top1_occlusion"] = _summary(top1, seed)
                rho = (fm.spearman(r.maps[kind], r.occlusion) for r in with_map)
                entry["spearman_occlusion"] = _summary(rho, seed)
                pairs = randomised.get((kind, c), [])
                if len(pairs) >= 2:
                    ours, theirs = [a for a, _ in pairs], [b for _, b in pairs]
                    entry["randomisation_abs_spearman"] = _summary(fm.randomisation_abs_spearman(ours, theirs), seed)
                    entry["null_abs_spearman"] = _summary(fm.null_abs_spearman(ours), seed)
                boxed = [r for r in recs if r.cells is not None and kind in r.maps]
                if boxed:
                    entry["pointing"] = _summary((float(fm.pointing_hit(r.maps[kind], r.cells)) for r in boxed), seed)
                    entry["pointing_chance"] = float(np.mean([fm.pointing_chance(r.cells) for r in boxed]))
                    entry["mass_on_target"] = _summary((fm.mass_on_target(r.maps[kind], r.cells) for r in boxed), seed)
                    entry["nuisance_mass_ratio"] = _summary(
                        (fm.nuisance_mass_ratio(r.maps[kind], r.cells) for r in boxed), seed
                    )
            per_kind[kind] = entry
        cameras[c] = {"steps": len(recs), "steps_with_positive_optimum": len(usable), "kinds": per_kind}
    return {
        "ig_completeness": ig_summary(run),
        "run_dir": str(run.run_dir),
        "run_id": run.run_info.get("run_id", run.run_dir.name),
        "options": dataclasses.asdict(opts),
        "steps_evaluated": max((len(r) for r in records.values()), default=0),
        "skipped": skipped,
        "score_replay_max_abs_diff": max(replay_diffs, default=None),
        "cameras": cameras,
        "steps": _per_step(records),
    }


def _per_step(records: Mapping[str, list[_CameraRecord]]) -> dict[str, dict[str, Any]]:
    """Each evaluated step's own figures by seq (a string: JSON keys) and camera: the best single patch's drop, and
    per kind (and "random", the mean over random orders) the drop of painting its top patch alone as a fraction of
    that best drop, with whether its top patch is the best one. Fractions are None where no patch lowers the
    score (nothing to normalise by)."""
    steps: dict[str, dict[str, Any]] = {}
    for c, recs in records.items():
        for r in recs:
            scored = r.optimum > 0
            steps.setdefault(str(r.step), {})[c] = {
                "optimum": r.optimum,
                "deletion_k1": {k: float(d[0]) if scored and d is not None else None for k, d in r.deletion.items()},
                "top1_occlusion": {
                    k: bool(fm.top1_agreement(m, r.occlusion)) if scored else None for k, m in r.maps.items()
                },
            }
    return steps


def read_report(run_dir: str | pathlib.Path) -> dict[str, Any] | None:
    """The run's saved faithfulness report (`REPORT_FILE`), or None when there is none or it cannot be read."""
    return read_json(pathlib.Path(run_dir) / REPORT_FILE)


def ig_summary(run: CAMRun) -> dict[str, Any] | None:
    """IG's completeness over the run's logged steps (as the side channel stored it): the largest and median
    relative error |sum of attributions - (score - baseline score)| / |score - baseline score|, and the quadrature
    points used."""
    checks = [s.meta["ig_completeness"] for s in run.steps if s.meta.get("ig_completeness")]
    if not checks:
        return None
    errors = np.concatenate([np.ravel(np.asarray(c["relative_error"], np.float64)) for c in checks])
    points, counts = np.unique([int(c["steps"]) for c in checks], return_counts=True)
    return {
        "steps": len(checks),
        "max_relative_error": float(errors.max()),
        "median_relative_error": float(np.median(errors)),
        "quadrature_points": {int(p): int(n) for p, n in zip(points, counts, strict=True)},
    }


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
