"""MP4 writing with PyAV (a core dependency, so every install renders videos)."""

from __future__ import annotations

import fractions
import pathlib
from typing import Any

import av
import numpy as np


class Mp4Writer:
    """Streams RGB uint8 frames [H, W, 3] of one size into an H.264 MP4 (yuv420p). Frames with an odd side are padded
    by one black row / column, which yuv420p needs."""

    def __init__(self, path: pathlib.Path, fps: float | fractions.Fraction, crf: int = 18) -> None:
        self.path, self.crf = pathlib.Path(path), crf
        self.fps = fps if isinstance(fps, fractions.Fraction) else fractions.Fraction(fps).limit_denominator(1000)
        self.container: Any = None
        self.stream: Any = None
        self.count = 0

    def add(self, image: np.ndarray) -> None:
        image = np.asarray(image, np.uint8)
        h, w = image.shape[:2]
        if h % 2 or w % 2:
            image = np.pad(image, ((0, h % 2), (0, w % 2), (0, 0)))
        if self.container is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.container = av.open(str(self.path), "w")
            self.stream = self.container.add_stream("libx264", rate=self.fps)
            self.stream.height, self.stream.width = image.shape[:2]
            self.stream.pix_fmt = "yuv420p"
            self.stream.options = {"crf": str(self.crf)}
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
        self.container.mux(self.stream.encode(frame))
        self.count += 1

    def close(self) -> None:
        if self.container is not None:
            self.container.mux(self.stream.encode())
            self.container.close()
            self.container = None
