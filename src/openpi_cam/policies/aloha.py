"""ALOHA (bimanual) pipeline (upstream `AlohaInputs` / `AlohaOutputs`, with the joint/gripper conversion to the
space pi0 was pretrained in when ``adapt_to_pi``).

Unlike DROID and LIBERO, upstream's ALOHA inputs mask absent wrist cameras even for FAST models; we keep that.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from openpi_cam.errors import InvalidRequest
from openpi_cam.policies.robot import pass_prompt
from openpi_cam.transforms import DataDict, make_bool_mask, parse_image, parse_vector, require

STATE_KEY = "state"
IMAGES_KEY = "images"
STATE_DIM = 14  # per arm: 6 joints + gripper
ACTION_DIM = 14
GRIPPER_DIMS = [6, 13]
CLIENT_CAMERAS = ("cam_high", "cam_low", "cam_left_wrist", "cam_right_wrist")
# cam_low is accepted (upstream allows it) but no model camera reads it.
CAMERA_SOURCES: Mapping[str, str | None] = {
    "base_0_rgb": "images/cam_high",
    "left_wrist_0_rgb": "images/cam_left_wrist",
    "right_wrist_0_rgb": "images/cam_right_wrist",
}
# Joints are actions relative to the current state; grippers stay absolute.
DELTA_ACTION_MASK = make_bool_mask(6, -1, 6, -1)
RESET_POSE = (0, -1.5, 1.5, 0, 0, 0)

# Sign flips between the ALOHA and pi joint conventions.
_JOINT_FLIP = np.array([1, -1, -1, 1, 1, 1, 1, 1, -1, -1, 1, 1, 1, 1])
# Interbotix puppet gripper: linear position range, linkage geometry, and the joint range in radians.
_GRIPPER_LINEAR_RANGE = (0.01844, 0.05800)
_GRIPPER_ARM_LENGTH, _GRIPPER_HORN_RADIUS = 0.036, 0.022
_GRIPPER_JOINT_RANGE = (-0.6213, 1.4910)
# pi0's gripper normalisation: encoder counts (2405, 3110) of 4096 around 2048, expressed in radians.
_PI_GRIPPER_RANGE = (0.5476, 1.6296)


def _to_unit(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return (x - lo) / (hi - lo)


def _from_unit(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return x * (hi - lo) + lo


def gripper_to_angular(value: np.ndarray) -> np.ndarray:
    """ALOHA's normalised linear gripper position -> pi0's normalised angular gripper position."""
    linear = _from_unit(value, *_GRIPPER_LINEAR_RANGE)
    # Invert the linkage's angle -> linear-travel relation (law of cosines).
    cos_like = (_GRIPPER_HORN_RADIUS**2 + linear**2 - _GRIPPER_ARM_LENGTH**2) / (2 * _GRIPPER_HORN_RADIUS * linear)
    radians = np.arcsin(np.clip(cos_like, -1.0, 1.0))
    return _to_unit(radians, *_PI_GRIPPER_RANGE)


def gripper_from_angular(value: np.ndarray) -> np.ndarray:
    """pi0's gripper output -> ALOHA's normalised gripper joint command (no rescaling: the model works in radians)."""
    return _to_unit(value + _PI_GRIPPER_RANGE[0], *_GRIPPER_JOINT_RANGE)


def gripper_from_angular_inv(value: np.ndarray) -> np.ndarray:
    return _from_unit(value, *_GRIPPER_JOINT_RANGE) - _PI_GRIPPER_RANGE[0]


def decode_state(state: np.ndarray, *, adapt_to_pi: bool) -> np.ndarray:
    if not adapt_to_pi:
        return state
    state = _JOINT_FLIP * state
    state[GRIPPER_DIMS] = gripper_to_angular(state[GRIPPER_DIMS])
    return state


def encode_actions(actions: np.ndarray, *, adapt_to_pi: bool) -> np.ndarray:
    if not adapt_to_pi:
        return actions
    actions = _JOINT_FLIP * actions
    actions[:, GRIPPER_DIMS] = gripper_from_angular(actions[:, GRIPPER_DIMS])
    return actions


def encode_actions_inv(actions: np.ndarray, *, adapt_to_pi: bool) -> np.ndarray:
    if not adapt_to_pi:
        return actions
    actions = _JOINT_FLIP * actions
    actions[:, GRIPPER_DIMS] = gripper_from_angular_inv(actions[:, GRIPPER_DIMS])
    return actions


def _client_images(data: Mapping[str, Any]) -> Mapping[str, Any]:
    images = require(data, IMAGES_KEY)
    if not isinstance(images, Mapping):
        raise InvalidRequest(f"'{IMAGES_KEY}': expected a dict of camera name -> image, got {type(images).__name__}")
    unknown = sorted(set(map(str, images)) - set(CLIENT_CAMERAS))
    if unknown:
        raise InvalidRequest(f"'{IMAGES_KEY}': unknown cameras {unknown}; expected a subset of {list(CLIENT_CAMERAS)}")
    if images.get("cam_high") is None:
        raise InvalidRequest(f"missing observation key '{IMAGES_KEY}/cam_high' (the base camera is required)")
    return images


@dataclasses.dataclass(frozen=True)
class AlohaInputs:
    adapt_to_pi: bool = True

    @property
    def camera_sources(self) -> Mapping[str, str | None]:
        return dict(CAMERA_SOURCES)

    def camera_sources_for(self, obs: Mapping[str, Any]) -> dict[str, str | None]:
        images = obs.get(IMAGES_KEY)
        present = {k for k, v in images.items() if v is not None} if isinstance(images, Mapping) else set()
        return {name: key if key.split("/", 1)[1] in present else None for name, key in CAMERA_SOURCES.items()}

    def example(self) -> dict[str, Any]:
        return make_aloha_example()

    def __call__(self, data: DataDict) -> DataDict:
        state = parse_vector(require(data, STATE_KEY), STATE_KEY, dim=STATE_DIM)
        state = decode_state(state, adapt_to_pi=self.adapt_to_pi)
        # ALOHA clients always send channel-first images.
        client_images = {
            name: parse_image(img, f"{IMAGES_KEY}/{name}", channels_first=True)
            for name, img in _client_images(data).items()
            if img is not None
        }
        base = client_images["cam_high"]
        images, masks = {}, {}
        for name, key in CAMERA_SOURCES.items():
            source = key.split("/", 1)[1]
            images[name] = client_images.get(source, np.zeros_like(base))
            masks[name] = np.True_ if source in client_images else np.False_
        inputs: DataDict = {"image": images, "image_mask": masks, "state": state}
        if "actions" in data:
            inputs["actions"] = encode_actions_inv(np.asarray(data["actions"]), adapt_to_pi=self.adapt_to_pi)
        return pass_prompt(data, inputs)


@dataclasses.dataclass(frozen=True)
class AlohaOutputs:
    adapt_to_pi: bool = True

    def __call__(self, data: DataDict) -> DataDict:
        actions = np.asarray(data["actions"][:, :ACTION_DIM])
        return {"actions": encode_actions(actions, adapt_to_pi=self.adapt_to_pi)}


def make_aloha_example(height: int = 224, width: int = 224, seed: int = 0) -> dict[str, Any]:
    """A random observation shaped like what upstream's ALOHA client sends (channel-first images)."""
    rng = np.random.default_rng(seed)
    return {
        STATE_KEY: np.ones((STATE_DIM,)),
        IMAGES_KEY: {name: rng.integers(256, size=(3, height, width), dtype=np.uint8) for name in CLIENT_CAMERAS},
        "prompt": "do something",
    }
