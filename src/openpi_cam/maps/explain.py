"""Explaining a LeRobot dataset into a maps dataset (`openpi-cam explain DATASET_DIR`).

An episode is the unit of work: its frames are decoded forward once (`lerobot.dataset`), every selected frame is
served to the policy as a robot would send it (one `infer_traced` call each, exactly as served), the traced calls are
explained `batch_size` at a time, each explanation gets its spot check, and the episode's rows are written as one
shard (`maps.dataset`). The local engine runs episodes in a loop; the Ray engine (`maps.ray_engine`) runs
the same `EpisodeExplainer` in an actor per worker, so both write the same rows.
"""

from __future__ import annotations

import collections
import dataclasses
import hashlib
import logging
import pathlib
import time
from collections.abc import Callable, Container, Iterable, Iterator, Mapping, Sequence
from typing import Any

import numpy as np

from openpi_cam.cam.batching import data_mesh, explain_batch
from openpi_cam.cam.records import resume_mismatch
from openpi_cam.cam.run_format import Reliance, SpotCheck, dumps
from openpi_cam.cam.sample_spread import check_samples, with_sample_spread
from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.lerobot.dataset import DatasetError, LeRobotDataset, open_dataset
from openpi_cam.lerobot.writer import REWARD, SUCCESS
from openpi_cam.maps import dataset as fmt
from openpi_cam.monitor import monitor_file
from openpi_cam.monitor.monitor_file import Monitor
from openpi_cam.monitor.stream import FLAG, SCORE, StepScore, Stream, execution_horizon
from openpi_cam.nested import unflatten_dict
from openpi_cam.policies.family import ExplainSkipped, Explanation, resolve_target
from openpi_cam.policies.policy import InferenceTrace, Policy
from openpi_cam.vocabulary import ACTION_FEATURES, DATASET_ACTIONS, FEATURES_PREFIX, PROMPT_FEATURES, ExplainOptions

log = logging.getLogger(__name__)

PROMPT_KEY = "prompt"
ACTIONS_KEY = "actions"  # in a LeRobot mapping: the feature holding the recorded actions, not an observation key
NOISE_SEED = 0  # with the frame's index, seeds a flow-matching policy's noise for that frame
STAGES = ("decode", "inference", "explanation", "writing")  # where an episode's seconds go


