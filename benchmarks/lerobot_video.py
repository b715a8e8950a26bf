"""`export lerobot --video` beside LeRobot's own video writer on the same frames: how far each
one's decoded frames are from the source images, and the MP4 sizes. Runs in the LeRobot
environment with the `video` extra (docs/lerobot.md):

    .venv-lerobot/bin/python benchmarks/lerobot_video.py

The frames: Meta-World's `corner` camera (256 px) rendered along the 4 episodes (25 steps)
of tests/lerobot_demos.py, each marked in one corner with its index. Both datasets are
read back by LeRobot's `LeRobotDataset`; the figures are absolute differences in levels of
255 over every pixel and channel. Prints a table and writes JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results" / "lerobot_video.json"
KEY = "observation.images.corner"


def errors(dataset, images: np.ndarray) -> np.ndarray:
    """|decoded - source| of every frame, as LeRobot's reader gives it (float CHW in [0, 1])."""
    decoded = [(dataset[i][KEY].numpy() * 255).round().astype(np.int16) for i in range(len(dataset))]
    return np.abs(np.stack(decoded).transpose(0, 2, 3, 1) - images.astype(np.int16))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", type=Path, default=RESULTS, help=f"where the JSON goes (default {RESULTS})")
    args = parser.parse_args()
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from harness.export_lerobot import export_demos
    from tests.lerobot_demos import demos, lerobot_writes, marked, rendered_frames

    root = Path(tempfile.mkdtemp(prefix="lerobot-video-"))
    frames = demos(root / "demos", ("corner",), marked(rendered_frames()))
    export_demos(root / "demos", root / "ours", "local/ours", video=True)
    features = json.loads((root / "ours" / "meta" / "info.json").read_text())["features"]
    lerobot_writes(
        root / "theirs",
        {KEY: {k: v for k, v in features[KEY].items() if k != "info"}, "action": features["action"]},
        lambda episode, i: {KEY: frames["image"][i], "action": frames["action"][i]},
        video=True,
    )
    result: dict = {"frames": len(frames["image"]), "image_size": list(frames["image"].shape[1:])}
    print(f"{'writer':>14} {'mean':>6} {'p99':>5} {'max':>5} {'MP4 bytes':>10}")
    for name in ("ours", "theirs"):
        diff = errors(LeRobotDataset(f"local/{name}", root=root / name), frames["image"])
        mp4 = next((root / name / "videos").rglob("*.mp4"))
        figures = {
            "mean_abs_diff": round(float(diff.mean()), 3),
            "p99_abs_diff": float(np.percentile(diff, 99)),
            "max_abs_diff": int(diff.max()),
            "mp4_bytes": mp4.stat().st_size,
        }
        result["export --video" if name == "ours" else "LeRobot's writer"] = figures
        label = "export --video" if name == "ours" else "LeRobot writer"
        print(f"{label:>14} {figures['mean_abs_diff']:>6} {figures['p99_abs_diff']:>5.0f} "
              f"{figures['max_abs_diff']:>5} {figures['mp4_bytes']:>10}")  # fmt: skip
    result |= {
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "load_average": [round(x, 2) for x in os.getloadavg()],
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }
    args.json.parent.mkdir(exist_ok=True)
    args.json.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
