"""DROID pipeline (upstream `DroidInputs(model_type)` / `DroidOutputs`).

The camera layout follows the model family, as upstream's: pi0-FAST sees (base_0_rgb, a blank base_1_rgb, wrist_0_rgb)
with every mask True; pi0 / pi0.5 see (base_0_rgb, left_wrist_0_rgb, a blank right_wrist_0_rgb) with the blank one
masked."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import numpy as np

from openpi_cam.policies.robot import Family, pass_prompt
from openpi_cam.transforms import DataDict, parse_image, parse_vector, require

EXTERIOR_IMAGE_KEY = "observation/exterior_image_1_left"
WRIST_IMAGE_KEY = "observation/wrist_image_left"
JOINT_POSITION_KEY = "observation/joint_position"
GRIPPER_POSITION_KEY = "observation/gripper_position"
JOINT_DIM = 7
ACTION_DIM = 8  # 7 joint velocities + gripper

CAMERA_SOURCES: Mapping[str, Mapping[str, str | None]] = {
    "pi0_fast": {"base_0_rgb": EXTERIOR_IMAGE_KEY, "base_1_rgb": None, "wrist_0_rgb": WRIST_IMAGE_KEY},
    "pi0": {"base_0_rgb": EXTERIOR_IMAGE_KEY, "left_wrist_0_rgb": WRIST_IMAGE_KEY, "right_wrist_0_rgb": None},
}


@dataclasses.dataclass(frozen=True)
class DroidInputs:
    family: Family = "pi0_fast"

    @property
    def camera_sources(self) -> Mapping[str, str | None]:
        return dict(CAMERA_SOURCES["pi0_fast" if self.family == "pi0_fast" else "pi0"])

    def camera_sources_for(self, obs: Mapping[str, object]) -> dict[str, str | None]:
        return dict(self.camera_sources)

    def example(self) -> dict[str, object]:
        return make_droid_example()

    def __call__(self, data: DataDict) -> DataDict:
        joints = parse_vector(require(data, JOINT_POSITION_KEY), JOINT_POSITION_KEY, dim=JOINT_DIM)
        # Upstream accepts the gripper position as a scalar or a length-1 vector.
        gripper = parse_vector(require(data, GRIPPER_POSITION_KEY), GRIPPER_POSITION_KEY, dim=1, allow_scalar=True)
        state = np.concatenate([joints, gripper])
        base = parse_image(require(data, EXTERIOR_IMAGE_KEY), EXTERIOR_IMAGE_KEY)
        wrist = parse_image(require(data, WRIST_IMAGE_KEY), WRIST_IMAGE_KEY)
        sources = {EXTERIOR_IMAGE_KEY: base, WRIST_IMAGE_KEY: wrist}
        layout = self.camera_sources
        inputs: DataDict = {
            "state": state,
            "image": {c: np.zeros_like(base) if k is None else sources[k] for c, k in layout.items()},
            # pi0-FAST does not mask the blank camera; pi0 / pi0.5 do.
            "image_mask": {c: np.bool_(k is not None or self.family == "pi0_fast") for c, k in layout.items()},
        }
        if "actions" in data:
            inputs["actions"] = np.asarray(data["actions"])
        return pass_prompt(data, inputs)


@dataclasses.dataclass(frozen=True)
class DroidOutputs:
    def __call__(self, data: DataDict) -> DataDict:
        return {"actions": np.asarray(data["actions"][..., :ACTION_DIM])}


def make_droid_example(height: int = 180, width: int = 320, seed: int = 0) -> dict[str, object]:
    """A random observation shaped like what upstream's DROID client sends (its cameras' 180 x 320 frames)."""
    rng = np.random.default_rng(seed)
    return {
        EXTERIOR_IMAGE_KEY: rng.integers(256, size=(height, width, 3), dtype=np.uint8),
        WRIST_IMAGE_KEY: rng.integers(256, size=(height, width, 3), dtype=np.uint8),
        JOINT_POSITION_KEY: rng.random(JOINT_DIM),
        GRIPPER_POSITION_KEY: rng.random(1),
        "prompt": "do something",
    }
