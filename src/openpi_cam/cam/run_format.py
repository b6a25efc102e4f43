"""The CAM run-directory format, both directions (docs/FORMAT.md): names, schema, step-file encoding, atomic
writes, index and manifest records, and reading runs back.

The step files are the source of truth. `index.jsonl` and `manifest.json` are conveniences that may be stale or
damaged after a crash; everything here copes with that by falling back to the step files. The stateful writer
(caps, counters, one run at a time) is `cam.logger.CAMLogger`, built on these functions.
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import io
import json
import logging
import math
import os
import pathlib
import re
import secrets
import zipfile
import zlib
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from openpi_cam.errors import BadFile, load_json, reading, unreadable
from openpi_cam.vocabulary import MAP_KIND_INFO

log = logging.getLogger(__name__)

# What each version changed, and how older runs read: docs/FORMAT.md, "Schema history".
SCHEMA_VERSION = 3
RUN_JSON = "run.json"
INDEX_JSONL = "index.jsonl"
MANIFEST_JSON = "manifest.json"
STEPS_DIR = "steps"
FRAME_PREFIX = "frame/"
MODEL_FRAME_PREFIX = "frame_model/"
INPUT_PREFIX = "input/"  # the explained call's non-image model inputs (token ids, masks, generated output)
# under `input/`: a model image its uint8 `frame_model/` does not hold exactly (float32 [H, W, 3] in [-1, 1])
IMAGE_INPUT = "image/"
EXTRA_ARRAY_PREFIX = "extra/"  # numeric arrays a client sent under `cam_extra/` (other values: meta["extra"])
# the client's other numeric observation values (e.g. its state), stored with raw frames: what a replay sends again
CLIENT_PREFIX = "client/"
# with a failure monitor: the step's monitor inputs (`monitor/features/<name>`, `monitor/token_entropy`,
# `monitor/stac`), its score (`monitor/score`) and whether its connection was flagged by then (`monitor/flag`)
MONITOR_PREFIX = "monitor/"
META_KEY = "meta"

_STEP_FILE_RE = re.compile(r"^(\d{8,})\.npz$")
# What np.load and the meta lookup raise for a damaged or foreign step file.
_UNREADABLE = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error)
STEP_FILE_KIND = "step file"  # what `errors.reading` calls a step file that cannot be read


def step_file(seq: int) -> str:
    """Path of a step file relative to the run directory."""
    return f"{STEPS_DIR}/{seq:08d}.npz"


def utc_now_iso() -> str:
    return dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def json_default(value: Any) -> Any:
    """Lets numpy scalars and arrays (common in step metadata) pass through `json.dumps`."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, pathlib.Path):
        return str(value)
    raise TypeError(f"object of type {type(value).__name__} is not JSON serialisable")


def dumps(obj: Any, *, indent: int | None = None) -> str:
    return json.dumps(obj, default=json_default, indent=indent, ensure_ascii=False)


