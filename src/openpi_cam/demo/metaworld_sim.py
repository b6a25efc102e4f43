"""Meta-World as the demo's second simulator: a Sawyer arm in MuJoCo, one task, two cameras, a scripted expert.

The task is `button-press-topdown-v3`: the button's box lands anywhere in a 20 x 10 cm area of the table at each
reset, and the arm must press the button from above. The policy sees what a robot would: a fixed camera looking over
the table (`corner`, flipped upright: Meta-World's camera frame renders it upside down), a camera on the gripper
(`gripperPOV`) and the hand's position and opening; the button's position is not in the state, so a policy that
succeeds must find the box in the pixels. At the 64 px the model reads, the box covers about 8 x 8 pixels of the
fixed camera (docs/DEMO_NOTES.md, "The Meta-World demo").

The simulator also says where the target is in every frame from its own geometry: a segmentation render of the fixed
camera gives the pixels of the box's bodies (`Frame.target_mask`, occlusion by the arm included) and their bounding
box (`Frame.target_box`), the ground truth the pointing figures and the nuisance mass are scored against.

Perturbations (`Perturbation`) change the scene at construction, each at a stated strength: the box's colour, the
light, the fixed camera's position, distractor cubes added with `MjSpec`, and the prompt; the kinds the reaching task
shares are spelled as its perturbations are (`demo.perturb`).
MuJoCo renders headless through EGL (or OSMesa); `MUJOCO_GL` is set to `egl` unless the environment names another.
Shadows are off: the 4096-pixel shadow map makes a render about four times slower and adds nothing the policy needs.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import numpy as np

TASK = "button-press-topdown-v3"


@dataclasses.dataclass(frozen=True)
class TaskSpec:
    """One Meta-World task as the demos use it: its instructions (the first is the one a demo episode sends; training
    episodes cycle through all of them) and what the pointing figures score against, the bodies (and sites) of the
    object the task is about, as the task's MJCF names them."""

    prompts: tuple[str, ...]
    target_bodies: tuple[str, ...] = ()
    target_sites: tuple[str, ...] = ()
    max_steps: int = 150  # the episode budget: about twice the steps the expert needs (docs/DEMO_NOTES.md)
    # The least distance (m, on the table) between the object and the goal that the task's own reset insists on: it
    # redraws until they are apart, and loops forever on a frozen draw that is not (`MetaWorldSim` draws again).
    object_goal_distance: float = 0.0

    @property
    def prompt(self) -> str:
        return self.prompts[0]


# The tasks of the multi-task models (six of Meta-World's MT10, button press first) and two MT10 tasks no model is
# trained on, whose scenes (a drawer, a window) are those of trained tasks with the opposite goal.
TASKS: dict[str, TaskSpec] = {
    TASK: TaskSpec(
        ("press the button", "push the button down", "press down on the button"), ("box", "buttonbox", "button")
    ),
    "reach-v3": TaskSpec(
        ("reach the goal", "move your hand to the goal", "touch the goal marker"),
        target_sites=("goal",),
        object_goal_distance=0.15,
    ),
    "push-v3": TaskSpec(
        ("push the puck to the goal", "slide the puck to the goal", "push the puck onto the target"),
        ("obj",),
        object_goal_distance=0.15,
    ),
    "drawer-close-v3": TaskSpec(("close the drawer", "push the drawer shut", "shut the drawer"), ("drawer_link",)),
    "door-open-v3": TaskSpec(
        ("open the door", "pull the door open", "swing the door open"), ("door_link",), max_steps=200
    ),
    "window-open-v3": TaskSpec(
        ("open the window", "slide the window open", "push the window open"), ("windowb_a", "windowb_b"), max_steps=200
    ),
    "drawer-open-v3": TaskSpec(("open the drawer",), ("drawer_link",), max_steps=200),
    "window-close-v3": TaskSpec(("close the window",), ("windowb_a", "windowb_b"), max_steps=200),
}


