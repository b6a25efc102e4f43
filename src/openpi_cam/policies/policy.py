"""`Policy`: upstream's `Policy.infer`, plus a trace of exactly what the model saw and produced."""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import sentencepiece

from openpi_cam.counters import WarnOnceCounter
from openpi_cam.errors import InvalidRequest
from openpi_cam.letterbox import LetterboxGeometry, letterbox_geometry
from openpi_cam.model.checkpoint import read_param_shapes
from openpi_cam.model.config import MAX_DECODING_STEPS, family_of
from openpi_cam.model.observation import Observation, pad_rows, stack_observations
from openpi_cam.model.safetensors_weights import read_tensor_infos, torch_family
from openpi_cam.nested import flatten_dict
from openpi_cam.normalize import load_checkpoint_norm_stats
from openpi_cam.policies.checkpoint_format import PARAMS_DIR, WEIGHTS_FILE, checkpoint_format, read_head_counts
from openpi_cam.policies.config import PolicyConfig, resolve_config
from openpi_cam.policies.family import Explainer, OutputDecoder, Sampler
from openpi_cam.policies.pi0_family import FlowParts, build_pi0
from openpi_cam.policies.pi0_fast_family import FastParts, build_pi0_fast
from openpi_cam.policies.robot import RobotInputs, example_observation
from openpi_cam.tokenizers.fast import FastActionTokenizer
from openpi_cam.transforms import (
    OUTPUT_CONTEXT,
    DataDict,
    InjectDefaultPrompt,
    Normalize,
    ResizeImages,
    Transform,
    Unnormalize,
    compose,
    parse_prompt,
)
from openpi_cam.vocabulary import NORMALIZED_CHUNK

logger = logging.getLogger(__name__)
_REQUESTS = "requests"  # counted beside the malformed reasons


@dataclasses.dataclass(frozen=True)
class InferenceTrace:
    """One `infer` call as the model saw it. Per-camera dicts follow the model's camera order."""

    observation: Observation  # batched (B=1) model input, images float32 in [-1, 1]
    output: np.ndarray  # the model's raw output (pi0-FAST: generated ids, int32 [max_decoding_steps], 0 after EOS;
    # pi0 / pi0.5: the action chunk [horizon, model action dim] before the output transforms)
    sample_inputs: dict[str, np.ndarray]  # what else the sampler drew (pi0 / pi0.5: "noise" [horizon, action dim])
    raw_images: dict[str, np.ndarray | None]  # uint8 [H, W, 3] as the client sent it; None for synthesised cameras
    camera_sources: dict[str, str | None]  # client observation key per camera (None: synthesised)
    geometry: dict[str, LetterboxGeometry]  # where each client image sits inside the model image
    prompt: str  # the prompt before tokenisation (after default-prompt injection)
    malformed_reason: str | None  # why the generation decoded to zero actions; None if well formed
    # the client's numeric observation values other than its images and prompt, at their `a/b` keys (e.g. the state):
    # with the raw images and the prompt, what the client sent
    client_inputs: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    # the client's observation as it was sent (its arrays shared, not copied): what `Policy.with_prompt` prepares
    # again with another prompt
    request: Mapping[str, Any] | None = None
    # what the input transforms left for the output transforms (`OUTPUT_CONTEXT`): with the state, what turns the
    # raw output into the robot's actions again (`Policy.resample`)
    output_context: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    # what a failure monitor reads of this call (`vocabulary`'s names: pooled features, pi0-FAST's token entropies
    # and action-token flags, the normalised chunk), computed by the served call itself when asked (`signals=True`)
    signals: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)

    @property
    def camera_names(self) -> tuple[str, ...]:
        return self.observation.camera_names


def batch_bucket(rows: int) -> int:
    """The batch size a model call of `rows` requests runs at: the next power of two, so that a batched server
    compiles one program per bucket (1, 2, 4, 8, ...) rather than one per request count."""
    if rows < 1:
        raise ValueError(f"a model call needs at least one request, got {rows}")
    return 1 << (rows - 1).bit_length()


