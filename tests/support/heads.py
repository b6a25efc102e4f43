"""Occlusion heads with known answers, for the tests that carry the `occlusion-head` kind through a path (serving,
replays, faithfulness) without fitting one: a linear head whose map is its input's map, normalised; and a small maps
dataset to fit one on without explaining anything."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.maps import dataset as fmt
from openpi_cam.model.occlusion_head import OcclusionHead, save
from openpi_cam.vocabulary import HeadRef


def planted_head(path: Path, spec: ModelSpec, target: str, kind: str = "gradnorm") -> HeadRef:
    """A head for `spec`'s model and `target` whose map is `kind`'s map divided by its largest |value| (weight 1 on
    it, no bias), saved at `path` and checked against the model as a command checks it."""
    facts = spec.facts()
    cameras = tuple(facts.camera_sources)
    head = OcclusionHead(
        inputs=(kind,),
        cameras=cameras,
        grid=facts.grid,
        target=target,
        family=facts.family,
        w1=None,
        b1=None,
        w2=np.eye(1 + len(cameras))[0],
        b2=0.0,
        position_bias=np.zeros((len(cameras), facts.grid[0] * facts.grid[1])),
        model=spec.resolved().to_json(),
    )
    save(head, path)
    return spec.occlusion_head(path)


def random_maps(root: Path, episodes: int = 8, frames: int = 3, seed: int = 0) -> Path:
    """A maps dataset in the real format, of random `gradnorm` and `lrp` maps on two 4 x 4 cameras and `occlusion`
    close to `lrp`: what `head fit` reads, made without a model."""
    cameras, grid = ("base_0_rgb", "wrist_0_rgb"), (4, 4)
    info = fmt.MapsInfo(
        source="synthetic",
        source_version="v3.0",
        source_fps=10.0,
        model={"config": "demo_reach"},
        family="pi0_fast",
        target="action-token",
        kinds=["gradnorm", "lrp", "occlusion"],
        grids={c: list(grid) for c in cameras},
        camera_sources={c: c for c in cameras},
        keys={},
        options={},
    )
    fmt.write_json(root / fmt.INFO_JSON, info.to_json())
    rng = np.random.default_rng(seed)
    for e in range(episodes):
        rows = []
        for f in range(frames):
            row = {"index": e * frames + f, "episode_index": e, "frame_index": f}
            row[fmt.CAMERAS_COLUMN] = json.dumps({c: {"valid": True} for c in cameras})
            for camera in cameras:
                lrp = rng.normal(size=grid[0] * grid[1])
                maps = {
                    "gradnorm": np.abs(rng.normal(size=lrp.size)),
                    "lrp": lrp,
                    "occlusion": lrp + 0.1 * rng.normal(size=lrp.size),
                }
                for kind, m in maps.items():
                    row[fmt.map_column(kind, camera)] = m.astype(np.float32).tolist()
            rows.append(row)
        fmt.write_shard(root, info, e, rows)
    return root