def write_bytes_atomic(path: pathlib.Path, data: bytes) -> None:
    """Writes to a unique temporary name in the same directory, then renames: readers never see a partial file."""
    tmp = path.with_name(f"{path.name}.{os.getpid()}-{secrets.token_hex(4)}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_json_atomic(path: pathlib.Path, obj: Any) -> None:
    write_bytes_atomic(path, (dumps(obj, indent=1) + "\n").encode())


def map_summary(cam_map: np.ndarray) -> dict[str, Any]:
    """max, mean and argmax [row, col] of a (Hp, Wp) map, or of the mean over T of a (T, Hp, Wp) stack.

    Non-finite cells are ignored; a map without any finite cell summarises to None values.
    """
    m = np.asarray(cam_map, dtype=np.float32)
    if m.ndim == 3:
        m = m.mean(axis=0)
    if m.ndim != 2 or m.size == 0:
        raise ValueError(f"expected a non-empty (Hp, Wp) or (T, Hp, Wp) map, got shape {np.shape(cam_map)}")
    finite = np.isfinite(m)
    if not finite.any():
        return {"max": None, "mean": None, "argmax": None}
    masked = np.where(finite, m, -np.inf)
    row, col = np.unravel_index(int(np.argmax(masked)), m.shape)
    return {"max": float(masked[row, col]), "mean": float(m[finite].mean()), "argmax": [int(row), int(col)]}


def index_entry(seq: int, meta: Mapping[str, Any], maps: Mapping[str, Mapping[str, np.ndarray]]) -> dict[str, Any]:
    """One line of index.jsonl (also one element of the manifest's "steps"); `summary` describes the maps of
    `summary_kind` (Grad-CAM when logged)."""
    kind = summary_kind(maps)
    return {
        "seq": seq,
        "file": step_file(seq),
        "connection": meta.get("connection"),
        "step": meta.get("step"),
        "timestamp": meta.get("timestamp"),
        "target": meta.get("target"),
        "malformed": meta.get("malformed"),
        "summary_kind": kind,
        "summary": {} if kind is None else {camera: map_summary(m) for camera, m in maps[kind].items()},
    }


def build_manifest(
    run_info: Mapping[str, Any], counters: Mapping[str, Any], entries: Iterable[dict[str, Any]], **extra: Any
) -> dict[str, Any]:
    steps = sorted(entries, key=lambda e: e["seq"])
    head = {**run_info, **extra, "updated_at": utc_now_iso(), "num_steps": len(steps)}
    return head | {"counters": counters, "steps": steps}


@dataclasses.dataclass
class StepRecord:
    """One step to write; `meta` holds the step JSON fields other than those the logger fills (`RESERVED_META`)."""

    connection: str
    step: int
    timestamp: float
    maps: dict[str, dict[str, np.ndarray]]  # kind -> camera -> float32 (Hp, Wp) or (T, Hp, Wp)
    frames: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    model_frames: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    inputs: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    meta: dict[str, Any] = dataclasses.field(default_factory=dict)
    extra_arrays: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)  # stored as `extra/<key>`
    client_inputs: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)  # stored as `client/<key>`
    monitor: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)  # stored as `monitor/<name>`


# Fields of the step JSON that the writer owns; StepRecord.meta must not set them.
RESERVED_META = ("schema_version", "run_id", "seq", "connection", "step", "timestamp")


def _str_or_none(value: Any) -> str | None:
    return None if value is None else str(value)


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _int_or_none(value: Any) -> int | None:
    return int(value) if _number(value) and math.isfinite(value) else None


def _float_or_none(value: Any) -> float | None:
    return float(value) if _number(value) else None


def _ints(value: Any) -> tuple[int, ...] | None:
    if not isinstance(value, list | tuple) or not all(_int_or_none(v) is not None for v in value):
        return None
    return tuple(int(v) for v in value)


def _pair(value: Any) -> tuple[int, int] | None:
    ints = _ints(value)
    return (ints[0], ints[1]) if ints is not None and len(ints) == 2 else None


def _strs(value: Any) -> tuple[str, ...] | None:
    return tuple(str(v) for v in value) if isinstance(value, list | tuple) else None


def _score(value: Any) -> float | tuple[float, ...] | None:
    if isinstance(value, np.ndarray | np.generic):
        value = value.tolist()
    if isinstance(value, list | tuple):
        return tuple(float(v) if _number(v) else math.nan for v in value)
    return float(value) if _number(value) else None


def _list(value: tuple[Any, ...] | None) -> list[Any] | None:
    return None if value is None else list(value)


@dataclasses.dataclass(frozen=True)
class CameraCheck:
    """One camera's spot check (`meta.check.cameras.<camera>`, `cam.spot_check`)."""

    score: float  # the explained score, nothing painted
    top_patch: dict[str, int]  # kind -> row-major index of the map's highest cell
    top_patch_drop: dict[str, float]  # kind -> score minus the score with that patch alone painted
    random_patches: tuple[int, ...]
    random_patch_drops: tuple[float, ...]

    @classmethod
    def from_json(cls, value: Any) -> CameraCheck:
        d = dict(value) if isinstance(value, Mapping) else {}
        top, drop = d.get("top_patch") or {}, d.get("top_patch_drop") or {}
        return cls(
            score=float(d.get("score", math.nan)),
            top_patch={str(k): int(v) for k, v in top.items() if _number(v)},
            top_patch_drop={str(k): float(v) for k, v in drop.items() if _number(v)},
            random_patches=tuple(int(i) for i in d.get("random_patches") or ()),
            random_patch_drops=tuple(float(x) for x in d.get("random_patch_drops") or ()),
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "score": self.score,
            "top_patch": dict(self.top_patch),
            "top_patch_drop": dict(self.top_patch_drop),
            "random_patches": list(self.random_patches),
            "random_patch_drops": list(self.random_patch_drops),
        }

    def drops(self, kind: str) -> tuple[float, tuple[float, ...]] | None:
        """(the kind's top patch's drop, the random patches' drops), or None when the kind was not checked. A random
        draw of the kind's own top patch is left out: it is no competitor, and without it a top patch no better than
        a random one beats the R' others with probability 1 / (R' + 1)."""
        if kind not in self.top_patch_drop:
            return None
        own = self.top_patch.get(kind)
        pairs = zip(self.random_patches, self.random_patch_drops, strict=False)
        return self.top_patch_drop[kind], tuple(d for i, d in pairs if i != own)


