"""Rollout videos: what an episode looked like, from the suite's own camera, as MP4.

Off by default; `--video N` records the first N episodes of every task for every
configuration, `--video failures` every episode that does not succeed. A frame is taken
after the env's reset and after each step, from the env's `video_frame()` (an adapter
renders its suite's camera: Meta-World's `corner` view, LIBERO's `agentview`, ManiSkill3's
render camera) and streamed to an ffmpeg encoder (imageio-ffmpeg, the `video` extra), so
an episode of 500 steps never sits in memory. Under an inference latency a step the robot
held still (harness/episode/plan.py) gets a red border.

Recording changes nothing an episode measures: frames are taken outside every timed
span (no episode is charged for them, as no episode is charged for building an env),
and rendering reads the simulator's state without stepping it or drawing from any
random stream (tests/test_video.py compares rows with and without video).
"""

from __future__ import annotations

import os
import re
import tempfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

FPS = 20
HOLD_RGB = (220, 30, 30)  # the border of a frame the robot held still in
BORDER = 4  # pixels
VIDEOS = "videos"  # the run folder's subfolder


class VideoUnavailable(RuntimeError):
    """The suite renders no frames, or the encoder is not installed (one line, exit 2)."""


@dataclass(frozen=True)
class VideoPlan:
    """Which episodes a run records: the first `episodes` of each task (per configuration),
    and with `failures` every episode that does not succeed. Plain data (crosses processes)."""

    episodes: int = 0
    failures: bool = False

    def records(self, index: int) -> bool:
        """Whether episode `index` of a task is recorded while it runs."""
        return self.failures or index < self.episodes

    def keeps(self, index: int, success: bool) -> bool:
        """Whether a recorded episode's video is kept once it has ended."""
        return index < self.episodes or (self.failures and not success)

    def spec(self) -> str:
        return "failures" if self.failures else str(self.episodes)


def parse_video(text: str) -> VideoPlan:
    """`--video N` or `--video failures`; ValueError naming the choices otherwise."""
    value = text.strip().lower()
    if value == "failures":
        return VideoPlan(failures=True)
    if value.isdigit() and int(value) > 0:
        return VideoPlan(episodes=int(value))
    raise ValueError(
        f"--video {text!r}: give N (record the first N episodes of every task, N >= 1) or failures "
        "(every episode that does not succeed)"
    )


def require_encoder() -> None:
    """The encoder, or VideoUnavailable naming the extra that installs it."""
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        raise VideoUnavailable(
            '--video needs an MP4 encoder: pip install -c constraints.txt ".[video]" (imageio-ffmpeg)'
        ) from None


def check_frames(envs: Iterable[Any]) -> None:
    """VideoUnavailable unless every env (a suite's, as built) can give video frames."""
    for env in envs:
        try:
            env.get_wrapper_attr("video_frame")
        except AttributeError:
            raise VideoUnavailable(NO_FRAMES) from None


NO_FRAMES = (
    "this suite's env renders no video frames (its adapter has no video_frame()); --video works "
    "on Meta-World, LIBERO, the chain suites and the ManiSkill3 suites"
)


def frame_of(env: Any) -> np.ndarray:
    """The env's current frame (H x W x 3 uint8) from its adapter's `video_frame()`."""
    try:
        render = env.get_wrapper_attr("video_frame")
    except AttributeError:
        raise VideoUnavailable(NO_FRAMES) from None
    return np.ascontiguousarray(render(), dtype=np.uint8)


def mark_hold(frame: np.ndarray) -> np.ndarray:
    """`frame` with a red border: the robot held still at this step."""
    marked = frame.copy()
    marked[:BORDER], marked[-BORDER:] = HOLD_RGB, HOLD_RGB
    marked[:, :BORDER], marked[:, -BORDER:] = HOLD_RGB, HOLD_RGB
    return marked


class Recording:
    """One episode's frames streamed into an MP4 file of its own (a temporary file the
    writer of the run moves into place, or drops)."""

    def __init__(self, first: np.ndarray):
        import imageio_ffmpeg

        fd, name = tempfile.mkstemp(prefix="dvla-video-", suffix=".mp4")
        os.close(fd)
        self.path = Path(name)
        height, width = first.shape[:2]
        self.size = (width, height)
        self.writer = imageio_ffmpeg.write_frames(
            str(self.path),
            self.size,
            fps=FPS,
            codec="libx264",
            quality=6,
            macro_block_size=1,
            ffmpeg_log_level="error",
            output_params=["-pix_fmt", "yuv420p"] if width % 2 == 0 and height % 2 == 0 else None,
        )
        self.writer.send(None)  # start ffmpeg
        self.frames = 0
        self.add(first)

    def add(self, frame: np.ndarray, held: bool = False) -> None:
        self.writer.send(np.ascontiguousarray(mark_hold(frame) if held else frame))
        self.frames += 1

    def finish(self, keep: bool) -> bytes | None:
        """The MP4's bytes (None when not kept); the temporary file is removed either way."""
        try:
            self.writer.close()
            return self.path.read_bytes() if keep else None
        finally:
            self.path.unlink(missing_ok=True)

    def abandon(self) -> None:
        try:
            self.writer.close()
        except Exception:  # an interrupted ffmpeg: the file goes either way
            pass
        self.path.unlink(missing_ok=True)


def video_path(config_id: str, task: str, index: int) -> str:
    """Where an episode's video goes, relative to the run folder: by configuration, task
    and episode, as the row names them (`videos/b1eb93d9ac7f/reach-v3/episode-003.mp4`)."""
    safe = re.sub(r"[^A-Za-z0-9_.=+-]", "_", task)
    return f"{VIDEOS}/{config_id}/{safe}/episode-{index:03d}.mp4"
