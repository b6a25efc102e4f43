"""Which tokens to explain: maps the side channel's targets onto the model's Grad-CAM entry points.

Targets (the `--cam-target` values):
  action-token       the `action_index`-th FAST action token of the generation (one map per camera);
  all-action-tokens  every FAST action token, one shared forward pass (a (T, Hp, Wp) stack per camera);
  chunk              score = sum of log-probabilities of all FAST action tokens (one map per camera).
FAST action tokens are the generated tokens after `Action: ` and before `|` / EOS; the tokenizer finds their steps.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

import numpy as np

from openpi_cam.model import pi0_fast_maps
from openpi_cam.model.observation import Observation

Target = Literal["action-token", "all-action-tokens", "chunk"]
TARGETS: tuple[str, ...] = ("action-token", "all-action-tokens", "chunk")


class CamSkipped(Exception):
    """This generation cannot be explained with the requested target; `kind` names why (counted, not an error)."""

    def __init__(self, kind: str, message: str):
        super().__init__(message)
        self.kind = kind


@dataclasses.dataclass(frozen=True)
class Explanation:
    target: str
    maps: dict[str, np.ndarray]  # camera -> float32 (Hp, Wp) or (T, Hp, Wp); batch row 0
    token_ids: list[int]
    decode_steps: list[int]
    positions: list[int]
    action_indices: list[int]
    score: float | list[float]
    cameras: dict[str, dict[str, Any]]  # camera -> {"valid", "grid", "span"}
    # like `maps`: the norm of dScore/dE per token (model.gradcam's gradient-norm map)
    gradnorm_maps: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)


def explain(
    model: Any, tokenizer: Any, observation: Observation, generated: np.ndarray, *, target: str, action_index: int = 0
) -> Explanation:
    """Grad-CAM of one inference (batch row 0) for `target`, from the exact inputs and tokens of that inference."""
    generated = np.asarray(generated).reshape(-1).astype(np.int32)
    steps = np.asarray(tokenizer.action_token_steps(generated), np.int32)
    if steps.size == 0:
        raise CamSkipped("no_action_tokens", "the generation holds no FAST action tokens to explain")
    indices = list(range(len(steps)))
    if target == "action-token":
        if not 0 <= action_index < len(steps):
            raise CamSkipped(
                "action_index_out_of_range", f"action token {action_index} requested, generation has {len(steps)}"
            )
        steps, indices = steps[[action_index]], [action_index]
        result = pi0_fast_maps.gradcam_for_action_token(model, observation, generated, int(steps[0]))
    elif target == "all-action-tokens":
        result = pi0_fast_maps.gradcam_for_steps(model, observation, generated, steps)
    elif target == "chunk":
        result = pi0_fast_maps.gradcam_for_chunk(model, observation, generated, steps)
    else:
        raise ValueError(f"unknown Grad-CAM target {target!r}; expected one of {TARGETS}")
    score = np.asarray(result.score)[0]
    grid = list(model.config.siglip.grid)
    return Explanation(
        target=target,
        maps={c: np.asarray(m[0], np.float32) for c, m in result.maps.items()},
        gradnorm_maps={c: np.asarray(m[0], np.float32) for c, m in result.gradnorm_maps.items()},
        token_ids=[int(t) for t in np.asarray(result.token_ids)[0]],
        decode_steps=[int(s) for s in steps],
        positions=[int(p) for p in np.asarray(result.positions)[0]],
        action_indices=indices,
        score=float(score) if score.ndim == 0 else [float(s) for s in score],
        cameras={
            c: {"valid": bool(result.valid[c][0]), "grid": grid, "span": list(result.spans[c])} for c in result.cameras
        },
    )