@dataclasses.dataclass(frozen=True)
class SpotCheck:
    """A step's spot check (`meta.check`): per valid camera its figures, or why it was skipped."""

    patches: int = 0  # random patches per camera
    seed: int = 0
    cameras: dict[str, CameraCheck] = dataclasses.field(default_factory=dict)
    skipped: str | None = None  # why there are no figures (e.g. "multi_score_target", "failed_<Error>")
    error: str | None = None  # the first 200 characters of a failure's message

    @classmethod
    def from_json(cls, value: Any) -> SpotCheck:
        d = dict(value) if isinstance(value, Mapping) else {}
        cameras = d.get("cameras") if isinstance(d.get("cameras"), Mapping) else {}
        return cls(
            patches=int(d.get("patches", 0)),
            seed=int(d.get("seed", 0)),
            cameras={str(c): CameraCheck.from_json(v) for c, v in cameras.items()},
            skipped=_str_or_none(d.get("skipped")),
            error=_str_or_none(d.get("error")),
        )

    def to_json(self) -> dict[str, Any]:
        if self.skipped is not None:
            return {"skipped": self.skipped, **({} if self.error is None else {"error": self.error})}
        return {
            "patches": self.patches,
            "seed": self.seed,
            "cameras": {c: v.to_json() for c, v in self.cameras.items()},
        }


@dataclasses.dataclass(frozen=True)
class CameraMeta:
    """One camera of a logged step (`meta.cameras.<camera>`, docs/FORMAT.md)."""

    obs_key: str | None = None  # the client observation key its image came from
    valid: bool = True  # the image mask the model saw
    grid: tuple[int, int] | None = None  # (Hp, Wp): the token grid of its maps
    span: tuple[int, int] | None = None  # [start, end) of its tokens in the model prefix
    geometry: dict[str, int] | None = None  # the letterbox (`image_tools.LetterboxGeometry` fields); None: unknown
    details: dict[str, Any] = dataclasses.field(default_factory=dict)  # fields this reader does not know, as read

    @classmethod
    def from_json(cls, value: Any) -> CameraMeta:
        d = dict(value) if isinstance(value, Mapping) else {}
        geometry = d.get("geometry")
        return cls(
            obs_key=_str_or_none(d.get("obs_key")),
            valid=bool(d.get("valid", True)),
            grid=_pair(d.get("grid")),
            span=_pair(d.get("span")),
            geometry={str(k): int(v) for k, v in geometry.items()} if isinstance(geometry, Mapping) else None,
            details={k: v for k, v in d.items() if k not in _CAMERA_FIELDS},
        )

    def to_json(self) -> dict[str, Any]:
        return {
            "obs_key": self.obs_key,
            "valid": self.valid,
            "grid": _list(self.grid),
            "span": _list(self.span),
            "geometry": self.geometry,
            **self.details,
        }


_CAMERA_FIELDS = frozenset(f.name for f in dataclasses.fields(CameraMeta)) - {"details"}


RELIANCE_PROMPT = "prompt"  # a step's reliance on its prompt, beside its cameras' (`cam.reliance`)


@dataclasses.dataclass(frozen=True)
class Dependence:
    """How much a step depends on one of its inputs, measured without it (`meta.reliance.cameras.<camera>`, or
    `meta.reliance.prompt`)."""

    score_drop: float | None  # the explained score minus its value without the input; None: a target of many scores
    action_change: float  # root mean square over the chunk of the returned actions' change, in the robot's units

    @classmethod
    def from_json(cls, value: Any) -> Dependence:
        d = dict(value) if isinstance(value, Mapping) else {}
        return cls(_float_or_none(d.get("score_drop")), float(d.get("action_change", math.nan)))

    def to_json(self) -> dict[str, Any]:
        return {"score_drop": self.score_drop, "action_change": self.action_change}


