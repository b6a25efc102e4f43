"""Normalisation statistics in upstream OpenPI's ``norm_stats.json`` format.

The file holds ``{"norm_stats": {key: {"mean": [...], "std": [...], "q01": [...] | null, "q99": [...] | null}}}``
and lives at ``<checkpoint>/assets/<asset_id>/norm_stats.json``.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from openpi_cam.errors import reading

NORM_STATS_FILENAME = "norm_stats.json"


@dataclasses.dataclass(frozen=True)
class NormStats:
    mean: np.ndarray
    std: np.ndarray
    q01: np.ndarray | None = None  # 1st percentile
    q99: np.ndarray | None = None  # 99th percentile

    @property
    def has_quantiles(self) -> bool:
        return self.q01 is not None and self.q99 is not None

    def to_json_dict(self) -> dict[str, list[float] | None]:
        return {f.name: _to_list(getattr(self, f.name)) for f in dataclasses.fields(self)}

    @classmethod
    def from_json_dict(cls, d: Mapping, *, where: str = "norm stats") -> NormStats:
        if not isinstance(d, Mapping):
            raise ValueError(f"{where}: expected an object of statistics, got {type(d).__name__}")
        missing = [name for name in ("mean", "std") if d.get(name) is None]
        if missing:
            raise ValueError(f"{where}: missing {', '.join(missing)}")
        # float64 like upstream (pydantic/numpydantic parse JSON numbers into float64 arrays).
        try:
            arrays = {
                f.name: None if d.get(f.name) is None else np.asarray(d[f.name], dtype=np.float64)
                for f in dataclasses.fields(cls)
            }
        except (TypeError, ValueError) as e:
            raise ValueError(f"{where}: {e}") from None
        return cls(**arrays)


def _to_list(x: np.ndarray | None) -> list[float] | None:
    return None if x is None else np.asarray(x, dtype=np.float64).tolist()


def norm_stats_path(checkpoint_dir: str | Path, asset_id: str) -> Path:
    """Where a checkpoint keeps the stats for one asset id."""
    return Path(checkpoint_dir) / "assets" / asset_id / NORM_STATS_FILENAME


def serialize_norm_stats(stats: Mapping[str, NormStats]) -> str:
    return json.dumps({"norm_stats": {k: v.to_json_dict() for k, v in stats.items()}}, indent=2)


def deserialize_norm_stats(text: str, *, where: str = "norm stats") -> dict[str, NormStats]:
    with reading(where, "JSON file"):
        data = json.loads(text)
    if not isinstance(data, dict) or not isinstance(data.get("norm_stats"), dict):
        raise ValueError(f'{where}: expected a JSON object with a "norm_stats" mapping')
    return {k: NormStats.from_json_dict(v, where=f"{where} [{k}]") for k, v in data["norm_stats"].items()}


def load_norm_stats(path: str | Path) -> dict[str, NormStats]:
    """Load stats from a ``norm_stats.json`` file or from a directory holding one."""
    path = Path(path)
    if path.is_dir() or path.name != NORM_STATS_FILENAME:
        path = path / NORM_STATS_FILENAME
    if not path.is_file():
        raise FileNotFoundError(f"norm stats file not found: expected {path}")
    with reading(path, "JSON file"):
        text = path.read_text()
    return deserialize_norm_stats(text, where=str(path))


def load_checkpoint_norm_stats(checkpoint_dir: str | Path, asset_id: str) -> dict[str, NormStats]:
    return load_norm_stats(norm_stats_path(checkpoint_dir, asset_id))


def save_norm_stats(directory: str | Path, stats: Mapping[str, NormStats]) -> Path:
    """Write ``<directory>/norm_stats.json`` (creating the directory) and return its path."""
    path = Path(directory) / NORM_STATS_FILENAME
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(serialize_norm_stats(stats))
    return path


def compute_norm_stats(values: np.ndarray) -> NormStats:
    """Exact statistics over the leading axes of ``[..., D]`` values (for small datasets such as the demo's).

    Upstream estimates quantiles from streaming histograms; exact quantiles are what those estimates approximate.
    """
    flat = np.asarray(values, dtype=np.float64).reshape(-1, np.shape(values)[-1])
    if flat.shape[0] < 2:
        raise ValueError("need at least 2 vectors to compute norm stats")
    return NormStats(
        mean=flat.mean(axis=0),
        std=flat.std(axis=0),
        q01=np.quantile(flat, 0.01, axis=0),
        q99=np.quantile(flat, 0.99, axis=0),
    )
