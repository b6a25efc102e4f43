"""Perturbations of the reaching task that make the bundled policies fail some of the time: a scene or a view the
training data never showed, or a prompt naming a block that is not there.

Each is a kind and a strength, written `kind=strength` on the command line (`openpi-cam demo --perturb hue=60`):

- `clean`: the task as trained.
- `distractors=N`: N (1 or 2) more blocks, painted in colours no training scene has (`task.UNSEEN_COLORS`), at free
  places.
- `hue=D`: every block's colour turned D degrees round the hue circle, in both cameras; the prompt still names the
  colour the block had.
- `shift=P`: the base camera moved by P pixels in a direction drawn per episode (the table slides in the image, the
  uncovered border is black); the state, and so the end effector's true place, stays. The wrist camera rides on the
  end effector and is unchanged.
- `dim=F`: both cameras' pixel values multiplied by F (less light).
- `absent`: the prompt names a training colour that no block of the scene has (no strength).

The episode is the clean one of the same seed with the perturbation laid over it (its own random stream), so every
perturbation meets the same scenes and starts. Success is always judged against the block the clean prompt names:
for `absent` the policy is told something else and succeeds only by going there anyway.
"""

from __future__ import annotations

import colorsys
import dataclasses
from collections.abc import Callable
from typing import Literal, get_args

import numpy as np

from openpi_cam.demo import sim, task

Kind = Literal["clean", "distractors", "hue", "shift", "dim", "absent"]
KINDS: tuple[str, ...] = get_args(Kind)
_NO_STRENGTH = ("clean", "absent")
# Three blocks and two more still leave room on the 64 px table for every random placement to find a free spot fast.
MAX_DISTRACTORS = 2
PERTURB_STREAM = 7919  # with the episode's seed, seeds the perturbation's own draws (the clean episode's are untouched)


@dataclasses.dataclass(frozen=True)
class Perturbation:
    kind: Kind = "clean"
    strength: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown perturbation {self.kind!r}; expected one of {KINDS}")
        if self.kind in _NO_STRENGTH and self.strength:
            raise ValueError(f"perturbation {self.kind!r} takes no strength, got {self.strength}")
        if self.kind == "distractors" and not (
            float(self.strength).is_integer() and 1 <= self.strength <= MAX_DISTRACTORS
        ):
            raise ValueError(f"distractors=N takes a whole N from 1 to {MAX_DISTRACTORS}, got {self.strength}")
        if self.kind == "shift" and self.strength <= 0:
            raise ValueError(f"shift=P takes P > 0 pixels, got {self.strength}")
        if self.kind == "dim" and not 0 <= self.strength < 1:
            raise ValueError(f"dim=F takes a factor 0 <= F < 1, got {self.strength}")

    @classmethod
    def parse(cls, text: str) -> Perturbation:
        """`kind` or `kind=strength` (the form `name` gives back)."""
        kind, sep, value = text.strip().partition("=")
        if kind in _NO_STRENGTH or not sep:
            if sep or kind not in _NO_STRENGTH:
                raise ValueError(f"perturbation {text!r}: write one of {KINDS}, with =STRENGTH except clean, absent")
            return cls(kind)  # type: ignore[arg-type]
        try:
            strength = float(value)
        except ValueError:
            raise ValueError(f"perturbation {text!r}: the strength after '=' must be a number") from None
        return cls(kind, strength)  # type: ignore[arg-type]

    @property
    def name(self) -> str:
        return self.kind if self.kind in _NO_STRENGTH else f"{self.kind}={self.strength:g}"

    def episode(self, seed: int, cfg: task.TaskConfig | None = None) -> sim.ReachSim:
        """The clean episode of `seed` (`sim.new_episode`) under this perturbation."""
        episode = sim.new_episode(seed, cfg)
        if self.kind == "clean":
            return episode
        rng = np.random.default_rng([seed, PERTURB_STREAM])
        scene, view = episode.scene, None
        if self.kind == "distractors":
            n = int(self.strength)
            colors = rng.choice(list(task.UNSEEN_COLORS), size=n, replace=False)
            boxes = task.place_boxes(rng, n, episode.cfg, taken=tuple(b.box for b in scene.blocks))
            added = tuple(task.Block(str(c), b) for c, b in zip(colors, boxes, strict=True))
            scene = dataclasses.replace(scene, blocks=scene.blocks + added)
        elif self.kind == "hue":
            view = _recoloured(self.strength)
        elif self.kind == "shift":
            angle = rng.uniform(0.0, 2.0 * np.pi)
            dx, dy = (round(float(self.strength * f(angle))) for f in (np.cos, np.sin))
            view = _shifted(dx, dy)
        elif self.kind == "dim":
            view = _dimmed(self.strength)
        else:  # absent
            present = {b.color for b in scene.blocks}
            color = str(rng.choice([c for c in task.COLORS if c not in present]))
            view = _prompted(task.prompt_for(color))
        return dataclasses.replace(episode, scene=scene, view=view)


CLEAN = Perturbation()
View = Callable[[task.Sample], task.Sample]


def _recoloured(degrees: float) -> View:
    turned = {}
    for rgb in task.PALETTE.values():
        h, s, v = colorsys.rgb_to_hsv(*(c / 255.0 for c in rgb))
        new = colorsys.hsv_to_rgb((h + degrees / 360.0) % 1.0, s, v)
        turned[rgb] = np.array([round(c * 255.0) for c in new], np.uint8)

    def recolour(image: np.ndarray) -> np.ndarray:
        out = image.copy()
        for rgb, new in turned.items():
            out[np.all(image == rgb, axis=-1)] = new
        return out

    return lambda s: dataclasses.replace(s, base_image=recolour(s.base_image), wrist_image=recolour(s.wrist_image))


def _shifted(dx: int, dy: int) -> View:
    def shift(s: task.Sample) -> task.Sample:
        size = s.base_image.shape[0]
        out = np.empty_like(s.base_image)
        out[:] = task.OUTSIDE
        ys, xs = slice(max(dy, 0), size + min(dy, 0)), slice(max(dx, 0), size + min(dx, 0))
        out[ys, xs] = s.base_image[max(-dy, 0) : size - max(dy, 0), max(-dx, 0) : size - max(dx, 0)]
        x0, y0, x1, y1 = s.target_box
        box = tuple(int(np.clip(v, 0, size)) for v in (x0 + dx, y0 + dy, x1 + dx, y1 + dy))
        return dataclasses.replace(s, base_image=out, target_box=box)  # type: ignore[arg-type]

    return shift


def _dimmed(factor: float) -> View:
    def dim(image: np.ndarray) -> np.ndarray:
        return np.round(image.astype(np.float64) * factor).astype(np.uint8)

    return lambda s: dataclasses.replace(s, base_image=dim(s.base_image), wrist_image=dim(s.wrist_image))


def _prompted(prompt: str) -> View:
    return lambda s: dataclasses.replace(s, prompt=prompt)
