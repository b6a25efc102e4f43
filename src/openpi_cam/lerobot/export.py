"""An OpenPI orbax pi0 / pi0.5 checkpoint written as a LeRobot policy folder (`openpi-cam export --to lerobot`).

The folder is what LeRobot 0.6's `save_pretrained` and processor `save_pretrained` write for the same policy:
`config.json` (its PI0Config / PI05Config fields), `model.safetensors` (every tensor of its module, the LM heads
included, which its strict loader requires), the two processor pipelines in LeRobot 0.6.1's step order with the
normaliser statistics, a `tokenizer/` directory with the SentencePiece model (when one is given), and for sizes
LeRobot's variant table lacks, the sizes record `checkpoint_format.read_head_counts` and a LeRobot loader read.

The statistics are the checkpoint's own (`<checkpoint>/assets/<asset id>/norm_stats.json`); OpenPI's own converter
copies them from the checkpoint's parent folder instead. The policy must be one LeRobot's pipeline can express: a
`GenericInputs` robot (the cameras as LeRobot features, blank cameras last and masked: LeRobot's empty cameras) and
`GenericOutputs`, no default prompt, and for pi0.5 the state in the prompt. Served as LeRobot serves it, the folder
differs from the original in float rounding (LeRobot's normaliser epsilon, its Euler times and time embedding:
`Pi0Config.flow_time`), so its chunks are the original's to float32 precision, for frames at the model's resolution:
frames of other sizes LeRobot resizes with torch's bilinear interpolation, OpenPI with PIL's, and the two images
differ visibly.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
from safetensors.numpy import save_file

from openpi_cam.lerobot.policy import ACTION, OBS_IMAGES, OBS_STATE
from openpi_cam.model.pi0 import MAX_PERIOD, MIN_PERIOD, Pi0
from openpi_cam.model.safetensors_weights import save_safetensors_params
from openpi_cam.normalize import NormStats, load_checkpoint_norm_stats
from openpi_cam.policies.checkpoint_format import (
    ASSETS_DIR,
    CONFIG_FILE,
    PARAMS_DIR,
    POSTPROCESSOR_FILE,
    PREPROCESSOR_FILE,
    WEIGHTS_FILE,
    checkpoint_format,
    write_sizes_record,
)
from openpi_cam.policies.config import PolicyConfig, resolve_config
from openpi_cam.policies.robot import GenericInputs, GenericOutputs
from openpi_cam.tokenizers.paligemma import PALIGEMMA_HUB_ID, load_paligemma_tokenizer, resolve_paligemma_tokenizer_path

TOKENIZER_DIR = "tokenizer"
EXPORT_DTYPES = ("float32", "bfloat16")  # the values of LeRobot's pi0 / pi0.5 `dtype` field
# What LeRobot's converted PaliGemma tokenizer declares; transformers builds it from tokenizer.model.
TOKENIZER_CONFIG = {
    "tokenizer_class": "GemmaTokenizer",
    "bos_token": "<bos>",
    "eos_token": "<eos>",
    "pad_token": "<pad>",
    "unk_token": "<unk>",
    "add_bos_token": True,
    "add_eos_token": False,
}
# The training fields of LeRobot 0.6.1's PI0Config / PI05Config at their defaults (serving reads none of them).
_TRAINING_DEFAULTS: dict[str, Any] = {
    "n_obs_steps": 1, "device": "cpu", "use_amp": False, "use_peft": False, "push_to_hub": False, "repo_id": None,
    "private": None, "tags": None, "license": None, "pretrained_path": None, "pretrained_revision": None,
    "time_sampling_beta_alpha": 1.5, "time_sampling_beta_beta": 1.0, "time_sampling_scale": 0.999,
    "time_sampling_offset": 0.001, "use_relative_actions": False, "relative_exclude_joints": ["gripper"],
    "action_feature_names": None, "rtc_config": None, "gradient_checkpointing": False, "compile_model": False,
    "compile_mode": "max-autotune", "freeze_vision_encoder": False, "train_expert_only": False,
    "optimizer_lr": 2.5e-05, "optimizer_betas": [0.9, 0.95], "optimizer_eps": 1e-08, "optimizer_weight_decay": 0.01,
    "optimizer_grad_clip_norm": 1.0, "scheduler_warmup_steps": 1000, "scheduler_decay_steps": 30000,
    "scheduler_decay_lr": 2.5e-06,
}  # fmt: skip


@dataclasses.dataclass(frozen=True)
class ExportPlan:
    """How an OpenPI policy config's robot maps onto LeRobot features."""

    cameras: dict[str, str]  # model camera -> LeRobot image feature (real cameras, in model order)
    blank: tuple[str, ...]  # model cameras that are always blank (LeRobot's empty cameras, last)
    state_dim: int
    action_dim: int


