"""Which model to load: one `ModelSpec` that every command takes as the same flags, that creates the policy, and
that runs and maps datasets record as JSON, so a run is explained or measured again with the very model that made it.

A spec is resolved once (`ModelSpec.source`) into the source its weights come from, and every question about the
model is answered by matching on that source:

- `BundledModel`: no checkpoint folder names the bundled demo model of the config (`demo_reach`, the tiny pi0-FAST, by
  default; `demo_reach_pi05`, ...); a folder with a demo config is one trained by `demo.train`. Its tokenizers lie
  beside its checkpoint; it computes in float32 and decodes few steps.
- `OpenPICheckpoint`: OpenPI's orbax checkpoint or PyTorch export (`checkpoint_format`), served with a named config
  (pi0_fast_droid unless one is named) in bfloat16 as upstream serves.
- `LeRobotFolder`: a LeRobot pi0 / pi0.5 policy folder, which its own config.json describes (naming a config is
  refused) and which computes in the dtype it was saved with.
"""

from __future__ import annotations

import dataclasses
import functools
import pathlib
from collections.abc import Mapping
from typing import Any, Literal

import jax

from openpi_cam.lerobot.policy import LeRobotConfig, RequestLayout, create_lerobot_policy, read_pipeline
from openpi_cam.model import occlusion_head
from openpi_cam.model.checkpoint import read_param_shapes
from openpi_cam.model.config import MAX_DECODING_STEPS, Pi0Config, architecture_from_params, family_of
from openpi_cam.model.safetensors_weights import pi0_config_from_tensors, read_tensor_infos
from openpi_cam.policies import demo_metaworld, demo_reach
from openpi_cam.policies.checkpoint_format import (
    CONFIG_FILE,
    PARAMS_DIR,
    PREPROCESSOR_FILE,
    WEIGHTS_FILE,
    CheckpointFormat,
    checkpoint_format,
    read_head_counts,
)
from openpi_cam.policies.config import resolve_config
from openpi_cam.policies.policy import Policy, create_policy
from openpi_cam.vocabulary import HeadRef

Dtype = Literal["bfloat16", "float32"]
# The named config a checkpoint is served with when none is given (README, "Serving your checkpoint").
DEFAULT_CHECKPOINT_CONFIG = "pi0_fast_droid"
DEMO_DTYPE: Dtype = "float32"  # the bundled models were trained and are measured in float32
CHECKPOINT_DTYPE: Dtype = "bfloat16"  # upstream's `create_trained_policy`
LEROBOT_DTYPE: Dtype = "float32"  # a LeRobot config's default `dtype`
DTYPES: tuple[Dtype, ...] = ("bfloat16", "float32")
# The bundled models by name (`openpi-cam demo --model`), their configs and where they ship.
BUNDLED_CONFIGS = {
    **demo_reach.DEMO_CONFIGS,
    "metaworld": demo_metaworld.DEMO_METAWORLD_CONFIG,
    "metaworld_mt_pi05": demo_metaworld.DEMO_METAWORLD_MT_PI05_CONFIG,
    "metaworld_mt_pi0_fast": demo_metaworld.DEMO_METAWORLD_MT_PI0_FAST_CONFIG,
}
BUNDLED_ASSETS = {
    **demo_reach.DEFAULT_ASSETS,
    "metaworld": demo_metaworld.ASSETS_METAWORLD,
    "metaworld_mt_pi05": demo_metaworld.ASSETS_MT_PI05,
    "metaworld_mt_pi0_fast": demo_metaworld.ASSETS_MT_PI0_FAST,
}
BUNDLED_MODELS = {config.name: model for model, config in BUNDLED_CONFIGS.items()}  # config name -> bundled model
# A demo model's failure monitor, beside its checkpoint: `serve` and `demo` use it by default when it is there.
MONITOR_FILE = "monitor.json"
# What must be the same for new steps to join a run or maps dataset (tokenizer files may move between machines).
_OUTPUT_FIELDS = ("checkpoint_dir", "config", "dtype")


