"""Synthetic reaching task: coloured blocks on a table, an end effector, and a prompt naming the block to reach.

Coordinates: the state is the end-effector position (x, y) in [-1, 1]^2; x grows to the right, y downwards, and
(-1, -1) is the top-left corner of the base camera image. An action is one step's displacement in the same units, so an
action chunk is `[horizon, 2]`. Everything is a pure function of a seed, so data, tests and the demo are reproducible.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from openpi_cam.policies.demo_reach import ACTION_HORIZON

COLORS: dict[str, tuple[int, int, int]] = {
    "red": (220, 40, 40),
    "green": (40, 200, 60),
    "blue": (50, 90, 235),
    "yellow": (230, 210, 40),
}
# Colours no training scene shows: what `demo.perturb`'s distractor blocks are painted with.
UNSEEN_COLORS: dict[str, tuple[int, int, int]] = {
    "orange": (245, 130, 20),
    "purple": (150, 60, 200),
    "cyan": (40, 215, 225),
    "pink": (250, 125, 195),
}
PALETTE = {**COLORS, **UNSEEN_COLORS}
BACKGROUND = (70, 62, 55)
OUTSIDE = (0, 0, 0)
MARKER = (255, 255, 255)


@dataclasses.dataclass(frozen=True)
class TaskConfig:
    image_size: int = 64
    block_size: int = 12  # pixels: 1-4 of the model's 16 px patches, so the target shows on the maps' patch grid
    min_blocks: int = 2
    max_blocks: int = 3
    wrist_crop: int = 32  # pixels of the base view around the end effector, upsampled to image_size
    action_horizon: int = ACTION_HORIZON
    max_speed: float = 0.12  # largest displacement per step
    success_radius: float = 0.12
    near_fraction: float = 0.3  # share of training states sampled close to the target (decelerating chunks)


@dataclasses.dataclass(frozen=True)
class Block:
    color: str
    box: tuple[int, int, int, int]  # base-camera pixels (x0, y0, x1, y1), end exclusive


@dataclasses.dataclass(frozen=True)
class Scene:
    blocks: tuple[Block, ...]
    target: int  # index into blocks of the block the prompt names

    @property
    def target_block(self) -> Block:
        return self.blocks[self.target]

    def with_target(self, color: str) -> Scene:
        index = [b.color for b in self.blocks].index(color)
        return dataclasses.replace(self, target=index)


@dataclasses.dataclass(frozen=True)
class Sample:
    """One observation of the task plus the expert's answer and the ground truth for judging the maps."""

    base_image: np.ndarray  # [S, S, 3] uint8
    wrist_image: np.ndarray  # [S, S, 3] uint8
    state: np.ndarray  # [2] float32
    prompt: str
    actions: np.ndarray  # [horizon, 2] float32 expert chunk
    target_box: tuple[int, int, int, int]


def prompt_for(color: str) -> str:
    return f"reach the {color} block"


def pixel_to_state(px: np.ndarray | float, size: int) -> np.ndarray:
    return np.asarray(px, np.float64) / size * 2.0 - 1.0


def state_to_pixel(state: np.ndarray, size: int) -> np.ndarray:
    return (np.asarray(state, np.float64) + 1.0) / 2.0 * size


def block_center(block: Block, size: int) -> np.ndarray:
    x0, y0, x1, y1 = block.box
    return pixel_to_state(np.array([(x0 + x1) / 2.0, (y0 + y1) / 2.0]), size).astype(np.float32)


def place_boxes(
    rng: np.random.Generator, n: int, cfg: TaskConfig = TaskConfig(), taken: tuple[tuple[int, int, int, int], ...] = ()
) -> list[tuple[int, int, int, int]]:
    """`n` block boxes at random places on the table, apart from each other and from the `taken` ones."""
    margin, size, gap = 2, cfg.block_size, 3
    boxes: list[tuple[int, int, int, int]] = []
    while len(boxes) < n:
        x0, y0 = (int(v) for v in rng.integers(margin, cfg.image_size - margin - size + 1, size=2))
        box = (x0, y0, x0 + size, y0 + size)
        # Keep a gap between blocks so each one is a separate blob on the patch grid.
        if all(
            x0 >= b[2] + gap or b[0] >= box[2] + gap or y0 >= b[3] + gap or b[1] >= box[3] + gap
            for b in (*taken, *boxes)
        ):
            boxes.append(box)
    return boxes


def random_scene(rng: np.random.Generator, cfg: TaskConfig = TaskConfig()) -> Scene:
    n = int(rng.integers(cfg.min_blocks, cfg.max_blocks + 1))
    colors = rng.choice(list(COLORS), size=n, replace=False)
    boxes = place_boxes(rng, n, cfg)
    blocks = tuple(Block(str(c), b) for c, b in zip(colors, boxes, strict=True))
    return Scene(blocks=blocks, target=int(rng.integers(n)))


def render_scene(scene: Scene, cfg: TaskConfig = TaskConfig()) -> np.ndarray:
    img = np.empty((cfg.image_size, cfg.image_size, 3), np.uint8)
    img[:] = BACKGROUND
    for block in scene.blocks:
        x0, y0, x1, y1 = block.box
        img[y0:y1, x0:x1] = PALETTE[block.color]
    return img


