"""pi0-FAST prompt/action tokenizer: upstream `FASTTokenizer` semantics over a PaliGemma vocab and a FAST tokenizer."""

from __future__ import annotations

import functools
import logging
from pathlib import Path
from typing import Final

import numpy as np
import sentencepiece

from openpi_cam.errors import InvalidRequest
from openpi_cam.tokenizers.fast import FastActionTokenizer, resolve_fast_tokenizer_dir
from openpi_cam.tokenizers.paligemma import discretize_state, load_paligemma_tokenizer

logger = logging.getLogger(__name__)

ACTION_PREFIX: Final = "Action: "
END_OF_ACTION: Final = "|"
# Malformed-generation reasons (besides the FAST decode reasons in `openpi_cam.tokenizers.fast`).
NO_ACTION_PREFIX: Final = "no_action_prefix"
# PaliGemma's last 128 ids are <segNNN> tokens; FAST ids count down from just below them.
FAST_SKIP_TOKENS: Final = 128

TokenizedInputs = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def validated_state(state: np.ndarray) -> np.ndarray:
    array = np.asarray(state)
    if array.ndim != 1 or not np.issubdtype(array.dtype, np.number):
        raise InvalidRequest(f"state must be a 1-D numeric array, got shape {array.shape} dtype {array.dtype}")
    if not np.all(np.isfinite(array)):
        raise InvalidRequest("state contains NaN or infinite values")
    return array


