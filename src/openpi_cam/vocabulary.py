"""The vocabulary of explanations: map kinds, their options, explanation targets and frame-saving modes.

Plain data with no JAX, so that commands which only read results (`stats`, `render`) can name kinds and options
without loading the model stack. The model layer computes what these names describe; the side channel, offline
explanation and the command line validate against them.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import pathlib
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, Literal, TypeVar, get_args

BASELINES = ("blur", "mean")
IG_RULES = ("gauss-legendre", "midpoint", "trapezoid", "right-riemann")
OCCLUSION_MODES = ("regions", "random")
IG_SPACES = ("tokens", "pixels")
# The tuples as the types command lines offer as choices (a Literal subscripted with a tuple spells its members).
Baseline = Literal[BASELINES]  # type: ignore[valid-type]
IgSpace = Literal[IG_SPACES]  # type: ignore[valid-type]


@dataclasses.dataclass(frozen=True)
class MapOptions:
    """How the baseline-based maps are computed. Hashable: jitted programs take it as a static argument.

    Defaults were chosen by measurement on the bundled demo model (docs/MAP_KINDS.md; figures in
    docs/DESIGN_NOTES.md). The mean-colour frame is the default baseline because it removes what the policy reads:
    a blurred frame keeps the colour the demo policy reads and barely moves its score, so blur-based maps explain a
    residual and find the named block less often. Blur stays available (Zhang et al.'s replacement)."""

    baseline: str = "mean"  # "mean": the frame's per-channel mean colour; "blur": a Gaussian-blurred copy
    blur_sigma: float = 8.0  # pixels at the model resolution (the demo: half a 16 px patch)
    # Gauss-Legendre at 16 points meets the completeness target on most demo steps, as often as the other
    # second-order rules and far more often than the IG paper's right Riemann sum (docs/DESIGN_NOTES.md); the rest
    # are refined (ig_tolerance).
    ig_steps: int = 16  # gradient evaluations along the path (the first try, see ig_tolerance)
    ig_rule: str = "gauss-legendre"  # quadrature rule over the path, one of IG_RULES
    # Completeness target: while some explained score misses it (|sum of attributions - (score(E) - score(E0))| >
    # ig_tolerance * max(|score(E) - score(E0)|, COMPLETENESS_FLOOR)), the steps double, up to ig_max_steps, as long
    # as doubling helps (IG_STALL). 0 keeps ig_steps fixed. A path with a sharp turn (attention switching) defeats
    # any fixed rule on a few steps.
    ig_tolerance: float = 0.02
    ig_max_steps: int = 128
    # "tokens": the path runs between the SigLIP tokens of the baseline frame and of the frame (what the LLM reads);
    # "pixels": between the frames themselves, through SigLIP (the original IG; attributions summed per patch).
    ig_space: str = "tokens"
    # 1: every patch alone, which is exact, defines the deletion metric's optimum and costs C x (N + 1) model runs.
    occlusion_region: int = 1  # side of a square occlusion region, in patches
    occlusion_mode: str = "regions"  # "regions": every region once (exact); "random": Bernoulli masks (ISS)
    random_masks: int = 256  # masks per camera in "random" mode
    keep_prob: float = 0.5  # probability that a region keeps its pixels in a random mask
    seed: int = 0  # seed of the random masks (host-side; changing it does not recompile)
    mask_chunk: int = 16  # variants re-scored per vectorised chunk (bounds memory: chunk x B model runs at once)
    # SmoothGrad: the gradient averaged over this many copies of the image tokens with Gaussian noise of std
    # smoothgrad_sigma x the spread of each channel over the camera's tokens (noise drawn from `seed`).
    smoothgrad_samples: int = 16
    smoothgrad_sigma: float = 0.5
    # RISE: random masks per camera over the patch grid, each patch kept with probability rise_keep_prob (drawn from
    # `seed`). Chosen on the demo models (docs/MAP_KINDS.md): agreement with exhaustive occlusion levels off at 64
    # masks, and keeping 3 of 4 patches tracks single-patch occlusion more closely than RISE's 1 of 2.
    rise_masks: int = 64
    rise_keep_prob: float = 0.75

    def __post_init__(self):
        if self.baseline not in BASELINES:
            raise ValueError(f"baseline must be one of {BASELINES}, got {self.baseline!r}")
        if self.ig_rule not in IG_RULES:
            raise ValueError(f"ig_rule must be one of {IG_RULES}, got {self.ig_rule!r}")
        if self.ig_space not in IG_SPACES:
            raise ValueError(f"ig_space must be one of {IG_SPACES}, got {self.ig_space!r}")
        if self.occlusion_mode not in OCCLUSION_MODES:
            raise ValueError(f"occlusion_mode must be one of {OCCLUSION_MODES}, got {self.occlusion_mode!r}")
        if self.blur_sigma < 0 or self.ig_steps < 1 or self.occlusion_region < 1 or self.mask_chunk < 1:
            raise ValueError(f"invalid options {self}")
        if self.ig_tolerance < 0 or self.ig_max_steps < self.ig_steps:
            raise ValueError("ig_tolerance must be >= 0 and ig_max_steps >= ig_steps")
        if self.ig_rule == "trapezoid" and self.ig_steps < 2:
            raise ValueError("the trapezoid rule needs at least 2 steps")
        if not 0.0 < min(self.keep_prob, self.rise_keep_prob) <= max(self.keep_prob, self.rise_keep_prob) < 1.0:
            raise ValueError("random masks need a keep probability strictly between 0 and 1")
        if self.random_masks < 2 or self.rise_masks < 2:
            raise ValueError("random masks need at least 2 masks")
        if self.smoothgrad_samples < 1 or self.smoothgrad_sigma < 0:
            raise ValueError("smoothgrad needs at least 1 sample and a noise level >= 0")


# The maps the model layer computes. gradcam: Grad-CAM as the founding spec defines it; gradnorm: the per-token
# gradient norm from the same backward pass; ig: integrated gradients from the baseline frame's tokens; occlusion:
# the score's drop when a region is painted with the baseline frame and the model re-run; lrp: AttnLRP relevance,
# propagated through the language model and SigLIP to the pixels by one modified backward pass (`model.lrp`);
# gradxinput: gradient x input per token, from the gradient pass too; taylor: the first-order estimate of occlusion's
# drop, the pixel gradient dotted with (frame - baseline frame) per patch; smoothgrad: the gradient norm of the
# gradient averaged over noisy copies of the tokens; rise: random patch masks painted with the baseline frame (RISE),
# each patch's score with it kept against painted.
# occlusion-head is not the model layer's: a small head fitted to the policy's own occlusion maps predicts occlusion
# from other kinds' maps of the same call (`model.occlusion_head`, applied by the families).
MapKind = Literal[
    "gradcam", "gradnorm", "ig", "occlusion", "lrp", "gradxinput", "taylor", "smoothgrad", "rise", "occlusion-head"
]
MAP_KINDS: tuple[MapKind, ...] = get_args(MapKind)
# What a family's gradient program computes: one backward pass per explained score to the image tokens gives
# gradcam, gradnorm and gradxinput; taylor continues that pass through SigLIP to the pixels; smoothgrad adds
# `MapOptions.smoothgrad_samples` backward passes at noisy tokens.
GRADIENT_KINDS: tuple[MapKind, ...] = ("gradcam", "gradnorm", "gradxinput", "taylor", "smoothgrad")
# What the baseline program computes: IG's path from the baseline frame and the batched re-runs of painted frames.
BASELINE_KINDS: tuple[MapKind, ...] = ("ig", "occlusion", "rise")
# One backward pass of their own per score, with modified rules (`model.lrp`), in a program of their own.
RELEVANCE_KINDS: tuple[MapKind, ...] = ("lrp",)
# Computed by a head fitted offline from other kinds' maps of the same call (its inputs): no model pass of its own.
# The model computes its inputs' maps in their groups' programs (`policies.family.model_kinds`), and records the
# options where an input reads them.
OCCLUSION_HEAD: MapKind = "occlusion-head"
HEAD_KINDS: tuple[MapKind, ...] = (OCCLUSION_HEAD,)
# What the model layer's programs compute (`model.pi0_fast_maps`, `model.pi0_maps`): every kind but the head's.
MODEL_KINDS: tuple[MapKind, ...] = (*GRADIENT_KINDS, *RELEVANCE_KINDS, *BASELINE_KINDS)
# The kinds whose maps depend on `MapOptions` (an explained step records its options beside them).
OPTION_KINDS: tuple[MapKind, ...] = ("taylor", "smoothgrad", *BASELINE_KINDS)
# What one backward pass gives: Grad-CAM (the founding spec's kind) and the gradient norm. The model layer's gradient
# functions compute these unless told otherwise, and a run recorded before runs named their kinds carries these.
ONE_PASS_KINDS: tuple[MapKind, ...] = ("gradcam", "gradnorm")
# What the side channel (`ExplainOptions`, `serve --cam.maps`) and the Meta-World demo compute unless told
# otherwise: the cheapest kind that held on the maps bench's test split for every task and camera
# (`benchmarks/maps_bench.py`; README, "Which map to trust"). No kind at the cost of one or two backward passes held;
# occlusion itself did.
DEFAULT_KINDS: tuple[MapKind, ...] = ("occlusion",)
# What the offline commands (`explain-run`, `explain-dataset`) and the demo compute unless told otherwise: the kinds
# their reports compare. Spelled out rather than built from the groups, so that a kind added to a group stays out of
# the defaults, asked for by name, until a bench measures it against these (lrp, gradxinput, taylor, smoothgrad, rise,
# occlusion-head).
COMPARED_KINDS: tuple[MapKind, ...] = ("gradcam", "gradnorm", "ig", "occlusion")
# The kinds by their mean top-1 agreement with occlusion over the maps bench's tasks and cameras on its dev split
# (the test split ranks the kinds it carried the same way; `occlusion-head`, not benched, just before Grad-CAM):
# render, stats and the viewers draw the first a run carries unless told which (`drawn_kind`).
TRUST_ORDER: tuple[MapKind, ...] = (
    "occlusion",
    "rise",
    "taylor",
    "lrp",
    "ig",
    "gradnorm",
    "smoothgrad",
    "occlusion-head",
    "gradcam",
    "gradxinput",
)
DEFAULT_MAP_KIND: MapKind = TRUST_ORDER[0]


def drawn_kind(carried: Iterable[str]) -> str:
    """The kind drawn where none is named: the most trusted (`TRUST_ORDER`) of those a run or maps dataset carries;
    `DEFAULT_MAP_KIND` when it carries none (drawing it then says so)."""
    present = set(carried)
    return next((kind for kind in TRUST_ORDER if kind in present), DEFAULT_MAP_KIND)


@dataclasses.dataclass(frozen=True)
class KindInfo:
    """What the rest of the package says about a map kind."""

    prefix: str  # step-file key prefix, followed by the camera name (docs/FORMAT.md)
    label: str  # display name: what the kind is, in a figure's words
    note: str  # what the kind is in a reader's words, and what that implies for reading it


MAP_KIND_INFO: dict[MapKind, KindInfo] = {
    "gradcam": KindInfo(
        "cam/",
        "Grad-CAM",
        "Grad-CAM as its founding definition states it: ReLU of each image token times the mean gradient over the "
        "camera's tokens. On the bundled demo models its top patch removed no more of the explained score than a "
        "random patch, its peak fell on the named block at chance, and a re-initialised language model left it "
        "correlated with itself (README, 'Which map to trust'): check this run's figures before trusting it.",
    ),
    "gradnorm": KindInfo(
        "gradnorm/",
        "gradient norm (unsigned sensitivity)",
        "Gradient norm per image token: unsigned sensitivity. A hot patch is one the explained score reacts to most; "
        "the map does not say whether the patch raises or lowers the score.",
    ),
    "ig": KindInfo(
        "ig/",
        "integrated gradients (vs baseline frame)",
        "Integrated gradients from the baseline frame's tokens: signed (positive supports the explained score); the "
        "attributions of a step add up to its score minus the baseline frame's score (completeness, checked per step).",
    ),
    "occlusion": KindInfo(
        "occlusion/",
        "occlusion (score drop, baseline-painted)",
        "Occlusion: the drop of the explained score when one region is painted with the baseline frame and the model "
        "re-run. It is the interventional reference the other kinds are scored against, exact for one region at a "
        "time.",
    ),
    "lrp": KindInfo(
        "lrp/",
        "AttnLRP relevance (signed)",
        "AttnLRP relevance: the explained score propagated back through the language model and SigLIP to the pixels "
        "with rules that conserve it (one modified backward pass), summed per patch: signed (positive supports the "
        "score). The relevance of a step adds up to its score less what biases and softmaxes absorb.",
    ),
    "gradxinput": KindInfo(
        "gradxinput/",
        "gradient x input (token level, signed)",
        "Gradient x input at each image token: the gradient's dot product with the token, from the same backward "
        "pass as the gradient norm. Signed: it is the linear term of scaling the token to zero, which no camera "
        "produces, so it mixes what the patch shows with how large its token is.",
    ),
    "taylor": KindInfo(
        "taylor/",
        "occlusion's first-order (Taylor) estimate",
        "The first-order estimate of occlusion: the pixel gradient times (frame - baseline frame), summed over each "
        "patch. Signed like occlusion (positive: painting the patch would lower the score); exact where the score is "
        "linear in the patch's pixels, one backward pass through SigLIP instead of a re-run per patch.",
    ),
    "smoothgrad": KindInfo(
        "smoothgrad/",
        "SmoothGrad (noise-averaged gradient norm)",
        "SmoothGrad: the gradient norm per image token of the gradient averaged over noisy copies of the tokens. "
        "Unsigned sensitivity like the gradient norm, less sensitive to the gradient's local jitter; several "
        "backward passes.",
    ),
    "rise": KindInfo(
        "rise/",
        "RISE (random masks, baseline-painted)",
        "RISE: the explained score re-run with random patch masks painted with the baseline frame; each patch's map "
        "is the mean score with it kept minus the mean score with it painted, which estimates occlusion's drop "
        "where patches act additively. Signed; one forward per mask and camera.",
    ),
    "occlusion-head": KindInfo(
        "head/",
        "amortised occlusion (fitted head)",
        "Amortised occlusion: a small head fitted offline to this policy's own occlusion maps predicts each patch's "
        "occlusion drop from cheaper kinds' maps of the same call (`openpi-cam head fit`; its file names its inputs "
        "and its held-out agreement with occlusion). Values are the predicted drop as a share of the camera's "
        "largest one: compare patches within a camera, not across cameras.",
    ),
}


def check_kinds(kinds: Sequence[str], choices: Sequence[MapKind] = MAP_KINDS) -> tuple[MapKind, ...]:
    """The requested kinds, deduplicated in order; a kind not among `choices` or an empty selection is an error
    naming the choices (the model layer's are `MODEL_KINDS`: a kind it would accept and not compute is refused)."""
    kinds = tuple(dict.fromkeys(kinds))
    unknown = [k for k in kinds if k not in choices]
    if unknown or not kinds:
        raise ValueError(f"map kinds must be a non-empty selection of {tuple(choices)}, got {list(kinds)}")
    return kinds  # type: ignore[return-value]


# What a map explains (the `--cam.target` values). pi0-FAST: `action-token`, `all-action-tokens`, `chunk` (sum of the
# action tokens' log-probabilities), `generated-tokens` (every emitted token; also what a malformed generation without
# action tokens falls back to, so that failures leave maps too). pi0 / pi0.5: `action` (one dimension at one horizon
# step) and `chunk` (the whole chunk, weighted by itself). LeRobot datasets only: `dataset-actions`, the recorded
# chunk instead of the model's own generation (pi0-FAST: the log-probability of its FAST tokens, as the `chunk` target
# of those tokens); no family explains it from a served call.
Target = Literal["action-token", "all-action-tokens", "chunk", "generated-tokens", "action", "dataset-actions"]
TARGETS: tuple[str, ...] = get_args(Target)
FALLBACK_TARGET: Target = "generated-tokens"
DATASET_ACTIONS: Target = "dataset-actions"
# What each family explains when no target is named. pi0-FAST: the first action token, one decision of the policy at
# one backward pass; pi0 / pi0.5: the whole chunk, measured more faithful than one action dimension (docs/MAP_KINDS.md).
DEFAULT_TARGETS: dict[str, Target] = {"pi0_fast": "action-token", "pi0": "chunk", "pi05": "chunk"}

# Which camera frames are stored beside the maps: the client's (raw), the model's input (model), both or none.
SaveFrames = Literal["none", "raw", "model", "both"]
SAVE_FRAMES: tuple[str, ...] = ("none", "raw", "model", "both")
# Observation keys with this prefix are not passed to the policy; their values are recorded beside what was served
# (the step's `extra` metadata, a recorded frame's features: e.g. the demo's ground-truth target box).
EXTRA_PREFIX = "cam_extra/"

# What a served call leaves for a failure monitor when asked (`InferenceTrace.signals`, each [..] of one request):
# last-layer features pooled per span, `features/<camera>`, `features/prompt` and `features/actions` (float32 [D]);
# pi0-FAST's per-token entropies of its generation (float32 [S]) with the flags of its action tokens (bool [S]); and
# the action chunk in the model's normalised units (`chunk`, [H, A] over the robot's action dimensions).
FEATURES_PREFIX = "features/"
PROMPT_FEATURES = FEATURES_PREFIX + "prompt"
ACTION_FEATURES = FEATURES_PREFIX + "actions"
TOKEN_ENTROPIES = "token_entropies"
ACTION_TOKENS = "action_tokens"
NORMALIZED_CHUNK = "chunk"

# Random single patches of each explained step's spot check (`cam.spot_check`): with each kind's top patch and the
# unpainted score, 1 + kinds + 4 re-runs per camera in one call.
DEFAULT_PATCHES = 4
_O = TypeVar("_O", bound="ExplainOptions")
# What runs made before an option was recorded used.
_UNRECORDED = {
    "ig_space": "tokens",
    "occlusion_region": 1,
    "occlusion_masks": 0,
    "reliance": False,
    "smoothgrad_samples": MapOptions.smoothgrad_samples,
    "smoothgrad_sigma": MapOptions.smoothgrad_sigma,
    "rise_masks": MapOptions.rise_masks,
    "rise_keep_prob": MapOptions.rise_keep_prob,
    "occlusion_head": None,
    "occlusion_head_file": None,
}
# Recorded for the reader, not compared when adding to a run or maps dataset: the same head may move between machines.
_NOT_COMPARED = ("occlusion_head_file",)


@dataclasses.dataclass(frozen=True)
class HeadRef:
    """An occlusion head file (`model.occlusion_head`) as options name it: where it is read from, and the SHA-256 of
    its bytes, which is its identity (steps join a run or maps dataset only with the head its earlier steps used)."""

    path: str
    sha256: str

    @classmethod
    def of(cls, path: str | os.PathLike[str]) -> HeadRef:
        """The head file at `path`, hashed; a missing or unreadable file is refused in one line naming it."""
        path = pathlib.Path(path).expanduser()
        try:
            data = path.read_bytes()
        except OSError as e:
            raise ValueError(
                f"{path}: cannot read the occlusion head file ({e.strerror or type(e).__name__})"
            ) from None
        return cls(str(path.resolve()), hashlib.sha256(data).hexdigest())


@dataclasses.dataclass(frozen=True)
class ExplainOptions:
    """What an explained step explains and carries: one set for the side channel, recorded runs and datasets (the
    side channel's options add its queue to these, `cam.side_channel.CAMOptions`). Families compute `maps` of
    `target` with `map_options`; the spot check re-runs `check_patches` random patches beside each map's top one;
    `reliance` re-runs the step with each camera replaced by the baseline frame and with the prompt emptied
    (`cam.reliance`)."""

    # None: the family's own default (`DEFAULT_TARGETS`), resolved against the loaded model.
    target: Target | None = None
    action_index: int = 0  # pi0-FAST: which action token ("action-token"); pi0 / pi0.5: which horizon step ("action")
    action_dim_index: int = 0  # pi0 / pi0.5: which action dimension ("action")
    maps: tuple[MapKind, ...] = DEFAULT_KINDS
    map_options: MapOptions = dataclasses.field(default_factory=MapOptions)  # of the `OPTION_KINDS`
    check_patches: int = DEFAULT_PATCHES  # 0: no spot check
    reliance: bool = False  # measure camera and prompt reliance: one re-run per camera and one for the prompt
    # the head the "occlusion-head" kind applies (None: the kind cannot be computed; `HeadRef.of` names a file)
    occlusion_head: HeadRef | None = None

    def __post_init__(self) -> None:
        if self.target is not None and self.target not in TARGETS:
            raise ValueError(f"unknown target {self.target!r}; expected one of {TARGETS}")
        if self.action_index < 0 or self.action_dim_index < 0:
            raise ValueError(f"action indices must be >= 0, got {self.action_index}, {self.action_dim_index}")
        check_kinds(self.maps)
        if self.check_patches < 0:
            raise ValueError(f"check_patches must be >= 0, got {self.check_patches}")

    @property
    def explanation(self) -> ExplainOptions:
        """These options alone, without what a subclass adds (a hashable key for grouping requests)."""
        return self.extended(ExplainOptions)

    def extended(self, cls: type[_O], **more: Any) -> _O:
        """These options as a subclass's (`CAMOptions`, `ReplayOptions`) with its own fields `more`."""
        return cls(**{f.name: getattr(self, f.name) for f in dataclasses.fields(ExplainOptions)}, **more)

    def to_json(self) -> dict[str, Any]:
        """The options as runs and maps datasets record them, as the flags name them; every field must match to add
        to a run or maps dataset (`mismatch`)."""
        o = self.map_options
        return {
            "target": self.target,
            "action_index": self.action_index,
            "action_dim_index": self.action_dim_index,
            "maps": list(self.maps),
            "baseline": o.baseline,
            "ig_space": o.ig_space,
            "occlusion_region": o.occlusion_region,
            "occlusion_masks": o.random_masks if o.occlusion_mode == "random" else 0,
            "smoothgrad_samples": o.smoothgrad_samples,
            "smoothgrad_sigma": o.smoothgrad_sigma,
            "rise_masks": o.rise_masks,
            "rise_keep_prob": o.rise_keep_prob,
            "check_patches": self.check_patches,
            "reliance": self.reliance,
            "occlusion_head": None if self.occlusion_head is None else self.occlusion_head.sha256,
            "occlusion_head_file": None if self.occlusion_head is None else self.occlusion_head.path,
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> ExplainOptions:
        """The options a run or maps dataset recorded (`to_json`; other keys are ignored)."""
        data = {**_UNRECORDED, **data}
        map_options = MapOptions(
            baseline=data.get("baseline", MapOptions.baseline),
            ig_space=data["ig_space"],
            occlusion_region=int(data["occlusion_region"]),
            smoothgrad_samples=int(data["smoothgrad_samples"]),
            smoothgrad_sigma=float(data["smoothgrad_sigma"]),
            rise_masks=int(data["rise_masks"]),
            rise_keep_prob=float(data["rise_keep_prob"]),
        )
        if masks := int(data["occlusion_masks"]):
            map_options = dataclasses.replace(map_options, occlusion_mode="random", random_masks=masks)
        head = None
        if data["occlusion_head"]:
            head = HeadRef(str(data["occlusion_head_file"] or ""), str(data["occlusion_head"]))
        return cls(
            target=data.get("target"),
            action_index=int(data.get("action_index", 0)),
            action_dim_index=int(data.get("action_dim_index", 0)),
            maps=tuple(data.get("maps") or ONE_PASS_KINDS),
            map_options=map_options,
            check_patches=int(data.get("check_patches", DEFAULT_PATCHES)),
            reliance=bool(data["reliance"]),
            occlusion_head=head,
        )

    def mismatch(self, recorded: Mapping[str, Any]) -> list[str]:
        """What differs between these options and those a run or maps dataset recorded, one `key: old != new` each."""
        old, new = {**_UNRECORDED, **recorded}, self.to_json()
        return [f"{k}: {old.get(k)!r} != {v!r}" for k, v in new.items() if k not in _NOT_COMPARED and old.get(k) != v]