@dataclasses.dataclass(frozen=True)
class DatasetJob:
    """One explanation of a LeRobot dataset into a maps dataset."""

    source: pathlib.Path
    out: pathlib.Path
    model: ModelSpec
    options: ExplainOptions
    keys: Mapping[str, str]  # observation key -> dataset feature
    batch_size: int = 8  # frames explained per model call (padded to a multiple of the device count)
    extra: Mapping[str, str] = dataclasses.field(default_factory=dict)  # dataset feature -> `extra/<name>` column
    episodes: tuple[int, ...] | None = None  # None: every episode
    every: int = 1  # explain every N-th frame of an episode (frame_index % every == 0)
    nested_keys: bool = False  # observation keys `a/b` are nested dicts (ALOHA's `images/cam_high`)
    keep_going: bool = False  # a bad episode is skipped, counted and named in the summary instead of ending the job
    # `--target dataset-actions`: the dataset feature whose recorded chunk (this frame's action and the next ones, the
    # last repeated past the episode's end, as LeRobot pads) is explained instead of the model's own generation.
    recorded_actions: str | None = None
    # the feature whose truth (non-zero) in any frame of an episode makes it a success, as lerobot-eval counts one;
    # None: `next.success` where the dataset records it (no outcomes otherwise).
    outcome: str | None = None
    monitor: pathlib.Path | None = None  # a failure monitor file: each row gets its score and flag
    monitor_features: bool = False  # also write each row's pooled features (`monitor/features/<name>`), to fit on
    # the actions a robot executes per call, which STAC-single shifts by (None: the monitor's, else 5)
    execution_horizon: int | None = None
    # action samples per frame for `monitor/sample_spread` (pi0 / pi0.5; 0: none, or the monitor's where it reads one)
    sample_spread: int = 0

    def __post_init__(self) -> None:
        if self.every < 1:
            raise ValueError(f"--every-k must be >= 1, got {self.every}")
        if self.batch_size < 1:
            raise ValueError(f"--batch-size must be >= 1, got {self.batch_size}")
        if not self.keys:
            raise ValueError("no observation keys mapped to dataset features (--keys OBS_KEY=FEATURE ...)")
        if ACTIONS_KEY in self.keys:
            raise ValueError(f"{ACTIONS_KEY!r} is not an observation key; the recorded actions are `recorded_actions`")
        if self.recorded_actions is not None and self.options.target != "chunk":
            raise ValueError("the recorded actions are explained as a whole chunk: options.target must be 'chunk'")
        if self.execution_horizon is not None and self.execution_horizon < 1:
            raise ValueError(f"--execution-horizon must be >= 1, got {self.execution_horizon}")
        if self.sample_spread:
            check_samples(self.sample_spread)

    def loaded_monitor(self) -> Monitor | None:
        """The job's monitor file, read (ValueError naming the file when it is not one), or None."""
        return None if self.monitor is None else monitor_file.load(self.monitor)

    def horizon(self, monitor: Monitor | None) -> int:
        """The execution horizon STAC assumes: the flag's, else the monitor's, else the default; a flag that
        contradicts the monitor is refused."""
        own = None if monitor is None else monitor.execution_horizon
        if self.execution_horizon is not None and own is not None and own != self.execution_horizon:
            raise ValueError(
                f"--execution-horizon {self.execution_horizon}: the monitor {self.monitor} was fitted for {own}"
            )
        return self.execution_horizon or execution_horizon(monitor)

    def samples(self, monitor: Monitor | None) -> int:
        """The action samples per frame of `monitor/sample_spread` (0: none): the flag's, else the monitor's where
        it reads the spread; a flag that contradicts the monitor is refused."""
        own = None if monitor is None else monitor.sample_spread
        if self.sample_spread and own is not None and own != self.sample_spread:
            raise ValueError(f"--sample-spread {self.sample_spread}: the monitor {self.monitor} was fitted on {own}")
        return self.sample_spread or own or 0


def parse_pairs(pairs: Sequence[str], flag: str) -> dict[str, str]:
    """`A=B` strings -> {A: B}; a malformed one is an error naming the flag."""
    out = {}
    for pair in pairs:
        left, sep, right = pair.partition("=")
        if not sep or not left.strip() or not right.strip():
            raise ValueError(f"{flag} takes KEY=VALUE pairs, got {pair!r}")
        out[left.strip()] = right.strip()
    return out


def dataset_keys(model: ModelSpec, overrides: Mapping[str, str]) -> tuple[dict[str, str], bool]:
    """(observation key -> dataset feature, whether keys `a/b` nest): the model's LeRobot mapping (a named config's
    declared one, a LeRobot policy's own feature names), overridden key by key, without its `actions` entry
    (`recorded_actions_feature`)."""
    declared, nested = model.dataset_keys()
    keys = {**declared, **overrides}
    keys.pop(ACTIONS_KEY, None)
    return keys, nested


def recorded_actions_feature(model: ModelSpec, overrides: Mapping[str, str]) -> str | None:
    """The feature holding the recorded actions: the mapping's `actions` entry (`--keys actions=FEATURE`)."""
    return {**model.dataset_keys()[0], **overrides}.get(ACTIONS_KEY)


def check_features(ds: LeRobotDataset, job: DatasetJob) -> None:
    """Every mapped and carried feature exists in the dataset (one line naming the missing one and what exists)."""
    wanted = [(f"--keys {k}", f) for k, f in job.keys.items()] + [(f"--extra {f}", f) for f in job.extra]
    if job.recorded_actions is not None:
        wanted.append((f"--target {DATASET_ACTIONS} (--keys {ACTIONS_KEY}=FEATURE)", job.recorded_actions))
    if job.outcome is not None:
        wanted.append(("--outcome", job.outcome))
    for flag, feature in wanted:
        if feature not in ds.features:
            raise DatasetError(
                f"{ds.root / 'meta/info.json'}: feature {feature!r} ({flag}) is not in the dataset; it has "
                f"{sorted(ds.features)}"
            )


