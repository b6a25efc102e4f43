"""DROID pipeline for pi0-FAST (upstream `DroidInputs(PI0_FAST)` / `DroidOutputs`)."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

from openpi_cam.policies.robot import FixedCameraSources, pass_prompt
from openpi_cam.transforms import DataDict, parse_image, parse_vector, require

EXTERIOR_IMAGE_KEY = "observation/exterior_image_1_left"
WRIST_IMAGE_KEY = "observation/wrist_image_left"
JOINT_POSITION_KEY = "observation/joint_position"
GRIPPER_POSITION_KEY = "observation/gripper_position"
JOINT_DIM = 7
ACTION_DIM = 8  # 7 joint velocities + gripper

# pi0-FAST's DROID camera layout: the second exterior slot is a blank image (unmasked for FAST models).
CAMERA_SOURCES: Mapping[str, str | None] = {
    "base_0_rgb": EXTERIOR_IMAGE_KEY,
    "base_1_rgb": None,
    "wrist_0_rgb": WRIST_IMAGE_KEY,
}


@dataclasses.dataclass(frozen=True)
class DroidInputs(FixedCameraSources):
    CAMERA_SOURCES = CAMERA_SOURCES

    def __call__(self, data: DataDict) -> DataDict:
        joints = parse_vector(require(data, JOINT_POSITION_KEY), JOINT_POSITION_KEY, dim=JOINT_DIM)
        # Upstream accepts the gripper position as a scalar or a length-1 vector.
        gripper = parse_vector(require(data, GRIPPER_POSITION_KEY), GRIPPER_POSITION_KEY, dim=1, allow_scalar=True)
        state = np.concatenate([joints, gripper])
        base = parse_image(require(data, EXTERIOR_IMAGE_KEY), EXTERIOR_IMAGE_KEY)
        wrist = parse_image(require(data, WRIST_IMAGE_KEY), WRIST_IMAGE_KEY)
        inputs: DataDict = {
            "state": state,
            "image": {"base_0_rgb": base, "base_1_rgb": np.zeros_like(base), "wrist_0_rgb": wrist},
            "image_mask": {"base_0_rgb": np.True_, "base_1_rgb": np.True_, "wrist_0_rgb": np.True_},
        }
        if "actions" in data:
            inputs["actions"] = np.asarray(data["actions"])
        return pass_prompt(data, inputs)


@dataclasses.dataclass(frozen=True)
class DroidOutputs:
    def __call__(self, data: DataDict) -> DataDict:
        return {"actions": np.asarray(data["actions"][..., :ACTION_DIM])}
