"""A demonstrations folder as `collect` writes it, of random frames, for the LeRobot export's
tests (tests/test_export_lerobot.py here, tests/lerobot/ in LeRobot's environment)."""

from __future__ import annotations

import io
import json
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from harness.collect import DEMO_COLUMNS

LENGTHS = (7, 1, 12, 5)  # one single-frame episode: LeRobot's "basic" statistics
INSTRUCTIONS = ("reach the goal position", "push the puck to the goal")


def png(array: np.ndarray) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG")
    return buffer.getvalue()


def rendered_frames() -> list[np.ndarray]:
    """Meta-World's `corner` camera (256 px) along random-action episodes of reach-v3, one
    image per step of LENGTHS: real scenes, since a codec's loss on random pixels says
    nothing about its loss on a simulator's images."""
    from adapters.registry import load_suite

    suite = load_suite("metaworld/mt1/reach-v3")
    task = suite.tasks[0]
    env = suite.make_env(task)
    rng = np.random.default_rng(3)
    images = []
    try:
        for episode, length in enumerate(LENGTHS):
            env.reset(options={"episode": task.episodes[episode]})
            for _ in range(length):
                images.append(env.get_wrapper_attr("video_frame")())
                env.step(rng.uniform(-1, 1, 4).astype(np.float32))
    finally:
        env.close()
    return images


MARK = 24  # pixels: the side of the square that tells frames apart (level MARK_STEP * i on frame i)
MARK_STEP = 10


def marked(images: Sequence[np.ndarray]) -> list[np.ndarray]:
    """`images` with frame i's top-left square at grey level 10 i, so a decoded frame says
    which frame it is even where consecutive scenes look alike (a codec blurs an edge,
    not a flat square's level)."""
    out = []
    for i, image in enumerate(images):
        image = np.array(image, np.uint8)
        image[:MARK, :MARK] = MARK_STEP * i
        out.append(image)
    return out


def frame_number(image: np.ndarray) -> int:
    """Which frame a decoded `marked` image is."""
    return round(float(image[4 : MARK - 4, 4 : MARK - 4].mean()) / MARK_STEP)


def smooth_frames(height: int = 64, width: int = 96) -> list[np.ndarray]:
    """One image per step of LENGTHS: a colour gradient that moves a pixel a frame (what a
    camera sees, to a codec, without a simulator), marked."""
    y, x = np.mgrid[:height, :width]
    return marked(
        [
            np.stack([(x + i) * 2 % 256, y * 3 % 256, np.full_like(x, 40 + 5 * i)], -1).astype(np.uint8)
            for i in range(sum(LENGTHS))
        ]
    )


def demos(
    folder: Path, cameras: tuple[str, ...] = (), images: Sequence[np.ndarray] | None = None
) -> dict[str, np.ndarray]:
    """A demonstrations folder as `collect` writes it, of random states and actions, and
    camera images random or `images` (one per step, the same for every camera); returns them."""
    rng = np.random.default_rng(7)
    rows: dict[str, list] = {name: [] for name in DEMO_COLUMNS.names}
    pngs: dict[str, list[bytes]] = {c: [] for c in cameras}
    frames: dict[str, list] = {"state": [], "action": [], "image": []}
    for episode, length in enumerate(LENGTHS):
        for step in range(length):
            state = rng.normal(size=39).astype(np.float32)
            action = rng.uniform(-1, 1, size=4).astype(np.float32)
            values = (
                episode,
                "reach-v3",
                INSTRUCTIONS[episode % 2],
                10 + episode,
                1000 + episode,
                episode % 50,
                step,
            )
            for name, value in zip(DEMO_COLUMNS.names[:7], values, strict=True):
                rows[name].append(value)
            rows["observation"].append(state.tolist())
            rows["action"].append(action.tolist())
            frames["state"].append(state)
            frames["action"].append(action)
            for camera in cameras:
                if images is None:
                    image = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
                else:
                    image = np.asarray(images[len(frames["state"]) - 1], np.uint8)
                pngs[camera].append(png(image))
                frames["image"].append(image)
    table = pa.table(rows, schema=DEMO_COLUMNS)
    for camera in cameras:
        table = table.append_column(f"image_{camera}", pa.array(pngs[camera], pa.binary()))
    folder.mkdir()
    pq.write_table(table, folder / "steps.parquet")
    manifest = {
        "format": "dvla-harness-demos/2",
        "suite": "metaworld/mt10",
        "split": "train",
        "policy": "scripted",
        "proprio_dims": {"reach-v3": 4},
        "cameras": list(cameras),
        "steps_sha256": "ab" * 32,
    }
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return {k: np.stack(v) for k, v in frames.items() if v}


def lerobot_writes(
    root: Path, features: dict, frames_of: Callable[[int, int], dict], video: bool = False
) -> Path:
    """The frames of LENGTHS written by LeRobot's own writer (create, add_frame per frame,
    save_episode, finalize) into `root`: `frames_of(episode, i)` gives frame i's features.
    The reference the export is compared with (LeRobot's environment only)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dataset = LeRobotDataset.create(
        f"local/{root.name}", fps=80, features=features, root=root, use_videos=video
    )
    i = 0
    for episode, length in enumerate(LENGTHS):
        for _ in range(length):
            dataset.add_frame(frames_of(episode, i) | {"task": INSTRUCTIONS[episode % 2]})
            i += 1
        dataset.save_episode()
    dataset.finalize()
    return root