@dataclasses.dataclass(frozen=True)
class Reliance:
    """A step's reliance (`meta.reliance`, `cam.reliance`): the explained score re-run, and how much the step depends
    on each camera the model saw and on its prompt; or why it was not measured."""

    score: float | None = None  # the explained score re-run (None: a target of many scores)
    cameras: dict[str, Dependence] = dataclasses.field(default_factory=dict)
    prompt: Dependence | None = None  # with the prompt emptied, its state tokens kept
    skipped: str | None = None  # why there are no figures ("failed_<Error>")
    error: str | None = None  # the first 200 characters of a failure's message

    @classmethod
    def from_json(cls, value: Any) -> Reliance:
        d = dict(value) if isinstance(value, Mapping) else {}
        cameras = d.get("cameras") if isinstance(d.get("cameras"), Mapping) else {}
        prompt = d.get(RELIANCE_PROMPT)
        return cls(
            score=_float_or_none(d.get("score")),
            cameras={str(c): Dependence.from_json(v) for c, v in cameras.items()},
            prompt=Dependence.from_json(prompt) if isinstance(prompt, Mapping) else None,
            skipped=_str_or_none(d.get("skipped")),
            error=_str_or_none(d.get("error")),
        )

    def to_json(self) -> dict[str, Any]:
        if self.skipped is not None:
            return {"skipped": self.skipped, **({} if self.error is None else {"error": self.error})}
        return {
            "score": self.score,
            "cameras": {c: v.to_json() for c, v in self.cameras.items()},
            RELIANCE_PROMPT: None if self.prompt is None else self.prompt.to_json(),
        }

    def figures(self) -> dict[str, float | None]:
        """Flat figures: `<camera>/reliance_score` (the score's drop) and `<camera>/reliance_actions` (the actions'
        change), then the same under `prompt/`; {} when it was skipped."""
        entries = {**self.cameras, **({} if self.prompt is None else {RELIANCE_PROMPT: self.prompt})}
        return {
            f"{name}/reliance_{what}": value
            for name, entry in entries.items()
            for what, value in (("score", entry.score_drop), ("actions", entry.action_change))
        }


