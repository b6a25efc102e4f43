"""`Policy`: upstream's `Policy.infer` for pi0-FAST, plus a trace of exactly what the model saw and produced."""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import jax
import jax.numpy as jnp
import numpy as np

from openpi_cam.errors import InvalidRequest
from openpi_cam.image_tools import LetterboxGeometry, letterbox_geometry
from openpi_cam.model.observation import Observation
from openpi_cam.normalize import load_checkpoint_norm_stats
from openpi_cam.policies.config import PolicyConfig, resolve_config
from openpi_cam.policies.robot import RobotInputs
from openpi_cam.transforms import (
    DataDict,
    ExtractFASTActions,
    InjectDefaultPrompt,
    Normalize,
    ResizeImages,
    TokenizeFASTInputs,
    Transform,
    Unnormalize,
    compose,
    parse_prompt,
)

logger = logging.getLogger(__name__)


class SamplingModel(Protocol):
    """What `Policy` needs from `openpi_cam.model.pi0_fast.Pi0FAST`."""

    def sample_actions(self, rng: jax.Array, observation: Observation, **kwargs: Any) -> jax.Array: ...


@dataclasses.dataclass(frozen=True)
class InferenceTrace:
    """One `infer` call as the model saw it. Per-camera dicts follow the model's camera order."""

    observation: Observation  # batched (B=1) model input, images float32 in [-1, 1]
    generated_tokens: np.ndarray  # int32 [max_decoding_steps], 0 after the decode loop stopped
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
    """Input transforms -> batched `Observation` -> `sample_actions` -> output transforms, as upstream's `Policy`.

    ``output_transforms`` are those after FAST action extraction (``extract``), which runs first, as in upstream's
    output chain; keeping it separate lets the policy report malformed generations.
    """

    def __init__(
        self,
        model: SamplingModel,
        *,
        tokenizer: Any,
        transforms: Sequence[Transform],
        extract: ExtractFASTActions,
        output_transforms: Sequence[Transform] = (),
        rng: jax.Array | None = None,
        sample_kwargs: Mapping[str, Any] | None = None,
        metadata: Mapping[str, Any] | None = None,
    ) -> None:
        self._model = model
        self._tokenizer = tokenizer
        self._transforms = tuple(transforms)
        self._extract = extract
        self._output_transform = compose(output_transforms)
        self._sample_kwargs = dict(sample_kwargs or {})
        self._metadata = dict(metadata or {})
        self._rng = jax.random.key(0) if rng is None else rng
        robot = [t for t in self._transforms if isinstance(t, RobotInputs)]
        resize = [t for t in self._transforms if isinstance(t, ResizeImages)]
        if len(robot) != 1 or len(resize) != 1:
            raise ValueError("Policy transforms need exactly one robot input transform and one ResizeImages")
        self._robot_inputs: RobotInputs = robot[0]
        self._resolution = (resize[0].height, resize[0].width)
        self._lock = threading.Lock()
        self._requests = 0
        self._malformed: Counter[str] = Counter()

    @property
    def model(self) -> SamplingModel:
        return self._model

    @property
    def tokenizer(self) -> Any:
        """The `Pi0FastTokenizer` (e.g. for `action_token_steps`)."""
        return self._tokenizer

    @property
    def metadata(self) -> dict[str, Any]:
        return self._metadata

    @property
    def image_resolution(self) -> tuple[int, int]:
        return self._resolution

    @property
    def camera_sources(self) -> Mapping[str, str | None]:
        return self._robot_inputs.camera_sources

    @property
    def sample_kwargs(self) -> dict[str, Any]:
        return dict(self._sample_kwargs)

    def stats(self) -> dict[str, Any]:
        with self._lock:
            return {"requests": self._requests, "malformed": dict(self._malformed)}

    def close(self, timeout: float | None = None) -> None:
        """Nothing to release; present so every served object has the same interface."""

    def infer(self, obs: Mapping[str, Any], context: Any = None) -> dict[str, Any]:
        return self.infer_traced(obs)[0]

    def infer_traced(self, obs: Mapping[str, Any]) -> tuple[dict[str, Any], InferenceTrace]:
        if not isinstance(obs, Mapping):
            raise InvalidRequest(f"an observation must be a dict, got {type(obs).__name__}")
        if "actions" in obs:
            # Upstream would tokenise them into the prompt as a training target; at inference that is never meant.
            raise InvalidRequest("'actions' must not be sent with an observation")
        camera_sources = self._robot_inputs.camera_sources_for(obs)
        inputs, pre_resize_images, prompt = self._apply_inputs(_copy_containers(obs))

        # Like upstream: a leading batch axis on every leaf (jax pytree order, i.e. cameras sorted by name), then the
        # policy's rng is split once per call.
        batched = jax.tree.map(lambda x: jnp.asarray(x)[np.newaxis, ...], inputs)
        with self._lock:
            self._rng, sample_rng = jax.random.split(self._rng)
        observation = Observation.from_dict(batched)

        start = time.monotonic()
        tokens = jax.block_until_ready(self._model.sample_actions(sample_rng, observation, **self._sample_kwargs))
        model_time = time.monotonic() - start

        generated = np.asarray(tokens[0]).astype(np.int32)
        state = np.asarray(batched["state"][0])
        actions, reason = self._extract.extract(generated)
        outputs = self._output_transform({"state": state, "actions": actions})
        outputs["policy_timing"] = {"infer_ms": model_time * 1000}
        self._count(reason)

        cameras = observation.camera_names
        trace = InferenceTrace(
            observation=observation,
            generated_tokens=generated,
            raw_images={c: None if camera_sources.get(c) is None else pre_resize_images[c] for c in cameras},
            camera_sources={c: camera_sources.get(c) for c in cameras},
            geometry={c: letterbox_geometry(*pre_resize_images[c].shape[-3:-1], *self._resolution) for c in cameras},
            prompt=prompt,
            malformed_reason=reason,
        )
        return outputs, trace

    def _apply_inputs(self, data: DataDict) -> tuple[DataDict, dict[str, np.ndarray], str]:
        """Run the input transforms, keeping the images just before resizing and the prompt just before tokenising."""
        images: dict[str, np.ndarray] = {}
        prompt = ""
        for transform in self._transforms:
            if isinstance(transform, ResizeImages):
                images = dict(data["image"])
            if isinstance(transform, TokenizeFASTInputs) and data.get("prompt") is not None:
                prompt = parse_prompt(data["prompt"])
            data = transform(data)
        return data, images, prompt

    def _count(self, reason: str | None) -> None:
        with self._lock:
            self._requests += 1
            if reason is None:
                return
            self._malformed[reason] += 1
            first = self._malformed[reason] == 1
        if first:
            logger.warning(
                "Malformed generation (%s): returning upstream's zero-action fallback; further ones are "
                "only counted (see stats())",
                reason,
            )


