"""Flags shared by several subcommands, each declared once: which model to load (`checkpoints.model_spec.ModelSpec`,
taken as it is) and what an explanation explains and carries (`ExplainFlags`, building `vocabulary.ExplainOptions`).
Allowed values come from `openpi_cam.vocabulary`."""

from __future__ import annotations

import dataclasses
import pathlib
from typing import ClassVar, Literal

from openpi_cam.checkpoints.model_spec import ModelSpec
from openpi_cam.model import occlusion_head
from openpi_cam.vocabulary import (
    BASELINES,
    COMPARED_KINDS,
    DATASET_ACTIONS,
    DEFAULT_KINDS,
    DEFAULT_PATCHES,
    DEFAULT_TARGETS,
    OCCLUSION_HEAD,
    Baseline,
    ExplainOptions,
    HeadRef,
    IgSpace,
    MapKind,
    MapOptions,
    Target,
)

# What `faithfulness` paints deletions with: the baseline the run's own maps used, or one named.
DeletionBaseline = Literal[("run", *BASELINES)]  # type: ignore[valid-type]


def parse_action_index(text: str) -> tuple[int, int]:
    """`--action-index`: "I" (pi0-FAST: the I-th action token; pi0 / pi0.5: horizon step I, dimension 0) or "H,D"
    (pi0 / pi0.5: dimension D at horizon step H) -> (index, dimension)."""
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) not in (1, 2) or not all(p.isdigit() for p in parts):
        raise ValueError(f"action index must be 'I' or 'H,D' with non-negative integers, got {text!r}")
    return int(parts[0]), int(parts[1]) if len(parts) == 2 else 0


