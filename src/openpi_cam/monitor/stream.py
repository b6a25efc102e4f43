"""A monitor's view of one stream of served calls, in order: a connection live, an episode's explained frames
offline. Each call's signals (`InferenceTrace.signals`) become the step's named inputs, STAC-single against the
chunk served before it on the same stream, and, with a monitor, the step's score and whether the stream is flagged
so far. Live scoring and a dataset job both go through `Stream.step`, so the same calls give the same numbers.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import numpy as np

from openpi_cam.monitor.monitor_file import EpisodeScore, Monitor
from openpi_cam.monitor.signals import STAC, TOKEN_ENTROPY, stac_single, token_entropy
from openpi_cam.vocabulary import ACTION_TOKENS, NORMALIZED_CHUNK, TOKEN_ENTROPIES

# The actions a robot executes from each chunk before it asks again, where a monitor does not say: the demo robots'
# (`openpi-cam demo --execute`, 5).
DEFAULT_EXECUTION_HORIZON = 5
# Names of a scored step's outcome, beside its inputs (step files and maps datasets prefix them with `monitor/`).
SCORE, FLAG = "score", "flag"


def execution_horizon(monitor: Monitor | None) -> int:
    """The shift STAC-single assumes between consecutive calls: the monitor's, else DEFAULT_EXECUTION_HORIZON."""
    if monitor is None or monitor.execution_horizon is None:
        return DEFAULT_EXECUTION_HORIZON
    return monitor.execution_horizon


def step_inputs(signals: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """One call's monitor inputs from its trace's signals, STAC aside: the pooled features (`features/...`) as they
    are, and, where the call has per-token entropies (pi0-FAST), `token_entropy`, their mean over the action tokens
    (`signals.token_entropy`). The normalised chunk is what STAC compares, not an input."""
    inputs = {
        name: np.asarray(value)
        for name, value in signals.items()
        if name not in (TOKEN_ENTROPIES, ACTION_TOKENS, NORMALIZED_CHUNK)
    }
    if TOKEN_ENTROPIES in signals:
        inputs[TOKEN_ENTROPY] = np.float64(token_entropy(signals[TOKEN_ENTROPIES], signals.get(ACTION_TOKENS)))
    return inputs


@dataclasses.dataclass(frozen=True)
class StepScore:
    """One scored call: its named inputs (features, `token_entropy`, `stac`), and with a monitor its step score
    (NaN where the monitor cannot score it, e.g. `stac` on a stream's first call) and whether the stream is flagged
    as of this call (some step so far scored above the threshold); None for both without a monitor."""

    inputs: dict[str, np.ndarray]
    score: float | None = None
    flag: bool | None = None

    def arrays(self) -> dict[str, np.ndarray]:
        """The step's inputs, score and flag as arrays under their names (what a step file stores as `monitor/...`)."""
        out = dict(self.inputs)
        if self.score is not None:
            out[SCORE] = np.float64(self.score)
        if self.flag is not None:
            out[FLAG] = np.bool_(self.flag)
        return out


class Stream:
    """The calls of one connection (or one episode's explained frames), scored in order. Not thread-safe."""

    def __init__(self, monitor: Monitor | None, horizon: int) -> None:
        if horizon < 1:
            raise ValueError(f"the execution horizon must be >= 1 action, got {horizon}")
        self.monitor = monitor
        self.horizon = horizon
        self.episode: EpisodeScore | None = None if monitor is None else monitor.episode()
        self._previous: np.ndarray | None = None

    @property
    def flagged(self) -> bool:
        return self.episode is not None and self.episode.flagged

    def step(self, signals: Mapping[str, np.ndarray], *, follows: bool = True, prompt: str | None = None) -> StepScore:
        """Score the next call from its trace's signals and the prompt it was served under (`InferenceTrace.prompt`,
        which a gated monitor reads). `follows`: whether the stream's previous call was served `horizon` actions
        before this one (live: always; offline: the frame indices differ by it); STAC-single against it is NaN
        otherwise, and on the stream's first call. Raises ValueError when the monitor reads an input the call lacks
        (one line naming it)."""
        if NORMALIZED_CHUNK not in signals:
            raise ValueError(f"the call's signals hold no {NORMALIZED_CHUNK!r} (it was served without signals)")
        chunk = np.asarray(signals[NORMALIZED_CHUNK], np.float64)
        inputs = step_inputs(signals)
        previous, self._previous = self._previous, chunk
        stac = math.nan if previous is None or not follows else stac_single(previous, chunk, self.horizon)
        inputs[STAC] = np.float64(stac)
        if self.episode is None:
            return StepScore(inputs)
        score = self.episode.update(inputs, prompt)
        return StepScore(inputs, score, self.episode.flagged)
