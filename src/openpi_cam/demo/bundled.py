"""The demo model's architecture and what the demo robot sends (its artefacts and policy config live in
`openpi_cam.policies.demo_reach`)."""

from __future__ import annotations

import dataclasses
from typing import Any, Protocol

import numpy as np

from openpi_cam.cam.records import split_extra
from openpi_cam.demo import task
from openpi_cam.demo.recorded import PERTURBATION_FEATURE
from openpi_cam.model.config import GemmaConfig, Pi0Config, Pi0FASTConfig, SiglipConfig, scan_by_default
from openpi_cam.policies.config import PolicyConfig
from openpi_cam.policies.demo_reach import (
    DEMO_CONFIG,
    DEMO_PI05_CONFIG,
    IMAGE_KEY,
    LEROBOT_KEYS,
    LEROBOT_TARGET_BOX,
    STATE_KEY,
    WRIST_KEY,
)
from openpi_cam.vocabulary import EXTRA_PREFIX

PATCH_SIZE = 16  # 64 px images -> a 4 x 4 map grid per camera


def model_config(
    vocab_size: int,
    *,
    width: int = 128,
    depth: int = 2,
    vit_width: int = 64,
    patch_size: int = PATCH_SIZE,
    scan: bool | None = None,
    image_size: int = task.TaskConfig().image_size,
    robot: PolicyConfig = DEMO_CONFIG,
) -> Pi0FASTConfig:
    """pi0-FAST's architecture scaled down, for the demo robot `robot` (its action sizes and prompt length) at
    `image_size` px. 16 px patches rather than 8: each block then covers a larger share of the
    image tokens (1-4 of 16), and colour binding is learned within the CPU budget (at 8 px it was not:
    docs/DEMO_NOTES.md).
    `scan` None: the layout a checkpoint of this depth is served with (`scan_by_default`)."""
    scan = scan_by_default(depth) if scan is None else scan
    gemma = GemmaConfig(
        width=width,
        depth=depth,
        mlp_dim=2 * width,
        num_heads=4,
        num_kv_heads=1,
        head_dim=32,
        vocab_size=vocab_size,
        scan=scan,
    )
    siglip = SiglipConfig(
        width=vit_width,
        depth=depth,
        mlp_dim=2 * vit_width,
        num_heads=2,
        patch_size=patch_size,
        image_size=image_size,
        out_dim=width,
        scan=scan,
    )
    return Pi0FASTConfig(
        gemma=gemma,
        siglip=siglip,
        action_dim=robot.action_dim,
        action_horizon=robot.action_horizon,
        max_token_len=robot.max_token_len,
        dtype="float32",
    )


def pi05_model_config(
    vocab_size: int,
    *,
    width: int = 128,
    depth: int = 2,
    vit_width: int = 64,
    patch_size: int = PATCH_SIZE,
    expert_width: int = 64,
    scan: bool | None = None,
    image_size: int = task.TaskConfig().image_size,
    robot: PolicyConfig = DEMO_PI05_CONFIG,
) -> Pi0Config:
    """pi0.5's architecture scaled down like `model_config`'s backbone, with an action expert half as wide (upstream's
    gemma_300m is half of gemma_2b's width; depth, heads and head dim must equal the LLM's)."""
    sizes = {"width": width, "depth": depth, "vit_width": vit_width, "patch_size": patch_size}
    fast = model_config(vocab_size, **sizes, scan=scan, image_size=image_size)
    expert = dataclasses.replace(fast.gemma, width=expert_width, mlp_dim=2 * expert_width, vocab_size=0)
    return Pi0Config(
        gemma=fast.gemma,
        expert=expert,
        siglip=fast.siglip,
        pi05=True,
        action_dim=robot.action_dim,
        action_horizon=robot.action_horizon,
        max_token_len=robot.max_token_len,
        dtype="float32",
    )


class Observed(Protocol):
    """What a demo robot observes at a step: a reaching-task `task.Sample` or a Meta-World `metaworld_sim.Frame`."""

    base_image: np.ndarray  # [S, S, 3] uint8
    wrist_image: np.ndarray  # [S, S, 3] uint8
    state: np.ndarray  # float32
    prompt: str
    target_box: tuple[int, int, int, int]  # the target in the base camera (x0, y0, x1, y1)


def client_observation(sample: Observed, scene: task.Scene | None = None) -> dict[str, Any]:
    """What a demo robot sends; the `cam_extra/` entries are ground truth for judging the maps (the reaching task's
    `scene` adds every block's box and colour)."""
    obs: dict[str, Any] = {
        IMAGE_KEY: sample.base_image,
        WRIST_KEY: sample.wrist_image,
        STATE_KEY: sample.state.astype(np.float64),
        "prompt": sample.prompt,
        EXTRA_PREFIX + "target_box": np.asarray(sample.target_box, np.int32),
    }
    if scene is not None:
        obs[EXTRA_PREFIX + "block_boxes"] = np.asarray([b.box for b in scene.blocks], np.int32)
        obs[EXTRA_PREFIX + "block_colors"] = [b.color for b in scene.blocks]
    return obs


def recorded_frame(sample: Observed, action: np.ndarray, perturbation: int = 0) -> dict[str, np.ndarray]:
    """A recorded step by LeRobot feature name (`demo_reach.LEROBOT_KEYS`, which both demos' datasets use): the
    cameras, the state, the executed action, the target's box as the base camera shows it and the index of the
    episode's perturbation."""
    return {
        LEROBOT_KEYS[IMAGE_KEY]: sample.base_image,
        LEROBOT_KEYS[WRIST_KEY]: sample.wrist_image,
        LEROBOT_KEYS[STATE_KEY]: np.asarray(sample.state, np.float32),
        LEROBOT_KEYS["actions"]: np.asarray(action, np.float32),
        LEROBOT_TARGET_BOX: np.asarray(sample.target_box, np.float32),
        PERTURBATION_FEATURE: np.array([perturbation], np.int64),
    }


def policy_input(obs: dict[str, Any]) -> dict[str, Any]:
    return split_extra(obs)[0]