@dataclasses.dataclass(frozen=True)
class ExplainFlags:
    """What each explained step explains and which maps it carries (`ExplainOptions`). `serve` nests these under
    `--cam.`, the explain commands take them unprefixed; they are checked as the command line is parsed."""

    # how the command line spells these flags, for messages that name one (`serve`'s are `--cam.` flags)
    FLAG_PREFIX: ClassVar[str] = "--"

    # which score the maps explain; default: the model family's own (pi0-FAST `action-token`, pi0 / pi0.5 `chunk`).
    # A pi0-FAST generation without action tokens is explained with `generated-tokens` whatever this says.
    target: Target | None = None
    # pi0-FAST: which action token (`action-token`); pi0 / pi0.5: `H,D`, dimension D at horizon step H (`action`).
    action_index: str = "0"
    # which kinds of map each explained step carries (README, "Which map to trust"): `gradcam`, `gradnorm` and
    # `gradxinput` cost one backward pass together, `taylor` continues it through SigLIP; `smoothgrad` costs
    # --smoothgrad-samples backward passes; `ig`, `occlusion` and `rise` cost several inferences each; `lrp` (AttnLRP
    # relevance at the pixels) one backward pass of its own, through SigLIP too; `occlusion-head` (occlusion predicted
    # by a head fitted to the policy's own occlusion maps, `openpi-cam head fit`) its inputs' passes.
    maps: tuple[MapKind, ...] = DEFAULT_KINDS
    # the head file `occlusion-head` applies (`openpi-cam head fit`); default: the model's own (`occlusion_head.json`
    # in its assets), where it ships one.
    head: pathlib.Path | None = None
    # the frame `ig` starts from and `occlusion` paints with: the frame's mean colour or a Gaussian-blurred copy.
    baseline: Baseline = MapOptions.baseline
    # side of an `occlusion` region in patches (1: every patch alone, C x (N + 1) re-runs per step).
    occlusion_region: int = MapOptions.occlusion_region
    # 0: every `occlusion` region once; M > 0: M random region masks per camera, scored with the Interventional
    # Significance Score (for large grids).
    occlusion_masks: int = 0
    # `smoothgrad`: how many noisy copies of the image tokens are averaged over.
    smoothgrad_samples: int = MapOptions.smoothgrad_samples
    # `smoothgrad`: the noise's std, in units of each channel's spread over the camera's tokens.
    smoothgrad_sigma: float = MapOptions.smoothgrad_sigma
    # `rise`: random patch masks per camera (each a re-run).
    rise_masks: int = MapOptions.rise_masks
    # `rise`: the probability that a mask keeps a patch.
    rise_keep_prob: float = MapOptions.rise_keep_prob
    # where the `ig` path runs: between the SigLIP tokens of the baseline frame and the frame, or between the frames'
    # pixels, through SigLIP.
    ig_space: IgSpace = MapOptions.ig_space
    # each explained step's spot check paints each map's top patch and this many random patches (a few re-runs per
    # camera) and stores the score drops with the maps, so every map carries evidence of its own; 0: no check.
    check_patches: int = DEFAULT_PATCHES
    # also measure how much each step relies on each camera and on its prompt: the explained score's drop and the
    # action chunk's change with the camera replaced by the baseline frame, and with the prompt emptied (one re-run
    # per camera and one for the prompt, each a full inference).
    reliance: bool = False

    def __post_init__(self) -> None:
        # What the options would refuse later is refused as the command line is parsed (a subclass's `options`
        # included: `serve`'s flags build CAMOptions here).
        self.options()

    def options(self, target: Target | None = None, model: ModelSpec | None = None) -> ExplainOptions:
        """The options these flags name; `target`, when given, stands for the flag's (a family's resolved one);
        `model`, the model they explain, whose own occlusion head stands in for `--head` (without it, as the command
        line is parsed, the head is checked only where `--head` names one)."""
        if self.occlusion_masks < 0:
            raise ValueError(f"occlusion_masks must be >= 0 (0: every region once), got {self.occlusion_masks}")
        map_options = MapOptions(
            baseline=self.baseline,
            occlusion_region=self.occlusion_region,
            ig_space=self.ig_space,
            smoothgrad_samples=self.smoothgrad_samples,
            smoothgrad_sigma=self.smoothgrad_sigma,
            rise_masks=self.rise_masks,
            rise_keep_prob=self.rise_keep_prob,
        )
        if self.occlusion_masks:
            map_options = dataclasses.replace(map_options, occlusion_mode="random", random_masks=self.occlusion_masks)
        index, dim_index = parse_action_index(self.action_index)
        return ExplainOptions(
            target=target or self.target,
            action_index=index,
            action_dim_index=dim_index,
            maps=self.maps,
            map_options=map_options,
            check_patches=self.check_patches,
            reliance=self.reliance,
            occlusion_head=self._head(target or self.target, model),
        )

    def _head(self, target: Target | None, model: ModelSpec | None) -> HeadRef | None:
        """The head `occlusion-head` applies, checked against the model and the target (one line when it does not
        fit); None when the kind is not asked for."""
        if OCCLUSION_HEAD not in self.maps:
            if self.head is not None:
                flag = self.FLAG_PREFIX
                raise ValueError(
                    f"{flag}head {self.head} given but {OCCLUSION_HEAD} is not among the maps: add it to {flag}maps"
                )
            return None
        if model is None:
            return None if self.head is None else HeadRef.of(self.head)
        ref = model.occlusion_head(self.head)
        head = occlusion_head.load_ref(ref)
        explained = target or DEFAULT_TARGETS[head.family]
        explained = "chunk" if explained == DATASET_ACTIONS else explained  # the recorded chunk is explained as one
        if head.target != explained:
            raise ValueError(
                f"{ref.path}: the occlusion head was fitted on {head.target} maps; these explain {explained}"
            )
        return ref


# The explain commands' default: every kind their reports compare, since offline there is no robot to keep waiting.
EVERY_KIND = ExplainFlags(maps=COMPARED_KINDS)
# No model flags: the bundled demo model (`ModelSpec`'s defaults).
BUNDLED_MODEL = ModelSpec()
