"""The video encoder's child process (`lerobot.video.EncoderProcess`): an encode that never answers (SVT-AV1 can
deadlock on a frame, idle) or whose process dies is made again on a fresh child instead of holding the recording;
one that keeps hanging, or fails, ends in one line. The targets below stand in for the encoder: a real deadlock
cannot be brought about on demand."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest
from one_line import assert_one_line

from openpi_cam.lerobot.video import EncoderProcess, VideoEncodingError, encode_timeout_s

FRAMES = [np.zeros((4, 4, 3), np.uint8)]


def _stuck_first(frames: list, marker: str, out: str) -> None:
    """Never answers the first time it is called (anywhere), then writes `out` and says which process did."""
    if not os.path.exists(marker):
        Path(marker).write_text(str(os.getpid()))
        time.sleep(3600)
    Path(out).write_text(str(os.getpid()))


def _dies_first(frames: list, marker: str, out: str) -> None:
    if not os.path.exists(marker):
        Path(marker).write_text(str(os.getpid()))
        os._exit(3)
    Path(out).write_text(str(os.getpid()))


def _always_stuck(frames: list, marker: str, out: str) -> None:
    time.sleep(3600)


def _fails(frames: list, marker: str, out: str) -> None:
    raise ValueError("no encoder for these frames\nwith a second line")


@pytest.mark.parametrize("target", [_stuck_first, _dies_first])
def test_a_hung_or_dead_encoder_is_replaced_and_the_episode_encoded_again(target, tmp_path):
    encoder = EncoderProcess(target, lambda frames: 3.0)
    marker, out = tmp_path / "marker", tmp_path / "out"
    try:
        encoder(FRAMES, str(marker), str(out))
        first = out.read_text()
        assert marker.read_text() != first  # another process encoded it
        encoder(FRAMES, str(tmp_path / "marker"), str(out))  # the fresh child serves the next calls
        assert out.read_text() == first
    finally:
        encoder.close()


def test_an_encoder_that_keeps_hanging_or_fails_ends_in_one_line(tmp_path):
    stuck = EncoderProcess(_always_stuck, lambda frames: 1.0, attempts=2)
    started = time.monotonic()
    with pytest.raises(VideoEncodingError) as e:
        stuck(FRAMES, str(tmp_path / "marker"), str(tmp_path / "out"))
    assert time.monotonic() - started < 60  # two waits of a second each, not the target's hour
    assert_one_line(e.value, "no answer within 1 s", "2 times")
    stuck.close()
    failing = EncoderProcess(_fails, lambda frames: 30.0)
    try:
        with pytest.raises(VideoEncodingError) as e:
            failing(FRAMES, str(tmp_path / "marker"), str(tmp_path / "out"))
        assert_one_line(e.value, "ValueError: no encoder for these frames")
    finally:
        failing.close()


def test_the_encode_timeout_grows_with_the_pixels():
    small = encode_timeout_s([np.zeros((96, 96, 3), np.uint8)] * 100)
    large = encode_timeout_s([np.zeros((480, 640, 3), np.uint8)] * 1000)
    assert 60 <= small < 65 and 600 < large < 700
