"""A demonstrations folder as `collect` writes it, of random frames, for the LeRobot export's
tests (tests/test_export_lerobot.py here, tests/lerobot/ in LeRobot's environment)."""

from __future__ import annotations

import io
import json
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


def demos(folder: Path, cameras: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """A demonstrations folder as `collect` writes it, of random frames; returns them."""
    rng = np.random.default_rng(7)
    rows: dict[str, list] = {name: [] for name in DEMO_COLUMNS.names}
    images: dict[str, list[bytes]] = {c: [] for c in cameras}
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
                image = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
                images[camera].append(png(image))
                frames["image"].append(image)
    table = pa.table(rows, schema=DEMO_COLUMNS)
    for camera in cameras:
        table = table.append_column(f"image_{camera}", pa.array(images[camera], pa.binary()))
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
