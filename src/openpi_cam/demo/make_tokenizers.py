"""The demo's two tokenizers, built reproducibly from the task (`python -m openpi_cam.demo.train` calls both).

* SentencePiece: a small BPE model with PaliGemma's special ids (pad 0, eos 1, bos 2, unk 3) and byte fallback,
  trained on the task's prompt texts; then 256 `<locNNNN>` and 128 `<segNNN>` pieces are appended as in PaliGemma.
  The last 128 ids are skipped and FAST id f maps to `vocab_size - 1 - 128 - f`, i.e. onto the `<loc>` pieces.
* FAST: fitted with `FastActionTokenizer.fit` on expert chunks normalised with the checkpoint's norm stats.

Standalone: `python -m openpi_cam.demo.make_tokenizers --out DIR` (the FAST fit then uses stats computed here).
"""

from __future__ import annotations

import dataclasses
import io
from collections.abc import Callable
from pathlib import Path

import numpy as np
import sentencepiece as spm
from sentencepiece import sentencepiece_model_pb2

from openpi_cam.demo import task
from openpi_cam.normalize import compute_norm_stats
from openpi_cam.policies import demo_reach
from openpi_cam.tokenizers.fast import FastActionTokenizer, dct_coefficients

TEXT_VOCAB = 320  # 4 specials + 256 byte pieces + merges over the task's few words
MERGES = 32
FAST_VOCAB = 256  # the <loc> region, like PaliGemma: the most FAST ids the vocabulary can hold
SEG_PIECES = 128  # the skipped tail
VOCAB_SIZE = TEXT_VOCAB + FAST_VOCAB + SEG_PIECES  # the model's embedding rows
FAST_SCALE = 10.0


REACH_PROMPTS = tuple(task.prompt_for(color) for color in task.COLORS)


def _corpus(rng: np.random.Generator, n: int, prompts: tuple[str, ...], state_dim: int) -> list[str]:
    lines = []
    for _ in range(n):
        state = " ".join(str(int(v)) for v in rng.integers(0, 256, size=state_dim))
        lines.append(f"Task: {rng.choice(prompts)}, State: {state};")
    # The postfix markers occur once per training example, so give them the same weight as the prompts.
    return lines + ["Action: ", "Action: |", "|"] * (n // 3)


def sentencepiece_model(seed: int = 0, prompts: tuple[str, ...] = REACH_PROMPTS, state_dim: int = 2) -> bytes:
    """Trained on the task's prompts with discretised states of `state_dim` values, as the models' prompts read."""
    buffer = io.BytesIO()
    spm.SentencePieceTrainer.train(
        sentence_iterator=iter(_corpus(np.random.default_rng(seed), 2000, prompts, state_dim)),
        model_writer=buffer,
        model_type="bpe",
        vocab_size=TEXT_VOCAB,
        byte_fallback=True,
        split_digits=True,
        add_dummy_prefix=False,
        remove_extra_whitespaces=False,
        normalization_rule_name="identity",
        pad_id=0,
        eos_id=1,
        bos_id=2,
        unk_id=3,
        pad_piece="<pad>",
        eos_piece="<eos>",
        bos_piece="<bos>",
        unk_piece="<unk>",
        num_threads=1,
        minloglevel=2,
    )
    proto = sentencepiece_model_pb2.ModelProto()
    proto.ParseFromString(buffer.getvalue())
    names = [f"<loc{i:04d}>" for i in range(FAST_VOCAB)] + [f"<seg{i:03d}>" for i in range(SEG_PIECES)]
    for name in names:
        piece = proto.pieces.add()
        piece.piece, piece.score = name, 0.0
        piece.type = sentencepiece_model_pb2.ModelProto.SentencePiece.USER_DEFINED
    return proto.SerializeToString()


def train_sentencepiece(
    out: Path, *, seed: int = 0, prompts: tuple[str, ...] = REACH_PROMPTS, state_dim: int = 2
) -> Path:
    path = out / demo_reach.PALIGEMMA_TOKENIZER.name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(sentencepiece_model(seed, prompts, state_dim))
    return path


def fit_fast(
    out: Path,
    normalize: Callable[[np.ndarray], np.ndarray],
    *,
    seed: int = 1,
    num_chunks: int = 5000,
    chunks: np.ndarray | None = None,
) -> FastActionTokenizer:
    """FAST fitted on normalised expert chunks; `normalize` must be the checkpoint's action normalisation. `chunks`
    [N, H, A]: the expert's recorded chunks (`num_chunks` of them drawn with `seed`); None: the reaching task's.

    The BPE vocabulary is asked for as the coefficient alphabet plus `MERGES` merges, but FAST's byte-level BPE starts
    from 256 byte symbols, more than that budget, so the fit learns no merges at all (a larger vocabulary does fold a
    constant chunk: docs/DESIGN_NOTES.md). A constant chunk is therefore 20 ids, and a policy
    must emit exactly 18 zero ids after the two informative ones or the chunk fails to decode (upstream then returns
    zeros). Room for merges needs more FAST ids than the 256 `<loc>` pieces, i.e. a larger text vocabulary.
    """
    rng = np.random.default_rng(seed)
    if chunks is None:
        cfg = task.TaskConfig()
        chunks = np.stack([task.training_sample(rng, cfg).actions for _ in range(num_chunks)])
    else:
        chunks = np.asarray(chunks)[rng.permutation(len(chunks))[:num_chunks]]
    normalised = list(normalize(chunks))
    coefficients = np.concatenate([np.around(dct_coefficients(c) * FAST_SCALE).ravel() for c in normalised])
    alphabet = int(coefficients.max() - coefficients.min()) + 1
    if alphabet + MERGES > FAST_VOCAB:
        raise ValueError(f"FAST alphabet {alphabet} + {MERGES} merges does not fit the {FAST_VOCAB} <loc> pieces")
    horizon, action_dim = chunks.shape[1:]
    fast = FastActionTokenizer.fit(
        normalised, scale=FAST_SCALE, vocab_size=alphabet + MERGES, action_dim=action_dim, time_horizon=horizon
    )
    fast.save(out / demo_reach.FAST_TOKENIZER.name)
    return fast


@dataclasses.dataclass(frozen=True)
class Args:
    out: Path = Path("/tmp/openpi_cam_demo_tokenizers")
    seed: int = 0


def main(args: Args) -> None:
    sp_path = train_sentencepiece(args.out, seed=args.seed)
    data = task.make_dataset(2, 20000)
    stats = compute_norm_stats(data["actions"].reshape(-1, 2))
    fast = fit_fast(args.out, lambda c: (c - stats.q01) / (stats.q99 - stats.q01 + 1e-6) * 2.0 - 1.0)
    vocab = spm.SentencePieceProcessor(model_file=str(sp_path)).vocab_size()
    print(f"sentencepiece: {vocab} pieces -> {sp_path}; FAST: {fast.bpe_vocab_size} ids -> {args.out}")


if __name__ == "__main__":
    import tyro

    main(tyro.cli(Args))