@dataclasses.dataclass(frozen=True)
class StepMeta:
    """A step's metadata (the step file's `meta` JSON, docs/FORMAT.md), read once into typed fields.

    The fields the logger fills (`RESERVED_META`) are None in a record not yet written. `details` holds what the
    model family wrote (pi0-FAST's token ids and decode steps, pi0's action index, the map options and IG's
    completeness check; typed below as properties) and any field this reader does not know, exactly as read, so
    `to_json` gives back what was written. Older schema versions read with the defaults of what they lack."""

    schema_version: int | None = None
    run_id: str | None = None
    seq: int | None = None
    connection: str | None = None
    step: int | None = None  # the request's index within its connection
    timestamp: float | None = None  # unix time of the request
    target: str = ""  # what was explained
    score: float | tuple[float, ...] | None = None  # the explained score(s)
    map_kinds: tuple[str, ...] | None = None  # None: a schema 1 step, which does not list them (read its file)
    prompt: str = ""
    cameras: dict[str, CameraMeta] = dataclasses.field(default_factory=dict)  # in the model's camera order
    malformed: str | None = None  # why the served generation decoded to zero actions
    explain_ms: float | None = None
    extra: dict[str, Any] = dataclasses.field(default_factory=dict)  # `cam_extra/` values other than numeric arrays
    extra_arrays: tuple[str, ...] = ()  # the `cam_extra/` keys stored as `extra/<key>` arrays
    check: SpotCheck | None = None  # the spot check (`cam.spot_check`); None when it was off
    reliance: Reliance | None = None  # camera and prompt reliance (`cam.reliance`); None when not measured
    details: dict[str, Any] = dataclasses.field(default_factory=dict)

    @classmethod
    def from_json(cls, value: Mapping[str, Any]) -> StepMeta:
        """The metadata of a step JSON object (or of an index line, whose extra fields land in `details`)."""
        d = dict(value)
        cameras, extra, check, reliance = d.get("cameras"), d.get("extra"), d.get("check"), d.get("reliance")
        return cls(
            schema_version=_int_or_none(d.get("schema_version")),
            run_id=_str_or_none(d.get("run_id")),
            seq=_int_or_none(d.get("seq")),
            connection=_str_or_none(d.get("connection")),
            step=_int_or_none(d.get("step")),
            timestamp=_float_or_none(d.get("timestamp")),
            target="" if d.get("target") is None else str(d["target"]),
            score=_score(d.get("score")),
            map_kinds=_strs(d.get("map_kinds")),
            prompt="" if d.get("prompt") is None else str(d["prompt"]),
            cameras={str(c): CameraMeta.from_json(i) for c, i in cameras.items()} if isinstance(cameras, dict) else {},
            # schema 1 called it `malformed_reason`
            malformed=_str_or_none(d.get("malformed", d.get("malformed_reason"))),
            explain_ms=_float_or_none(d.get("explain_ms")),
            extra=dict(extra) if isinstance(extra, Mapping) else {},
            extra_arrays=_strs(d.get("extra_arrays")) or (),
            check=SpotCheck.from_json(check) if isinstance(check, Mapping) else None,
            reliance=Reliance.from_json(reliance) if isinstance(reliance, Mapping) else None,
            details={k: v for k, v in d.items() if k not in _STEP_FIELDS},
        )

    def to_json(self) -> dict[str, Any]:
        """The step JSON object: what the writer stores (the logger-filled fields only where set; `check` and
        `reliance` only when there is one)."""
        written = {name: getattr(self, name) for name in RESERVED_META if getattr(self, name) is not None}
        body = {
            "target": self.target,
            **self.details,
            "score": _list(self.score) if isinstance(self.score, tuple) else self.score,
            "map_kinds": _list(self.map_kinds),
            "prompt": self.prompt,
            "cameras": {c: info.to_json() for c, info in self.cameras.items()},
            "malformed": self.malformed,
            "explain_ms": self.explain_ms,
            "extra": self.extra,
            "extra_arrays": list(self.extra_arrays),
        }
        measured = {k: v.to_json() for k, v in (("check", self.check), ("reliance", self.reliance)) if v is not None}
        return written | body | measured

    def explained(self) -> dict[str, Any]:
        """What the model family wrote about its explanation, with the target: what `Explainer.rescore` reads."""
        return {"target": self.target, **self.details}

    def valid_cameras(self) -> list[str]:
        """The cameras whose image the model saw (mask true), in the model's order."""
        return [c for c, info in self.cameras.items() if info.valid]

    @property
    def token_ids(self) -> tuple[int, ...]:
        """pi0-FAST: the generated token(s) explained; () for other families."""
        return _ints(self.details.get("token_ids")) or ()

    @property
    def decode_steps(self) -> tuple[int, ...]:
        """pi0-FAST: the decode steps of those tokens; () for other families."""
        return _ints(self.details.get("decode_steps")) or ()

    @property
    def action_indices(self) -> tuple[int, ...] | None:
        """pi0-FAST: the action-token indices the target covers; None when it is not made of action tokens."""
        return _ints(self.details.get("action_indices"))

    @property
    def action_index(self) -> tuple[int, int] | None:
        """pi0 / pi0.5: (horizon step, action dimension) of an `action` target; None for `chunk`."""
        return _pair(self.details.get("action_index"))

    @property
    def map_options(self) -> dict[str, Any] | None:
        """The options the ig / occlusion maps ran with (`vocabulary.MapOptions` fields); None without those kinds."""
        value = self.details.get("map_options")
        return dict(value) if isinstance(value, Mapping) else None

    @property
    def ig_completeness(self) -> dict[str, Any] | None:
        """IG's completeness check (score, baseline_score, attribution_sum, relative_error, steps); None without ig."""
        value = self.details.get("ig_completeness")
        return dict(value) if isinstance(value, Mapping) else None


# The step JSON keys StepMeta reads into its own fields (schema 1's `malformed_reason` is read as `malformed`).
_STEP_FIELDS = frozenset(f.name for f in dataclasses.fields(StepMeta)) - {"details"} | {"malformed_reason"}


