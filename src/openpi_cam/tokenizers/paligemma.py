"""Locating and loading the PaliGemma SentencePiece model without any download, and upstream's state bins."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import sentencepiece

from openpi_cam.errors import reading
from openpi_cam.tokenizers.fast import huggingface_hub_cache

OPENPI_DATA_HOME_ENV = "OPENPI_DATA_HOME"
DEFAULT_OPENPI_DATA_HOME = "~/.cache/openpi"
# Where upstream's `maybe_download("gs://big_vision/paligemma_tokenizer.model")` leaves the file inside its cache.
PALIGEMMA_TOKENIZER_CACHE_PATH = Path("big_vision") / "paligemma_tokenizer.model"
# The Hugging Face repository LeRobot's pi0 / pi0.5 processors load their tokenizer from.
PALIGEMMA_HUB_ID = "google/paligemma-3b-pt-224"
STATE_BINS = 256


def discretize_state(state: np.ndarray) -> np.ndarray:
    """Upstream's state bins: 256 equal bins over [-1, 1]; below -1 gives -1, 1 and above give 255 (as upstream)."""
    return np.digitize(state, bins=np.linspace(-1, 1, STATE_BINS + 1)[:-1]) - 1


def openpi_data_home() -> Path:
    """Upstream's cache root: `$OPENPI_DATA_HOME`, else `~/.cache/openpi` (not created here)."""
    return Path(os.environ.get(OPENPI_DATA_HOME_ENV, DEFAULT_OPENPI_DATA_HOME)).expanduser()


def resolve_paligemma_tokenizer_path(path: str | Path | None = None) -> Path:
    """The SentencePiece model to use: `path` if given, else the file in upstream's cache.

    Raises FileNotFoundError naming every place looked at and how to provide the file.
    """
    if path is not None:
        candidate = Path(path).expanduser()
        if candidate.is_file():
            return candidate.resolve()
        raise FileNotFoundError(f"PaliGemma tokenizer model not found at the given path {candidate}")
    candidate = openpi_data_home() / PALIGEMMA_TOKENIZER_CACHE_PATH
    if candidate.is_file():
        return candidate.resolve()
    raise FileNotFoundError(
        f"PaliGemma tokenizer model not found. Looked at {candidate} "
        f"(${OPENPI_DATA_HOME_ENV} or {DEFAULT_OPENPI_DATA_HOME} + /{PALIGEMMA_TOKENIZER_CACHE_PATH.as_posix()}). "
        "Pass an explicit path, or copy gs://big_vision/paligemma_tokenizer.model to that place "
        "(e.g. `gsutil cp gs://big_vision/paligemma_tokenizer.model <place>`); nothing is downloaded at run time."
    )


def hf_cached_file(repo_id: str, filename: str) -> Path | None:
    """`filename` of a model repository's snapshot in the hub cache (the one `refs/main` names, else any), or None."""
    repo = huggingface_hub_cache() / f"models--{repo_id.replace('/', '--')}"
    ref = repo / "refs" / "main"
    if ref.is_file() and (candidate := repo / "snapshots" / ref.read_text().strip() / filename).is_file():
        return candidate
    return next((path for path in sorted(repo.glob(f"snapshots/*/{filename}")) if path.is_file()), None)


def load_paligemma_tokenizer(path: str | Path | None = None) -> sentencepiece.SentencePieceProcessor:
    """Load the SentencePiece model found by `resolve_paligemma_tokenizer_path`."""
    resolved = resolve_paligemma_tokenizer_path(path)
    with reading(resolved, "SentencePiece model", RuntimeError):  # SentencePiece's parse errors are RuntimeErrors
        return sentencepiece.SentencePieceProcessor(model_proto=resolved.read_bytes())