def all_prompts() -> tuple[str, ...]:
    """Every instruction of every task, trained or held out (what the multi-task models' text tokenizer learns)."""
    return tuple(p for spec in TASKS.values() for p in spec.prompts)


def task_of(prompt: str) -> str | None:
    """The task one of whose instructions `prompt` is, or None."""
    return next((name for name, spec in TASKS.items() if prompt in spec.prompts), None)


TRAINED_TASKS = ("button-press-topdown-v3", "reach-v3", "push-v3", "drawer-close-v3", "door-open-v3", "window-open-v3")
HELD_OUT_TASKS = ("drawer-open-v3", "window-close-v3")
BASE_CAMERA = "corner"
WRIST_CAMERA = "gripperPOV"
FLIPPED = frozenset({BASE_CAMERA})  # cameras whose frame comes out upside down
IMAGE_SIZE = 64
STATE_DIM = 4  # hand x, y, z and the gripper's opening: Meta-World's observation without the object and goal
ACTION_DIM = 4  # hand displacement (x, y, z) and grip effort, each in [-1, 1]
MAX_STEPS = TASKS[TASK].max_steps
PERTURBATION_KINDS = ("clean", "hue", "dim", "shift", "distractors", "prompt")
# MuJoCo picks its GL backend when it is first imported, by whoever imports it (metaworld does): set it first.
os.environ.setdefault("MUJOCO_GL", "egl")


@dataclasses.dataclass(frozen=True)
class Perturbation:
    """One change to the scene, `kind=strength` on the command line:

    - `clean`: none;
    - `hue=DEGREES`: the box's colours turned around the hue circle;
    - `dim=FACTOR`: every light's diffuse and ambient intensity (the head light's too) times the factor;
    - `shift=METRES`: the fixed camera moved that far sideways (along its image's x axis), still pointing the same way;
    - `distractors=N`: N cubes of unseen colours placed on the table, clear of the box's area;
    - `prompt=TEXT`: the prompt replaced (`prompt=` empties it).
    """

    kind: str = "clean"
    strength: str = ""

    @classmethod
    def parse(cls, text: str) -> Perturbation:
        kind, _, strength = text.partition("=")
        if kind not in PERTURBATION_KINDS:
            raise ValueError(f"unknown perturbation {text!r}: one of {', '.join(PERTURBATION_KINDS)} (kind=strength)")
        if kind in ("hue", "dim", "shift", "distractors"):
            try:
                float(strength)
            except ValueError:
                raise ValueError(f"perturbation {text!r} needs a number: {kind}=VALUE") from None
        if kind == "distractors" and (not strength.isdigit() or int(strength) < 1):
            raise ValueError(f"perturbation {text!r}: distractors=N with N a positive whole number")
        if kind == "dim" and float(strength) < 0:
            raise ValueError(f"perturbation {text!r}: dim=FACTOR with FACTOR >= 0")
        if kind == "clean" and strength:
            raise ValueError(f"perturbation {text!r}: clean takes no strength")
        return cls(kind, strength)

    @property
    def name(self) -> str:
        return self.kind if self.kind == "clean" else f"{self.kind}={self.strength}"

    @property
    def value(self) -> float:
        return float(self.strength)


CLEAN = Perturbation()


@dataclasses.dataclass(frozen=True)
class Frame:
    """What the robot observes at one step, and where the target is in it."""

    base_image: np.ndarray  # [S, S, 3] uint8, the fixed camera
    wrist_image: np.ndarray  # [S, S, 3] uint8, the gripper camera
    state: np.ndarray  # [STATE_DIM] float32
    prompt: str
    target_mask: np.ndarray  # [S, S] bool: the fixed camera's pixels showing the box
    target_box: tuple[int, int, int, int]  # the mask's bounding box (x0, y0, x1, y1), end exclusive; zeros if hidden


def _mujoco() -> Any:
    import mujoco  # an optional dependency: `pip install -e ".[metaworld]"`

    return mujoco


