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
from openpi_cam.image_tools import LetterboxGeometry, letterbox_geometry
from openpi_cam.model.checkpoint import read_param_shapes
from openpi_cam.model.config import MAX_DECODING_STEPS, family_of
from openpi_cam.model.observation import Observation
from openpi_cam.normalize import load_checkpoint_norm_stats
from openpi_cam.policies.config import PolicyConfig, resolve_config
from openpi_cam.policies.family import Explainer, OutputDecoder, Sampler
from openpi_cam.policies.pi0_family import FlowParts, build_pi0
from openpi_cam.policies.pi0_fast_family import FastParts, build_pi0_fast
from openpi_cam.policies.robot import RobotInputs, example_observation
from openpi_cam.tokenizers.fast import FastActionTokenizer
from openpi_cam.transforms import (
    DataDict,
    InjectDefaultPrompt,
    Normalize,
    ResizeImages,
    Transform,
    Unnormalize,
    compose,
    parse_prompt,
)

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

    @property
    def camera_names(self) -> tuple[str, ...]:
        return self.observation.camera_names


def _copy_containers(tree: Any) -> Any:
    # Transforms may modify dicts in place; the client's own containers must stay untouched (upstream copies too).
    if isinstance(tree, Mapping):
        return {k: _copy_containers(v) for k, v in tree.items()}
    if isinstance(tree, list):
        return [_copy_containers(v) for v in tree]
    return tree


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

    def infer_traced(
        self, obs: Mapping[str, Any], *, noise: np.ndarray | None = None
    ) -> tuple[dict[str, Any], InferenceTrace]:
        if not isinstance(obs, Mapping):
            raise InvalidRequest(f"an observation must be a dict, got {type(obs).__name__}")
        if "actions" in obs:
            # Upstream would tokenise them into the prompt as a training target; at inference that is never meant.
            raise InvalidRequest("'actions' must not be sent with an observation")
        camera_sources = self._robot_inputs.camera_sources_for(obs)
        inputs, pre_resize_images, prompt = self._apply_inputs(_copy_containers(obs))

        # Like upstream: the policy's rng is split once per call.
        with self._lock:
            self._rng, sample_rng = jax.random.split(self._rng)
        outputs, trace = self._run(inputs, pre_resize_images, prompt, camera_sources, sample_rng, noise)
        self._malformed.count(_REQUESTS)
        if trace.malformed_reason is not None:
            self._malformed.count(trace.malformed_reason, "the model's output decodes to no actions")
        return outputs, trace

    def warm_up(self) -> InferenceTrace | None:
        """Compiles inference for the served shapes by running the robot's example observation (model inputs have
        fixed shapes whatever the client's image size), so the first request does not wait for XLA. The policy's rng
        stream and counters are untouched: served actions stay upstream's. Returns the example's trace (the side
        channel warms its explanation with it), or None when the robot transform offers no example."""
        example = example_observation(self._robot_inputs)
        if example is None:
            return None
        camera_sources = self._robot_inputs.camera_sources_for(example)
        inputs, pre_resize_images, prompt = self._apply_inputs(example)
        with self._lock:
            _, sample_rng = jax.random.split(self._rng)  # compiles the per-request split; self._rng is not advanced
        return self._run(inputs, pre_resize_images, prompt, camera_sources, sample_rng, None)[1]

    def _run(
        self,
        inputs: DataDict,
        pre_resize_images: dict[str, np.ndarray],
        prompt: str,
        camera_sources: Mapping[str, str | None],
        sample_rng: jax.Array,
        noise: np.ndarray | None,
    ) -> tuple[dict[str, Any], InferenceTrace]:
        # A leading batch axis on every leaf (jax pytree order, i.e. cameras sorted by name), as upstream.
        batched = jax.tree.map(lambda x: jnp.asarray(x)[np.newaxis, ...], inputs)
        observation = Observation.from_dict(batched)

        start = time.monotonic()
        raw, drawn = self._sample(sample_rng, observation, noise)
        model_time = time.monotonic() - start

        output = np.asarray(raw[0])
        state = np.asarray(batched["state"][0])
        actions, reason = self._decoder.extract(output)
        outputs = self._output_transform({"state": state, "actions": actions})
        outputs["policy_timing"] = {"infer_ms": model_time * 1000}

        cameras = observation.camera_names
        trace = InferenceTrace(
            observation=observation,
            output=output,
            sample_inputs={k: np.asarray(v)[0] for k, v in drawn.items()},
            raw_images={c: None if camera_sources.get(c) is None else pre_resize_images[c] for c in cameras},
            camera_sources={c: camera_sources.get(c) for c in cameras},
            geometry={c: letterbox_geometry(*pre_resize_images[c].shape[-3:-1], *self._resolution) for c in cameras},
            prompt=prompt,
            malformed_reason=reason,
        )
        return outputs, trace

    def _apply_inputs(self, data: DataDict) -> tuple[DataDict, dict[str, np.ndarray], str]:
        """Run the input transforms, keeping the images just before resizing and the prompt just before it is
        tokenised (the last value it has before a transform consumes it)."""
        images: dict[str, np.ndarray] = {}
        prompt = ""
        for transform in self._transforms:
            if isinstance(transform, ResizeImages):
                images = dict(data["image"])
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
    config: str | PolicyConfig,
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
    """A served policy from ``<checkpoint_dir>/params`` and ``<checkpoint_dir>/assets/<asset_id>/norm_stats.json``.

    ``paligemma_tokenizer``: a SentencePiece model path or a loaded processor (None: upstream's cache location);
    ``fast_tokenizer``: a FAST tokenizer directory or a loaded `FastActionTokenizer` (None: the HF cache).
    ``stop_at_action_end`` ends decoding at the first token containing "|" (upstream decodes to EOS; what follows
    "|" is ignored by action extraction, so actions are unchanged, only the generation is shorter).
    """
    cfg = resolve_config(config)
    checkpoint_dir = Path(checkpoint_dir)
    params_dir = checkpoint_dir / "params"
    if not params_dir.is_dir():
        raise FileNotFoundError(f"model params not found: expected an orbax checkpoint directory at {params_dir}")
    checkpoint_family = family_of(read_param_shapes(params_dir))
    if checkpoint_family != cfg.family:
        raise ValueError(
            f"config {cfg.name!r} serves {cfg.family}, the checkpoint at {params_dir} is {checkpoint_family}"
        )
    norm_stats = load_checkpoint_norm_stats(checkpoint_dir, cfg.asset_id)
    parts: FastParts | FlowParts
    if cfg.family == "pi0_fast":
        parts = build_pi0_fast(
            cfg,
            params_dir,
            paligemma_tokenizer=paligemma_tokenizer,
            fast_tokenizer=fast_tokenizer,
            dtype=dtype,
            max_decoding_steps=max_decoding_steps,
            stop_at_action_end=stop_at_action_end,
        )
    else:
        parts = build_pi0(cfg, params_dir, paligemma_tokenizer=paligemma_tokenizer, dtype=dtype)
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