def plan_export(cfg: PolicyConfig) -> ExportPlan:
    """The LeRobot features of `cfg`'s robot, or a one-line refusal naming what LeRobot's pipeline cannot express."""
    if cfg.family not in ("pi0", "pi05"):
        raise ValueError(f"config {cfg.name!r} serves {cfg.family}; LeRobot folders are exported for pi0 / pi0.5")
    if len(cfg.inputs) != 1 or not isinstance(cfg.inputs[0], GenericInputs):
        raise ValueError(f"config {cfg.name!r}: only a GenericInputs robot maps onto LeRobot's features")
    if len(cfg.outputs) != 1 or not isinstance(cfg.outputs[0], GenericOutputs):
        raise ValueError(f"config {cfg.name!r}: only GenericOutputs maps onto LeRobot's postprocessor")
    if cfg.default_prompt is not None:
        raise ValueError(f"config {cfg.name!r} has a default prompt, which a LeRobot policy cannot carry")
    if cfg.family == "pi05" and not cfg.discrete_state_input:
        raise ValueError(f"config {cfg.name!r}: LeRobot's pi0.5 always reads the state in its prompt")
    robot: GenericInputs = cfg.inputs[0]
    if robot.state_dim is None:
        raise ValueError(f"config {cfg.name!r}: its robot declares no state_dim, which LeRobot's features need")
    keys = dict(cfg.lerobot_keys or {})
    sources = list(robot.cameras.items())
    blank = tuple(c for c, key in sources if key is None)
    if blank and (not robot.mask_blank or [c for c, _ in sources[-len(blank) :]] != list(blank)):
        raise ValueError(f"config {cfg.name!r}: blank cameras must be masked and last to be LeRobot's empty cameras")
    cameras = {c: keys.get(key, OBS_IMAGES + c) for c, key in sources if key is not None}
    if not all(name.startswith(OBS_IMAGES) for name in cameras.values()):
        raise ValueError(f"config {cfg.name!r}: LeRobot image features are {OBS_IMAGES}<name>, got {cameras}")
    if keys.get(robot.state_key, OBS_STATE) != OBS_STATE or keys.get("actions", ACTION) != ACTION:
        raise ValueError(f"config {cfg.name!r}: LeRobot's pi0 / pi0.5 read '{OBS_STATE}' and write '{ACTION}'")
    return ExportPlan(cameras, blank, robot.state_dim, cfg.outputs[0].action_dim)


