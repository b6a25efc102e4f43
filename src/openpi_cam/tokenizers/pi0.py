"""pi0 / pi0.5 prompt tokenizer: upstream `PaligemmaTokenizer` semantics over the PaliGemma SentencePiece model."""

from __future__ import annotations

import logging

import numpy as np
import sentencepiece

from openpi_cam.errors import InvalidRequest
from openpi_cam.tokenizers.paligemma import discretize_state
from openpi_cam.tokenizers.pi0_fast import validated_state

logger = logging.getLogger(__name__)


def clean_prompt(prompt: str) -> str:
    """The task text as pi0.5's prompt holds it (upstream and LeRobot alike): stripped, `_` and newlines as spaces."""
    return prompt.strip().replace("_", " ").replace("\n", " ")


def pi05_prompt(prompt: str, state: np.ndarray) -> str:
    """pi0.5's prompt with the normalised state discretised into 256 bins (before BOS is prepended)."""
    bins = " ".join(map(str, discretize_state(validated_state(state))))
    return f"Task: {clean_prompt(prompt)}, State: {bins};\nAction: "


def pad_tokens(tokens: list[int], max_len: int, pad_id: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(tokens int32 [max_len], mask bool [max_len]): right-padded with `pad_id` / False, truncated with a warning."""
    if len(tokens) > max_len:
        logger.warning(
            "Token length (%d) exceeds max length (%d), truncating; consider a larger max_token_len",
            len(tokens),
            max_len,
        )
    n = min(len(tokens), max_len)
    return (
        np.asarray(tokens[:n] + [pad_id] * (max_len - n), np.int32),
        np.asarray([True] * n + [False] * (max_len - n), bool),
    )


class Pi0PromptTokenizer:
    """The prompt (pi0), or the prompt with the discretised state (pi0.5 with discrete state input), to token ids."""

    def __init__(self, paligemma_sp: sentencepiece.SentencePieceProcessor, max_len: int) -> None:
        if max_len <= 0:
            raise ValueError(f"max_len must be positive, got {max_len}")
        self._sp = paligemma_sp
        self.max_len = max_len

    @property
    def paligemma(self) -> sentencepiece.SentencePieceProcessor:
        return self._sp

    def tokenize(self, prompt: str, state: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(tokens int32 [max_len], mask bool [max_len]); padded with 0 / False, truncated with a warning.

        Unlike pi0-FAST's, the prompt keeps its case. pi0: `prompt` with BOS, then `\n` encoded on its own (the
        "start of answer" token). With a state (pi0.5): `Task: {prompt}, State: {bins};\nAction: ` with BOS."""
        if not isinstance(prompt, str):
            raise InvalidRequest(f"prompt must be a string, got {type(prompt).__name__}")
        if state is None:
            tokens = self._sp.encode(clean_prompt(prompt), add_bos=True) + self._sp.encode("\n")
        else:
            tokens = self._sp.encode(pi05_prompt(prompt, state), add_bos=True)
        return pad_tokens(tokens, self.max_len)
