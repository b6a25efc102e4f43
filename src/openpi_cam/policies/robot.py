"""What every robot pipeline provides, plus a generic one for user-declared robots.

A robot's input transform turns a client observation into upstream's model layout (``state``, ``image``,
``image_mask``, ``prompt``) and knows which client key feeds each model camera (None for a synthesised blank camera);
the side channel's logger records that mapping. Its output transform turns model-space actions back into robot actions.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, ClassVar, Literal, Protocol, runtime_checkable

import numpy as np

from openpi_cam.transforms import DataDict, parse_image, parse_prompt, parse_vector, require

# The model families a robot pipeline may have to lay its cameras out for (upstream's `ModelType`).
Family = Literal["pi0_fast", "pi0", "pi05"]


@runtime_checkable
class RobotInputs(Protocol):
    """A robot input transform that can say where each model camera comes from."""

    @property
    def camera_sources(self) -> Mapping[str, str | None]:
        """Model camera -> client observation key, in model camera order (None: always a blank image)."""
        ...

    def camera_sources_for(self, obs: Mapping[str, Any]) -> dict[str, str | None]:
        """The same for one observation: None where this observation's camera was synthesised."""
        ...

    def __call__(self, data: DataDict) -> DataDict: ...


def example_observation(robot_inputs: RobotInputs) -> dict[str, Any] | None:
    """A client observation the robot's transform accepts (random pixels, every key and shape a real client sends;
    serving shapes do not depend on the values), from its optional ``example()``; None where it has none."""
    example = getattr(robot_inputs, "example", None)
    return example() if callable(example) else None


class FixedCameraSources:
    """For robots whose camera layout is the same for every observation: subclasses set ``CAMERA_SOURCES``."""

    CAMERA_SOURCES: ClassVar[Mapping[str, str | None]]

    @property
    def camera_sources(self) -> Mapping[str, str | None]:
        return dict(self.CAMERA_SOURCES)

    def camera_sources_for(self, obs: Mapping[str, Any]) -> dict[str, str | None]:
        return dict(self.CAMERA_SOURCES)


def lookup(data: Mapping[str, Any], key: str) -> Any:
    """``data[key]`` where ``key`` may be a ``a/b`` path into nested dicts (flat keys win, as clients send them)."""
    if key in data:
        return require(data, key)
    node: Any = data
    for part in key.split("/"):
        if not isinstance(node, Mapping) or part not in node:
            return require(data, key)  # raises InvalidRequest naming the full key
        node = node[part]
    if node is None:
        return require(data, key)
    return node


def pass_prompt(data: Mapping[str, Any], inputs: DataDict) -> DataDict:
    """Carry the prompt over (bytes decoded), leaving its absence to the default-prompt / tokenizer steps."""
    if data.get("prompt") is not None:
        inputs["prompt"] = parse_prompt(data["prompt"])
    return inputs


@dataclasses.dataclass(frozen=True)
class GenericInputs:
    """Inputs for a user-declared robot: named client keys for each camera and one state vector.

    ``cameras`` maps model camera names (in model order) to client keys; None synthesises a black image shaped like
    the first real camera. Every camera mask is True, as upstream's FAST pipelines do, unless ``mask_blank`` masks
    the synthesised ones, as upstream's pi0 / pi0.5 pipelines do.
    """

    cameras: Mapping[str, str | None]
    state_key: str
    state_dim: int | None = None
    channels_first: bool | None = None  # None: upstream's rule (a leading axis of 3 means [3, H, W])
    mask_blank: bool = False

    def __post_init__(self) -> None:
        if not any(k is not None for k in self.cameras.values()):
            raise ValueError("GenericInputs needs at least one camera with a client key")

    @property
    def camera_sources(self) -> Mapping[str, str | None]:
        return dict(self.cameras)

    def camera_sources_for(self, obs: Mapping[str, Any]) -> dict[str, str | None]:
        return dict(self.cameras)

    def example(self) -> dict[str, Any] | None:
        """Random 224 x 224 frames and state; None without a declared ``state_dim`` (its size is then unknown)."""
        if self.state_dim is None:
            return None
        rng = np.random.default_rng(0)
        obs: dict[str, Any] = {self.state_key: rng.random(self.state_dim), "prompt": "do something"}
        for key in self.cameras.values():
            if key is not None:
                image = rng.integers(256, size=(224, 224, 3), dtype=np.uint8)
                obs[key] = np.moveaxis(image, -1, 0) if self.channels_first else image
        return obs

    def __call__(self, data: DataDict) -> DataDict:
        state = parse_vector(lookup(data, self.state_key), self.state_key, dim=self.state_dim)
        parsed = {
            name: parse_image(lookup(data, key), key, channels_first=self.channels_first)
            for name, key in self.cameras.items()
            if key is not None
        }
        blank = np.zeros_like(next(iter(parsed.values())))
        images = {name: parsed.get(name, blank) for name in self.cameras}
        inputs: DataDict = {
            "state": state,
            "image": images,
            "image_mask": {
                name: np.bool_(key is not None or not self.mask_blank) for name, key in self.cameras.items()
            },
        }
        if "actions" in data:
            inputs["actions"] = np.asarray(data["actions"])
        return pass_prompt(data, inputs)


@dataclasses.dataclass(frozen=True)
class GenericOutputs:
    """Keep the first ``action_dim`` action dimensions."""

    action_dim: int

    def __call__(self, data: DataDict) -> DataDict:
        return {"actions": np.asarray(data["actions"][..., : self.action_dim])}
