"""Camera images as LeRobotDataset v3 videos (`export lerobot --video`), encoded with ffmpeg.

LeRobot's own datasets keep cameras as video: an AV1 stream per camera, the episodes of
a file one after another on one timeline, each episode's place in it recorded in
meta/episodes as `videos/<key>/{chunk_index,file_index,from_timestamp,to_timestamp}`.
Its reader decodes the frame of timestamp `from_timestamp + frame_index / fps` and
refuses a frame more than 1e-4 s away, so the stream's frame k must sit at exactly k /
fps. A video is ~11x smaller than the PNGs of image mode on LIBERO's 128 px cameras, and
lossy (docs/lerobot.md has the figures).

The encoder settings are LeRobot 0.6.1's defaults (configs/video.py, RGBEncoderConfig):
libsvtav1, yuv420p, keyframe every 2 frames (so a random frame decodes from at most one
frame before it), CRF 30, preset 12, fast-decode 0. They are recorded in the feature's
`info` under LeRobot's names, so its tools (aggregation, appending episodes) re-encode
the same way. The encoder is the ffmpeg that imageio-ffmpeg ships (the `video` extra);
LeRobot itself is not imported.
"""

from __future__ import annotations

import io
import os
import subprocess
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from harness.errors import UsageError

VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
VIDEO_FILE_MB = 200  # LeRobot's default: a video file is closed past this size
CHUNKS_SIZE = 1000  # LeRobot's default: files per chunk folder
CODEC, PIX_FMT, GOP, CRF, PRESET, FAST_DECODE = "libsvtav1", "yuv420p", 2, 30, 12, 0
SVT_PARAMS = ("-svtav1-params", f"fast-decode={FAST_DECODE}")
NO_ENCODER = (
    'export --video needs an MP4 encoder: pip install -c constraints.txt ".[video]" '
    "(imageio-ffmpeg, which ships an ffmpeg with libsvtav1)"
)


def require_encoder() -> None:
    """A usage error unless imageio-ffmpeg's ffmpeg runs and has LeRobot's codec (AV1
    through libsvtav1), naming the extra that installs one."""
    try:
        import imageio_ffmpeg
    except ImportError:
        raise UsageError(NO_ENCODER) from None
    try:
        exe = imageio_ffmpeg.get_ffmpeg_exe()
        listed = subprocess.run(
            [exe, "-hide_banner", "-encoders"], capture_output=True, text=True, check=True
        )
    except (RuntimeError, OSError, subprocess.CalledProcessError) as exc:
        raise UsageError(f"{NO_ENCODER}; the ffmpeg found does not run: {exc}") from None
    if f" {CODEC} " not in listed.stdout:
        raise UsageError(
            f"{exe} has no {CODEC} encoder (LeRobot's AV1 codec); use imageio-ffmpeg's own binary "
            "(unset IMAGEIO_FFMPEG_EXE) or an ffmpeg built with --enable-libsvtav1"
        )


def video_features(features: dict[str, dict[str, Any]], fps: int) -> dict[str, dict[str, Any]]:
    """`features` with every image feature made a video one, with the `info` LeRobot's
    writer records for it (datasets/video_utils.py get_video_info: the stream's
    properties, then the encoder's settings)."""
    out = {}
    for name, feature in features.items():
        if feature["dtype"] != "image":
            out[name] = feature
            continue
        height, width, channels = feature["shape"]
        if channels != 3 or height % 2 or width % 2:
            raise UsageError(
                f"{name} is {height}x{width}x{channels}: video mode ({PIX_FMT}) needs RGB images "
                "of even height and width; export it without --video (image mode keeps any image)"
            )
        info = {
            "video.height": height,
            "video.width": width,
            "video.codec": "av1",
            "video.pix_fmt": PIX_FMT,
            "video.fps": fps,
            "video.channels": 3,
            "has_audio": False,
            "video.g": GOP,
            "video.crf": CRF,
            "video.preset": PRESET,
            "video.fast_decode": FAST_DECODE,
            "video.video_backend": "pyav",  # the backend LeRobot's tools re-encode with
            "video.extra_options": {},
            "is_depth_map": False,
        }
        out[name] = {**feature, "dtype": "video", "info": info}
    return out


