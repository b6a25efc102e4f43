"""What the dataset tests share: a job reading a dataset by the model's own LeRobot mapping, the pointing figures of a
maps dataset, and a demo dataset with a truncated video."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from paths import LEROBOT_DIR
from shared_copies import writable_copy

from openpi_cam.cam.faithfulness import box_cells, pointing_chance, pointing_hit
from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.maps import dataset as fmt
from openpi_cam.maps.explain import DatasetJob, dataset_keys
from openpi_cam.vocabulary import ExplainOptions

# The demo datasets' client images, which the boxes of `extra/target_box` are given in.
DEMO_IMAGE_SIZE = 64
BUNDLED = ModelSpec()  # the bundled demo model (pi0-FAST)


def model_job(source: Path, out: Path, options: ExplainOptions, model: ModelSpec = BUNDLED, **kw: Any) -> DatasetJob:
    """A job over `source` with the observation keys the model's config (or LeRobot folder) maps, no overrides."""
    keys, nested = dataset_keys(model, {})
    return DatasetJob(source, out, model, options, keys, nested_keys=nested, **kw)


def pointing(maps: fmt.MapsDataset, camera: str) -> tuple[float, float]:
    """(share of frames whose gradient-norm peak on `camera` lies in the named block, chance of a random peak)."""
    boxes = maps.table(columns=["extra/target_box"]).to_pydict()["extra/target_box"]
    grid = maps.grid(camera)
    cells = [box_cells([round(v) for v in box], grid, DEMO_IMAGE_SIZE) for box in boxes]
    stack = maps.maps("gradnorm", camera)
    return (
        float(np.mean([pointing_hit(m, c) for m, c in zip(stack, cells, strict=True)])),
        float(np.mean([pointing_chance(c) for c in cells])),
    )


def truncated_video_copy(dst: Path) -> Path:
    """A writable copy of `demo_reach_v21_video` whose episode 2 base-camera video is cut to its first third."""
    source = writable_copy(LEROBOT_DIR / "demo_reach_v21_video", dst)
    broken = source / "videos/chunk-000/observation.images.base/episode_000002.mp4"
    broken.write_bytes(broken.read_bytes()[: broken.stat().st_size // 3])
    return source