def outcome_features(ds: LeRobotDataset, job: DatasetJob) -> tuple[str | None, str | None]:
    """(the feature an episode's success is read from, the feature its return sums): the job's outcome feature, or
    lerobot-eval's `next.success` where the dataset has it; `next.reward` beside it where the dataset has it."""
    outcome = job.outcome or (SUCCESS if SUCCESS in ds.features else None)
    return outcome, (REWARD if outcome is not None and REWARD in ds.features else None)


def episode_outcome(ds: LeRobotDataset, episode: int, outcome: str, reward: str | None) -> dict[str, Any]:
    """The `episode_*` columns of one episode (`maps.dataset.OUTCOME_COLUMNS`), read from all its frames."""
    frames = list(ds.frames(episode, features=[outcome] if reward is None else [outcome, reward]))
    rewards = None if reward is None else [np.asarray(f[reward], np.float64).sum() for f in frames]
    return {
        fmt.EPISODE_LENGTH: len(frames),
        fmt.EPISODE_SUCCESS: any(bool(np.asarray(f[outcome]).any()) for f in frames),
        fmt.EPISODE_RETURN: None if rewards is None else float(sum(rewards)),
    }


def selected_episodes(ds: LeRobotDataset, job: DatasetJob) -> list[int]:
    if job.episodes is None:
        return list(ds.episodes)
    missing = sorted(set(job.episodes) - set(ds.episodes))
    if missing:
        raise DatasetError(f"{ds.root}: episodes {missing} are not in the dataset (it has {len(ds.episodes)})")
    return list(job.episodes)


def job_info(
    ds: LeRobotDataset,
    job: DatasetJob,
    *,
    family: str,
    grid: Sequence[int],
    camera_sources: Mapping[str, str | None],
) -> fmt.MapsInfo:
    """The maps dataset's meta/info.json for this job: the model's family, patch grid and cameras (model camera ->
    observation key) are all it needs of the model, so a driver can make it without loading one. The job's target
    must be resolved (the family's default filled in)."""
    if job.options.target is None:
        raise ValueError("job_info needs the job's target resolved against the model's family")
    options = job.options
    outcome, reward = outcome_features(ds, job)
    monitor = job.loaded_monitor()
    features = [FEATURES_PREFIX + c for c in camera_sources] + [PROMPT_FEATURES, ACTION_FEATURES]
    return fmt.MapsInfo(
        source=str(pathlib.Path(job.source).resolve()),
        source_version=ds.version,
        source_fps=ds.fps,
        model=job.model.resolved().to_json(),
        family=family,
        target=DATASET_ACTIONS if job.recorded_actions is not None else options.target,
        recorded_actions=job.recorded_actions,
        kinds=list(options.maps),
        grids={c: [int(g) for g in grid] for c in camera_sources},
        camera_sources={c: (None if k is None else job.keys.get(k, k)) for c, k in camera_sources.items()},
        keys=dict(job.keys),
        extra=dict(job.extra),
        every=job.every,
        nested_keys=job.nested_keys,
        scores_per_row=0 if options.target == "all-action-tokens" else 1,
        options={**options.to_json(), "batch_size": job.batch_size},
        outcome=outcome,
        reward=reward,
        monitor=None if job.monitor is None else str(pathlib.Path(job.monitor).resolve()),
        monitor_sha256=None if job.monitor is None else hashlib.sha256(job.monitor.read_bytes()).hexdigest(),
        execution_horizon=job.horizon(monitor),
        monitor_features=features if job.monitor_features else [],
        sample_spread=job.samples(monitor),
    )


