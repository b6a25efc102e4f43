"""Labelled rollouts for the failure monitor, read from maps datasets: each episode's explained frames in order, its
`monitor/...` columns as a monitor's named inputs and its outcome (`episode_success`), as `monitor.fit.Episode`s.
Reads with pyarrow and NumPy only."""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Sequence

import numpy as np

from openpi_cam.maps import dataset as fmt
from openpi_cam.monitor.fit import Episode
from openpi_cam.monitor.signals import SAMPLE_SPREAD


@dataclasses.dataclass(frozen=True)
class Rollouts:
    """Episodes of one or more maps datasets, ready to fit on: `episodes` in dataset then episode order, `names`
    the (dataset, episode) of each, the execution horizon their `stac` assumed, and the samples per call their
    `sample_spread` compared (None: they carry none)."""

    episodes: list[Episode]
    names: list[tuple[str, int]]
    execution_horizon: int
    sample_spread: int | None = None

    @property
    def inputs(self) -> list[str]:
        """The inputs every episode carries with some finite value (a flow family has no token entropy)."""
        if not self.episodes:
            return []
        names = set.intersection(*(set(e.columns) for e in self.episodes))
        return sorted(n for n in names if any(np.isfinite(e.columns[n]).any() for e in self.episodes))


def _scalar(values: list[float | None]) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], np.float64)


def _vectors(values: list[list[float] | None], where: str) -> np.ndarray:
    widths = {len(v) for v in values if v is not None}
    if len(widths) != 1:
        raise ValueError(f"{where}: feature vectors of widths {sorted(widths) or 'none'}, expected one width")
    (width,) = widths
    return np.array([np.full(width, np.nan) if v is None else v for v in values], np.float64)


def read_rollouts(roots: Sequence[pathlib.Path]) -> Rollouts:
    """Every episode of the maps datasets at `roots` as a labelled `Episode` whose columns are the monitor inputs
    the datasets carry (`stac`, `token_entropy`, and the `features/...` written with `--monitor-features`). Bad
    input raises ValueError in one line naming the dataset and what it lacks."""
    if not roots:
        raise ValueError("no maps datasets named")
    episodes, names, horizons, samples = [], [], set(), set()
    for root in roots:
        try:
            ds = fmt.open_maps_dataset(root)
        except FileNotFoundError as e:
            raise ValueError(str(e)) from None
        info = ds.info
        if not info.monitored:
            raise ValueError(f"{root}: its rows have no monitor columns (made before them): explain the dataset again")
        if info.outcome is None:
            raise ValueError(f"{root}: its rows carry no episode outcomes (its source records no next.success)")
        horizons.add(info.execution_horizon)
        samples.add(info.sample_spread or None)
        features = [fmt.MONITOR_PREFIX + name for name in info.monitor_features]
        scalars = [fmt.MONITOR_PREFIX + name for name in info.monitor_scalars]
        for episode in ds.episodes:
            table = ds.table(episode, ["index", fmt.FRAME_INDEX, "task", fmt.EPISODE_SUCCESS, *scalars, *features])
            if table.num_rows == 0:
                continue
            columns = {n: _scalar(table.column(fmt.MONITOR_PREFIX + n).to_pylist()) for n in info.monitor_scalars}
            for column in features:
                where = f"{root}, episode {episode}, {column}"
                columns[column[len(fmt.MONITOR_PREFIX) :]] = _vectors(table.column(column).to_pylist(), where)
            success = table.column(fmt.EPISODE_SUCCESS).to_pylist()
            frames = np.asarray(table.column(fmt.FRAME_INDEX).to_pylist(), np.int64)
            prompts = tuple(table.column("task").to_pylist())
            episodes.append(Episode(columns, bool(success[0]), frames, prompts))
            names.append((str(root), episode))
    if len(horizons) > 1:
        raise ValueError(f"the maps datasets assumed different execution horizons {sorted(horizons)}: fit on one")
    if len(samples) > 1:
        drawn = sorted(map(str, samples))
        raise ValueError(f"the maps datasets drew different samples per call for {SAMPLE_SPREAD!r}: {drawn}")
    if not episodes:
        raise ValueError(f"the maps datasets {[str(r) for r in roots]} hold no explained frames")
    return Rollouts(episodes, names, horizons.pop(), samples.pop())