@dataclasses.dataclass(frozen=True)
class _Prepared:
    """One request after the input transforms: the model input (B = 1) and what its trace needs."""

    observation: Observation
    state: np.ndarray  # the state the output transforms see
    pre_resize_images: dict[str, np.ndarray]  # uint8 [H, W, 3] client frames
    prompt: str
    camera_sources: Mapping[str, str | None]
    client_inputs: dict[str, np.ndarray]
    context: Mapping[str, Any]  # what the input transforms left for the output transforms (`OUTPUT_CONTEXT`)
    request: Mapping[str, Any]  # the client's observation as it was sent

    @property
    def signature(self) -> tuple:
        """What must agree for two requests to share a model call: tree structure, shapes and dtypes."""
        leaves, treedef = jax.tree.flatten(self.observation)
        return treedef, tuple((np.shape(x), np.asarray(x).dtype.str) for x in leaves)


def _copy_containers(tree: Any) -> Any:
    # Transforms may modify dicts in place; the client's own containers must stay untouched (upstream copies too).
    if isinstance(tree, Mapping):
        return {k: _copy_containers(v) for k, v in tree.items()}
    if isinstance(tree, list):
        return [_copy_containers(v) for v in tree]
    return tree


def _client_inputs(obs: Mapping[str, Any], camera_keys: set[str | None]) -> dict[str, np.ndarray]:
    """The numeric values of a client observation other than its cameras and prompt, at `a/b` keys."""
    out = {}
    for key, value in flatten_dict(obs).items():
        if key in camera_keys or key == "prompt" or isinstance(value, str | bytes):
            continue
        array = np.asarray(value)
        if array.dtype.kind in "biuf":
            out[key] = array
    return out