def monitor_values(scored: StepScore, info: fmt.MapsInfo) -> dict[str, Any]:
    """A row's monitor columns (`maps.dataset.MONITOR_COLUMNS` and the feature columns the info names) from its
    call's `Stream.step`: null where a value is undefined (STAC without the previous call, token entropy for a flow
    family, score and flag without a monitor)."""
    values = scored.arrays()

    def scalar(name: str) -> float | None:
        value = values.get(name)
        return None if value is None or not np.isfinite(value) else float(value)

    row: dict[str, Any] = {fmt.MONITOR_PREFIX + name: scalar(name) for name in (*info.monitor_scalars, SCORE)}
    row[fmt.MONITOR_PREFIX + FLAG] = None if scored.flag is None else bool(scored.flag)
    for name in info.monitor_features:
        value = values.get(name)
        row[fmt.MONITOR_PREFIX + name] = None if value is None else _flat(value)
    return row


def _observation(frame: Mapping[str, Any], job: DatasetJob) -> dict[str, Any]:
    obs: dict[str, Any] = {key: frame[feature] for key, feature in job.keys.items()}
    if job.nested_keys:
        obs = unflatten_dict(obs)
    obs.setdefault(PROMPT_KEY, frame["task"])
    return obs


def _flat(values: Any, dtype: Any = np.float32) -> list[float]:
    return np.asarray(values, dtype).reshape(-1).tolist()


def frame_row(
    frame: Mapping[str, Any],
    trace: InferenceTrace,
    explanation: Explanation,
    response: Mapping[str, Any],
    check: SpotCheck | None,
    reliance: Reliance | None,
    *,
    info: fmt.MapsInfo,
    job: DatasetJob,
    explain_ms: float,
) -> dict[str, Any]:
    """The maps-dataset row of one explained frame (`maps.dataset` lists the columns)."""
    score = explanation.score
    row: dict[str, Any] = {
        "index": int(frame["index"]),
        "episode_index": int(frame["episode_index"]),
        "frame_index": int(frame["frame_index"]),
        "timestamp": float(np.asarray(frame["timestamp"]).reshape(-1)[0]),
        "task": str(frame["task"]),
        "target": DATASET_ACTIONS if job.recorded_actions is not None else explanation.target,
        "score": [float(s) for s in score] if isinstance(score, list | tuple) else float(score),
        "malformed": trace.malformed_reason,
        "actions": _flat(response["actions"]),
        "explain_ms": round(explain_ms, 3),
        fmt.CAMERAS_COLUMN: dumps(
            {
                camera: {
                    **values,
                    "geometry": None if trace.geometry.get(camera) is None else trace.geometry[camera].as_dict(),
                }
                for camera, values in explanation.cameras.items()
            }
        ),
        "details": dumps(explanation.details),
        "check": None if check is None else dumps(check.to_json()),
    }
    for kind in info.kinds:
        for camera in info.cameras:
            m = explanation.maps.get(kind, {}).get(camera)
            row[fmt.map_column(kind, camera)] = None if m is None else _flat(m)
    check_cameras = {} if check is None else check.cameras
    for camera in info.cameras:
        figures = check_cameras.get(camera)
        for kind in info.kinds:
            row[fmt.check_column(kind, camera)] = None if figures is None else figures.top_patch_drop.get(kind)
        row[fmt.check_column(fmt.CHECK_RANDOM, camera)] = None if figures is None else list(figures.random_patch_drops)
    for feature, name in job.extra.items():
        row[fmt.extra_column(name)] = _flat(frame[feature], np.float64)
    if info.reliance:
        measured = {} if reliance is None else reliance.figures()
        row["reliance"] = None if reliance is None else dumps(reliance.to_json())
        row |= {column: measured.get(column) for column in fmt.reliance_columns(info)}
    return row


@dataclasses.dataclass
class EpisodeResult:
    episode: int
    rows: list[dict[str, Any]]
    counts: collections.Counter[str]
    seconds: dict[str, float]  # per STAGES


