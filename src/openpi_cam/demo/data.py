"""The demo task as training data: norm stats of a model directory and batches in the policy's model format."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from openpi_cam.demo import task
from openpi_cam.model.observation import Observation
from openpi_cam.normalize import compute_norm_stats, load_norm_stats, save_norm_stats
from openpi_cam.policies import demo_reach
from openpi_cam.tokenizers.pi0_fast import Pi0FastTokenizer
from openpi_cam.transforms import Normalize


def norm_stats_dir(out: Path) -> Path:
    return out / demo_reach.CHECKPOINT.name / "assets" / demo_reach.ASSET_ID


def load_normalize(out: Path) -> Normalize:
    """The checkpoint's normalisation, as the policy applies it (quantiles, like upstream's pi0-FAST configs)."""
    return Normalize(load_norm_stats(norm_stats_dir(out)), use_quantiles=True)


def write_norm_stats(out: Path, *, seed: int = 2, n: int = 20000) -> Normalize:
    data = task.make_dataset(seed, n)
    stats = {"state": compute_norm_stats(data["state"]), "actions": compute_norm_stats(data["actions"])}
    save_norm_stats(norm_stats_dir(out), stats)
    return load_normalize(out)


class Batches:
    """Fresh procedural samples every step, in the format the policy's input transforms produce."""

    def __init__(self, out: Path, normalize: Normalize, batch_size: int, seed: int, *, contrast_pairs: bool = False):
        self.tokenizer = Pi0FastTokenizer.from_files(
            out / demo_reach.PALIGEMMA_TOKENIZER.name,
            out / demo_reach.FAST_TOKENIZER.name,
            max_len=demo_reach.DEMO_CONFIG.max_token_len,
        )
        self.normalize = normalize
        self.rng = np.random.default_rng(seed)
        self.batch_size = batch_size
        self.contrast_pairs = contrast_pairs

    def __call__(self) -> Observation:
        if self.contrast_pairs:
            pairs = [task.contrast_pair(self.rng) for _ in range((self.batch_size + 1) // 2)]
            samples = [s for pair in pairs for s in pair][: self.batch_size]
        else:
            samples = [task.training_sample(self.rng) for _ in range(self.batch_size)]
        return self.observation(samples)

    def observation(self, samples: list[task.Sample]) -> Observation:
        """Training format: the prompt, state and expert chunk tokenized together, loss on the postfix."""
        states, rows = [], []
        for s in samples:
            norm = self.normalize({"state": s.state.astype(np.float64), "actions": s.actions.astype(np.float64)})
            states.append(norm["state"])
            rows.append(self.tokenizer.tokenize(s.prompt, norm["state"], norm["actions"]))
        tokens, mask, ar, loss = (np.stack(x) for x in zip(*rows, strict=True))
        images = {
            "base_0_rgb": np.stack([s.base_image for s in samples]),
            "wrist_0_rgb": np.stack([s.wrist_image for s in samples]),
        }
        return Observation.from_dict(
            {
                "image": images,
                "image_mask": {k: np.ones(len(samples), bool) for k in images},
                "state": np.stack(states).astype(np.float32),
                "tokenized_prompt": tokens,
                "tokenized_prompt_mask": mask,
                "token_ar_mask": ar,
                "token_loss_mask": loss,
            }
        )