def render_base(scene: Scene, state: np.ndarray, cfg: TaskConfig = TaskConfig()) -> np.ndarray:
    img = render_scene(scene, cfg)
    cx, cy = np.floor(state_to_pixel(state, cfg.image_size)).astype(int)
    s = cfg.image_size
    # A small plus sign: drawn last so it stays visible on top of a block once the end effector arrives.
    for dx, dy in [(0, 0), (-1, 0), (1, 0), (-2, 0), (2, 0), (0, -1), (0, 1), (0, -2), (0, 2)]:
        x, y = cx + dx, cy + dy
        if 0 <= x < s and 0 <= y < s:
            img[y, x] = MARKER
    return img


def render_wrist(scene: Scene, state: np.ndarray, cfg: TaskConfig = TaskConfig()) -> np.ndarray:
    """A camera riding on the end effector: the base view around it, magnified; black beyond the table."""
    scene_img = render_scene(scene, cfg)
    half = cfg.wrist_crop // 2
    padded = np.empty((cfg.image_size + 2 * half, cfg.image_size + 2 * half, 3), np.uint8)
    padded[:] = OUTSIDE
    padded[half:-half, half:-half] = scene_img
    cx, cy = np.floor(state_to_pixel(state, cfg.image_size)).astype(int)
    crop = padded[cy : cy + cfg.wrist_crop, cx : cx + cfg.wrist_crop]
    reps = cfg.image_size // cfg.wrist_crop
    return np.repeat(np.repeat(crop, reps, axis=0), reps, axis=1)


def expert_chunk(state: np.ndarray, goal: np.ndarray, cfg: TaskConfig = TaskConfig()) -> np.ndarray:
    """Head for the goal at `max_speed`: the same step repeated over the chunk (the robot replans every few steps and
    the simulator stops on arrival). A constant chunk has a single non-zero DCT coefficient per dimension, so its FAST
    tokens are two informative ids followed by 18 zero-coefficient ids (the shipped FAST fit learned no merges:
    see `make_tokenizers.fit_fast`)."""
    d = np.asarray(goal, np.float64) - np.asarray(state, np.float64)
    dist = float(np.linalg.norm(d))
    step = d * (cfg.max_speed / dist) if dist > 1e-9 else np.zeros(2)
    return np.tile(step, (cfg.action_horizon, 1)).astype(np.float32)


def observe(scene: Scene, state: np.ndarray, cfg: TaskConfig = TaskConfig()) -> Sample:
    state = np.asarray(state, np.float32)
    target = scene.target_block
    return Sample(
        base_image=render_base(scene, state, cfg),
        wrist_image=render_wrist(scene, state, cfg),
        state=state,
        prompt=prompt_for(target.color),
        actions=expert_chunk(state, block_center(target, cfg.image_size), cfg),
        target_box=target.box,
    )


def random_start(rng: np.random.Generator, scene: Scene, cfg: TaskConfig = TaskConfig(), min_dist: float = 0.5):
    goal = block_center(scene.target_block, cfg.image_size)
    while True:
        state = rng.uniform(-0.9, 0.9, size=2).astype(np.float32)
        if np.linalg.norm(state - goal) >= min_dist:
            return state


def training_state(rng: np.random.Generator, scene: Scene, cfg: TaskConfig = TaskConfig()) -> np.ndarray:
    """Anywhere on the table, or (`near_fraction` of the time) close to the named block so decelerating chunks occur."""
    goal = block_center(scene.target_block, cfg.image_size)
    if rng.random() < cfg.near_fraction:
        state = goal + rng.uniform(-0.4, 0.4, size=2)
    else:
        state = rng.uniform(-0.95, 0.95, size=2)
    return np.clip(state, -0.95, 0.95)


def training_sample(rng: np.random.Generator, cfg: TaskConfig = TaskConfig()) -> Sample:
    """An i.i.d. (scene, state) pair: the expert is Markov in the state, so this covers every state a rollout meets."""
    scene = random_scene(rng, cfg)
    return observe(scene, training_state(rng, scene, cfg), cfg)


def other_block(rng: np.random.Generator, scene: Scene) -> int:
    """A random block other than the named one (scenes hold at least two)."""
    return int(rng.choice([i for i in range(len(scene.blocks)) if i != scene.target]))


def contrast_pair(rng: np.random.Generator, cfg: TaskConfig = TaskConfig()) -> tuple[Sample, Sample]:
    """One scene and state observed twice, the prompt naming two different blocks: identical images, different
    answers, so only the prompt can tell the two apart (a batch of such pairs rewards reading the colour)."""
    scene = random_scene(rng, cfg)
    state = training_state(rng, scene, cfg)
    other = dataclasses.replace(scene, target=other_block(rng, scene))
    return observe(scene, state, cfg), observe(other, state, cfg)


def make_dataset(seed: int, n: int, cfg: TaskConfig = TaskConfig()) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    samples = [training_sample(rng, cfg) for _ in range(n)]
    return {
        "base_image": np.stack([s.base_image for s in samples]),
        "wrist_image": np.stack([s.wrist_image for s in samples]),
        "state": np.stack([s.state for s in samples]),
        "actions": np.stack([s.actions for s in samples]),
        "prompt": np.array([s.prompt for s in samples]),
        "target_box": np.array([s.target_box for s in samples], np.int32),
    }
