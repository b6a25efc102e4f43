"""The amortised occlusion head: a small per-patch model, fitted offline to one policy's own occlusion maps
(`openpi-cam head fit`), that predicts each patch's occlusion drop from cheaper kinds' maps of the same call. It is
what the `occlusion-head` kind applies: NumPy, no model pass of its own.

Per camera and explained score, every input map and the occlusion target are divided by their largest absolute
value over the camera's patches (`normalised`), so the head reads each map's shape, not its scale, which varies by
orders of magnitude between steps, cameras and kinds. A patch's features are its K normalised input values and its
camera (one-hot, C values); with H hidden units

    y[c, n] = w2 . tanh(W1 x[c, n] + b1) + b2 + position_bias[c, n]

(H = 0: y = w2 . x + b2 + position_bias, a linear head), y being the patch's predicted normalised occlusion drop:
1 where the head expects the camera's largest drop. The head is saved as one JSON file (arrays as lists of floats,
which round-trip float64 exactly) recording its inputs, normalisation, cameras, grid, the target and model it was
fitted for and the fit's held-out figures; `load` refuses a file it cannot trust in one line naming it.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import os
import pathlib
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from openpi_cam.vocabulary import HEAD_KINDS, MAP_KINDS, HeadRef

FORMAT = "openpi-cam occlusion head"
FORMAT_VERSION = 1
# The one normalisation this version knows: each camera's map of one score divided by its largest |value|.
NORMALISATION = "max-abs per camera and score"
# Where a model ships its head: in its assets folder (`checkpoints.model_spec.ModelSpec.occlusion_head`).
HEAD_FILE = "occlusion_head.json"
TARGET_KIND = "occlusion"
# What a head cannot read: the map it stands in for, and itself.
NOT_INPUTS = (TARGET_KIND, *HEAD_KINDS)


def check_inputs(inputs: Sequence[str]) -> tuple[str, ...]:
    """A head's input kinds, deduplicated in order; one that is not a map kind, or is occlusion or the head itself,
    is refused in one line."""
    inputs = tuple(dict.fromkeys(inputs))
    usable = [k for k in MAP_KINDS if k not in NOT_INPUTS]
    bad = [k for k in inputs if k not in usable]
    if bad or not inputs:
        raise ValueError(f"a head's inputs must be a non-empty selection of {usable}, got {list(inputs)}")
    return inputs


def normalised(maps: np.ndarray) -> np.ndarray:
    """[..., N] -> float64 [..., N], each row divided by its largest |value| (a row of zeros stays zeros)."""
    m = np.asarray(maps, np.float64)
    scale = np.max(np.abs(m), axis=-1, keepdims=True)
    return np.divide(m, scale, out=np.zeros_like(m), where=scale > 0)


@dataclasses.dataclass(frozen=True)
class OcclusionHead:
    """A fitted head (module docstring). w1 [K + C, H] and b1 [H] are None for a linear head (H = 0), w2 is [H] (or
    [K + C]), position_bias [C, N]. `model` is the model the maps were explained with (`ModelSpec.to_json`), `fit`
    how it was fitted and its held-out figures."""

    inputs: tuple[str, ...]
    cameras: tuple[str, ...]
    grid: tuple[int, int]
    target: str
    family: str
    w1: np.ndarray | None
    b1: np.ndarray | None
    w2: np.ndarray
    b2: float
    position_bias: np.ndarray
    model: dict[str, Any] = dataclasses.field(default_factory=dict)
    fit: dict[str, Any] = dataclasses.field(default_factory=dict)

    @property
    def hidden(self) -> int:
        return 0 if self.w1 is None else int(self.w1.shape[1])

    @property
    def features(self) -> int:
        return len(self.inputs) + len(self.cameras)

    def forward(self, x: np.ndarray, camera: int) -> np.ndarray:
        """The head on normalised inputs x [..., N, K] of camera number `camera` -> float64 [..., N]."""
        x = np.asarray(x, np.float64)
        onehot = np.broadcast_to(np.eye(len(self.cameras))[camera], (*x.shape[:-1], len(self.cameras)))
        f = np.concatenate([x, onehot], axis=-1)
        if self.w1 is not None and self.b1 is not None:
            f = np.tanh(f @ self.w1 + self.b1)
        return f @ self.w2 + self.b2 + self.position_bias[camera]

    def predict(self, maps: Mapping[str, Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
        """The `occlusion-head` map of every camera from one call's maps of the input kinds (kind -> camera ->
        [..., Hp, Wp], leading axes one per score) -> camera -> float32 [..., Hp, Wp]. Maps of another grid, or
        cameras other than the head's, are refused in one line."""
        missing = [k for k in self.inputs if k not in maps]
        if missing:
            raise ValueError(f"the occlusion head reads {list(self.inputs)}; the call has no {missing} maps")
        out = {}
        for index, camera in enumerate(self.cameras):
            columns = []
            for kind in self.inputs:
                if set(maps[kind]) != set(self.cameras):
                    raise ValueError(
                        f"the occlusion head was fitted for cameras {list(self.cameras)}, the {kind} maps have "
                        f"{sorted(maps[kind])}"
                    )
                m = np.asarray(maps[kind][camera])
                if m.shape[-2:] != self.grid:
                    raise ValueError(
                        f"the occlusion head was fitted on a {self.grid} patch grid, {kind}/{camera} is {m.shape[-2:]}"
                    )
                columns.append(normalised(m.reshape(*m.shape[:-2], -1)))
            y = self.forward(np.stack(columns, axis=-1), index)
            out[camera] = y.reshape(*y.shape[:-1], *self.grid).astype(np.float32)
        return out


def _floats(a: np.ndarray | None) -> Any:
    return None if a is None else np.asarray(a, np.float64).tolist()