def _environment_class(task: str) -> Any:
    """Meta-World's environment class of `task`; an ImportError naming the extra where it is not installed."""
    try:
        _mujoco()
        from metaworld.env_dict import ALL_V3_ENVIRONMENTS  # optional: the `metaworld` extra
    except ImportError as e:
        raise ImportError(f'the Meta-World demo needs the metaworld extra: pip install -e ".[metaworld]" ({e})') from e
    return ALL_V3_ENVIRONMENTS[task]


def camera_names(model: Any) -> tuple[str, ...]:
    """The cameras of a task's MuJoCo model, in the model's order."""
    return tuple(model.camera(i).name for i in range(model.ncam))


def _check_camera(model: Any, task: str, name: str) -> None:
    if name not in (cameras := camera_names(model)):
        raise ValueError(f"Meta-World's {task} has no camera {name!r}: one of {', '.join(cameras)}")


def require_camera(name: str, task: str = TASK) -> None:
    """`MetaWorldSim`'s ValueError for a `wrist_camera` the task's scene lacks, raised before anything is run."""
    _check_camera(_environment_class(task)().model, task, name)


def require_simulator(task: str = TASK) -> None:
    """Raises the `_environment_class` ImportError before anything is loaded, where the extra is missing."""
    _environment_class(task)


def expert_policy(task: str = TASK) -> Any:
    """Meta-World's scripted policy of the task (`metaworld.policies`)."""
    _environment_class(task)
    from metaworld import policies

    name = "Sawyer" + "".join(w.capitalize() for w in task.removesuffix("-v3").split("-")) + "V3Policy"
    return getattr(policies, name)()


def _hue_turn(rgb: np.ndarray, degrees: float) -> np.ndarray:
    """Rotate RGB colours (last axis, in [0, 1]) around the grey axis, which turns the hue and keeps the brightness."""
    angle = np.radians(degrees)
    axis = np.ones(3) / np.sqrt(3.0)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.cos(angle) * np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * np.outer(axis, axis)
    return np.clip(rgb @ rotation.T, 0.0, 1.0)


DISTRACTOR_COLOURS = ((0.1, 0.3, 0.9), (0.1, 0.8, 0.2), (0.8, 0.2, 0.8), (0.1, 0.8, 0.8), (0.95, 0.95, 0.95))
DISTRACTOR_HALF_SIZE = 0.03


def _distractor_spots(rng: np.random.Generator, n: int, box_xy: np.ndarray) -> list[np.ndarray]:
    """Places on the table in front of the robot, each at least 12 cm from the box and 8 cm from the others."""
    spots: list[np.ndarray] = []
    while len(spots) < n:
        xy = rng.uniform([-0.3, 0.5], [0.3, 0.95])
        if np.linalg.norm(xy - box_xy) >= 0.12 and all(np.linalg.norm(xy - s) >= 0.08 for s in spots):
            spots.append(xy)
    return spots


def _target_geoms(model: Any, bodies: tuple[str, ...]) -> list[int]:
    """The geoms of the task's target bodies."""
    return [g for g in range(model.ngeom) if model.body(model.geom_bodyid[g]).name in bodies]


def set_scene(env: Any, rand_vec: np.ndarray) -> None:
    """What Meta-World's `set_task` does with a task of its benchmark, for a scene drawn here (the episode's own draw
    keeps seeds exact): the object and goal placement frozen to `rand_vec`, the goal in the observation (the scripted
    experts of tasks with a goal read it there; the observation space is recomputed, or the observation is clipped to
    the partially observable one's zeros)."""
    env._last_rand_vec = np.asarray(rand_vec, np.float64)
    env._freeze_rand_vec = True
    env._set_task_called = True
    if env._partially_observable:
        env._partially_observable = False
        env.__dict__.pop("sawyer_observation_space", None)