def lerobot_config(cfg: PolicyConfig, plan: ExportPlan, model: Pi0, dtype: str = "float32") -> dict[str, Any]:
    """config.json of the exported policy: LeRobot's fields, the sizes named as its variants (the real ones are in
    the weights and, for sizes it lacks, the sizes record), `dtype` the policy's compute dtype."""
    res = model.config.siglip.image_size
    empty = {f"{OBS_IMAGES}empty_camera_{i}": [3, res, res] for i in range(len(plan.blank))}
    quantiles = cfg.use_quantile_norm
    return {
        "type": cfg.family,
        "input_features": {
            **{name: {"type": "VISUAL", "shape": [3, res, res]} for name in plan.cameras.values()},
            **{name: {"type": "VISUAL", "shape": shape} for name, shape in empty.items()},
            OBS_STATE: {"type": "STATE", "shape": [plan.state_dim]},
        },
        "output_features": {ACTION: {"type": "ACTION", "shape": [plan.action_dim]}},
        "paligemma_variant": "gemma_2b",
        "action_expert_variant": "gemma_300m",
        "dtype": dtype,
        "chunk_size": cfg.action_horizon,
        "n_action_steps": cfg.action_horizon,
        "max_state_dim": model.config.action_dim,
        "max_action_dim": model.config.action_dim,
        "num_inference_steps": model.config.num_steps,
        "min_period": MIN_PERIOD,
        "max_period": MAX_PERIOD,
        "image_resolution": [res, res],
        "empty_cameras": len(plan.blank),
        "tokenizer_max_length": cfg.max_token_len,
        "normalization_mapping": {
            "VISUAL": "IDENTITY",
            "STATE": "QUANTILES" if quantiles else "MEAN_STD",
            "ACTION": "QUANTILES" if quantiles else "MEAN_STD",
        },
        **_TRAINING_DEFAULTS,
    }


def _stats_tensors(norm_stats: dict[str, NormStats], plan: ExportPlan, where: str) -> dict[str, np.ndarray]:
    """`<feature>.<stat>` float32 arrays of the state and the action, cut to their dims (OpenPI's may be longer)."""
    out = {}
    for ours, feature, dim in (("state", OBS_STATE, plan.state_dim), ("actions", ACTION, plan.action_dim)):
        if ours not in norm_stats:
            raise ValueError(f"{where}: no '{ours}' statistics")
        stats = norm_stats[ours]
        for name in ("mean", "std", "q01", "q99"):
            value = getattr(stats, name)
            if value is not None:
                if value.shape[-1] < dim:
                    raise ValueError(f"{where}: '{ours}' {name} has {value.shape[-1]} dims, the feature {dim}")
                out[f"{feature}.{name}"] = np.ascontiguousarray(value[..., :dim], np.float32)
    return out


def _pipelines(cfg: PolicyConfig, config: dict[str, Any], tokenizer_name: str) -> tuple[dict, dict]:
    """LeRobot 0.6.1's pre- and postprocessor step lists for pi0 / pi0.5 (`make_pi0_pre_post_processors`,
    `make_pi05_pre_post_processors`), the normaliser entries' state files named by their step index."""
    features = {**config["input_features"], **config["output_features"]}
    norm = {"eps": 1e-08, "norm_map": config["normalization_mapping"]}
    normalizer = {"registry_name": "normalizer_processor", "config": {**norm, "features": features}}
    relative = {"registry_name": "relative_actions_processor",
                "config": {"enabled": False, "exclude_joints": ["gripper"], "action_names": None}}  # fmt: skip
    tokenizer = {
        "registry_name": "tokenizer_processor",
        "config": {"max_length": cfg.max_token_len, "task_key": "task", "padding_side": "right",
                   "padding": "max_length", "truncation": True, "tokenizer_name": tokenizer_name},
    }  # fmt: skip
    device = {"registry_name": "device_processor", "config": {"device": "cpu", "float_dtype": None}}
    head = [
        {"registry_name": "rename_observations_processor", "config": {"rename_map": {}}},
        {"registry_name": "to_batch_processor", "config": {}},
    ]
    if cfg.family == "pi05":
        prompt = {"registry_name": "pi05_prepare_state_tokenizer_processor_step", "config": {}}
        steps = [*head, relative, normalizer, prompt, tokenizer, device]
    else:
        steps = [*head, {"registry_name": "pi0_new_line_processor", "config": {}}, tokenizer, device, relative,
                 normalizer]  # fmt: skip
    unnormalizer = {"registry_name": "unnormalizer_processor",
                    "config": {**norm, "features": config["output_features"]}}  # fmt: skip
    post = [unnormalizer, {"registry_name": "absolute_actions_processor", "config": {"enabled": False}}, device]
    for name, pipeline in (("policy_preprocessor", steps), ("policy_postprocessor", post)):
        for i, step in enumerate(pipeline):
            if step["registry_name"] in ("normalizer_processor", "unnormalizer_processor"):
                step["state_file"] = f"{name}_step_{i}_{step['registry_name']}.safetensors"
    return {"name": "policy_preprocessor", "steps": steps}, {"name": "policy_postprocessor", "steps": post}