def to_json(head: OcclusionHead) -> dict[str, Any]:
    return {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "inputs": list(head.inputs),
        "normalisation": NORMALISATION,
        "cameras": list(head.cameras),
        "grid": list(head.grid),
        "target": head.target,
        "family": head.family,
        "model": head.model,
        "hidden": head.hidden,
        "weights": {
            "w1": _floats(head.w1),
            "b1": _floats(head.b1),
            "w2": _floats(head.w2),
            "b2": float(head.b2),
            "position_bias": _floats(head.position_bias),
        },
        "fit": head.fit,
    }


def save(head: OcclusionHead, path: str | os.PathLike[str]) -> pathlib.Path:
    """Write the head as one JSON file (atomically: a reader never sees half a file)."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    staged = path.with_name(path.name + ".tmp")
    staged.write_text(json.dumps(to_json(head), allow_nan=False, indent=1) + "\n")
    os.replace(staged, path)
    return path


def load(path: str | os.PathLike[str]) -> OcclusionHead:
    """Read and validate a head file; a bad file raises ValueError in one line naming the file and the problem."""
    path = pathlib.Path(path)
    try:
        return _parse(path.read_bytes())
    except FileNotFoundError:
        raise ValueError(f"{path}: no such occlusion head file") from None
    except OSError as e:
        raise ValueError(f"{path}: cannot read the occlusion head file ({e.strerror or type(e).__name__})") from None
    except ValueError as e:
        raise ValueError(f"{path}: {str(e).splitlines()[0] if str(e) else type(e).__name__}") from None


def load_ref(ref: HeadRef) -> OcclusionHead:
    """The head a run's options name, read once per file identity; a file whose bytes are no longer the ones the
    options hashed is refused (a run must not mix heads)."""
    return _load_checked(ref.path, ref.sha256)


@functools.lru_cache(maxsize=8)
def _load_checked(path: str, sha256: str) -> OcclusionHead:
    try:
        data = pathlib.Path(path).read_bytes()
    except OSError as e:
        raise ValueError(f"{path}: cannot read the occlusion head file ({e.strerror or type(e).__name__})") from None
    found = hashlib.sha256(data).hexdigest()
    if found != sha256:
        raise ValueError(
            f"{path}: the occlusion head file changed (sha256 {found[:12]}, the options name {sha256[:12]})"
        )
    try:
        return _parse(data)
    except ValueError as e:
        raise ValueError(f"{path}: {str(e).splitlines()[0]}") from None


def _parse(data: bytes) -> OcclusionHead:
    try:
        return from_json(json.loads(data))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"not a JSON occlusion head file ({str(e).splitlines()[0]})") from None
    except (KeyError, TypeError) as e:
        raise ValueError(f"malformed occlusion head file ({type(e).__name__}: {e})") from None


def _array(weights: Mapping[str, Any], key: str, shape: tuple[int, ...]) -> np.ndarray:
    """weights[key] as a finite float64 array of `shape`, else ValueError naming `weights.key`."""
    try:
        a = np.asarray(weights[key], np.float64)
    except (ValueError, TypeError):
        raise ValueError(f"weights.{key} is not a numeric array") from None
    if a.shape != shape:
        raise ValueError(f"weights.{key} has shape {list(a.shape)}, expected {list(shape)}")
    if not np.isfinite(a).all():
        raise ValueError(f"weights.{key} has non-finite values")
    return a


def _strings(data: Mapping[str, Any], key: str) -> tuple[str, ...]:
    value = data.get(key)
    if not isinstance(value, list) or not value or not all(isinstance(v, str) for v in value):
        raise ValueError(f"{key} must be a non-empty list of names, got {value!r}")
    return tuple(value)


def from_json(data: Any) -> OcclusionHead:
    """A head from its JSON object, validated (ValueError naming the first problem)."""
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        found = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise ValueError(f"not an occlusion head file (format {found!r}, expected {FORMAT!r})")
    version = data.get("format_version")
    if not isinstance(version, int) or not 1 <= version <= FORMAT_VERSION:
        raise ValueError(f"format_version {version!r} is not one this openpi-cam reads (1 to {FORMAT_VERSION})")
    if data.get("normalisation") != NORMALISATION:
        raise ValueError(f"normalisation {data.get('normalisation')!r} is not {NORMALISATION!r}")
    inputs, cameras = check_inputs(_strings(data, "inputs")), _strings(data, "cameras")
    grid = data.get("grid")
    if not isinstance(grid, list) or len(grid) != 2 or not all(isinstance(g, int) and g > 0 for g in grid):
        raise ValueError(f"grid must be [rows, columns] of patches, got {grid!r}")
    hidden = data.get("hidden")
    if not isinstance(hidden, int) or hidden < 0:
        raise ValueError(f"hidden {hidden!r} is not a number of units >= 0")
    for key in ("target", "family"):
        if not isinstance(data.get(key), str):
            raise ValueError(f"{key} {data.get(key)!r} is not a name")
    weights = data.get("weights")
    if not isinstance(weights, dict):
        raise ValueError("weights is missing or not an object")
    features, n = len(inputs) + len(cameras), grid[0] * grid[1]
    w1 = b1 = None
    if hidden:
        w1, b1 = _array(weights, "w1", (features, hidden)), _array(weights, "b1", (hidden,))
    return OcclusionHead(
        inputs=inputs,
        cameras=cameras,
        grid=(grid[0], grid[1]),
        target=data["target"],
        family=data["family"],
        w1=w1,
        b1=b1,
        w2=_array(weights, "w2", (hidden or features,)),
        b2=float(_array(weights, "b2", ())),
        position_bias=_array(weights, "position_bias", (len(cameras), n)),
        model=dict(data.get("model") or {}),
        fit=dict(data.get("fit") or {}),
    )
