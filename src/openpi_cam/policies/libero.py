"""LIBERO pipeline (upstream `LiberoInputs(model_type)` / `LiberoOutputs`): the blank right-wrist camera is masked for
pi0 / pi0.5 and not for pi0-FAST, as upstream."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from openpi_cam.policies.robot import Family, FixedCameraSources, pass_prompt
from openpi_cam.transforms import DataDict, parse_image, parse_vector, require

IMAGE_KEY = "observation/image"
WRIST_IMAGE_KEY = "observation/wrist_image"
STATE_KEY = "observation/state"
STATE_DIM = 8  # end-effector position (3) + axis-angle (3) + gripper joints (2), what the LIBERO client sends
ACTION_DIM = 7

# The right-wrist slot is a blank image.
CAMERA_SOURCES: Mapping[str, str | None] = {
    "base_0_rgb": IMAGE_KEY,
    "left_wrist_0_rgb": WRIST_IMAGE_KEY,
    "right_wrist_0_rgb": None,
}


@dataclasses.dataclass(frozen=True)
class LiberoInputs(FixedCameraSources):
    CAMERA_SOURCES = CAMERA_SOURCES
    family: Family = "pi0_fast"

    def example(self) -> dict[str, Any]:
        return make_libero_example()

    def __call__(self, data: DataDict) -> DataDict:
        base = parse_image(require(data, IMAGE_KEY), IMAGE_KEY)
        wrist = parse_image(require(data, WRIST_IMAGE_KEY), WRIST_IMAGE_KEY)
        inputs: DataDict = {
            "state": parse_vector(require(data, STATE_KEY), STATE_KEY, dim=STATE_DIM),
            "image": {"base_0_rgb": base, "left_wrist_0_rgb": wrist, "right_wrist_0_rgb": np.zeros_like(base)},
            "image_mask": {
                "base_0_rgb": np.True_,
                "left_wrist_0_rgb": np.True_,
                "right_wrist_0_rgb": np.bool_(self.family == "pi0_fast"),
            },
        }
        if "actions" in data:
            inputs["actions"] = data["actions"]
        return pass_prompt(data, inputs)


@dataclasses.dataclass(frozen=True)
class LiberoOutputs:
    def __call__(self, data: DataDict) -> DataDict:
        return {"actions": np.asarray(data["actions"][..., :ACTION_DIM])}


def make_libero_example(height: int = 224, width: int = 224, seed: int = 0) -> dict[str, Any]:
    """A random observation shaped like what upstream's LIBERO client sends."""
    rng = np.random.default_rng(seed)
    return {
        STATE_KEY: rng.random(STATE_DIM),
        IMAGE_KEY: rng.integers(256, size=(height, width, 3), dtype=np.uint8),
        WRIST_IMAGE_KEY: rng.integers(256, size=(height, width, 3), dtype=np.uint8),
        "prompt": "do something",
    }