def file_full(path: Path) -> bool:
    """Has a video file passed VIDEO_FILE_MB? As ffmpeg has written it so far (it may not
    exist yet; the encoder holds a few frames back): near enough for a 200 MB rule."""
    return path.exists() and path.stat().st_size >= VIDEO_FILE_MB * 1024 * 1024


def _encoder(path: Path, size: tuple[int, int], fps: int) -> Any:
    import imageio_ffmpeg

    path.parent.mkdir(parents=True, exist_ok=True)
    writer = imageio_ffmpeg.write_frames(
        str(path),
        size,
        fps=fps,
        codec=CODEC,
        pix_fmt_out=PIX_FMT,
        quality=None,
        macro_block_size=1,
        ffmpeg_log_level="error",
        output_params=[*("-g", str(GOP), "-crf", str(CRF), "-preset", str(PRESET)), *SVT_PARAMS],
    )
    quiet = "SVT_LOG" not in os.environ  # SVT-AV1 prints its configuration to stderr unless told
    if quiet:
        os.environ["SVT_LOG"] = "1"  # errors only; ffmpeg inherits it as it starts
    try:
        writer.send(None)  # start ffmpeg
    finally:
        if quiet:
            del os.environ["SVT_LOG"]
    return writer


def check_video_source(source: Path, manifest: Mapping[str, Any]) -> None:
    """Video mode needs cameras, and an encoder: a usage error before anything is written."""
    if not manifest.get("cameras"):
        raise UsageError(
            f"--video: {source} has no camera images (its manifest's cameras: []; suite "
            f"{manifest.get('suite')}); record them with a suite that gives images (e.g. "
            "libero/spatial:obs=images) or export without --video"
        )
    require_encoder()


def write_videos(
    root: Path,
    keys: Sequence[str],
    columns: Mapping[str, Any],
    bounds: Sequence[tuple[int, int]],
    fps: int,
) -> list[dict[str, Any]]:
    """Each video feature's MP4 files; returns, per episode, its `videos/<key>/...` entries
    for meta/episodes (empty dicts without video features)."""
    out: list[dict[str, Any]] = [{} for _ in bounds]
    if keys:
        require_encoder()
    for key in keys:
        for entries, placed in zip(out, _write_camera(root, key, columns[key], bounds, fps), strict=True):
            entries.update(placed)
    return out


def _write_camera(
    root: Path, key: str, pngs: Sequence[bytes], bounds: Sequence[tuple[int, int]], fps: int
) -> list[dict[str, Any]]:
    """One camera's frames as MP4 files under `root`, episodes in order on one timeline per
    file (a new file once one passes VIDEO_FILE_MB, at an episode's start, as LeRobot's
    writer does); returns each episode's `videos/<key>/...` entries for meta/episodes."""
    from PIL import Image

    chunk, file, frames_in_file = 0, 0, 0
    writer, path, out = None, None, []
    try:
        for start, end in ((int(a), int(b)) for a, b in bounds):
            if writer is not None and file_full(path):
                writer.close()
                writer, frames_in_file = None, 0
                file += 1
                if file >= CHUNKS_SIZE:
                    chunk, file = chunk + 1, 0
            for i in range(start, end):
                image = np.asarray(Image.open(io.BytesIO(pngs[i])).convert("RGB"))
                if writer is None:
                    path = root / VIDEO_PATH.format(video_key=key, chunk_index=chunk, file_index=file)
                    writer = _encoder(path, (image.shape[1], image.shape[0]), fps)
                writer.send(np.ascontiguousarray(image))
            out.append(
                {
                    f"videos/{key}/chunk_index": chunk,
                    f"videos/{key}/file_index": file,
                    f"videos/{key}/from_timestamp": frames_in_file / fps,
                    f"videos/{key}/to_timestamp": (frames_in_file + end - start) / fps,
                }
            )
            frames_in_file += end - start
    finally:
        if writer is not None:
            writer.close()
    return out