def _checked_maps(kind: str, maps: Any) -> dict[str, np.ndarray]:
    if kind not in MAP_KIND_INFO:
        raise ValueError(f"unknown map kind {kind!r}; the format knows {sorted(MAP_KIND_INFO)}")
    if not isinstance(maps, dict):
        raise TypeError(f"StepRecord.maps[{kind!r}] must be a dict, got {type(maps).__name__}")
    checked = {}
    for camera, cam_map in maps.items():
        arr = np.asarray(cam_map, dtype=np.float32)
        if arr.ndim not in (2, 3):
            raise ValueError(f"{kind} map {camera!r} must be (Hp, Wp) or (T, Hp, Wp), got shape {arr.shape}")
        checked[camera] = arr
    return checked


def _checked_images(images: Any, what: str) -> dict[str, np.ndarray]:
    if not isinstance(images, dict):
        raise TypeError(f"StepRecord.{what} must be a dict, got {type(images).__name__}")
    checked = {}
    for camera, image in images.items():
        arr = np.asarray(image)
        if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[-1] != 3:
            raise TypeError(f"StepRecord.{what}[{camera!r}] must be uint8 (H, W, 3), got {arr.dtype} {arr.shape}")
        checked[camera] = arr
    return checked


def record_arrays(record: StepRecord) -> dict[str, np.ndarray]:
    """Validates a record and returns its npz members except meta (wrong types raise: those are bugs)."""
    if not isinstance(record, StepRecord):
        raise TypeError(f"expected a StepRecord, got {type(record).__name__}")
    if not isinstance(record.meta, dict):
        raise TypeError("StepRecord.meta must be a dict")
    if clash := [k for k in RESERVED_META if k in record.meta]:
        raise ValueError(f"StepRecord.meta must not set {clash}: the logger fills them")
    arrays = {}
    for kind, maps in record.maps.items():
        arrays |= {MAP_KIND_INFO[kind].prefix + c: a for c, a in _checked_maps(kind, maps).items()}
    arrays |= {FRAME_PREFIX + c: a for c, a in _checked_images(record.frames, "frames").items()}
    arrays |= {MODEL_FRAME_PREFIX + c: a for c, a in _checked_images(record.model_frames, "model_frames").items()}
    arrays |= {INPUT_PREFIX + k: np.asarray(v) for k, v in record.inputs.items()}
    arrays |= {EXTRA_ARRAY_PREFIX + k: np.asarray(v) for k, v in record.extra_arrays.items()}
    arrays |= {CLIENT_PREFIX + k: np.asarray(v) for k, v in record.client_inputs.items()}
    arrays |= {MONITOR_PREFIX + k: np.asarray(v) for k, v in record.monitor.items()}
    return arrays


def summary_kind(maps: Mapping[str, Mapping[str, np.ndarray]]) -> str | None:
    """The kind `index.jsonl` summarises: Grad-CAM when logged (as in version 1), else the first kind."""
    return "gradcam" if maps.get("gradcam") else next((k for k, m in maps.items() if m), None)


def encode_step(arrays: Mapping[str, np.ndarray], meta: Mapping[str, Any], *, compress: bool) -> bytes:
    buf = io.BytesIO()
    (np.savez_compressed if compress else np.savez)(buf, **arrays, **{META_KEY: np.array(dumps(meta))})
    return buf.getvalue()


@dataclasses.dataclass
class StepArrays:
    maps: dict[str, dict[str, np.ndarray]]  # kind -> camera -> map (kinds a step lacks are absent)
    frames: dict[str, np.ndarray]
    model_frames: dict[str, np.ndarray]
    inputs: dict[str, np.ndarray]
    extra: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    client: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    monitor: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)


def _split_arrays(npz: Any) -> StepArrays:
    arrays = StepArrays({}, {}, {}, {}, {}, {}, {})
    prefixes = [(info.prefix, arrays.maps.setdefault(k, {})) for k, info in MAP_KIND_INFO.items()]
    prefixes += [
        (FRAME_PREFIX, arrays.frames),
        (MODEL_FRAME_PREFIX, arrays.model_frames),
        (INPUT_PREFIX, arrays.inputs),
        (EXTRA_ARRAY_PREFIX, arrays.extra),
        (CLIENT_PREFIX, arrays.client),
        (MONITOR_PREFIX, arrays.monitor),
    ]
    for key in npz.files:
        for prefix, target in prefixes:
            if key.startswith(prefix):
                target[key[len(prefix) :]] = npz[key]
    arrays.maps = {k: m for k, m in arrays.maps.items() if m}
    return arrays