class EpisodeExplainer:
    """Explains whole episodes of one dataset with one loaded policy; the unit both engines run."""

    def __init__(self, job: DatasetJob, policy: Policy | None = None, *, mesh: Any = "auto") -> None:
        self.job = job
        self.dataset = open_dataset(job.source)
        check_features(self.dataset, job)
        self.episodes = selected_episodes(self.dataset, job)  # checked before a model is loaded
        self.policy = job.model.create() if policy is None else policy
        # The info and rows record the target actually explained: the family's default when none was named.
        self.job = job = dataclasses.replace(
            job,
            options=dataclasses.replace(job.options, target=resolve_target(self.policy.explainer, job.options.target)),
        )
        self.mesh = data_mesh() if mesh == "auto" else mesh
        self.explainer = self.policy.explainer.on_mesh(self.mesh)
        self.info = job_info(
            self.dataset,
            job,
            family=self.policy.model.family,
            grid=self.policy.model.config.siglip.grid,
            camera_sources=self.policy.camera_sources,
        )
        if job.recorded_actions is not None and self.policy.model.family != "pi0_fast":
            raise ValueError(
                f"--target {DATASET_ACTIONS}: {self.policy.model.family} has no likelihood of a given chunk to explain "
                "(README, 'Explaining a LeRobot dataset'); pi0-FAST explains the recorded chunk's FAST tokens"
            )
        if self.info.sample_spread and self.policy.model.family == "pi0_fast":
            raise ValueError(
                f"--sample-spread {self.info.sample_spread}: pi0-FAST decodes greedily, one chunk per input; the "
                "sample spread is pi0 / pi0.5's"
            )
        self.horizon = self.policy.model.config.action_horizon
        self.monitor = job.loaded_monitor()

    def explain(self, episode: int) -> EpisodeResult:
        """The rows of one episode (raises `DatasetError` for bad data: nothing of the episode is written)."""
        job, options = self.job, self.job.options
        counts: collections.Counter[str] = collections.Counter()
        seconds = dict.fromkeys(STAGES, 0.0)
        length = self.dataset.episode_length(episode)
        wanted = set(range(0, length, job.every))
        outcome = {}
        if self.info.outcome is not None:
            outcome = episode_outcome(self.dataset, episode, self.info.outcome, self.info.reward)
        rows: list[dict[str, Any]] = []
        pending: list[tuple[Mapping[str, Any], InferenceTrace, dict[str, Any], StepScore]] = []

        def flush() -> None:
            t0 = time.perf_counter()
            traces = [trace for _, trace, _, _ in pending]
            seeds = [int(frame["index"]) for frame, _, _, _ in pending]
            done = explain_batch(
                self.explainer, traces, options, seeds, mesh=self.mesh, pad_to=job.batch_size, policy=self.policy
            )
            for (frame, trace, response, scored), explained in zip(pending, done, strict=True):
                if isinstance(explained.result, ExplainSkipped):
                    counts[f"skipped_{explained.result.reason}"] += 1
                    continue
                counts["explained_malformed"] += trace.malformed_reason is not None
                counts["explained"] += 1
                row = frame_row(
                    frame,
                    trace,
                    explained.result,
                    response,
                    explained.check,
                    explained.reliance,
                    info=self.info,
                    job=job,
                    explain_ms=explained.explain_ms,
                )
                rows.append(row | outcome | monitor_values(scored, self.info))
            seconds["explanation"] += time.perf_counter() - t0
            pending.clear()

        stream = self.stream()
        for frame, response, trace in self.served(episode, wanted, seconds, signals=True):
            counts["frames"] += 1
            signals = trace.signals
            if self.info.sample_spread:  # more samples of the served call: its inference's time
                t0 = time.perf_counter()
                signals = with_sample_spread(self.policy, trace, self.info.sample_spread)
                seconds["inference"] += time.perf_counter() - t0
            scored = stream.step(signals, int(frame["frame_index"]), trace.prompt)
            pending.append((frame, trace, response, scored))
            if len(pending) == job.batch_size:
                flush()
        if pending:
            flush()
        return EpisodeResult(episode, rows, counts, seconds)

    def stream(self) -> _EpisodeStream:
        """A new episode's monitor stream: its explained frames in order (`monitor.stream.Stream`)."""
        assert self.info.execution_horizon is not None
        return _EpisodeStream(Stream(self.monitor, self.info.execution_horizon), str(self.job.monitor))

    def served(
        self,
        episode: int,
        frame_indices: Container[int],
        seconds: dict[str, float] | None = None,
        *,
        signals: bool = False,
    ) -> Iterator[tuple[dict[str, Any], dict[str, Any], InferenceTrace]]:
        """(frame, response, trace) of each wanted frame of an episode, served one at a time as a robot's requests
        are (with `signals`, as a monitored server serves them: `Policy.infer_traced`); `seconds` accumulates the
        decode and inference time."""
        seconds = {} if seconds is None else seconds
        features = sorted(set(self.job.keys.values()) | set(self.job.extra))
        recorded = None
        if self.job.recorded_actions is not None:
            column = self.dataset.frames(episode, features=[self.job.recorded_actions])
            recorded = np.stack([np.asarray(f[self.job.recorded_actions]) for f in column])
        frames = iter(self.dataset.frames(episode, features=features, frame_indices=frame_indices))
        while True:
            t0 = time.perf_counter()
            frame = next(frames, None)
            seconds["decode"] = seconds.get("decode", 0.0) + time.perf_counter() - t0
            if frame is None:
                return
            t0 = time.perf_counter()
            obs = _observation(frame, self.job)
            response, trace = self.policy.infer_traced(obs, noise=self._noise(frame), signals=signals)
            if recorded is not None:
                trace = self._recorded_output(obs, trace, recorded, int(frame["frame_index"]))
            seconds["inference"] = seconds.get("inference", 0.0) + time.perf_counter() - t0
            yield frame, response, trace

    def _recorded_output(
        self, obs: Mapping[str, Any], trace: InferenceTrace, recorded: np.ndarray, frame_index: int
    ) -> InferenceTrace:
        """The traced call with its generation replaced by the tokens of the recorded chunk starting at this frame,
        as training tokenises it: explaining them with the `chunk` target differentiates the log-probability the
        model gives the demonstrated actions."""
        steps = np.minimum(np.arange(frame_index, frame_index + self.horizon), len(recorded) - 1)
        inputs = self.policy.training_inputs(obs, recorded[steps])
        postfix = np.asarray(inputs["tokenized_prompt"])[np.asarray(inputs["token_loss_mask"], bool)]
        output = np.zeros_like(np.asarray(trace.output))
        if len(postfix) > len(output):
            raise ValueError(
                f"the recorded chunk at frame {frame_index} is {len(postfix)} tokens, more than the {len(output)} "
                "decoding steps the policy allows"
            )
        output[: len(postfix)] = postfix
        return dataclasses.replace(trace, output=output, malformed_reason=None)

    def _noise(self, frame: Mapping[str, Any]) -> np.ndarray | None:
        """A flow-matching policy's noise for a frame, drawn from the frame's dataset `index`: the frame's actions and
        maps are then the same whichever worker explains it and in whatever order (pi0-FAST decodes greedily)."""
        if self.policy.model.family == "pi0_fast":
            return None
        config = self.policy.model.config
        rng = np.random.default_rng([NOISE_SEED, int(frame["index"])])
        return rng.standard_normal((config.action_horizon, config.action_dim)).astype(np.float32)

    def write(self, result: EpisodeResult) -> str:
        t0 = time.perf_counter()
        path = fmt.write_shard(self.job.out, self.info, result.episode, result.rows)
        result.seconds["writing"] += time.perf_counter() - t0
        return path


