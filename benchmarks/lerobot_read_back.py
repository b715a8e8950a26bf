"""Reads an exported LeRobotDataset back with LeRobot's own reader, every frame, against the
demonstrations folder it came from; prints a table and writes JSON. Runs in the LeRobot
environment (docs/lerobot.md):

    .venv-lerobot/bin/python benchmarks/lerobot_read_back.py demos/mt10 datasets/mt10

State, action and task must be equal, and each frame's timestamp its frame index / fps.
Cameras (image or video mode) are compared with the source PNGs: the largest and the mean
absolute difference in levels of 255 per camera (0 in image mode; video mode is lossy).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

RESULTS = Path(__file__).resolve().parent / "results" / "lerobot_read_back.json"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("demos", type=Path)
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--json", type=Path, default=RESULTS, help=f"where the JSON goes (default {RESULTS})")
    args = parser.parse_args()
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from policies.observations import unpng

    steps = pq.read_table(args.demos / "steps.parquet")
    order = np.argsort(steps.column("episode_id").to_numpy(), kind="stable")
    state = np.asarray(steps.column("observation").to_pylist(), np.float32)[order]
    action = np.asarray(steps.column("action").to_pylist(), np.float32)[order]
    instruction = np.asarray(steps.column("instruction").to_pylist())[order]
    pngs = {
        camera: [steps.column(f"image_{camera}")[int(i)].as_py() for i in order]
        for camera in json.loads((args.demos / "manifest.json").read_text()).get("cameras") or []
    }
    errors = {camera: [0, 0.0] for camera in pngs}  # largest, sum of per-frame means
    start = time.perf_counter()
    dataset = LeRobotDataset(f"local/{args.dataset.name}", root=args.dataset)
    mismatches = 0
    for i in range(len(dataset)):
        frame = dataset[i]
        same = (
            np.array_equal(frame["observation.environment_state"].numpy(), state[i])
            and np.array_equal(frame["action"].numpy(), action[i])
            and frame["task"] == instruction[i]
            and abs(float(frame["timestamp"]) - int(frame["frame_index"]) / dataset.fps) < 1e-6
        )
        mismatches += not same
        for camera, images in pngs.items():
            decoded = (frame[f"observation.images.{camera}"].numpy() * 255).round().astype(np.int16)
            error = np.abs(decoded.transpose(1, 2, 0) - unpng(images[i]).astype(np.int16))
            errors[camera][0] = max(errors[camera][0], int(error.max()))
            errors[camera][1] += float(error.mean())
    seconds = time.perf_counter() - start
    result = {
        "dataset": str(args.dataset),
        "frames": len(dataset),
        "episodes": dataset.meta.total_episodes,
        "fps": dataset.fps,
        "frames_differing": mismatches,
        "cameras": {
            c: {"max_abs_diff": e[0], "mean_abs_diff": round(e[1] / len(dataset), 3)}
            for c, e in errors.items()
        },
        "video_keys": list(dataset.meta.video_keys),
        "seconds": round(seconds, 1),
        "machine": platform.processor() or platform.machine(),
        "date": time.strftime("%Y-%m-%d"),
    }
    print(f"{'frames':>8} {'episodes':>8} {'fps':>4} {'differing':>9} {'seconds':>8}")
    print(f"{len(dataset):>8} {result['episodes']:>8} {dataset.fps:>4} {mismatches:>9} {seconds:>8.1f}")
    for camera, figures in result["cameras"].items():
        print(
            f"  {camera}: |decoded - source| max {figures['max_abs_diff']}, mean {figures['mean_abs_diff']}"
        )
    args.json.parent.mkdir(exist_ok=True)
    args.json.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