def client_extra(meta: StepMeta, arrays: StepArrays | None) -> dict[str, Any]:
    """What the client sent under `cam_extra/`: the JSON values of `meta.extra` and, from `arrays`, the numeric
    arrays (None: the step lists none, so its file need not be read)."""
    return {**meta.extra, **({} if arrays is None else arrays.extra)}


def _read_meta(npz: Any) -> dict[str, Any]:
    meta = json.loads(str(npz[META_KEY][()]))
    if not isinstance(meta, dict):
        raise ValueError(f"the step's {META_KEY} is not a JSON object")
    return meta


class CAMStep:
    """One logged step: its metadata (`meta`, read once) and its arrays, read from the step file on first access
    unless loaded eagerly."""

    def __init__(self, seq: int, meta: StepMeta, file: pathlib.Path, arrays: StepArrays | None = None) -> None:
        self.seq = seq
        self.meta = meta
        self.file = file
        self._arrays = arrays

    def arrays(self) -> StepArrays:
        if self._arrays is None:
            # The scan read the meta only: a member damaged further in shows here.
            with reading(self.file, STEP_FILE_KIND, KeyError), np.load(self.file, allow_pickle=False) as npz:
                self._arrays = _split_arrays(npz)
        return self._arrays

    def lazy(self) -> CAMStep:
        """A copy that reads its arrays on use and drops them with itself, so that walking a long run does not keep
        every map and frame in memory."""
        return CAMStep(self.seq, self.meta, self.file)

    @property
    def map_kinds(self) -> tuple[str, ...]:
        return tuple(self.arrays().maps)

    def maps_of(self, kind: str) -> dict[str, np.ndarray]:
        """camera -> map of one kind; empty when the step has none of that kind."""
        return self.arrays().maps.get(kind, {})

    @property
    def frames(self) -> dict[str, np.ndarray]:
        return self.arrays().frames

    @property
    def model_frames(self) -> dict[str, np.ndarray]:
        return self.arrays().model_frames

    @property
    def inputs(self) -> dict[str, np.ndarray]:
        return self.arrays().inputs

    @property
    def monitor(self) -> dict[str, np.ndarray]:
        """The failure monitor's record of the step (`monitor/...`): its inputs, score and flag; empty without one."""
        return self.arrays().monitor

    @property
    def client_inputs(self) -> dict[str, np.ndarray]:
        """The client's numeric observation values besides its images and prompt (stored with raw frames)."""
        return self.arrays().client

    @property
    def extra(self) -> dict[str, Any]:
        """`client_extra` of this step; its file is read only when meta lists array extras."""
        return client_extra(self.meta, self.arrays() if self.meta.extra_arrays else None)

    def __repr__(self) -> str:
        return f"CAMStep(seq={self.seq}, file={str(self.file)!r})"


@dataclasses.dataclass
class CAMRun:
    run_dir: pathlib.Path
    run_info: dict[str, Any]
    manifest: dict[str, Any]
    steps: list[CAMStep]
    # Step files that could not be read (disk corruption, foreign files); reported rather than fatal.
    problems: list[str] = dataclasses.field(default_factory=list)

    @property
    def map_kinds(self) -> set[str]:
        """The kinds any of the run's steps carries, from their metadata (a schema 1 step's from its file)."""
        listed = (step.meta.map_kinds if step.meta.map_kinds is not None else step.map_kinds for step in self.steps)
        return {kind for kinds in listed for kind in kinds}


def read_json(path: pathlib.Path) -> dict[str, Any] | None:
    """A JSON object file, or None when it is missing, unreadable or not an object."""
    try:
        value = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return value if isinstance(value, dict) else None


def _read_index(run_dir: pathlib.Path) -> dict[int, dict[str, Any]]:
    """Parseable lines of index.jsonl by seq; a line cut short by a crash is skipped."""
    entries: dict[int, dict[str, Any]] = {}
    try:
        text = (run_dir / INDEX_JSONL).read_text(errors="replace")
    except OSError:
        return entries
    for line in text.splitlines():
        try:
            entry = json.loads(line)
        except ValueError:
            continue
        if isinstance(entry, dict) and isinstance(entry.get("seq"), int):
            entries[entry["seq"]] = entry
    return entries


