"""What one served call gives a failure monitor, each a small pure function of arrays the call already holds:

- consecutive-chunk disagreement (STAC-single: Agia et al.'s STAC with one sample per call, as SAFE runs it as a
  baseline): how far the current chunk departs from the previous one where the two cover the same time steps;
- the generation's token entropy (pi0-FAST);
- last-layer features pooled per camera and for the prompt;
- the spread of action chunks sampled from several noises (pi0 / pi0.5, opt-in: it costs N - 1 extra samples).

Actions are in normalised units (the policy's own normalisation, before unnormalising), so that every action
dimension weighs alike whatever its physical unit.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

# The names under which a step's scalar signals travel (a monitor's inputs, a maps dataset's columns).
STAC = "stac"
TOKEN_ENTROPY = "token_entropy"
SAMPLE_SPREAD = "sample_spread"


def _chunk(name: str, chunk: np.ndarray) -> np.ndarray:
    a = np.asarray(chunk, np.float64)
    if a.ndim != 2 or a.shape[0] == 0:
        raise ValueError(f"{name} must be an action chunk [H, A] with H >= 1, got shape {a.shape}")
    return a


def stac_single(previous: np.ndarray, current: np.ndarray, executed: int) -> float:
    """The disagreement of two consecutive action chunks where they overlap in time.

    previous: [Hp, A], the chunk served on the previous call; current: [Hc, A], this call's; executed: s, the number
    of the previous chunk's actions the robot executed between the two calls, so that previous[s + i] and
    current[i] are meant for the same time step. Returns the mean over the overlap (min(Hp - s, Hc) steps) of the
    per-step Euclidean distance ||previous[s + i] - current[i]||_2; NaN when the chunks do not overlap (s >= Hp).

    Why the per-step L2 norm: a step's action is one point in the normalised action space, and with one sample per
    call the distance between the two calls' predictions for that step is the distance between two points; the L2
    norm does not depend on how the action axes are rotated, and (unsquared) it keeps one step's large jump from
    outweighing the rest of the overlap as a sum of squares would. The mean, not the sum, keeps chunks of different
    overlaps comparable.
    """
    prev, cur = _chunk("previous", previous), _chunk("current", current)
    if prev.shape[1] != cur.shape[1]:
        raise ValueError(f"chunks of {prev.shape[1]} and {cur.shape[1]} action dimensions")
    if executed < 0:
        raise ValueError(f"executed must be >= 0, got {executed}")
    overlap = min(prev.shape[0] - executed, cur.shape[0])
    if overlap <= 0:
        return math.nan
    return float(np.linalg.norm(prev[executed : executed + overlap] - cur[:overlap], axis=1).mean())


def stac_aligned(previous: np.ndarray, current: np.ndarray, *, min_overlap: int = 1) -> tuple[float, int]:
    """A variant of `stac_single` for when the number of executed actions is unknown (a server does not see the
    client's replanning horizon): the minimum over the shifts s in [1, Hp - 1] whose overlap has at least
    `min_overlap` steps, and the shift that attains it (the smallest such s on ties). Returns (NaN, 0) when no shift
    qualifies.

    It is not the same figure: a minimum over shifts is biased low, and most of all over short overlaps, where one
    or two steps can agree by chance; raising `min_overlap` trades that bias for fewer admissible shifts.
    """
    prev, cur = _chunk("previous", previous), _chunk("current", current)
    best, shift = math.inf, 0
    for s in range(1, prev.shape[0]):
        if min(prev.shape[0] - s, cur.shape[0]) < min_overlap:
            break
        value = stac_single(prev, cur, s)
        if value < best:
            best, shift = value, s
    return (best, shift) if shift else (math.nan, 0)


def entropies_from_logits(logits: np.ndarray) -> np.ndarray:
    """The entropy (nats) of each generated token's distribution. logits: [T, V] -> [T]."""
    z = np.asarray(logits, np.float64)
    z = z - z.max(axis=-1, keepdims=True)
    log_p = z - np.log(np.exp(z).sum(axis=-1, keepdims=True))
    return -(np.exp(log_p) * log_p).sum(axis=-1)


def token_entropy(entropies: np.ndarray, action_tokens: np.ndarray | None = None) -> float:
    """One figure of a generation's uncertainty: the mean entropy over its action tokens.

    entropies: [T], each generated token's entropy; action_tokens: bool [T], the tokens that encode actions (FAST's
    tokens, not the `Action: ` prefix or the end of the answer, whose entropies say nothing of the action); None
    takes every token. NaN when no token is selected."""
    e = np.asarray(entropies, np.float64).reshape(-1)
    if action_tokens is not None:
        mask = np.asarray(action_tokens, bool).reshape(-1)
        if mask.shape != e.shape:
            raise ValueError(f"{mask.size} action-token flags for {e.size} entropies")
        e = e[mask]
    return float(e.mean()) if e.size else math.nan


def pool_spans(
    features: np.ndarray, spans: Mapping[str, tuple[int, int]], valid: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Per-token features pooled over named token spans: the mean over each span's valid tokens.

    features: [T, D], one layer's output for every token of the sequence (the last layer's, for a monitor); spans:
    name -> (start, stop), e.g. each camera's image tokens and the prompt's tokens; valid: bool [T] (the prompt's
    padding excluded), None for all. Returns name -> [D] (NaN where a span has no valid token).

    Why the mean and not the max: a camera has hundreds of image tokens and the prompt a varying number; the mean
    summarises all of them on one scale whatever their count, while a per-dimension max grows with the count and
    follows whichever single token is most extreme (an artefact token, a position that attracts attention), which
    is a poor input to a Gaussian distance or a linear probe.
    """
    x = np.asarray(features, np.float64)
    if x.ndim != 2:
        raise ValueError(f"features must be [T, D], got shape {x.shape}")
    keep = np.ones(x.shape[0], bool) if valid is None else np.asarray(valid, bool).reshape(-1)
    if keep.shape[0] != x.shape[0]:
        raise ValueError(f"{keep.shape[0]} validity flags for {x.shape[0]} tokens")
    pooled = {}
    for name, (start, stop) in spans.items():
        if not 0 <= start <= stop <= x.shape[0]:
            raise ValueError(f"span {name!r} ({start}, {stop}) is outside the {x.shape[0]} tokens")
        rows = x[start:stop][keep[start:stop]]
        pooled[name] = rows.mean(axis=0) if rows.shape[0] else np.full(x.shape[1], np.nan)
    return pooled


def sample_spread(chunks: np.ndarray) -> float:
    """How much N chunks sampled for one observation from N noises disagree: the mean over the H steps of the
    per-step spread, the root of the summed variances over the A action dimensions (ddof 1): the root-mean-square
    Euclidean distance of the samples from their mean, up to N / (N - 1), in the same units as `stac_single`.

    chunks: [N, H, A] with N >= 2."""
    c = np.asarray(chunks, np.float64)
    if c.ndim != 3 or c.shape[0] < 2 or c.shape[1] == 0:
        raise ValueError(f"chunks must be [N, H, A] with N >= 2 samples, got shape {c.shape}")
    return float(np.sqrt(c.var(axis=0, ddof=1).sum(axis=-1)).mean())
