"""Argument forms shared by several subcommands."""

from __future__ import annotations

import dataclasses

from openpi_cam.vocabulary import MapOptions


def parse_action_index(text: str) -> tuple[int, int]:
    """`--cam-action-index`: "I" (pi0-FAST: the I-th action token; pi0 / pi0.5: horizon step I, dimension 0) or "H,D"
    (pi0 / pi0.5: dimension D at horizon step H) -> (index, dimension)."""
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) not in (1, 2) or not all(p.isdigit() for p in parts):
        raise ValueError(f"action index must be 'I' or 'H,D' with non-negative integers, got {text!r}")
    return int(parts[0]), int(parts[1]) if len(parts) == 2 else 0


def map_options(
    baseline: str, occlusion_region: int, occlusion_masks: int, ig_space: str = MapOptions.ig_space
) -> MapOptions:
    """The `ig` / `occlusion` options of the command-line flags: `occlusion_masks` 0 paints every region once,
    M > 0 draws M random region masks per camera (Interventional Significance Score)."""
    if occlusion_masks < 0:
        raise ValueError(f"--occlusion-masks must be >= 0, got {occlusion_masks}")
    options = MapOptions(baseline=baseline, occlusion_region=occlusion_region, ig_space=ig_space)
    if occlusion_masks:
        return dataclasses.replace(options, occlusion_mode="random", random_masks=occlusion_masks)
    return options