class _EpisodeStream:
    """An episode's explained frames through a monitor stream: STAC-single against the previous explained frame
    only when it lies the execution horizon before (as consecutive calls of a robot executing that many actions)."""

    def __init__(self, stream: Stream, monitor: str) -> None:
        self._stream = stream
        self._monitor = monitor
        self._previous: int | None = None

    def step(self, signals: Mapping[str, np.ndarray], frame_index: int, prompt: str) -> StepScore:
        follows = self._previous is not None and frame_index - self._previous == self._stream.horizon
        self._previous = frame_index
        try:
            return self._stream.step(signals, follows=follows, prompt=prompt)
        except ValueError as e:  # the monitor reads an input this model's calls do not give
            raise ValueError(f"monitor {self._monitor}: {e}") from None


def prepare_output(job: DatasetJob, info: fmt.MapsInfo) -> set[int]:
    """Creates the maps dataset (or checks that the one at `job.out` was made with the same settings) and returns
    the episodes it already holds."""
    info_path = job.out / fmt.INFO_JSON
    if info_path.is_file():
        old = fmt.open_maps_dataset(job.out).info
        diffs = old.mismatch(info) + resume_mismatch(old.model, old.options, job.model, job.options)
        if diffs:
            raise ValueError(f"cannot add to {job.out}, it was made with other settings: {'; '.join(diffs)}")
    else:
        if job.out.exists() and any(job.out.iterdir()):
            raise ValueError(f"{job.out} exists and is not a maps dataset: choose an empty or new folder")
        fmt.write_json(info_path, info.to_json())
    return fmt.written_episodes(job.out)


