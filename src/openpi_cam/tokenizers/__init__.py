"""PaliGemma SentencePiece loading, the native FAST action tokenizer and the pi0-FAST prompt tokenizer."""

from openpi_cam.tokenizers.fast import (
    DECODE_ERROR,
    DECODE_SHAPE_MISMATCH,
    FastActionTokenizer,
    FastProcessorConfig,
    resolve_fast_tokenizer_dir,
)
from openpi_cam.tokenizers.paligemma import load_paligemma_tokenizer, resolve_paligemma_tokenizer_path
from openpi_cam.tokenizers.pi0_fast import NO_ACTION_PREFIX, Pi0FastTokenizer, discretize_state

__all__ = [
    "DECODE_ERROR",
    "DECODE_SHAPE_MISMATCH",
    "NO_ACTION_PREFIX",
    "FastActionTokenizer",
    "FastProcessorConfig",
    "Pi0FastTokenizer",
    "discretize_state",
    "load_paligemma_tokenizer",
    "resolve_fast_tokenizer_dir",
    "resolve_paligemma_tokenizer_path",
]