def _path(value: str | pathlib.Path | None) -> pathlib.Path | None:
    return None if value is None else pathlib.Path(value).expanduser()


@dataclasses.dataclass(frozen=True)
class ModelFacts:
    """What planning a job needs of a model without its weights."""

    family: str  # pi0_fast, pi0, pi05
    grid: tuple[int, int]  # SigLIP's patch grid of every camera
    camera_sources: dict[str, str | None]  # model camera -> observation key (None: a blank camera), in token order


@dataclasses.dataclass(frozen=True)
class BundledModel:
    """A bundled demo model, or one `demo.train` trained into a folder of its own: an orbax checkpoint served by the
    model's demo config."""

    name: str  # the bundled model ("pi0_fast", "pi05", "metaworld": `BUNDLED_CONFIGS`)
    checkpoint: pathlib.Path
    # the package's own copy: recorded as no checkpoint folder, so a run finds it wherever the package is installed
    installed: bool

    @property
    def config(self) -> str:
        return BUNDLED_CONFIGS[self.name].name


@dataclasses.dataclass(frozen=True)
class OpenPICheckpoint:
    """An OpenPI checkpoint (orbax, or OpenPI's PyTorch export) served by a named config."""

    checkpoint: pathlib.Path
    config: str
    format: CheckpointFormat


@dataclasses.dataclass(frozen=True)
class LeRobotFolder:
    """A LeRobot pi0 / pi0.5 policy folder, served by its own files."""

    checkpoint: pathlib.Path
    lerobot: LeRobotConfig  # its config.json, read once

    @property
    def dtype(self) -> Dtype:
        """The dtype the folder was saved with (a LeRobot config's default where it names another)."""
        return self.lerobot.dtype if self.lerobot.dtype in DTYPES else LEROBOT_DTYPE  # type: ignore[return-value]


ModelSource = BundledModel | OpenPICheckpoint | LeRobotFolder


