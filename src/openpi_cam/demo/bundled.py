"""The bundled demo model: artefact locations, its robot's policy config, and the client-side observation format."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from openpi_cam.cam.records import EXTRA_PREFIX, split_extra
from openpi_cam.demo import task
from openpi_cam.model.config import GemmaConfig, Pi0FASTConfig, SiglipConfig, scan_by_default
from openpi_cam.policies.config import PolicyConfig, register_config
from openpi_cam.policies.robot import GenericInputs, GenericOutputs

ASSETS = Path(__file__).resolve().parents[1] / "assets" / "demo"
CHECKPOINT = ASSETS / "checkpoint"  # OpenPI layout: params/ and assets/<ASSET_ID>/norm_stats.json
PALIGEMMA_TOKENIZER = ASSETS / "paligemma_tokenizer.model"
FAST_TOKENIZER = ASSETS / "fast_tokenizer"

IMAGE_KEY = "observation/image"
WRIST_KEY = "observation/wrist_image"
STATE_KEY = "observation/state"

ASSET_ID = "demo_reach"
PATCH_SIZE = 16  # 64 px images -> a 4 x 4 Grad-CAM grid per camera
# An expert postfix is 27 tokens (`Action: ` in 5, 20 FAST ids, `|`, EOS); a short cap keeps a broken model cheap.
MAX_DECODING_STEPS = 32

DEMO_CONFIG = register_config(
    PolicyConfig(
        name="demo_reach",
        inputs=(
            GenericInputs(
                cameras={"base_0_rgb": IMAGE_KEY, "wrist_0_rgb": WRIST_KEY}, state_key=STATE_KEY, state_dim=2
            ),
        ),
        outputs=(GenericOutputs(action_dim=2),),
        asset_id=ASSET_ID,
        action_dim=2,
        action_horizon=task.TaskConfig().action_horizon,
        max_token_len=56,  # the longest training sequence is 47 tokens
    )
)


def model_config(
    vocab_size: int,
    *,
    width: int = 128,
    depth: int = 2,
    vit_width: int = 64,
    patch_size: int = PATCH_SIZE,
    scan: bool | None = None,
) -> Pi0FASTConfig:
    """pi0-FAST's architecture scaled down. 16 px patches rather than 8: each block then covers a larger share of the
    image tokens (1-4 of 16), and colour binding is learned within the CPU budget (8 px patches: no binding seen).
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
        image_size=task.TaskConfig().image_size,
        out_dim=width,
        scan=scan,
    )
    cfg = DEMO_CONFIG
    return Pi0FASTConfig(
        gemma=gemma,
        siglip=siglip,
        action_dim=cfg.action_dim,
        action_horizon=cfg.action_horizon,
        max_token_len=cfg.max_token_len,
        dtype="float32",
    )


def create_demo_policy(*, assets: Path = ASSETS, dtype: str = "float32", **kwargs: Any):
    """The bundled model served through the same `create_policy` as any OpenPI checkpoint."""
    from openpi_cam.policies.policy import create_policy

    return create_policy(
        DEMO_CONFIG,
        assets / CHECKPOINT.name,
        paligemma_tokenizer=assets / PALIGEMMA_TOKENIZER.name,
        fast_tokenizer=assets / FAST_TOKENIZER.name,
        dtype=dtype,
        max_decoding_steps=MAX_DECODING_STEPS,
        **kwargs,
    )


def client_observation(sample: task.Sample, scene: task.Scene | None = None) -> dict[str, Any]:
    """What the demo robot sends; the `cam_extra/` entries are ground truth for judging the maps."""
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


def policy_input(obs: dict[str, Any]) -> dict[str, Any]:
    return split_extra(obs)[0]