class Pi0FastTokenizer:
    """Prompt + state (+ actions) to model tokens and generated tokens back to actions, exactly as upstream."""

    def __init__(
        self, paligemma_sp: sentencepiece.SentencePieceProcessor, fast: FastActionTokenizer, max_len: int = 256
    ) -> None:
        if max_len <= 0:
            raise ValueError(f"max_len must be positive, got {max_len}")
        self._sp = paligemma_sp
        self.fast = fast
        self.max_len = max_len

    @classmethod
    def from_files(
        cls, paligemma_path: str | Path | None = None, fast_dir: str | Path | None = None, *, max_len: int = 256
    ) -> Pi0FastTokenizer:
        """Load both tokenizers from local files (upstream's cache locations when a path is None)."""
        fast = FastActionTokenizer.load(resolve_fast_tokenizer_dir(fast_dir))
        return cls(load_paligemma_tokenizer(paligemma_path), fast, max_len)

    @property
    def paligemma(self) -> sentencepiece.SentencePieceProcessor:
        return self._sp

    @property
    def vocab_size(self) -> int:
        return self._sp.vocab_size()

    def fast_to_paligemma(self, ids: np.ndarray | list[int]) -> np.ndarray:
        """FAST ids to PaliGemma ids; the map is its own inverse, so it also serves the other way."""
        return self.vocab_size - 1 - FAST_SKIP_TOKENS - np.asarray(ids, dtype=np.int64)

    paligemma_to_fast = fast_to_paligemma

    def tokenize(self, prompt: str, state: np.ndarray, actions: np.ndarray | None = None) -> TokenizedInputs:
        """(tokens int32, token_mask bool, ar_mask int32, loss_mask bool), each [max_len]."""
        if not isinstance(prompt, str):
            raise InvalidRequest(f"prompt must be a string, got {type(prompt).__name__}")
        cleaned = prompt.lower().strip().replace("_", " ")
        state_text = " ".join(map(str, discretize_state(validated_state(state))))
        prefix = self._sp.encode(f"Task: {cleaned}, State: {state_text};\n", add_bos=True)
        postfix: list[int] = []
        if actions is not None:
            action_ids = self.fast_to_paligemma(self.fast.encode(actions)).tolist()
            postfix = self._sp.encode(ACTION_PREFIX) + action_ids + self._sp.encode(END_OF_ACTION, add_eos=True)

        tokens = prefix + postfix
        ar_mask = [0] * len(prefix) + [1] * len(postfix)
        loss_mask = [False] * len(prefix) + [True] * len(postfix)
        if len(tokens) > self.max_len:
            logger.warning(
                f"Token length ({len(tokens)}) exceeds max length ({self.max_len}), truncating. "
                "Consider increasing the `max_token_len` in your model config if this happens frequently."
            )
        n = min(len(tokens), self.max_len)
        padding = self.max_len - n
        return (
            np.asarray(tokens[:n] + [0] * padding, dtype=np.int32),
            np.asarray([True] * n + [False] * padding, dtype=bool),
            np.asarray(ar_mask[:n] + [0] * padding, dtype=np.int32),
            np.asarray(loss_mask[:n] + [False] * padding, dtype=bool),
        )

    def _token_list(self, tokens: np.ndarray) -> list[int]:
        array = np.asarray(tokens)
        if array.ndim != 1:
            raise ValueError(f"generated tokens must be 1-D, got shape {array.shape}")
        ids = array.astype(np.int64)
        if ids.size and (ids.min() < 0 or ids.max() >= self.vocab_size):
            raise ValueError(f"generated token ids must lie in [0, {self.vocab_size}), got [{ids.min()}, {ids.max()}]")
        return ids.tolist()

    def extract_actions_checked(
        self, tokens: np.ndarray, action_horizon: int, action_dim: int
    ) -> tuple[np.ndarray, str | None]:
        """Upstream's `extract_actions` result, plus why it is all zeros when the generation was malformed."""
        text = self._sp.decode(self._token_list(tokens))
        if ACTION_PREFIX not in text:
            return np.zeros((action_horizon, action_dim), dtype=np.float32), NO_ACTION_PREFIX
        segment = text.split(ACTION_PREFIX)[1].split(END_OF_ACTION)[0].strip()
        fast_ids = self.paligemma_to_fast(self._sp.encode(segment))
        return self.fast.decode_checked(fast_ids.tolist(), time_horizon=action_horizon, action_dim=action_dim)

    def extract_actions(self, tokens: np.ndarray, action_horizon: int, action_dim: int) -> np.ndarray:
        """Actions [action_horizon, action_dim] decoded from generated tokens; zeros when malformed (as upstream)."""
        return self.extract_actions_checked(tokens, action_horizon, action_dim)[0]

    def action_token_steps(self, tokens: np.ndarray) -> np.ndarray:
        """Indices into `tokens` (= decode steps) of the tokens that carry the actions `extract_actions` reads.

        Those are the tokens lying wholly inside the stripped text between the first "Action: " and the next "|"
        (or the next "Action: ", or the end), located with SentencePiece's own per-token byte spans.
        """
        ids = self._token_list(tokens)
        decoded = self._sp.decode(ids, out_type="proto")
        text = decoded.text.encode("utf-8")
        prefix, end_mark = ACTION_PREFIX.encode(), END_OF_ACTION.encode()
        found = text.find(prefix)
        if found < 0:
            return np.zeros((0,), dtype=np.int64)
        lo = found + len(prefix)
        ends = [pos for pos in (text.find(end_mark, lo), text.find(prefix, lo)) if pos >= 0]
        hi = min(ends, default=len(text))
        # Narrow to what upstream keeps after `.strip()`; byte offsets here are on character boundaries.
        segment = text[lo:hi].decode("utf-8")
        lo += len(segment[: len(segment) - len(segment.lstrip())].encode("utf-8"))
        hi -= len(segment[len(segment.rstrip()) :].encode("utf-8"))
        steps = [
            step
            for step, piece in enumerate(decoded.pieces)
            if lo <= piece.begin < hi and piece.end <= hi and not self._sp.is_control(piece.id)
        ]
        return np.asarray(steps, dtype=np.int64)

    @functools.cached_property
    def end_of_action_token_ids(self) -> tuple[int, ...]:
        """Every id whose text contains "|": generating one ends the action segment upstream reads."""
        pieces = self._sp.id_to_piece(list(range(self.vocab_size)))
        byte_piece = f"<0x{ord(END_OF_ACTION):02X}>"
        found = []
        for token_id, piece in enumerate(pieces):
            if self._sp.is_control(token_id) or self._sp.is_unknown(token_id):
                continue
            if (piece == byte_piece) if self._sp.is_byte(token_id) else (END_OF_ACTION in piece):
                found.append(token_id)
        return tuple(found)