def build_transforms(
    config: PolicyConfig,
    norm_stats: Mapping[str, Any],
    tokenizer: Any,
    image_resolution: tuple[int, int],
    *,
    default_prompt: str | None = None,
) -> tuple[list[Transform], ExtractFASTActions, list[Transform]]:
    """Upstream `create_trained_policy`'s chains: (input transforms, FAST extraction, remaining output transforms)."""
    inputs: list[Transform] = [
        InjectDefaultPrompt(default_prompt),
        *config.inputs,
        Normalize(norm_stats, use_quantiles=config.use_quantile_norm),
        InjectDefaultPrompt(config.default_prompt),
        ResizeImages(*image_resolution),
        TokenizeFASTInputs(tokenizer),
    ]
    extract = ExtractFASTActions(tokenizer, action_horizon=config.action_horizon, action_dim=config.action_dim)
    outputs: list[Transform] = [
        Unnormalize(norm_stats, use_quantiles=config.use_quantile_norm),
        *config.outputs,
    ]
    return inputs, extract, outputs


def create_policy(
    config: str | PolicyConfig,
    checkpoint_dir: str | Path,
    *,
    paligemma_tokenizer: Any = None,
    fast_tokenizer: Any = None,
    dtype: str = "bfloat16",
    default_prompt: str | None = None,
    stop_at_action_end: bool = False,
    max_decoding_steps: int = 256,
    rng: jax.Array | None = None,
) -> Policy:
    """A served policy from ``<checkpoint_dir>/params`` and ``<checkpoint_dir>/assets/<asset_id>/norm_stats.json``.

    ``paligemma_tokenizer``: a SentencePiece model path or a loaded processor (None: upstream's cache location);
    ``fast_tokenizer``: a FAST tokenizer directory or a loaded `FastActionTokenizer` (None: the HF cache).
    ``stop_at_action_end`` ends decoding at the first token containing "|" (upstream decodes to EOS; what follows
    "|" is ignored by action extraction, so actions are unchanged, only the generation is shorter).
    """
    from openpi_cam.model.pi0_fast import Pi0FAST
    from openpi_cam.tokenizers.fast import FastActionTokenizer, resolve_fast_tokenizer_dir
    from openpi_cam.tokenizers.paligemma import load_paligemma_tokenizer
    from openpi_cam.tokenizers.pi0_fast import Pi0FastTokenizer

    cfg = resolve_config(config)
    checkpoint_dir = Path(checkpoint_dir)
    params_dir = checkpoint_dir / "params"
    if not params_dir.is_dir():
        raise FileNotFoundError(f"model params not found: expected an orbax checkpoint directory at {params_dir}")
    norm_stats = load_checkpoint_norm_stats(checkpoint_dir, cfg.asset_id)

    if isinstance(paligemma_tokenizer, str | Path | None):
        paligemma_tokenizer = load_paligemma_tokenizer(paligemma_tokenizer)
    if not isinstance(fast_tokenizer, FastActionTokenizer):
        fast_tokenizer = FastActionTokenizer.load(resolve_fast_tokenizer_dir(fast_tokenizer))
    tokenizer = Pi0FastTokenizer(paligemma_tokenizer, fast_tokenizer, cfg.max_token_len)

    model = Pi0FAST.from_checkpoint(
        params_dir,
        action_dim=cfg.action_dim,
        action_horizon=cfg.action_horizon,
        max_token_len=cfg.max_token_len,
        dtype=dtype,
    )
    inputs, extract, outputs = build_transforms(
        cfg, norm_stats, tokenizer, model.config.image_resolution, default_prompt=default_prompt
    )
    sample_kwargs: dict[str, Any] = {"max_decoding_steps": max_decoding_steps}
    if stop_at_action_end:
        sample_kwargs["stop_token_ids"] = tuple(tokenizer.end_of_action_token_ids)
    return Policy(
        model,
        tokenizer=tokenizer,
        transforms=inputs,
        extract=extract,
        output_transforms=outputs,
        rng=rng,
        sample_kwargs=sample_kwargs,
        metadata=cfg.policy_metadata,
    )
