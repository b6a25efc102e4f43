"""Native FAST action tokenizer (DCT + byte-level BPE), file-compatible with HF `physical-intelligence/fast`.

The HF processor ships as Python code that would have to be executed (`trust_remote_code`); this module reads only
its data files (`tokenizer.json`, `processor_config.json`) and reimplements the encode/decode/fit rules.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np
import scipy.fft
from tokenizers import Tokenizer, decoders, models, pre_tokenizers, processors
from tokenizers.trainers import BpeTrainer

from openpi_cam.errors import load_json, reading

logger = logging.getLogger(__name__)

TOKENIZER_FILE: Final = "tokenizer.json"
PROCESSOR_CONFIG_FILE: Final = "processor_config.json"
FAST_HF_REPO_ID: Final = "physical-intelligence/fast"

# Reasons `decode_checked` gives for returning zeros (upstream returns the same zeros and only prints).
DECODE_ERROR: Final = "decode_error"
DECODE_SHAPE_MISMATCH: Final = "decode_shape_mismatch"


@dataclasses.dataclass(frozen=True)
class FastProcessorConfig:
    """The numeric part of `processor_config.json`."""

    scale: float
    vocab_size: int
    min_token: int
    action_dim: int | None = None
    time_horizon: int | None = None

    @classmethod
    def from_json_dict(cls, data: dict[str, Any], *, source: str = "processor config") -> FastProcessorConfig:
        missing = [key for key in ("scale", "vocab_size", "min_token") if key not in data]
        if missing:
            raise ValueError(f"{source} lacks required keys {missing}")
        try:
            return cls(
                scale=data["scale"],
                vocab_size=int(data["vocab_size"]),
                min_token=int(data["min_token"]),
                action_dim=data.get("action_dim"),
                time_horizon=data.get("time_horizon"),
            )
        except (TypeError, ValueError) as e:
            raise ValueError(f"{source}: {e}") from None

    def to_json_dict(self) -> dict[str, Any]:
        return {"processor_class": "UniversalActionProcessor", **dataclasses.asdict(self)}


def dct_coefficients(chunk: np.ndarray) -> np.ndarray:
    """Orthonormal DCT-II over time of a [T, D] chunk (the transform FAST quantises)."""
    return scipy.fft.dct(chunk, axis=0, norm="ortho")


def _validated_chunk(chunk: np.ndarray) -> np.ndarray:
    array = np.asarray(chunk, dtype=np.float64)
    if array.ndim != 2 or array.shape[0] == 0 or array.shape[1] == 0:
        raise ValueError(f"action chunk must have shape [time, action_dim] with both > 0, got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError("action chunk contains NaN or infinite values")
    return array


def _new_byte_level_bpe() -> Tokenizer:
    # The same pipeline `tokenizers.ByteLevelBPETokenizer()` builds, which is what FAST trains and serialises.
    tokenizer = Tokenizer(models.BPE())
    tokenizer.pre_tokenizer = pre_tokenizers.ByteLevel(add_prefix_space=False)
    tokenizer.decoder = decoders.ByteLevel()
    tokenizer.post_processor = processors.ByteLevel(trim_offsets=False)
    return tokenizer


class FastActionTokenizer:
    """FAST: quantised DCT coefficients of an action chunk, written as characters and compressed with BPE."""

    def __init__(self, bpe: Tokenizer, config: FastProcessorConfig) -> None:
        self._bpe = bpe
        self.config = config

    @property
    def scale(self) -> float:
        return self.config.scale

    @property
    def min_token(self) -> int:
        return self.config.min_token

    @property
    def bpe_vocab_size(self) -> int:
        return self._bpe.get_vocab_size()

    @classmethod
    def load(cls, directory: str | Path) -> FastActionTokenizer:
        """Read a directory laid out like HF `physical-intelligence/fast`; no code in it is executed."""
        directory = Path(directory).expanduser()
        missing = [name for name in (TOKENIZER_FILE, PROCESSOR_CONFIG_FILE) if not (directory / name).is_file()]
        if missing:
            raise FileNotFoundError(f"FAST tokenizer directory {directory} lacks {missing}")
        config_path = directory / PROCESSOR_CONFIG_FILE
        config = FastProcessorConfig.from_json_dict(load_json(config_path), source=str(config_path))
        # The tokenizers library raises a bare Exception for a file it cannot parse.
        with reading(directory / TOKENIZER_FILE, "tokenizer file", Exception):
            bpe = Tokenizer.from_file(str(directory / TOKENIZER_FILE))
        return cls(bpe, config)

    def save(self, directory: str | Path) -> Path:
        """Write `tokenizer.json` and `processor_config.json` so that `load` gives back an equal tokenizer."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        self._bpe.save(str(directory / TOKENIZER_FILE))
        (directory / PROCESSOR_CONFIG_FILE).write_text(json.dumps(self.config.to_json_dict(), indent=2) + "\n")
        return directory

    def coefficient_text(self, chunk: np.ndarray) -> str:
        """The character string BPE sees: one char per quantised coefficient, time-major, shifted by `min_token`."""
        quantised = np.around(dct_coefficients(_validated_chunk(chunk)) * self.scale)
        shifted = np.maximum(quantised.flatten() - self.min_token, 0).astype(int)
        return "".join(map(chr, shifted))

    def encode(self, chunk: np.ndarray) -> list[int]:
        """FAST token ids of one action chunk [T, D]."""
        return self._bpe.encode(self.coefficient_text(chunk)).ids

    def decode_checked(
        self, ids: Sequence[int], *, time_horizon: int, action_dim: int
    ) -> tuple[np.ndarray, str | None]:
        """Actions [time_horizon, action_dim] and None, or zeros and the reason the ids do not form such a chunk."""
        try:
            text = self._bpe.decode([int(token) for token in ids])
        except (OverflowError, TypeError, ValueError) as error:
            # Negative or non-integral ids: upstream's BPE call raises and the processor falls back to zeros.
            logger.warning("FAST decode failed (%s) for ids %s", error, list(ids))
            return np.zeros((time_horizon, action_dim)), DECODE_ERROR
        coefficients = np.array([ord(char) for char in text], dtype=np.int64) + self.min_token
        if coefficients.size != time_horizon * action_dim:
            logger.warning(
                "FAST decode gave %d coefficients, expected %d x %d", coefficients.size, time_horizon, action_dim
            )
            return np.zeros((time_horizon, action_dim)), DECODE_SHAPE_MISMATCH
        coefficients = coefficients.reshape(time_horizon, action_dim)
        return scipy.fft.idct(coefficients / self.scale, axis=0, norm="ortho"), None

    def decode(self, ids: Sequence[int], *, time_horizon: int, action_dim: int) -> np.ndarray:
        """Like upstream's processor: the decoded chunk, or zeros when the ids do not decode to that shape."""
        return self.decode_checked(ids, time_horizon=time_horizon, action_dim=action_dim)[0]

    @classmethod
    def fit(
        cls,
        chunks: Sequence[np.ndarray],
        *,
        scale: float = 10,
        vocab_size: int = 1024,
        min_frequency: int = 2,
        action_dim: int | None = None,
        time_horizon: int | None = None,
    ) -> FastActionTokenizer:
        """Train a FAST tokenizer on action chunks (each [T, D], normalised) with the FAST recipe."""
        if len(chunks) == 0:
            raise ValueError("fit needs at least one action chunk")
        quantised = [np.around(dct_coefficients(_validated_chunk(chunk)).flatten() * scale) for chunk in chunks]
        every = np.concatenate(quantised)
        min_token, max_token = int(every.min()), int(every.max())
        if max_token - min_token > vocab_size:
            raise ValueError(
                f"vocab_size {vocab_size} is smaller than the quantised coefficient range {max_token - min_token}; "
                "raise vocab_size or lower scale"
            )
        if max_token - min_token + 100 > vocab_size:
            logger.warning("coefficient alphabet (%d) is close to vocab_size %d", max_token - min_token, vocab_size)

        def texts() -> Iterator[str]:
            for values in quantised:
                yield "".join(map(chr, (values - min_token).astype(int)))

        trainer = BpeTrainer(
            vocab_size=vocab_size,
            min_frequency=min_frequency,
            show_progress=False,
            special_tokens=[],
            # The whole coefficient range, as raw characters: that is what FAST's recipe seeds the alphabet with.
            initial_alphabet=[chr(i) for i in range(max_token - min_token + 1)],
            max_token_length=10000,
        )
        bpe = _new_byte_level_bpe()
        bpe.train_from_iterator(texts(), trainer=trainer)
        config = FastProcessorConfig(
            scale=scale, vocab_size=vocab_size, min_token=min_token, action_dim=action_dim, time_horizon=time_horizon
        )
        return cls(bpe, config)