def step_files(run_dir: pathlib.Path) -> dict[int, pathlib.Path]:
    steps_dir = run_dir / STEPS_DIR
    if not steps_dir.is_dir():
        return {}
    found = {}
    for path in steps_dir.iterdir():
        match = _STEP_FILE_RE.match(path.name)
        if match and path.is_file():
            found[int(match.group(1))] = path
    return dict(sorted(found.items()))


def scan_steps(
    run_dir: pathlib.Path, *, load_arrays: bool
) -> tuple[list[CAMStep], dict[int, dict[str, Any]], list[str]]:
    """Reads every step file; returns the steps, an index entry per step, and the files that failed to read."""
    index = _read_index(run_dir)
    steps, entries, problems = [], {}, []
    for seq, path in step_files(run_dir).items():
        try:
            with np.load(path, allow_pickle=False) as npz:
                meta = _read_meta(npz)
                arrays = _split_arrays(npz) if load_arrays or seq not in index else None
        except _UNREADABLE as e:
            problems.append(f"{path.relative_to(run_dir)}: {unreadable(STEP_FILE_KIND, e)}")
            continue
        steps.append(CAMStep(seq, StepMeta.from_json(meta), path, arrays if load_arrays else None))
        # arrays were read above whenever the index lacks this step
        entries[seq] = index[seq] if seq in index else index_entry(seq, meta, arrays.maps)
    return steps, entries, problems


def _manifest_is_current(manifest: dict[str, Any] | None, seqs: list[int]) -> bool:
    if manifest is None or not isinstance(manifest.get("steps"), list):
        return False
    return [e.get("seq") for e in manifest["steps"] if isinstance(e, dict)] == seqs


def _rebuilt_manifest(
    run_info: dict[str, Any], old: dict[str, Any] | None, entries: dict[int, dict[str, Any]]
) -> dict[str, Any]:
    counters = old.get("counters", {}) if old else {}
    closed = bool(old.get("closed")) if old else False
    return build_manifest(run_info, counters, entries.values(), closed=closed, rebuilt_at=utc_now_iso())


def read_run_info(run_dir: pathlib.Path) -> dict[str, Any]:
    if not (run_dir / RUN_JSON).is_file():
        raise FileNotFoundError(f"{run_dir} is not a CAM run directory (no {RUN_JSON})")
    run_info = load_json(run_dir / RUN_JSON)
    version = run_info.get("schema_version")
    if not isinstance(version, int) or version > SCHEMA_VERSION:
        log.warning("%s has schema_version %r; this reader knows up to %d", run_dir, version, SCHEMA_VERSION)
    return run_info


def load_run(run_dir: str | os.PathLike[str], *, load_arrays: bool = True, skip_unreadable: bool = False) -> CAMRun:
    """Reads a run directory, including one whose writer was killed; never writes to it.

    `manifest` is manifest.json when it lists exactly the step files present, otherwise one rebuilt in memory. A step
    file that cannot be read is a `BadFile` naming it, unless `skip_unreadable` (the run's `problems` then list
    them, as a resumed logger and `rebuild_manifest` do).
    """
    run_dir = pathlib.Path(run_dir)
    run_info = read_run_info(run_dir)
    steps, entries, problems = scan_steps(run_dir, load_arrays=load_arrays)
    if problems and not skip_unreadable:
        more = f" (and {len(problems) - 1} more unreadable step files)" if len(problems) > 1 else ""
        raise BadFile(f"{run_dir}{os.sep}{problems[0]}{more}")
    manifest = read_json(run_dir / MANIFEST_JSON)
    if not _manifest_is_current(manifest, [s.seq for s in steps]):
        manifest = _rebuilt_manifest(run_info, manifest, entries)
    return CAMRun(run_dir, run_info, manifest, steps, problems)


def rebuild_manifest(run_dir: str | os.PathLike[str]) -> dict[str, Any]:
    """Rewrites manifest.json from the step files (and index.jsonl summaries), keeping an old manifest's counters."""
    run_dir = pathlib.Path(run_dir)
    run_info = read_run_info(run_dir)
    _, entries, problems = scan_steps(run_dir, load_arrays=False)
    manifest = _rebuilt_manifest(run_info, read_json(run_dir / MANIFEST_JSON), entries)
    if problems:
        manifest["unreadable_files"] = problems
    write_json_atomic(run_dir / MANIFEST_JSON, manifest)
    return manifest
