"""Shared fixtures. Reference data lives in `../shared/golden` beside the repo (read-only, never copied here).

- `golden_dir`: the upstream goldens folder (tests are skipped with a clear reason if it is absent).
- `tiny_policy_files`: paths of the tiny pi0-FAST DROID policy made by upstream (checkpoint + tokenizer stand-ins).
- `tiny_droid_policy`: the real `Policy` for `pi0_fast_droid` over those files, float32, built once per session
  (building and compiling it is the expensive part of any end-to-end test).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from paths import SHARED_DIR


@dataclasses.dataclass(frozen=True)
class TinyPolicyFiles:
    checkpoint: Path
    paligemma_tokenizer: Path
    fast_tokenizer: Path

    def create_kwargs(self) -> dict:
        """Keyword arguments of `create_policy` (besides config and checkpoint) for these files."""
        return {
            "paligemma_tokenizer": self.paligemma_tokenizer,
            "fast_tokenizer": self.fast_tokenizer,
            "dtype": "float32",
        }


@pytest.fixture(scope="session")
def golden_dir() -> Path:
    path = SHARED_DIR / "golden"
    if not path.is_dir():
        pytest.skip(f"upstream goldens not found at {path}")
    return path


@pytest.fixture(scope="session")
def tiny_policy_files(golden_dir: Path) -> TinyPolicyFiles:
    root = golden_dir / "tiny_policy_droid"
    return TinyPolicyFiles(
        checkpoint=root / "checkpoint",
        paligemma_tokenizer=root / "paligemma_tokenizer_tiny.model",
        fast_tokenizer=root / "fast_tokenizer",
    )


@pytest.fixture(scope="session")
def tiny_droid_policy(tiny_policy_files: TinyPolicyFiles):
    from openpi_cam.policies.policy import create_policy

    return create_policy("pi0_fast_droid", tiny_policy_files.checkpoint, **tiny_policy_files.create_kwargs())