def huggingface_hub_cache() -> Path:
    """The Hugging Face hub cache: `$HF_HUB_CACHE`, else `$HF_HOME/hub`, else `$XDG_CACHE_HOME/huggingface/hub`, else
    `~/.cache/huggingface/hub` (huggingface_hub's own order)."""
    if hub := os.environ.get("HF_HUB_CACHE"):
        return Path(hub).expanduser()
    home = os.environ.get("HF_HOME") or Path(os.environ.get("XDG_CACHE_HOME", "~/.cache")) / "huggingface"
    return Path(home).expanduser() / "hub"


def resolve_fast_tokenizer_dir(path: str | Path | None = None, *, repo_id: str = FAST_HF_REPO_ID) -> Path:
    """`path` if given, else the snapshot of `repo_id` that HF's cache points `main` at.

    Raises FileNotFoundError naming the places looked at; nothing is downloaded.
    """
    if path is not None:
        candidate = Path(path).expanduser()
        if (candidate / TOKENIZER_FILE).is_file():
            return candidate.resolve()
        raise FileNotFoundError(f"no FAST tokenizer ({TOKENIZER_FILE}) in the given directory {candidate}")
    repo_cache = huggingface_hub_cache() / f"models--{repo_id.replace('/', '--')}"
    looked_at = [repo_cache / "refs" / "main"]
    ref_file = repo_cache / "refs" / "main"
    if ref_file.is_file():
        snapshot = repo_cache / "snapshots" / ref_file.read_text().strip()
        looked_at.append(snapshot)
        if (snapshot / TOKENIZER_FILE).is_file() and (snapshot / PROCESSOR_CONFIG_FILE).is_file():
            return snapshot.resolve()
    raise FileNotFoundError(
        f"FAST tokenizer {repo_id} not found; looked at {[str(p) for p in looked_at]}. Pass a directory holding "
        f"{TOKENIZER_FILE} and {PROCESSOR_CONFIG_FILE}, or fetch it once with "
        f"`huggingface-cli download {repo_id}`; nothing is downloaded at run time."
    )
