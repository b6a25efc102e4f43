"""Occlusion heads with known answers, for the tests that carry the `occlusion-head` kind through a path (serving,
replays, faithfulness) without fitting one: a linear head whose map is its input's map, normalised."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from openpi_cam.checkpoints.model_spec import ModelSpec
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