@dataclasses.dataclass
class JobSummary:
    """What a job did: counts, the episodes it skipped (with why), and where the time went."""

    episodes_written: int = 0
    episodes_already_written: int = 0
    episodes_skipped: dict[int, str] = dataclasses.field(default_factory=dict)
    counts: collections.Counter[str] = dataclasses.field(default_factory=collections.Counter)
    seconds: dict[str, float] = dataclasses.field(default_factory=lambda: dict.fromkeys(STAGES, 0.0))
    engine: str = "local"
    workers: int = 1

    def add(self, result: EpisodeResult) -> None:
        self.episodes_written += 1
        self.counts.update(result.counts)
        for k, v in result.seconds.items():
            self.seconds[k] = self.seconds.get(k, 0.0) + v

    def as_json(self) -> dict[str, Any]:
        return {
            "engine": self.engine,
            "workers": self.workers,
            "episodes_written": self.episodes_written,
            "episodes_already_written": self.episodes_already_written,
            "episodes_skipped": {str(k): v for k, v in sorted(self.episodes_skipped.items())},
            **dict(self.counts),
            "seconds": {k: round(v, 3) for k, v in self.seconds.items()},
        }

    def line(self) -> str:
        skipped = f", {len(self.episodes_skipped)} episodes skipped" if self.episodes_skipped else ""
        return (
            f"{self.counts['explained']} frames explained in {self.episodes_written} episodes "
            f"({self.episodes_already_written} already written{skipped})"
        )


def run_local(
    job: DatasetJob,
    *,
    policy: Policy | None = None,
    progress: Callable[[Iterable[int], int], Iterable[int]] | None = None,
) -> JobSummary:
    """Explains the job's episodes one after another on this machine's devices, writing each episode's shard."""
    worker = EpisodeExplainer(job, policy)
    done = prepare_output(worker.job, worker.info)  # the job with its target resolved, as the info records it
    summary = JobSummary()
    todo = [e for e in worker.episodes if e not in done]
    summary.episodes_already_written = len(worker.episodes) - len(todo)
    episodes: Iterable[int] = todo if progress is None else progress(todo, len(todo))
    for episode in episodes:
        try:
            result = worker.explain(episode)
        except DatasetError as e:
            if not job.keep_going:
                raise
            summary.episodes_skipped[episode] = str(e)
            log.warning("explain: skipping episode %d: %s", episode, e)
            continue
        worker.write(result)
        summary.add(result)
    fmt.write_json(job.out / fmt.SUMMARY_JSON, summary.as_json())
    return summary
