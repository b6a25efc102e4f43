"""Video cameras of a LeRobot v3.0 dataset as LeRobot 0.6.1 writes them (its `video_utils`), with PyAV: each
episode encoded on its own (AV1 through libsvtav1, yuv420p, keyframe every 2 frames: LeRobot's defaults) and starting
on a keyframe, appended to a camera's current file by stream copy, and described in info.json as LeRobot describes
it."""

from __future__ import annotations

import atexit
import multiprocessing
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import av
import numpy as np

from openpi_cam.lerobot.dataset import dataset_error


@dataclass(frozen=True)
class VideoOptions:
    """How video cameras are encoded; recorded in info.json as LeRobot records its encoder settings. The defaults
    are LeRobot 0.6.1's. `preset` None: 12 for libsvtav1, the encoder's own default otherwise."""

    codec: str = "libsvtav1"
    pix_fmt: str = "yuv420p"
    gop: int = 2
    crf: int | None = 30
    preset: int | str | None = None
    fast_decode: int = 0

    @property
    def resolved_preset(self) -> int | str | None:
        return 12 if self.preset is None and self.codec == "libsvtav1" else self.preset

    def codec_options(self) -> dict[str, str]:
        options = {"g": str(self.gop)}
        if self.crf is not None:
            options["crf"] = str(self.crf)
        if self.resolved_preset is not None:
            options["preset"] = str(self.resolved_preset)
        if self.codec == "libsvtav1":
            options["svtav1-params"] = f"fast-decode={max(0, min(2, self.fast_decode))}"
        elif self.fast_decode and self.codec in ("libx264", "h264", "libx265", "hevc"):
            options["tune"] = "fastdecode"
        return options

    def recorded(self) -> dict[str, Any]:
        return {
            "video.g": self.gop,
            "video.crf": self.crf,
            "video.preset": self.resolved_preset,
            "video.fast_decode": self.fast_decode,
            "video.video_backend": "pyav",
            "video.extra_options": {},
        }


class VideoEncodingError(RuntimeError):
    """An episode's video could not be encoded: the encoder failed, or gave no answer in time (`EncoderProcess`)."""


class EncoderProcess:
    """Runs an encode function in a child process of its own, one call at a time, and waits at most `timeout_s(frames)`
    seconds for each call. SVT-AV1 can deadlock on a frame and wait forever with the CPU idle; in process that would
    hold a recording (and the server or demo recording it) for good. Here the child is killed instead and the call
    made again on a fresh one, up to `attempts` times; then VideoEncodingError. Thread-safe; the child starts on the
    first call and dies with its parent."""

    def __init__(
        self,
        target: Callable[..., None],
        timeout_s: Callable[[list[np.ndarray]], float],
        attempts: int = 2,
    ) -> None:
        self._target, self._timeout_s, self._attempts = target, timeout_s, attempts
        self._lock = threading.Lock()
        self._child: tuple[multiprocessing.process.BaseProcess, Connection] | None = None

    def __call__(self, frames: list[np.ndarray], *args: Any) -> None:
        timeout = self._timeout_s(frames)
        with self._lock:
            for _ in range(self._attempts):
                _, conn = self._child or self._start()
                try:
                    conn.send((frames, *args))
                    answer = conn.recv() if conn.poll(timeout) else None
                except (EOFError, OSError):  # the child died
                    answer = None
                if answer is None:  # hung or dead: the next attempt gets a fresh child
                    self.close()
                    continue
                ok, message = answer
                if not ok:
                    raise VideoEncodingError(message)
                return
        raise VideoEncodingError(f"the encoder gave no answer within {timeout:.0f} s (or died), {self._attempts} times")

    def _start(self) -> tuple[multiprocessing.process.BaseProcess, Connection]:
        spawn = multiprocessing.get_context("spawn")
        parent, child = spawn.Pipe()
        process = spawn.Process(target=_serve_encodes, args=(child, self._target), daemon=True)
        process.start()
        child.close()
        self._child = (process, parent)
        return self._child

    def close(self) -> None:
        if self._child is not None:
            process, conn = self._child
            self._child = None
            process.kill()
            process.join()
            conn.close()