class Policy:
    """Input transforms -> batched `Observation` -> the model's sampler -> output transforms, as upstream's `Policy`.

    `sample` is the family's inference (it also returns what it drew, e.g. pi0's noise); `decoder` turns the model's
    raw output into normalised actions (pi0-FAST: FAST action extraction, the first of upstream's output transforms);
    keeping it apart from `output_transforms` lets the policy report malformed outputs. `explainer` is the family's
    map computation, used by the side channel, never by `infer`.
    """

    def __init__(
        self,
        model: object,
        *,
        transforms: Sequence[Transform],
        sample: Sampler,
        decoder: OutputDecoder,
        explainer: Explainer,
        output_transforms: Sequence[Transform] = (),
        rng: jax.Array | None = None,
        metadata: Mapping[str, Any] | None = None,
    ) -> None:
        self._model = model
        self._transforms = tuple(transforms)
        self._sample = sample
        self._decoder = decoder
        self._explainer = explainer
        self._output_transform = compose(output_transforms)
        self._metadata = dict(metadata or {})
        self._rng = jax.random.key(0) if rng is None else rng
        robot = [t for t in self._transforms if isinstance(t, RobotInputs)]
        resize = [t for t in self._transforms if isinstance(t, ResizeImages)]
        if len(robot) != 1 or len(resize) != 1:
            raise ValueError("Policy transforms need exactly one robot input transform and one ResizeImages")
        self._robot_inputs: RobotInputs = robot[0]
        self._resolution = (resize[0].height, resize[0].width)
        self._lock = threading.Lock()
        self._malformed = WarnOnceCounter(logger, "Malformed generation, upstream's zero-action fallback returned")

    @property
    def model(self) -> object:
        """The family's model object (`Pi0FAST` or `Pi0`)."""
        return self._model

    @property
    def explainer(self) -> Explainer:
        return self._explainer

    @property
    def metadata(self) -> dict[str, Any]:
        return self._metadata

    @property
    def image_resolution(self) -> tuple[int, int]:
        return self._resolution

    @property
    def camera_sources(self) -> Mapping[str, str | None]:
        return self._robot_inputs.camera_sources

    def stats(self) -> dict[str, Any]:
        malformed = self._malformed.snapshot()
        requests = malformed.pop(_REQUESTS, 0)
        return {"requests": requests, "malformed": malformed}

    def close(self, timeout: float | None = None) -> None:
        """Nothing to release; present so every served object has the same interface."""

    def infer(
        self, obs: Mapping[str, Any], context: object = None, *, noise: np.ndarray | None = None
    ) -> dict[str, Any]:
        """Upstream's `Policy.infer`; `noise` [horizon, action dim] fixes a flow-matching policy's noise."""
        return self.infer_traced(obs, noise=noise)[0]

    def infer_batch(
        self, observations: Sequence[Mapping[str, Any]], contexts: Sequence[object] = ()
    ) -> list[dict[str, Any] | Exception]:
        """Batched serving (`infer_batch_traced`) without the traces: one response or exception per request."""
        return [r if isinstance(r, Exception) else r[0] for r in self.infer_batch_traced(observations)]

    def infer_traced(
        self, obs: Mapping[str, Any], *, noise: np.ndarray | None = None, signals: bool = False
    ) -> tuple[dict[str, Any], InferenceTrace]:
        """`infer` and the trace of the call; with `signals` the trace also holds what a failure monitor reads of the
        call (`InferenceTrace.signals`), computed by the same model call, whose response is the one without."""
        request = self._prepare(obs)
        with self._lock:  # like upstream: the policy's rng is split once per call
            self._rng, sample_rng = jax.random.split(self._rng)
        (result,) = self._serve([request], [sample_rng], noise, signals=signals)
        if isinstance(result, Exception):
            raise result
        return result

    def infer_batch_traced(
        self, observations: Sequence[Mapping[str, Any]], *, signals: bool = False
    ) -> list[tuple[dict[str, Any], InferenceTrace] | Exception]:
        """Several requests (e.g. from different robots) in one model call per input shape. Row i gets what
        `infer_traced(observations[i], signals=signals)` returns when the requests are served one after another in
        this order: the rng is split once per valid request, in order, and the sampler decodes each row as if alone.
        A request that fails gets its exception in its slot; the others are still served."""
        results: list[tuple[dict[str, Any], InferenceTrace] | Exception | None] = []
        prepared: list[tuple[int, _Prepared]] = []
        for i, obs in enumerate(observations):
            try:
                prepared.append((i, self._prepare(obs)))
                results.append(None)
            except Exception as e:  # this request's own problem: its slot says so, the batch goes on
                results.append(e)
        with self._lock:
            rngs = []
            for _ in prepared:
                self._rng, sample_rng = jax.random.split(self._rng)
                rngs.append(sample_rng)
        # Rows are stacked only when their model inputs have the same shapes (a robot with another camera set or
        # state size is its own group).
        groups: dict[Any, list[int]] = {}
        for k, (_, request) in enumerate(prepared):
            groups.setdefault(request.signature, []).append(k)
        for members in groups.values():
            served = self._serve([prepared[k][1] for k in members], [rngs[k] for k in members], None, signals=signals)
            for k, result in zip(members, served, strict=True):
                results[prepared[k][0]] = result
        return results  # type: ignore[return-value]  (every slot is filled above)

    def warm_up(self, batch_sizes: Sequence[int] = (1,), *, signals: bool = False) -> InferenceTrace | None:
        """Compiles inference for the served shapes (and each of `batch_sizes`, for batched serving; with `signals`
        the program that also computes them) by running the robot's example observation (model inputs have fixed
        shapes whatever the client's image size), so the first request does not wait for XLA. The policy's rng stream
        and counters are untouched: served actions stay upstream's. Returns the example's trace (the side channel
        warms its explanation with it), or None when the robot transform offers no example."""
        example = example_observation(self._robot_inputs)
        if example is None:
            return None
        request = self._prepare(example)
        with self._lock:
            _, sample_rng = jax.random.split(self._rng)  # compiles the per-request split; self._rng is not advanced
        traces = []
        for size in sorted({batch_bucket(n) for n in batch_sizes}):
            result = self._serve([request] * size, [sample_rng] * size, None, count=False, signals=signals)[0]
            if isinstance(result, Exception):
                raise result
            traces.append(result[1])
        return traces[0]

    def _prepare(self, obs: Mapping[str, Any]) -> _Prepared:
        """Validates one request and runs the input transforms (on a copy: the client's containers stay as sent)."""
        if not isinstance(obs, Mapping):
            raise InvalidRequest(f"an observation must be a dict, got {type(obs).__name__}")
        if "actions" in obs:
            # Upstream would tokenise them into the prompt as a training target; at inference that is never meant.
            raise InvalidRequest("'actions' must not be sent with an observation")
        camera_sources = self._robot_inputs.camera_sources_for(obs)
        inputs, pre_resize_images, prompt = self._apply_inputs(_copy_containers(obs))
        context = inputs.pop(OUTPUT_CONTEXT, {})
        # A leading batch axis on every leaf (jax pytree order, i.e. cameras sorted by name), as upstream.
        batched = jax.tree.map(lambda x: jnp.asarray(x)[np.newaxis, ...], inputs)
        observation = Observation.from_dict(batched)
        client = _client_inputs(obs, set(camera_sources.values()))
        state = np.asarray(batched["state"][0])
        return _Prepared(observation, state, pre_resize_images, prompt, camera_sources, client, context, obs)

    def _serve(
        self,
        requests: Sequence[_Prepared],
        rngs: Sequence[jax.Array],
        noise: np.ndarray | None,
        *,
        count: bool = True,
        signals: bool = False,
    ) -> list[tuple[dict[str, Any], InferenceTrace] | Exception]:
        """One model call for requests of one input signature, padded to a batch bucket (padding rows repeat the
        last request; their outputs are dropped); then each row's output transforms and trace."""
        rows = len(requests)
        padded = batch_bucket(rows)
        observation = requests[0].observation
        if padded > 1:
            stacked = stack_observations([r.observation for r in requests])
            observation = jax.tree.map(lambda x: pad_rows(x, padded), stacked)
        start = time.monotonic()
        try:
            raw, drawn, monitored = self._sample(
                list(rngs) + [rngs[-1]] * (padded - rows), observation, noise, signals=signals
            )
        except Exception as e:  # every row of this call failed the same way
            return [e] * rows
        model_time = time.monotonic() - start
        results: list[tuple[dict[str, Any], InferenceTrace] | Exception] = []
        for i, request in enumerate(requests):
            try:
                row = {k: v[i] for k, v in monitored.items()}
                results.append(
                    self._finish(request, raw[i], {k: v[i] for k, v in drawn.items()}, model_time, row, signals)
                )
            except Exception as e:
                results.append(e)
                continue
            if count:
                self._malformed.count(_REQUESTS)
                if (reason := results[-1][1].malformed_reason) is not None:
                    self._malformed.count(reason, "the model's output decodes to no actions")
        return results

    def _finish(
        self,
        request: _Prepared,
        raw: np.ndarray,
        drawn: dict[str, np.ndarray],
        model_time: float,
        monitored: dict[str, np.ndarray],
        signals: bool,
    ) -> tuple[dict[str, Any], InferenceTrace]:
        output = np.asarray(raw)
        actions, reason = self._decoder.extract(output)
        normalized = np.array(actions, np.float64)  # copied before the output transforms see the chunk
        outputs = self._output_transform({**request.context, "state": request.state, "actions": actions})
        if signals:
            # the robot's action dimensions lead the model's (a config pads actions at the end), and only they are
            # executed: a monitor compares chunks over those
            monitored = {**monitored, NORMALIZED_CHUNK: normalized[..., : np.shape(outputs["actions"])[-1]]}
        outputs["policy_timing"] = {"infer_ms": model_time * 1000}
        cameras = request.observation.camera_names
        images, sources = request.pre_resize_images, request.camera_sources
        trace = InferenceTrace(
            observation=request.observation,
            output=output,
            sample_inputs={k: np.asarray(v) for k, v in drawn.items()},
            raw_images={c: None if sources.get(c) is None else images[c] for c in cameras},
            camera_sources={c: sources.get(c) for c in cameras},
            geometry={c: letterbox_geometry(*images[c].shape[-3:-1], *self._resolution) for c in cameras},
            prompt=request.prompt,
            malformed_reason=reason,
            client_inputs=request.client_inputs,
            request=request.request,
            output_context=request.context,
            signals=monitored,
        )
        return outputs, trace

    def resample(self, trace: InferenceTrace, observation: Observation) -> np.ndarray:
        """The actions `infer` returns when the model sees `observation` (B = 1; e.g. the traced input with a camera
        replaced, or `with_prompt`'s) in place of the traced call's input: the traced call's noise (pi0 / pi0.5),
        state and output context through the same sampler, decoder and output transforms. The policy's rng and
        counters are untouched. -> actions [horizon, action dim] in the robot's units."""
        noise = trace.sample_inputs.get("noise")
        with self._lock:
            _, rng = jax.random.split(self._rng)  # unused by the families' samplers given the noise (pi0-FAST greedy)
        raw, _, _ = self._sample([rng], observation, None if noise is None else np.asarray(noise))
        return self._robot_actions(trace, raw[0])

    def normalized_chunks(self, trace: InferenceTrace, noises: np.ndarray) -> np.ndarray:
        """The chunks the traced call's input gives from each of `noises` [N, horizon, action dim] (pi0 / pi0.5), in
        the units a monitor compares them in (the trace's `NORMALIZED_CHUNK`: the robot's action dimensions before the
        output transforms) -> [N, horizon, robot action dim]. The policy's rng and counters are untouched."""
        if "noise" not in trace.sample_inputs:
            raise ValueError("the policy draws no noise (pi0-FAST decodes greedily): a call has no other samples")
        if NORMALIZED_CHUNK not in trace.signals:
            raise ValueError(f"the call was served without signals (no {NORMALIZED_CHUNK!r} to compare with)")
        width = np.shape(trace.signals[NORMALIZED_CHUNK])[-1]
        with self._lock:
            _, rng = jax.random.split(self._rng)  # unused given the noise
        chunks = []
        for noise in np.asarray(noises, np.float32):
            raw, _, _ = self._sample([rng], trace.observation, noise)
            actions, _ = self._decoder.extract(np.asarray(raw[0]))
            chunks.append(np.asarray(actions, np.float64)[..., :width])
        return np.stack(chunks)

    def served_actions(self, trace: InferenceTrace) -> np.ndarray:
        """The actions `infer` returned for the traced call, from its raw output (decoder and output transforms)."""
        return self._robot_actions(trace, trace.output)

    def _robot_actions(self, trace: InferenceTrace, raw: np.ndarray) -> np.ndarray:
        actions, _ = self._decoder.extract(np.asarray(raw))
        state = np.asarray(trace.observation.state)[0]
        outputs = self._output_transform({**trace.output_context, "state": state, "actions": actions})
        return np.asarray(outputs["actions"])

    def with_prompt(self, trace: InferenceTrace, prompt: str) -> Observation:
        """The traced call's model input with `prompt` in place of its prompt: the client's observation prepared
        again (every input transform, so the prompt is tokenised as served, with the state where the family puts
        it), its images and state unchanged."""
        if trace.request is None:
            raise ValueError("the trace does not hold the client's observation to prepare again")
        return self._prepare({**trace.request, "prompt": prompt}).observation

    def training_inputs(self, obs: Mapping[str, Any], actions: np.ndarray) -> DataDict:
        """The model inputs training builds from an observation and a recorded action chunk [horizon, action dim]:
        the same input transforms, with the actions delta-coded, normalised and (pi0-FAST) tokenised into the
        prompt's postfix. What a demonstrated chunk looks like to the model."""
        if not isinstance(obs, Mapping):
            raise InvalidRequest(f"an observation must be a dict, got {type(obs).__name__}")
        data = _copy_containers(obs)
        data["actions"] = np.asarray(actions)
        return self._apply_inputs(data)[0]

    def _apply_inputs(self, data: DataDict) -> tuple[DataDict, dict[str, np.ndarray], str]:
        """Run the input transforms, keeping the images just before resizing (as the uint8 frames a trace records)
        and the prompt just before it is tokenised (the last value it has before a transform consumes it)."""
        images: dict[str, np.ndarray] = {}
        prompt = ""
        for transform in self._transforms:
            if isinstance(transform, ResizeImages):
                images = {name: transform.client_frame(image) for name, image in data["image"].items()}
            if data.get("prompt") is not None:
                prompt = parse_prompt(data["prompt"])
            data = transform(data)
        return data, images, prompt