def _draw_scene(env: Any, rng: np.random.Generator, apart: float) -> np.ndarray:
    """A placement from the task's own reset range ([object xyz, goal xyz] where the task has both), drawn again
    until object and goal lie `apart` metres apart on the table, as the task's reset requires."""
    low, high = env._random_reset_space.low, env._random_reset_space.high
    while True:
        vec = rng.uniform(low, high)
        if apart == 0 or np.linalg.norm(vec[:2] - vec[-3:-1]) >= apart:
            return vec


class MetaWorldSim:
    """One episode of the task under a perturbation: `frame()` observes, `step(action)` acts, `success` says whether
    the button is pressed (Meta-World's `info["success"]`). Episode `seed` fixes the box's place (drawn from the task's
    own reset range) and the distractors' places, so every perturbation of a seed meets the same scene. `fovy`: the
    fixed camera's vertical field of view in degrees (None: Meta-World's, 45); a narrower one shows the table's
    middle, where every task's object sits, larger at the same pixel count. `wrist_camera`: the scene's camera seen
    as the wrist view; the bundled models see `WRIST_CAMERA`, and `behindGripper` follows the hand from half a metre
    behind it, looking ahead past the gripper."""

    def __init__(
        self,
        seed: int,
        perturbation: Perturbation = CLEAN,
        *,
        task: str = TASK,
        image_size: int = IMAGE_SIZE,
        prompt: str | None = None,
        fovy: float | None = None,
        wrist_camera: str = WRIST_CAMERA,
    ) -> None:
        if task not in TASKS:
            raise ValueError(f"unknown Meta-World task {task!r}: one of {', '.join(TASKS)}")
        mujoco = _mujoco()
        env = _environment_class(task)()
        _check_camera(env.model, task, wrist_camera)
        self.wrist_camera = wrist_camera
        rng = np.random.default_rng(seed)
        set_scene(env, _draw_scene(env, rng, TASKS[task].object_goal_distance))
        self.task, self.perturbation, self.seed, self.image_size = task, perturbation, seed, image_size
        self.spec = TASKS[task]
        self._prompt = self.spec.prompt if prompt is None else prompt
        if perturbation.kind == "distractors":
            self._add_distractors(env, mujoco, rng, int(perturbation.value), env._last_rand_vec[:2])
        env.model.light_castshadow[:] = 0
        self._perturb_model(env.model, mujoco)
        if fovy is not None:
            env.model.cam_fovy[env.model.camera(BASE_CAMERA).id] = fovy
        self.env = env
        self._obs, _ = env.reset()
        self._renderer = mujoco.Renderer(env.model, image_size, image_size)
        self._segmenter = mujoco.Renderer(env.model, image_size, image_size)
        self._segmenter.enable_segmentation_rendering()
        self._target_geoms = np.array(_target_geoms(env.model, self.spec.target_bodies), np.int64)
        self._target_sites = np.array([env.model.site(n).id for n in self.spec.target_sites], np.int64)
        self.steps = 0
        self.success = False
        self._expert = expert_policy(task)

    @staticmethod
    def _add_distractors(env: Any, mujoco: Any, rng: np.random.Generator, n: int, box_xy: np.ndarray) -> None:
        """Static cubes appended to the world in a recompiled model: new last bodies and geoms, so the ids and the
        state layout the task's code reads stay as they were."""
        spec = mujoco.MjSpec.from_file(env.model_name)
        for i, xy in enumerate(_distractor_spots(rng, n, box_xy)):
            body = spec.worldbody.add_body(name=f"distractor{i}", pos=[xy[0], xy[1], DISTRACTOR_HALF_SIZE])
            body.add_geom(
                type=mujoco.mjtGeom.mjGEOM_BOX,
                size=[DISTRACTOR_HALF_SIZE] * 3,
                rgba=[*DISTRACTOR_COLOURS[i % len(DISTRACTOR_COLOURS)], 1.0],
                contype=0,
                conaffinity=0,
            )
        model = spec.compile()
        model.vis.global_.offwidth = env.model.vis.global_.offwidth
        model.vis.global_.offheight = env.model.vis.global_.offheight
        env.model, env.data = model, mujoco.MjData(model)
        env.reset_mocap_welds()  # what Meta-World's constructor does to the model it loads

    def _perturb_model(self, model: Any, mujoco: Any) -> None:
        kind = self.perturbation.kind
        if kind == "hue":
            geoms = _target_geoms(model, self.spec.target_bodies)
            rgba = model.geom_rgba[geoms]
            rgba[:, :3] = _hue_turn(rgba[:, :3], self.perturbation.value)
            model.geom_rgba[geoms] = rgba
            # Geoms coloured by a material take the material's colour: turn those too.
            materials = sorted({int(model.geom_matid[g]) for g in geoms if model.geom_matid[g] >= 0})
            for m in materials:
                model.mat_rgba[m, :3] = _hue_turn(model.mat_rgba[m, :3], self.perturbation.value)
        elif kind == "dim":
            model.light_diffuse[:] *= self.perturbation.value
            model.light_ambient[:] *= self.perturbation.value
            model.vis.headlight.diffuse[:] *= self.perturbation.value
            model.vis.headlight.ambient[:] *= self.perturbation.value
        elif kind == "shift":
            camera = model.camera(BASE_CAMERA).id
            data = mujoco.MjData(model)
            mujoco.mj_forward(model, data)
            # The camera's x axis in its parent body's frame (cameras of this scene hang off the world body).
            x_axis = data.cam_xmat[camera].reshape(3, 3)[:, 0]
            model.cam_pos[camera] = model.cam_pos[camera] + self.perturbation.value * x_axis

    @property
    def prompt(self) -> str:
        if self.perturbation.kind == "prompt":
            return self.perturbation.strength
        return self._prompt

    def _render(self, renderer: Any, camera: str) -> np.ndarray:
        renderer.update_scene(self.env.data, camera=camera)
        image = renderer.render()
        return np.ascontiguousarray(image[::-1] if camera in FLIPPED else image)

    def target_mask(self) -> np.ndarray:
        """The base camera's pixels showing the task's target (a segmentation render: occlusion by the arm counts)."""
        segments = self._render(self._segmenter, BASE_CAMERA)
        objects = _mujoco().mjtObj
        geoms = (segments[..., 1] == objects.mjOBJ_GEOM) & np.isin(segments[..., 0], self._target_geoms)
        sites = (segments[..., 1] == objects.mjOBJ_SITE) & np.isin(segments[..., 0], self._target_sites)
        return geoms | sites

    def frame(self, *, with_target: bool = True) -> Frame:
        """What the robot observes now; `with_target` False skips the segmentation render (an empty mask and box)."""
        size = self.image_size
        mask = self.target_mask() if with_target else np.zeros((size, size), bool)
        ys, xs = np.nonzero(mask)
        box = (int(xs.min()), int(ys.min()), int(xs.max()) + 1, int(ys.max()) + 1) if len(xs) else (0, 0, 0, 0)
        return Frame(
            base_image=self._render(self._renderer, BASE_CAMERA),
            wrist_image=self._render(self._renderer, self.wrist_camera),
            state=np.asarray(self._obs[:STATE_DIM], np.float32),
            prompt=self.prompt,
            target_mask=mask,
            target_box=box,
        )

    def expert_action(self) -> np.ndarray:
        """The scripted expert's action at this state, clipped to the action space (it asks for up to +-12)."""
        return np.clip(self._expert.get_action(self._obs), -1.0, 1.0).astype(np.float32)

    def step(self, action: np.ndarray) -> bool:
        """Apply one action (clipped to the action space, as Meta-World's own step does); returns `success`."""
        action = np.clip(np.asarray(action, np.float64).reshape(-1)[:ACTION_DIM], -1.0, 1.0)
        self._obs, _, _, _, info = self.env.step(action)
        self.steps += 1
        self.success = self.success or bool(info["success"])
        return self.success

    def close(self) -> None:
        self._renderer.close()
        self._segmenter.close()
        self.env.close()

    def __enter__(self) -> MetaWorldSim:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
