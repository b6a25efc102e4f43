"""The demo tasks as training data: norm stats of a model directory and batches in the policy's model format, from
the reaching task's procedural samples or from recorded demonstrations (`metaworld_data.Demonstrations`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import jax
import numpy as np

from openpi_cam.demo import task
from openpi_cam.demo.metaworld_data import Demonstrations
from openpi_cam.model.observation import Observation
from openpi_cam.normalize import compute_norm_stats, load_norm_stats, save_norm_stats
from openpi_cam.policies import demo_reach
from openpi_cam.policies.config import PolicyConfig
from openpi_cam.tokenizers.paligemma import load_paligemma_tokenizer
from openpi_cam.tokenizers.pi0 import Pi0PromptTokenizer
from openpi_cam.tokenizers.pi0_fast import Pi0FastTokenizer
from openpi_cam.transforms import Normalize, pad_to_dim


def norm_stats_dir(out: Path, asset_id: str = demo_reach.ASSET_ID) -> Path:
    return out / demo_reach.CHECKPOINT.name / "assets" / asset_id


def load_normalize(out: Path, asset_id: str = demo_reach.ASSET_ID) -> Normalize:
    """The checkpoint's normalisation, as the policy applies it (quantiles, like upstream's pi0-FAST configs)."""
    return Normalize(load_norm_stats(norm_stats_dir(out, asset_id)), use_quantiles=True)


def write_norm_stats(
    out: Path,
    *,
    seed: int = 2,
    n: int = 20000,
    demonstrations: Demonstrations | None = None,
    asset_id: str = demo_reach.ASSET_ID,
) -> Normalize:
    """From `n` samples of the reaching task, or from every frame of recorded demonstrations."""
    if demonstrations is None:
        data = task.make_dataset(seed, n)
        state, actions = data["state"], data["actions"]
    else:
        state, actions = demonstrations.state, demonstrations.actions
    stats = {"state": compute_norm_stats(state), "actions": compute_norm_stats(actions)}
    save_norm_stats(norm_stats_dir(out, asset_id), stats)
    return load_normalize(out, asset_id)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class TrainingBatch:
    """What one training step consumes: the model input, and for pi0.5 the normalised, padded expert chunks (pi0-FAST
    carries them as tokens inside the observation)."""

    obs: Observation
    actions: np.ndarray | None  # [B, H, 32] for pi0.5


class Batches:
    """Fresh procedural samples every step (or frames drawn from `demonstrations`, with the action chunk that follows
    each), in the format the policy's input transforms produce for the family."""

    def __init__(
        self,
        out: Path,
        normalize: Normalize,
        batch_size: int,
        seed: int,
        *,
        contrast_pairs: bool = False,
        family: str = "pi0_fast",
        demonstrations: Demonstrations | None = None,
        config: PolicyConfig | None = None,
    ):
        self.family = family
        config = config or demo_reach.DEMO_CONFIGS[family]
        self.demonstrations = demonstrations
        self.horizon = config.action_horizon
        if family == "pi0_fast":
            self.tokenizer: Pi0FastTokenizer | Pi0PromptTokenizer = Pi0FastTokenizer.from_files(
                out / demo_reach.PALIGEMMA_TOKENIZER.name,
                out / demo_reach.FAST_TOKENIZER.name,
                max_len=config.max_token_len,
            )
        else:
            sp = load_paligemma_tokenizer(out / demo_reach.PALIGEMMA_TOKENIZER.name)
            self.tokenizer = Pi0PromptTokenizer(sp, config.max_token_len)
        self.model_action_dim = config.action_dim
        self.normalize = normalize
        self.rng = np.random.default_rng(seed)
        self.batch_size = batch_size
        self.contrast_pairs = contrast_pairs

    def samples(self) -> list[task.Sample]:
        if self.demonstrations is not None:
            return self.demonstrations.samples(self.rng, self.batch_size, self.horizon)
        if self.contrast_pairs:
            pairs = [task.contrast_pair(self.rng) for _ in range((self.batch_size + 1) // 2)]
            return [s for pair in pairs for s in pair][: self.batch_size]
        return [task.training_sample(self.rng) for _ in range(self.batch_size)]

    def __call__(self) -> TrainingBatch:
        return self.batch(self.samples())

    def batch(self, samples: list[task.Sample]) -> TrainingBatch:
        """pi0-FAST: the prompt, state and expert chunk tokenized together, loss on the postfix. pi0.5: the prompt with
        the discretised state, state and chunk zero-padded to the model's action dim."""
        states, rows, actions = [], [], []
        for s in samples:
            norm = self.normalize({"state": s.state.astype(np.float64), "actions": s.actions.astype(np.float64)})
            if isinstance(self.tokenizer, Pi0FastTokenizer):
                rows.append(self.tokenizer.tokenize(s.prompt, norm["state"], norm["actions"]))
                states.append(norm["state"])
            else:
                rows.append(self.tokenizer.tokenize(s.prompt, norm["state"]))
                states.append(pad_to_dim(norm["state"], self.model_action_dim))
                actions.append(pad_to_dim(norm["actions"], self.model_action_dim))
        columns = [np.stack(x) for x in zip(*rows, strict=True)]
        names = ("tokenized_prompt", "tokenized_prompt_mask", "token_ar_mask", "token_loss_mask")
        images = self._images(samples)
        obs = Observation.from_dict(
            {
                "image": images,
                "image_mask": {k: np.full(len(samples), k != "right_wrist_0_rgb") for k in images},
                "state": np.stack(states).astype(np.float32),
                **dict(zip(names, columns, strict=False)),
            }
        )
        return TrainingBatch(obs, np.stack(actions).astype(np.float32) if actions else None)

    def _images(self, samples: list[task.Sample]) -> dict[str, np.ndarray]:
        base = np.stack([s.base_image for s in samples])
        wrist = np.stack([s.wrist_image for s in samples])
        if self.family == "pi0_fast":
            return {"base_0_rgb": base, "wrist_0_rgb": wrist}
        return {"base_0_rgb": base, "left_wrist_0_rgb": wrist, "right_wrist_0_rgb": np.zeros_like(base)}
