"""The bundled demo robot ("demo_reach"): where its model and tokenizers ship, and its policy config.

It sits in the policies layer like DROID or LIBERO, so that the server and the demo both find the bundled default
without depending on each other. The task itself (scenes, expert, simulator) lives in `openpi_cam.demo`.
"""

from __future__ import annotations

from pathlib import Path

from openpi_cam.policies.config import PolicyConfig, register_config
from openpi_cam.policies.robot import GenericInputs, GenericOutputs

ASSETS = Path(__file__).resolve().parents[1] / "assets" / "demo"
ASSETS_PI05 = ASSETS.with_name("demo_pi05")  # the same task learned by a tiny pi0.5 (`openpi-cam demo --model pi05`)
CHECKPOINT = ASSETS / "checkpoint"  # OpenPI layout: params/ and assets/<ASSET_ID>/norm_stats.json
PALIGEMMA_TOKENIZER = ASSETS / "paligemma_tokenizer.model"
FAST_TOKENIZER = ASSETS / "fast_tokenizer"

IMAGE_KEY = "observation/image"
WRIST_KEY = "observation/wrist_image"
STATE_KEY = "observation/state"

ASSET_ID = "demo_reach"
# The demo task as LeRobot records it (../shared/lerobot, `openpi-cam explain DATASET_DIR`).
LEROBOT_KEYS = {
    IMAGE_KEY: "observation.images.base",
    WRIST_KEY: "observation.images.wrist",
    STATE_KEY: "observation.state",
    "actions": "action",
}
LEROBOT_TARGET_BOX = "observation.target_box"  # the named block's box in the base camera (x0, y0, x1, y1), float32
ACTION_HORIZON = 10
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
        action_horizon=ACTION_HORIZON,
        max_token_len=56,  # the longest training sequence is 47 tokens
        lerobot_keys=LEROBOT_KEYS,
        max_decoding_steps=MAX_DECODING_STEPS,
    )
)


# The pi0.5 demo robot: pi0.5 reads the three upstream cameras, so the wrist view is the left wrist and the right
# wrist a masked blank; states and actions are padded to the model's 32 dims, the state also goes into the prompt.
DEMO_PI05_CONFIG = register_config(
    PolicyConfig(
        name="demo_reach_pi05",
        family="pi05",
        inputs=(
            GenericInputs(
                cameras={"base_0_rgb": IMAGE_KEY, "left_wrist_0_rgb": WRIST_KEY, "right_wrist_0_rgb": None},
                state_key=STATE_KEY,
                state_dim=2,
                mask_blank=True,
            ),
        ),
        outputs=(GenericOutputs(action_dim=2),),
        asset_id=ASSET_ID,
        action_dim=32,
        action_horizon=ACTION_HORIZON,
        max_token_len=48,
        discrete_state_input=True,
        lerobot_keys=LEROBOT_KEYS,
    )
)
DEMO_CONFIGS = {"pi0_fast": DEMO_CONFIG, "pi05": DEMO_PI05_CONFIG}
DEFAULT_ASSETS = {"pi0_fast": ASSETS, "pi05": ASSETS_PI05}
DEMO_MODELS = {config.name: model for model, config in DEMO_CONFIGS.items()}  # config name -> bundled model