def build_transforms(
    config: PolicyConfig,
    norm_stats: Mapping[str, Any],
    tokenize: Sequence[Transform],
    image_resolution: tuple[int, int],
    *,
    default_prompt: str | None = None,
) -> tuple[list[Transform], list[Transform]]:
    """Upstream `create_trained_policy`'s chains around the family's own steps: (input transforms ending in the
    family's `tokenize` steps, output transforms after the family's output decoder)."""
    inputs: list[Transform] = [
        InjectDefaultPrompt(default_prompt),
        *config.inputs,
        Normalize(norm_stats, use_quantiles=config.use_quantile_norm),
        InjectDefaultPrompt(config.default_prompt),
        ResizeImages(*image_resolution),
        *tokenize,
    ]
    outputs: list[Transform] = [
        Unnormalize(norm_stats, use_quantiles=config.use_quantile_norm),
        *config.outputs,
    ]
    return inputs, outputs


def create_policy(
    config: str | PolicyConfig | None,
    checkpoint_dir: str | Path,
    *,
    paligemma_tokenizer: str | Path | sentencepiece.SentencePieceProcessor | None = None,
    fast_tokenizer: str | Path | FastActionTokenizer | None = None,
    dtype: str = "bfloat16",
    default_prompt: str | None = None,
    stop_at_action_end: bool = False,
    max_decoding_steps: int = MAX_DECODING_STEPS,
    rng: jax.Array | None = None,
) -> Policy:
    """A served policy from an OpenPI checkpoint folder, whose format `checkpoint_format` recognises: OpenPI's orbax
    checkpoint (``params/`` and ``assets/<asset_id>/norm_stats.json``) or OpenPI's PyTorch export
    (``model.safetensors`` and the same ``assets/``), served with the named `config` (None is refused, naming the
    folder's format). A LeRobot pi0 / pi0.5 policy folder is served by its own files (`lerobot.policy`), and refused
    here.

    ``paligemma_tokenizer``: a SentencePiece model path or a loaded processor (None: upstream's cache location);
    ``fast_tokenizer``: a FAST tokenizer directory or a loaded `FastActionTokenizer` (None: the HF cache).
    ``stop_at_action_end`` ends decoding at the first token containing "|" (upstream decodes to EOS; what follows
    "|" is ignored by action extraction, so actions are unchanged, only the generation is shorter).
    """
    checkpoint_dir = Path(checkpoint_dir)
    kind = checkpoint_format(checkpoint_dir)
    if kind == "lerobot":
        name = "" if config is None else f", not {config if isinstance(config, str) else config.name!r}"
        raise ValueError(f"{checkpoint_dir} is a LeRobot policy folder, served by its own config.json{name}")
    if config is None:
        raise ValueError(f"{checkpoint_dir} is an OpenPI checkpoint ({kind}): name the config that serves it")
    cfg = resolve_config(config)
    if kind == "orbax":
        weights = checkpoint_dir / PARAMS_DIR
        checkpoint_family = family_of(read_param_shapes(weights))
    else:
        weights = checkpoint_dir / WEIGHTS_FILE
        checkpoint_family = torch_family(read_tensor_infos(weights), where=str(weights))
    if checkpoint_family != cfg.family:
        raise ValueError(f"config {cfg.name!r} serves {cfg.family}, the checkpoint at {weights} is {checkpoint_family}")
    norm_stats = load_checkpoint_norm_stats(checkpoint_dir, cfg.asset_id)
    parts: FastParts | FlowParts
    if cfg.family == "pi0_fast":
        parts = build_pi0_fast(
            cfg,
            weights,
            paligemma_tokenizer=paligemma_tokenizer,
            fast_tokenizer=fast_tokenizer,
            dtype=dtype,
            max_decoding_steps=max_decoding_steps,
            stop_at_action_end=stop_at_action_end,
        )
    else:
        heads = read_head_counts(checkpoint_dir)
        parts = build_pi0(cfg, weights, paligemma_tokenizer=paligemma_tokenizer, dtype=dtype, heads=heads)
    inputs, outputs = build_transforms(
        cfg, norm_stats, parts.tokenize, parts.model.config.image_resolution, default_prompt=default_prompt
    )
    return Policy(
        parts.model,
        transforms=inputs,
        sample=parts.sample,
        decoder=parts.decoder,
        explainer=parts.explainer,
        output_transforms=outputs,
        rng=rng,
        metadata=cfg.policy_metadata,
    )