def resolve_source(spec: ModelSpec) -> ModelSource:
    """The source a spec names (module docstring); a folder is recognised by `checkpoint_format`."""
    if spec.checkpoint_dir is None:
        config = spec.config or demo_reach.DEMO_CONFIG.name
        if config not in BUNDLED_MODELS:
            raise ValueError(
                f"--config {config} needs --checkpoint-dir (the bundled models serve {sorted(BUNDLED_MODELS)})"
            )
        name = BUNDLED_MODELS[config]
        return BundledModel(name, BUNDLED_ASSETS[name] / demo_reach.CHECKPOINT.name, installed=True)
    folder = pathlib.Path(spec.checkpoint_dir).expanduser().resolve()
    if spec.config in BUNDLED_MODELS:
        name = BUNDLED_MODELS[spec.config]
        return BundledModel(name, folder, installed=folder == BUNDLED_ASSETS[name] / demo_reach.CHECKPOINT.name)
    kind = checkpoint_format(folder)
    if kind != "lerobot":
        return OpenPICheckpoint(folder, spec.config or DEFAULT_CHECKPOINT_CONFIG, kind)
    if spec.config is not None:
        raise ValueError(f"{folder} is a LeRobot policy folder, served by its own config.json, not {spec.config!r}")
    return LeRobotFolder(folder, LeRobotConfig.read(folder / CONFIG_FILE))


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """The model a command loads. Commands take these fields as flags (`--checkpoint-dir`, `--config`, ...)."""

    # checkpoint folder: OpenPI's (`params/` or `model.safetensors`, and `assets/<asset_id>/norm_stats.json`) or a
    # LeRobot pi0 / pi0.5 policy folder (`config.json`, `model.safetensors`, its processors); default: the bundled
    # demo model.
    checkpoint_dir: pathlib.Path | None = None
    # named policy config (pi0_fast_droid, pi05_droid, pi0_libero, ...); default: `demo_reach` for the bundled model,
    # pi0_fast_droid for an OpenPI checkpoint; a LeRobot folder takes none (its config.json says what it is).
    config: str | None = None
    # PaliGemma SentencePiece model; default: the bundled model's own, else $OPENPI_DATA_HOME's (README).
    paligemma_tokenizer: pathlib.Path | None = None
    # FAST action tokenizer folder (pi0-FAST); default: the bundled model's own, else the Hugging Face cache's.
    fast_tokenizer: pathlib.Path | None = None
    # parameter and compute dtype; default: float32 for the bundled model, a LeRobot folder's own (its config.json),
    # bfloat16 (as upstream serves) for an OpenPI checkpoint.
    dtype: Dtype | None = None
    # prompt used when a request has none.
    default_prompt: str | None = None

    @classmethod
    def demo(cls, model: str = "pi0_fast", assets: pathlib.Path | None = None, dtype: Dtype | None = None) -> ModelSpec:
        """A demo model: a bundled one ("pi0_fast" or "pi05" on the reaching task, "metaworld"), or one trained into
        `assets` by `python -m openpi_cam.demo.train` or `python -m openpi_cam.cli.train_demo` (its checkpoint/ and
        tokenizers)."""
        config = BUNDLED_CONFIGS[model].name
        return cls(None if assets is None else assets / demo_reach.CHECKPOINT.name, config, dtype=dtype)

    @functools.cached_property
    def source(self) -> ModelSource:
        """Where the weights come from, resolved once (`resolve_source`)."""
        return resolve_source(self)

    @property
    def checkpoint(self) -> pathlib.Path:
        """The folder the weights are read from (the bundled model's own for no `checkpoint_dir`)."""
        return self.source.checkpoint

    def resolved(self) -> ModelSpec:
        """The same model with the config and dtype defaults filled in and paths made absolute: what a run records.
        The bundled model is `checkpoint_dir` None (its files are found wherever the package is installed), also where
        it was named by its path (as runs made before specs were recorded name it)."""
        match self.source:
            case BundledModel(installed=installed, checkpoint=folder) as bundled:
                checkpoint, config, dtype = None if installed else folder, bundled.config, DEMO_DTYPE
            case OpenPICheckpoint(checkpoint=folder, config=config):
                checkpoint, dtype = folder, CHECKPOINT_DTYPE
            case LeRobotFolder(checkpoint=folder) as lerobot:
                checkpoint, config, dtype = folder, None, lerobot.dtype
        return ModelSpec(
            checkpoint_dir=checkpoint,
            config=config,
            paligemma_tokenizer=None if self.paligemma_tokenizer is None else self.paligemma_tokenizer.resolve(),
            fast_tokenizer=None if self.fast_tokenizer is None else self.fast_tokenizer.resolve(),
            dtype=self.dtype or dtype,
            default_prompt=self.default_prompt,
        )

    def tokenizers(self) -> tuple[pathlib.Path | None, pathlib.Path | None]:
        """(PaliGemma SentencePiece model, FAST tokenizer folder) as given; a demo model's ship beside its checkpoint
        (`demo.train` writes them there too); None leaves the choice to the loader (upstream's cache locations)."""
        spec = self.resolved()
        paligemma, fast = spec.paligemma_tokenizer, spec.fast_tokenizer
        if isinstance(self.source, BundledModel):
            paligemma = paligemma or self.checkpoint.parent / demo_reach.PALIGEMMA_TOKENIZER.name
            fast = fast or self.checkpoint.parent / demo_reach.FAST_TOKENIZER.name
        return paligemma, fast

    def default_monitor(self) -> pathlib.Path | None:
        """The failure monitor a demo model ships beside its checkpoint (`<assets>/monitor.json`, as its tokenizers
        are), when it is there; None otherwise, and for every other model (name one with `--monitor`)."""
        if not isinstance(self.source, BundledModel):
            return None
        path = self.assets() / MONITOR_FILE
        return path if path.is_file() else None

    def chosen_monitor(self, given: pathlib.Path | None, off: bool) -> pathlib.Path | None:
        """The monitor a command scores with: `--monitor` (given), else the model's own (`default_monitor`), none with
        `--no-monitor` (off); both flags at once are refused (ValueError). A model the flags cannot name has none here:
        loading it reports why."""
        if off and given is not None:
            raise ValueError("--monitor and --no-monitor name opposite things: give one")
        if off or given is not None:
            return given
        try:
            return self.default_monitor()
        except (KeyError, ValueError, OSError):
            return None

    def create(self, *, stop_at_action_end: bool = False, rng: jax.Array | None = None) -> Policy:
        """The policy; a FAST tokenizer named for a model of another family is refused (it would go unread)."""
        spec = self.resolved()
        paligemma, fast = self.tokenizers()
        match self.source:
            case LeRobotFolder(checkpoint=folder):
                policy = create_lerobot_policy(
                    folder, paligemma_tokenizer=paligemma, dtype=spec.dtype, default_prompt=spec.default_prompt, rng=rng
                )
            case BundledModel(checkpoint=folder) | OpenPICheckpoint(checkpoint=folder) as source:
                policy = create_policy(
                    source.config,
                    folder,
                    paligemma_tokenizer=paligemma,
                    fast_tokenizer=fast,
                    dtype=spec.dtype,  # type: ignore[arg-type]
                    default_prompt=spec.default_prompt,
                    stop_at_action_end=stop_at_action_end,
                    max_decoding_steps=_decoding_budget(source.config),
                    rng=rng,
                )
        if self.fast_tokenizer is not None and policy.model.family != "pi0_fast":  # given, and nothing would read it
            family = policy.model.family
            raise ValueError(f"--fast-tokenizer {self.fast_tokenizer}: a {family} model has no FAST tokenizer")
        return policy

    def dataset_keys(self) -> tuple[dict[str, str], bool]:
        """How a LeRobot dataset feeds this model: observation key -> dataset feature (with `actions`, the recorded
        actions), and whether observation keys `a/b` nest. A named config declares it (upstream's `RepackTransform`); a
        LeRobot policy reads its own feature names."""
        match self.source:
            case LeRobotFolder() as lerobot:
                return _layout(lerobot).dataset_keys, False
            case BundledModel() | OpenPICheckpoint() as source:
                config = resolve_config(source.config)
                return dict(config.lerobot_keys or {}), config.lerobot_nested

    def facts(self) -> ModelFacts:
        """The family, SigLIP patch grid and cameras of the model, read from the folder's metadata, tensor shapes and
        configs without loading a weight (a Ray driver plans a job with them)."""
        match self.source:
            case LeRobotFolder(checkpoint=folder, lerobot=cfg) as lerobot:
                return ModelFacts(cfg.type, _torch_architecture(folder).siglip.grid, _layout(lerobot).camera_sources)
            case OpenPICheckpoint(checkpoint=folder, format="openpi_pytorch", config=config):
                cfg = _torch_architecture(folder)
                sources = dict(resolve_config(config).camera_sources)
                return ModelFacts("pi05" if cfg.pi05 else "pi0", cfg.siglip.grid, sources)
            case BundledModel(checkpoint=folder) | OpenPICheckpoint(checkpoint=folder) as source:
                shapes = read_param_shapes(folder / PARAMS_DIR)
                sources = dict(resolve_config(source.config).camera_sources)
                return ModelFacts(family_of(shapes), architecture_from_params(shapes)[1].grid, sources)

    def assets(self) -> pathlib.Path:
        """Where the model's own files beside its weights live: a bundled model's assets folder, an OpenPI
        checkpoint's `assets/`, a LeRobot folder itself."""
        match self.source:
            case BundledModel(checkpoint=folder):
                return folder.parent
            case OpenPICheckpoint(checkpoint=folder):
                return folder / "assets"
            case LeRobotFolder(checkpoint=folder):
                return folder

    def occlusion_head(self, path: pathlib.Path | None = None) -> HeadRef:
        """The occlusion head the `occlusion-head` kind applies to this model: the file at `path`, else the one the
        model ships (`occlusion_head.HEAD_FILE` in `assets()`). Refused in one line when there is none, when the file
        is not a head, or when the head was fitted for another model (config, family, cameras or patch grid)."""
        if path is None:
            path = self.assets() / occlusion_head.HEAD_FILE
            if not path.is_file():
                raise ValueError(
                    f"occlusion-head needs a head file: --head FILE (serve: --cam.head FILE); `openpi-cam head fit` "
                    f"fits one; the model ships none ({path})"
                )
        ref = HeadRef.of(path)
        head = occlusion_head.load_ref(ref)
        facts, config = self.facts(), self.resolved().config
        fitted = (head.model.get("config"), head.family, set(head.cameras), head.grid)
        serving = (config, facts.family, set(facts.camera_sources), facts.grid)
        if fitted != serving:
            raise ValueError(
                f"{path}: the occlusion head was fitted for config {fitted[0]} ({fitted[1]}, cameras "
                f"{sorted(fitted[2])}, grid {fitted[3]}), this model is config {config} ({facts.family}, cameras "
                f"{sorted(serving[2])}, grid {facts.grid})"
            )
        return ref

    def to_json(self) -> dict[str, Any]:
        return {f.name: _jsonable(getattr(self, f.name)) for f in dataclasses.fields(self)}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> ModelSpec:
        """The spec a run or maps dataset recorded (other keys of `data` are ignored)."""
        return cls(
            checkpoint_dir=_path(data.get("checkpoint_dir")),
            config=data.get("config"),
            paligemma_tokenizer=_path(data.get("paligemma_tokenizer")),
            fast_tokenizer=_path(data.get("fast_tokenizer")),
            dtype=data.get("dtype"),
            default_prompt=data.get("default_prompt"),
        )

    def mismatch(self, recorded: Mapping[str, Any]) -> list[str]:
        """What differs, of what determines the outputs (weights, pipeline, dtype), between this model and one a run or
        maps dataset recorded: one `key: old != new` each."""
        old, new = ModelSpec.from_json(recorded).resolved().to_json(), self.resolved().to_json()
        return [f"{k}: {old[k]!r} != {new[k]!r}" for k in _OUTPUT_FIELDS if old[k] != new[k]]

    def overridden_by(self, flags: ModelSpec) -> ModelSpec:
        """This (recorded) spec with every field the command line set replacing it; a new checkpoint folder also
        drops the recorded config and tokenizers unless they are given again."""
        if flags.checkpoint_dir is not None and flags.checkpoint_dir != self.checkpoint_dir:
            return flags
        values = {
            f.name: getattr(flags, f.name) for f in dataclasses.fields(flags) if getattr(flags, f.name) is not None
        }
        return dataclasses.replace(self, **values)