def _serve_encodes(conn: Connection, target: Callable[..., None]) -> None:
    """The child's loop: each call's arguments in, (True, None) or (False, the error in one line) out."""
    while True:
        try:
            args = conn.recv()
        except EOFError:
            return
        try:
            target(*args)
            conn.send((True, None))
        except Exception as e:
            conn.send((False, f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"))


def encode_timeout_s(frames: list[np.ndarray]) -> float:
    """How long an episode's encode may take before its encoder counts as hung: a minute, and 2 microseconds a
    pixel (about ten minutes for a thousand 640 x 480 frames), generous for a loaded machine."""
    return 60.0 + 2e-6 * sum(int(np.prod(np.shape(f)[:2])) for f in frames)


def encode_video(frames: list[np.ndarray], path: Path, fps: int, options: VideoOptions) -> None:
    """Encode one episode's frames [H, W, 3] uint8 into `path` (`EncoderProcess`: a hung encoder is replaced);
    VideoEncodingError in one line when it cannot."""
    _ENCODER(frames, str(path), fps, options)


def _encode(frames: list[np.ndarray], path: str, fps: int, options: VideoOptions) -> None:
    height, width = frames[0].shape[:2]
    # SVT-AV1 prints a banner of some twenty lines to stderr for every encoder it opens unless SVT_LOG lowers its
    # level; errors still show, and a level the user set wins
    os.environ.setdefault("SVT_LOG", "1")
    with av.open(path, "w", format="mp4") as container:
        stream = container.add_stream(options.codec, rate=fps, options=options.codec_options())
        stream.pix_fmt = options.pix_fmt
        stream.width, stream.height = width, height
        for frame in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")))
        container.mux(stream.encode())


_ENCODER = EncoderProcess(_encode, encode_timeout_s)
atexit.register(_ENCODER.close)


def duration_s(path: Path) -> float:
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        if stream.duration is not None:
            return float(stream.duration * stream.time_base)
        return float(container.duration / av.time_base)


def append_video(head: Path, tail: Path, offset_s: float, out: Path) -> None:
    """`head`'s packets before `offset_s`, then `tail`'s moved there, stream-copied into `out` (no re-encoding).
    Packets of `head` past `offset_s` belong to an episode whose save failed after its video moved."""
    with av.open(str(head)) as first, av.open(str(tail)) as second:
        a, b = first.streams.video[0], second.streams.video[0]
        if a.time_base != b.time_base or a.codec_context.name != b.codec_context.name:
            raise dataset_error(f"cannot append a {b.codec_context.name} video in time base {b.time_base}", file=head)
        offset = round(offset_s / a.time_base)
        with av.open(str(out), "w", format="mp4", options={"movflags": "faststart"}) as container:
            stream = container.add_stream_from_template(a, opaque=True)
            stream.time_base = a.time_base
            for source, shift in ((first.demux(a), 0), (second.demux(b), offset)):
                for packet in source:
                    if packet.dts is None or (shift == 0 and packet.pts >= offset):  # None: the demuxer's flush
                        continue
                    packet.pts += shift
                    packet.dts += shift
                    packet.stream = stream
                    container.mux(packet)


def video_info(path: Path, options: VideoOptions) -> dict[str, Any]:
    """info.json's `info` of a video camera: what the encoded stream says, then the encoder settings."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        info = {
            "video.height": stream.height,
            "video.width": stream.width,
            "video.codec": stream.codec.canonical_name,
            "video.pix_fmt": stream.pix_fmt,
            "video.fps": int(stream.base_rate),
            "video.channels": len(av.VideoFormat(stream.pix_fmt).components),
            "has_audio": bool(container.streams.audio),
        }
    return info | options.recorded() | {"is_depth_map": False}
