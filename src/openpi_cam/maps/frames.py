"""A maps dataset's rows beside the frames they explain: what the overlay videos (`maps.render`) and the Rerun
recording (`maps.rerun`) both draw from.

The frames are decoded again from the LeRobot dataset the maps were computed from (`MapsInfo.source`, read with
`lerobot.dataset`), only those the maps dataset lists, and each row's `index` and `frame_index` are checked against
the source's, so a map is never drawn over another frame.
"""

from __future__ import annotations

import dataclasses
import fractions
import pathlib
from collections.abc import Iterator, Mapping, Sequence
from typing import Any

import numpy as np

from openpi_cam.lerobot.dataset import LeRobotDataset, open_dataset
from openpi_cam.maps.dataset import MapsDataset
from openpi_cam.maps.views import displayable


def select_episodes(ds: MapsDataset, episodes: Sequence[int] | None) -> list[int]:
    """`episodes` (default: every written one), each checked to have a shard."""
    written = ds.episodes
    chosen = list(written if episodes is None else episodes)
    missing = [e for e in chosen if e not in written]
    if missing:
        raise ValueError(f"{ds.root}: no shard for episode(s) {', '.join(map(str, missing))}")
    return chosen


def source_dataset(ds: MapsDataset, source: pathlib.Path | None = None) -> LeRobotDataset:
    """The LeRobot dataset the maps were computed from (`source` overrides the path info.json names)."""
    path = pathlib.Path(source if source is not None else ds.info.source)
    if not path.is_dir():
        raise FileNotFoundError(f"{ds.root / 'meta/info.json'}: its source LeRobot dataset {str(path)!r} is not there")
    return open_dataset(path)


def video_fps(ds: MapsDataset, lr: LeRobotDataset) -> fractions.Fraction:
    """One video frame per explained frame: the source's rate divided by the explain job's `every`."""
    every = max(1, ds.info.every)
    return fractions.Fraction(ds.info.source_fps or lr.fps).limit_denominator(1001) / every


@dataclasses.dataclass(frozen=True)
class EpisodeRows:
    """One episode's rows of a maps dataset, in `index` order, with one kind's displayable maps."""

    episode: int
    index: list[int]
    frame_index: list[int]
    timestamp: list[float]
    task: list[str]
    score: list[Any]
    valid: list[dict[str, bool]]  # per row: model camera -> whether the model saw it
    maps: dict[str, np.ndarray]  # camera -> [N, Hp, Wp] (`viz.overlay.reduce_tokens` of each row's map)

    def __len__(self) -> int:
        return len(self.index)

    def frame_maps(self, i: int) -> dict[str, np.ndarray]:
        return {c: m[i] for c, m in self.maps.items()}


def episode_rows(ds: MapsDataset, episode: int, kind: str) -> EpisodeRows:
    frames = ds.episode_frames(episode, kind)
    validity = {c: frames.valid(c) for c in ds.cameras}
    return EpisodeRows(
        episode=episode,
        index=[int(m["index"]) for m in frames.meta],
        frame_index=[int(m["frame_index"]) for m in frames.meta],
        timestamp=[float(m["timestamp"]) for m in frames.meta],
        task=[str(m["task"]) for m in frames.meta],
        score=[m["score"] for m in frames.meta],
        valid=[{c: bool(v[i]) for c, v in validity.items()} for i in range(len(frames))],
        maps={c: displayable(m) for c, m in frames.maps.items()},
    )


def aligned_frames(ds: MapsDataset, lr: LeRobotDataset, rows: EpisodeRows) -> Iterator[dict[str, np.ndarray]]:
    """Per row of the episode, in order: model camera -> the source's frame, uint8 [H, W, 3]. A model camera with no
    dataset feature is left out. Raises when the source does not hold exactly the rows' frames."""
    sources = {c: f for c, f in ds.info.camera_sources.items() if f in lr.features}
    wanted = set(rows.frame_index)
    frames = lr.frames(rows.episode, features=list(dict.fromkeys(sources.values())), frame_indices=wanted)
    count = 0
    for i, frame in enumerate(frames):
        count = i + 1
        got = (int(frame["index"]), int(frame["frame_index"]))
        want = (rows.index[i], rows.frame_index[i]) if i < len(rows) else None
        if got != want:
            raise ValueError(
                f"{lr.root}: episode {rows.episode}: the source gives index {got[0]}, frame {got[1]} where the maps "
                f"dataset has {'no more rows' if want is None else f'index {want[0]}, frame {want[1]}'}; it is not "
                "the dataset the maps were computed from"
            )
        yield {c: np.asarray(frame[f], np.uint8) for c, f in sources.items()}
    if count != len(rows):
        raise ValueError(
            f"{lr.root}: episode {rows.episode}: the source holds {count} of the maps dataset's {len(rows)} frames"
        )


def frame_scale(maps: Mapping[str, np.ndarray], valid: Mapping[str, bool]) -> float:
    """The per-frame normaliser: the largest value of the frame's valid cameras' maps."""
    return max((float(m.max()) for c, m in maps.items() if valid.get(c, True) and m.size), default=0.0)


def dataset_scale(ds: MapsDataset, kind: str, episodes: list[int]) -> float:
    """The normaliser over `episodes`: the largest value of any valid camera's map."""
    best = 0.0
    for e in episodes:
        rows = episode_rows(ds, e, kind)
        for i in range(len(rows)):
            best = max(best, frame_scale(rows.frame_maps(i), rows.valid[i]))
    return best
