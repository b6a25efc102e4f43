"""A spot check of every explained step, computed with its maps: does painting a map's top patch move the explained
score more than painting a random patch?

The full faithfulness report (`cam.faithfulness_run`) re-runs a step once per patch and camera plus 16 per map kind
and random order: far too much to do live on a real checkpoint (~1,350 re-runs per step for three 224 px cameras).
The spot check re-runs the step a handful of times per camera, in one batched call: nothing painted, each kind's top
patch alone, and `patches` random single patches (drawn without replacement, seeded by the step), all painted with
the baseline frame the run's ig / occlusion maps use. It stores the score drops in the step's meta (`meta.check`,
docs/FORMAT.md), so every logged map carries evidence of its own: a top patch whose drop is no larger than a random
patch's is a map the model does not follow at that step.
"""

from __future__ import annotations

import contextlib
import zlib
from collections.abc import Mapping

import jax
import numpy as np
from jax.sharding import Mesh

from openpi_cam.cam.faithfulness import patch_order
from openpi_cam.cam.run_format import CameraCheck, SpotCheck
from openpi_cam.policies.family import Explainer, ExplainSkipped, Explanation
from openpi_cam.policies.policy import InferenceTrace
from openpi_cam.vocabulary import MapOptions


def spot_check_masks(
    maps: Mapping[str, np.ndarray], grid: tuple[int, int], patches: int, seed: int
) -> tuple[np.ndarray, list[int], list[int]]:
    """Masks bool [1 + K + R, Hp, Wp] (row 0 paints nothing; then each of the K maps' top patch; then R random
    patches), with the top patches' and the random patches' flat (row-major) indices."""
    n = grid[0] * grid[1]
    tops = [int(patch_order(m)[0]) for m in maps.values()]
    randoms = [int(i) for i in np.random.default_rng(seed).choice(n, size=min(patches, n), replace=False)]
    masks = np.zeros((1 + len(tops) + len(randoms), n), bool)
    masks[np.arange(1, len(masks)), tops + randoms] = True
    return masks.reshape(-1, *grid), tops, randoms


def _camera_masks(
    explanation: Explanation, patches: int, seed: int
) -> tuple[dict[str, np.ndarray], dict[str, tuple[list[int], list[int]]]]:
    """Per valid camera: its masks (`spot_check_masks`) and (top patches in kind order, random patches)."""
    masks, layout = {}, {}
    for index, (camera, info) in enumerate(explanation.cameras.items()):
        if not info.get("valid", True):
            continue
        per_kind = {k: m[camera] for k, m in explanation.maps.items()}
        # One stream per camera and step: the same step checks the same random patches whenever it is re-explained.
        camera_seed = [seed, index, zlib.crc32(camera.encode())]
        masks[camera], tops, randoms = spot_check_masks(per_kind, tuple(info["grid"]), patches, camera_seed)
        layout[camera] = (tops, randoms)
    return masks, layout


def check_trace(
    explainer: Explainer,
    trace: InferenceTrace,
    explanation: Explanation,
    options: MapOptions,
    *,
    patches: int,
    seed: int,
    mesh: Mesh | None = None,
) -> SpotCheck:
    """`meta.check` of one traced, explained inference: per valid camera, the unpainted score, each kind's top patch
    and its drop, the random patches and their drops. `SpotCheck(skipped=why)` when the target has one score per
    token (one number cannot check it), and best effort like the rest of the side channel: a failure is recorded as
    `SpotCheck(skipped="failed_<Error>")` and the step keeps its maps. With a `mesh`, `explainer` is placed on it."""
    try:
        masks, layout = _camera_masks(explanation, patches, seed)
        if not masks:
            return SpotCheck(skipped="no_valid_camera")
        with jax.set_mesh(mesh) if mesh is not None else contextlib.nullcontext():
            scores = explainer.rescore(
                trace.observation,
                np.asarray(trace.output)[None],
                {k: np.asarray(v)[None] for k, v in trace.sample_inputs.items()},
                {"target": explanation.target, **explanation.details},
                masks,
                options,
            )
    except ExplainSkipped as e:
        return SpotCheck(skipped=e.reason)
    except Exception as e:
        return SpotCheck(skipped=f"failed_{type(e).__name__}", error=str(e)[:200])
    kinds = list(explanation.maps)
    cameras = {}
    for camera, (tops, randoms) in layout.items():
        s = np.asarray(scores[camera], np.float64)
        drops = s[0] - s[1:]
        cameras[camera] = CameraCheck(
            score=float(s[0]),
            top_patch=dict(zip(kinds, tops, strict=True)),
            top_patch_drop={k: float(d) for k, d in zip(kinds, drops[: len(kinds)], strict=True)},
            random_patches=tuple(randoms),
            random_patch_drops=tuple(float(d) for d in drops[len(kinds) :]),
        )
    return SpotCheck(patches=patches, seed=seed, cameras=cameras)