def _decoding_budget(config: str | None) -> int:
    """pi0-FAST's decoding budget under a named config (its own, else upstream's)."""
    budget = None if config is None else resolve_config(config).max_decoding_steps
    return MAX_DECODING_STEPS if budget is None else budget


def _layout(source: LeRobotFolder) -> RequestLayout:
    """What a LeRobot folder's requests carry (its config, read once, and its preprocessor's renaming)."""
    return RequestLayout.of(source.lerobot, read_pipeline(source.checkpoint / PREPROCESSOR_FILE))


def _torch_architecture(folder: pathlib.Path) -> Pi0Config:
    """The architecture of a folder's `model.safetensors`, from its header and the folder's head counts."""
    return pi0_config_from_tensors(read_tensor_infos(folder / WEIGHTS_FILE), read_head_counts(folder))[0]


def _jsonable(value: Any) -> Any:
    return str(value) if isinstance(value, pathlib.Path) else value


def create_demo_policy(
    model: str = "pi0_fast",
    *,
    assets: pathlib.Path | None = None,
    dtype: Dtype | None = None,
    stop_at_action_end: bool = False,
    rng: jax.Array | None = None,
) -> Policy:
    """The policy of a demo model (`ModelSpec.demo`)."""
    return ModelSpec.demo(model, assets, dtype).create(stop_at_action_end=stop_at_action_end, rng=rng)
