"""The bundled Meta-World robot ("demo_metaworld"): where its tiny pi0.5 ships, and its policy config.

It sits in the policies layer like `demo_reach`, so the server and the demo both find it without depending on each
other; the simulator, the expert and the task's prompts live in `openpi_cam.demo.metaworld_sim`. The client sends
what the reaching demo's robot sends (a fixed camera, a wrist camera, a state vector, a prompt) under the same keys.
"""

from __future__ import annotations

import dataclasses

from openpi_cam.policies.config import register_config
from openpi_cam.policies.demo_reach import ASSETS, DEMO_CONFIG, DEMO_PI05_CONFIG
from openpi_cam.policies.robot import GenericOutputs

ASSETS_METAWORLD = ASSETS.with_name("demo_metaworld")
ASSET_ID = "demo_metaworld"
STATE_DIM = 4  # hand x, y, z and the gripper's opening
ACTION_DIM = 4  # hand displacement x, y, z and grip effort
ACTION_HORIZON = 10

# The reaching demo's pi0.5 robot (the gripper camera as the left wrist, the right wrist a masked blank, the state in
# the prompt) with Meta-World's state and action sizes.
DEMO_METAWORLD_CONFIG = register_config(
    dataclasses.replace(
        DEMO_PI05_CONFIG,
        name="demo_metaworld_pi05",
        inputs=tuple(dataclasses.replace(t, state_dim=STATE_DIM) for t in DEMO_PI05_CONFIG.inputs),
        outputs=(GenericOutputs(action_dim=ACTION_DIM),),
        asset_id=ASSET_ID,
        action_horizon=ACTION_HORIZON,
    )
)


# The multi-task robot: the same cameras, state and actions at 96 px (the reach goal and the puck are a few pixels
# wide at 64), served by a tiny pi0.5 and a tiny pi0-FAST trained on six tasks (`demo.metaworld_sim.TRAINED_TASKS`).
MT_ASSET_ID = "demo_metaworld_mt"
MT_IMAGE_SIZE = 96
ASSETS_MT_PI05 = ASSETS.with_name("demo_metaworld_mt_pi05")
ASSETS_MT_PI0_FAST = ASSETS.with_name("demo_metaworld_mt_pi0_fast")
DEMO_METAWORLD_MT_PI05_CONFIG = register_config(
    dataclasses.replace(
        DEMO_METAWORLD_CONFIG,
        name="demo_metaworld_mt_pi05",
        asset_id=MT_ASSET_ID,
        max_token_len=64,  # the longest prompt with a discretised state is 50 tokens
    )
)
# pi0-FAST's chunk of 10 four-dimensional actions is about 40 FAST ids behind `Action: `, so it decodes more than the
# reaching demo's 32 steps (the budget covers the longest training postfix with a margin).
DEMO_METAWORLD_MT_PI0_FAST_CONFIG = register_config(
    dataclasses.replace(
        DEMO_CONFIG,
        name="demo_metaworld_mt_pi0_fast",
        inputs=tuple(dataclasses.replace(t, state_dim=STATE_DIM) for t in DEMO_CONFIG.inputs),
        outputs=(GenericOutputs(action_dim=ACTION_DIM),),
        asset_id=MT_ASSET_ID,
        action_dim=ACTION_DIM,
        action_horizon=ACTION_HORIZON,
        max_token_len=128,
        max_decoding_steps=64,
    )
)
