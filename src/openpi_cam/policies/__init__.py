"""Robot pipelines (DROID, LIBERO, ALOHA, user-declared), named configs and the `Policy` that serves them."""

from openpi_cam.policies.config import (
    PI0_FAST_ALOHA,
    PI0_FAST_DROID,
    PI0_FAST_LIBERO,
    PolicyConfig,
    config_names,
    get_config,
    register_config,
    resolve_config,
)
from openpi_cam.policies.policy import InferenceTrace, Policy, build_transforms, create_policy
from openpi_cam.policies.robot import GenericInputs, GenericOutputs, RobotInputs

__all__ = [
    "PI0_FAST_ALOHA",
    "PI0_FAST_DROID",
    "PI0_FAST_LIBERO",
    "GenericInputs",
    "GenericOutputs",
    "InferenceTrace",
    "Policy",
    "PolicyConfig",
    "RobotInputs",
    "build_transforms",
    "config_names",
    "create_policy",
    "get_config",
    "register_config",
    "resolve_config",
]
