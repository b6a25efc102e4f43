"""What a logged run says about its own faithfulness, read without the model: the faithfulness report saved beside
its steps (`openpi-cam faithfulness`, `REPORT_FILE`), IG's completeness over its steps, and each step's spot check
(`meta.check`, written by `cam.spot_check`). NumPy only, so `render` and `stats` load no JAX.
"""

from __future__ import annotations

import pathlib
from typing import Any

import numpy as np

from openpi_cam.cam.run_format import CAMRun, StepMeta, read_json

# Where a run's faithfulness report lives: beside its steps, where `render` looks for it.
REPORT_FILE = "faithfulness.json"


def read_report(run_dir: str | pathlib.Path) -> dict[str, Any] | None:
    """The run's saved faithfulness report (`REPORT_FILE`), or None when there is none or it cannot be read."""
    return read_json(pathlib.Path(run_dir) / REPORT_FILE)


def ig_summary(run: CAMRun) -> dict[str, Any] | None:
    """IG's completeness over the run's logged steps (as the side channel stored it): the largest and median
    relative error |sum of attributions - (score - baseline score)| / |score - baseline score|, and the quadrature
    points used."""
    checks = [check for s in run.steps if (check := s.meta.ig_completeness)]
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


def read_check(meta: StepMeta, kind: str) -> dict[str, tuple[float, tuple[float, ...]]]:
    """A logged step's spot check of one map kind: camera -> (its top patch's score drop, the random patches' drops
    without the kind's own top patch: `CameraCheck.drops`)."""
    cameras = {} if meta.check is None else meta.check.cameras
    return {camera: drops for camera, c in cameras.items() if (drops := c.drops(kind)) is not None}
