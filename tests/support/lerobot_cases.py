"""The frames of the LeRobot goldens (`../shared/golden/lerobot_pi0*_tiny/cases.npz`), as requests to their policy."""

from __future__ import annotations

from pathlib import Path

import numpy as np

CAMERAS = ("observation.images.base", "observation.images.wrist")


def cases(folder: Path) -> dict[str, np.ndarray]:
    """Every array of a LeRobot golden's `cases.npz`, by its key."""
    with np.load(folder / "cases.npz", allow_pickle=False) as npz:
        return {k: npz[k] for k in npz.files}


def request(d: dict[str, np.ndarray], case: str = "case0", *, uint8: bool = False) -> dict:
    """A frame as a LeRobot dataset gives it (float [3, H, W]) or as a robot sends it (uint8 [H, W, 3])."""
    images = {c: d[f"{case}/input_uint8_hwc/{c}" if uint8 else f"{case}/input/{c}"] for c in CAMERAS}
    return images | {"observation.state": d[f"{case}/input/observation.state"], "task": str(d[f"{case}/input/task"])}
