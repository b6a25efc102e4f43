"""The bundled Meta-World robot ("demo_metaworld"): where its tiny pi0.5 ships, and its policy config.

It sits in the policies layer like `demo_reach`, so the server and the demo both find it without depending on each
other; the simulator, the expert and the task's prompts live in `openpi_cam.demo.metaworld_sim`. The client sends
what the reaching demo's robot sends (a fixed camera, a wrist camera, a state vector, a prompt) under the same keys.
"""

from __future__ import annotations

from openpi_cam.policies.config import PolicyConfig, register_config
from openpi_cam.policies.demo_reach import ASSETS, IMAGE_KEY, LEROBOT_KEYS, STATE_KEY, WRIST_KEY
from openpi_cam.policies.robot import GenericInputs, GenericOutputs

ASSETS_METAWORLD = ASSETS.with_name("demo_metaworld")
ASSET_ID = "demo_metaworld"
STATE_DIM = 4  # hand x, y, z and the gripper's opening
ACTION_DIM = 4  # hand displacement x, y, z and grip effort
ACTION_HORIZON = 10

# pi0.5 reads upstream's three cameras: the gripper camera is the left wrist, the right wrist a masked blank.
DEMO_METAWORLD_CONFIG = register_config(
    PolicyConfig(
        name="demo_metaworld_pi05",
        family="pi05",
        inputs=(
            GenericInputs(
                cameras={"base_0_rgb": IMAGE_KEY, "left_wrist_0_rgb": WRIST_KEY, "right_wrist_0_rgb": None},
                state_key=STATE_KEY,
                state_dim=STATE_DIM,
                mask_blank=True,
            ),
        ),
        outputs=(GenericOutputs(action_dim=ACTION_DIM),),
        asset_id=ASSET_ID,
        action_dim=32,
        action_horizon=ACTION_HORIZON,
        max_token_len=48,
        discrete_state_input=True,
        lerobot_keys=LEROBOT_KEYS,
    )
)