def export_lerobot(
    checkpoint_dir: str | Path,
    config: str | PolicyConfig,
    out_dir: str | Path,
    *,
    paligemma_tokenizer: str | Path | None = None,
    dtype: str = "float32",
) -> Path:
    """Writes `checkpoint_dir` (OpenPI orbax, served by `config`) as a LeRobot policy folder `out_dir` (new or empty).
    `paligemma_tokenizer`: the SentencePiece model copied into the folder's `tokenizer/` (None: the folder names
    PaliGemma's Hub tokenizer, as LeRobot's own folders do). `dtype`: the policy's dtype, LeRobot's `dtype` field
    (float32 or bfloat16): the weights are stored in it (LeRobot's loader casts each into its parameter's dtype), the
    normaliser statistics stay float32."""
    checkpoint_dir, out = Path(checkpoint_dir), Path(out_dir)
    if dtype not in EXPORT_DTYPES:
        raise ValueError(f"dtype {dtype!r}: a LeRobot pi0 / pi0.5 policy is one of {', '.join(EXPORT_DTYPES)}")
    cfg = resolve_config(config)
    if (kind := checkpoint_format(checkpoint_dir)) != "orbax":
        raise ValueError(f"{checkpoint_dir} is a {kind} checkpoint; export reads OpenPI orbax checkpoints")
    if out.exists() and any(out.iterdir()):
        raise FileExistsError(f"{out} is not empty: export writes a new LeRobot folder")
    plan = plan_export(cfg)
    norm_stats = load_checkpoint_norm_stats(checkpoint_dir, cfg.asset_id)
    where = f"{checkpoint_dir}/{ASSETS_DIR}/{cfg.asset_id}"
    stats = _stats_tensors(norm_stats, plan, where)
    model = Pi0.from_checkpoint(
        checkpoint_dir / PARAMS_DIR, dtype="float32", action_horizon=cfg.action_horizon, max_token_len=cfg.max_token_len
    )
    if model.family != cfg.family:
        raise ValueError(f"config {cfg.name!r} serves {cfg.family}, the checkpoint is a {model.family} model")
    tokenizer_name = PALIGEMMA_HUB_ID
    if paligemma_tokenizer is not None:
        source = resolve_paligemma_tokenizer_path(paligemma_tokenizer)
        load_paligemma_tokenizer(source)  # a readable SentencePiece model
        tokenizer_name = TOKENIZER_DIR
    config_json = lerobot_config(cfg, plan, model, dtype)
    pre, post = _pipelines(cfg, config_json, tokenizer_name)
    out.mkdir(parents=True, exist_ok=True)
    (out / CONFIG_FILE).write_text(json.dumps(config_json, indent=4))
    save_safetensors_params(out / WEIGHTS_FILE, model.params, model.config, dtype=dtype, lm_heads=True)
    for pipeline, filename in ((pre, PREPROCESSOR_FILE), (post, POSTPROCESSOR_FILE)):
        (out / filename).write_text(json.dumps(pipeline, indent=2))
        for step in pipeline["steps"]:
            if "state_file" in step:
                features = step["config"]["features"]
                save_file(
                    {k: v for k, v in stats.items() if k.rpartition(".")[0] in features}, str(out / step["state_file"])
                )
    if paligemma_tokenizer is not None:
        (out / TOKENIZER_DIR).mkdir()
        shutil.copyfile(source, out / TOKENIZER_DIR / "tokenizer.model")
        (out / TOKENIZER_DIR / "tokenizer_config.json").write_text(json.dumps(TOKENIZER_CONFIG, indent=2))
    write_sizes_record(out, model.config)
    return out
