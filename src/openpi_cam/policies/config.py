"""Named policy configs (what upstream's `TrainConfig` contributes at inference) and a registry for custom ones.

A `PolicyConfig` fixes the robot pipeline, the action shape the FAST decoder must produce, the prompt length, the
asset id of the normalisation stats and an optional default prompt. The model architecture (and with it the image
resolution) comes from the checkpoint, not from here.

Declaring a custom robot::

    from openpi_cam.policies import GenericInputs, GenericOutputs, PolicyConfig, register_config

    register_config(
        PolicyConfig(
            name="my_robot",
            inputs=(GenericInputs(cameras={"base_0_rgb": "observation/image", "wrist_0_rgb": None},
                                  state_key="observation/state", state_dim=4),),
            outputs=(GenericOutputs(action_dim=2),),
            asset_id="my_robot",
            action_dim=2,
            action_horizon=8,
            max_token_len=64,
            default_prompt="reach the target",
        )
    )

after which ``create_policy("my_robot", checkpoint_dir)`` (and the CLI's ``--config my_robot``) can use it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import openpi_cam.policies.aloha as aloha
import openpi_cam.policies.droid as droid
import openpi_cam.policies.libero as libero
from openpi_cam.policies.robot import Family, RobotInputs
from openpi_cam.transforms import AbsoluteActions, DeltaActions, Transform, make_bool_mask


@dataclasses.dataclass(frozen=True)
class PolicyConfig:
    name: str
    # Which model family the checkpoint must be: "pi0_fast", "pi0" or "pi05" (checked when the policy loads).
    # Robot transforms (upstream's `data_transforms`): the first `RobotInputs` among `inputs` names the cameras.
    inputs: tuple[Transform, ...]
    outputs: tuple[Transform, ...]
    # Norm stats are read from `<checkpoint>/assets/<asset_id>/norm_stats.json`.
    asset_id: str
    action_dim: int
    action_horizon: int
    max_token_len: int
    # Injected after normalisation when the request has no prompt (upstream's model-transform default prompt).
    default_prompt: str | None = None
    # Upstream uses quantile normalisation for every model type except pi0.
    use_quantile_norm: bool = True
    # Returned to clients as the policy's metadata (upstream's `policy_metadata`).
    policy_metadata: Mapping[str, Any] | None = None
    family: Family = "pi0_fast"
    # pi0.5 only: the normalised state goes into the prompt as text (upstream `discrete_state_input`, default True for
    # pi0.5; `pi05_libero` turns it off).
    discrete_state_input: bool = False
    # How a LeRobot dataset of this robot feeds the policy (upstream's `RepackTransform` of its training config):
    # observation key -> dataset feature. `openpi-cam explain DATASET_DIR` uses it; `--keys` overrides it.
    lerobot_keys: Mapping[str, str] | None = None
    # Whether observation keys `a/b` are nested dicts (ALOHA's `images/cam_high`) rather than flat keys.
    lerobot_nested: bool = False
    # pi0-FAST: the decoding budget in tokens (upstream's `max_decoding_steps`; a bundled tiny model's chunk needs far
    # fewer, and a short budget keeps a broken model cheap). None: upstream's 256.
    max_decoding_steps: int | None = None

    def __post_init__(self) -> None:
        for field in ("action_dim", "action_horizon", "max_token_len"):
            if int(getattr(self, field)) < 1:
                raise ValueError(f"PolicyConfig {self.name!r}: {field} must be positive")
        if not self.name:
            raise ValueError("PolicyConfig needs a name")
        if not self.asset_id:
            raise ValueError(f"PolicyConfig {self.name!r}: asset_id is empty")
        if self.family not in ("pi0_fast", "pi0", "pi05"):
            raise ValueError(f"PolicyConfig {self.name!r}: unknown family {self.family!r}")
        if self.max_decoding_steps is not None and self.max_decoding_steps < 1:
            raise ValueError(f"PolicyConfig {self.name!r}: max_decoding_steps must be positive")
        if self.discrete_state_input and self.family != "pi05":
            raise ValueError(f"PolicyConfig {self.name!r}: only pi0.5 reads the state as prompt text")
        self.robot_inputs  # noqa: B018  (fail at declaration, not at first request)

    @property
    def robot_inputs(self) -> RobotInputs:
        for transform in self.inputs:
            if isinstance(transform, RobotInputs):
                return transform
        raise ValueError(f"PolicyConfig {self.name!r}: no input transform provides camera_sources")

    @property
    def camera_sources(self) -> Mapping[str, str | None]:
        """Model camera -> client observation key (None: a synthesised blank camera)."""
        return self.robot_inputs.camera_sources


# The LeRobot feature names of upstream's LIBERO and ALOHA training data (the `RepackTransform` of their configs);
# `actions` names the recorded actions, which `--target dataset-actions` explains.
LIBERO_LEROBOT_KEYS = {
    "observation/image": "image",
    "observation/wrist_image": "wrist_image",
    "observation/state": "state",
    "actions": "actions",
}
ALOHA_LEROBOT_KEYS = {"images/cam_high": "observation.images.top", "state": "observation.state", "actions": "action"}
_LIBERO_DATA = {"lerobot_keys": LIBERO_LEROBOT_KEYS}
_ALOHA_DATA = {"lerobot_keys": ALOHA_LEROBOT_KEYS, "lerobot_nested": True}


PI0_FAST_DROID = PolicyConfig(
    name="pi0_fast_droid",
    inputs=(droid.DroidInputs(),),
    outputs=(droid.DroidOutputs(),),
    asset_id="droid",
    action_dim=8,
    action_horizon=10,
    max_token_len=250,
)

# Upstream trains pi0_fast_libero with `extra_delta_transform=True`: the first 6 action dims are deltas w.r.t. the
# state, so at inference the state is added back before the actions are returned.
_LIBERO_DELTA_MASK = make_bool_mask(6, -1)
PI0_FAST_LIBERO = PolicyConfig(
    name="pi0_fast_libero",
    inputs=(libero.LiberoInputs(), DeltaActions(_LIBERO_DELTA_MASK)),
    outputs=(AbsoluteActions(_LIBERO_DELTA_MASK), libero.LiberoOutputs()),
    asset_id="physical-intelligence/libero",
    action_dim=7,
    action_horizon=10,
    max_token_len=180,
    **_LIBERO_DATA,
)

# Upstream (15a9616) has no pi0-FAST ALOHA config. This one combines upstream's `pi0_aloha` data pipeline (trossen
# stats, adapt_to_pi, delta joint actions, reset pose) with `Pi0FASTConfig`'s defaults (the pi0_fast_base values).
PI0_FAST_ALOHA = PolicyConfig(
    name="pi0_fast_aloha",
    inputs=(aloha.AlohaInputs(adapt_to_pi=True), DeltaActions(aloha.DELTA_ACTION_MASK)),
    outputs=(AbsoluteActions(aloha.DELTA_ACTION_MASK), aloha.AlohaOutputs(adapt_to_pi=True)),
    asset_id="trossen",
    action_dim=32,
    action_horizon=32,
    max_token_len=250,
    policy_metadata={"reset_pose": list(aloha.RESET_POSE)},
    **_ALOHA_DATA,
)

# pi0 and pi0.5 (upstream's `Pi0Config`): the model's action dim is 32 (states and actions are zero-padded to it), the
# horizon and prompt length follow upstream's train configs; pi0 normalises with mean/std, the others with quantiles.
_PI0 = {"family": "pi0", "action_dim": 32, "max_token_len": 48, "use_quantile_norm": False}
_PI05 = {"family": "pi05", "action_dim": 32, "max_token_len": 200, "use_quantile_norm": True}
PI0_DROID = PolicyConfig(
    name="pi0_droid",
    inputs=(droid.DroidInputs("pi0"),),
    outputs=(droid.DroidOutputs(),),
    asset_id="droid",
    action_horizon=10,
    **_PI0,
)
PI05_DROID = PolicyConfig(
    name="pi05_droid",
    inputs=(droid.DroidInputs("pi05"),),
    outputs=(droid.DroidOutputs(),),
    asset_id="droid",
    action_horizon=15,
    discrete_state_input=True,
    **_PI05,
)
PI0_LIBERO = PolicyConfig(
    name="pi0_libero",
    inputs=(libero.LiberoInputs("pi0"), DeltaActions(_LIBERO_DELTA_MASK)),
    outputs=(AbsoluteActions(_LIBERO_DELTA_MASK), libero.LiberoOutputs()),
    asset_id="physical-intelligence/libero",
    action_horizon=50,
    **_PI0,
    **_LIBERO_DATA,
)
# Upstream's pi05_libero: no delta-action transform and no state in the prompt.
PI05_LIBERO = PolicyConfig(
    name="pi05_libero",
    inputs=(libero.LiberoInputs("pi05"),),
    outputs=(libero.LiberoOutputs(),),
    asset_id="physical-intelligence/libero",
    action_horizon=10,
    **_PI05,
    **_LIBERO_DATA,
)
PI0_ALOHA = PolicyConfig(
    name="pi0_aloha",
    inputs=(aloha.AlohaInputs(adapt_to_pi=True), DeltaActions(aloha.DELTA_ACTION_MASK)),
    outputs=(AbsoluteActions(aloha.DELTA_ACTION_MASK), aloha.AlohaOutputs(adapt_to_pi=True)),
    asset_id="trossen",
    action_horizon=50,
    policy_metadata={"reset_pose": list(aloha.RESET_POSE)},
    **_PI0,
    **_ALOHA_DATA,
)
PI05_ALOHA = PolicyConfig(
    name="pi05_aloha",
    inputs=(aloha.AlohaInputs(adapt_to_pi=True), DeltaActions(aloha.DELTA_ACTION_MASK)),
    outputs=(AbsoluteActions(aloha.DELTA_ACTION_MASK), aloha.AlohaOutputs(adapt_to_pi=True)),
    asset_id="trossen",
    action_horizon=50,
    discrete_state_input=True,
    policy_metadata={"reset_pose": list(aloha.RESET_POSE)},
    **_PI05,
    **_ALOHA_DATA,
)

_REGISTRY: dict[str, PolicyConfig] = {}


def register_config(config: PolicyConfig, *, replace: bool = False) -> PolicyConfig:
    """Make ``config`` available by name; registering a different config under a taken name needs ``replace``."""
    existing = _REGISTRY.get(config.name)
    if existing is not None and existing != config and not replace:
        raise ValueError(f"a different policy config named {config.name!r} is already registered")
    _REGISTRY[config.name] = config
    return config


def get_config(name: str) -> PolicyConfig:
    try:
        return _REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown policy config {name!r}; known: {', '.join(sorted(_REGISTRY))}") from None


def config_names() -> list[str]:
    return sorted(_REGISTRY)


def resolve_config(config: str | PolicyConfig) -> PolicyConfig:
    return config if isinstance(config, PolicyConfig) else get_config(config)


for _config in (
    PI0_FAST_DROID,
    PI0_FAST_LIBERO,
    PI0_FAST_ALOHA,
    PI0_DROID,
    PI05_DROID,
    PI0_LIBERO,
    PI05_LIBERO,
    PI0_ALOHA,
    PI05_ALOHA,
):
    register_config(_config)
