"""Reads an exported LeRobotDataset back with LeRobot's own reader, every frame, against the
demonstrations folder it came from; prints a table and writes JSON. Runs in the LeRobot
environment (docs/lerobot.md):

    .venv-lerobot/bin/python benchmarks/lerobot_read_back.py demos/mt10 datasets/mt10
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
    args = parser.parse_args()
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    steps = pq.read_table(args.demos / "steps.parquet")
    order = np.argsort(steps.column("episode_id").to_numpy(), kind="stable")
    state = np.asarray(steps.column("observation").to_pylist(), np.float32)[order]
    action = np.asarray(steps.column("action").to_pylist(), np.float32)[order]
    instruction = np.asarray(steps.column("instruction").to_pylist())[order]
    start = time.perf_counter()
    dataset = LeRobotDataset(f"local/{args.dataset.name}", root=args.dataset)
    mismatches = 0
    for i in range(len(dataset)):
        frame = dataset[i]
        same = (
            np.array_equal(frame["observation.environment_state"].numpy(), state[i])
            and np.array_equal(frame["action"].numpy(), action[i])
            and frame["task"] == instruction[i]
        )
        mismatches += not same
    seconds = time.perf_counter() - start
    result = {
        "dataset": str(args.dataset),
        "frames": len(dataset),
        "episodes": dataset.meta.total_episodes,
        "fps": dataset.fps,
        "frames_differing": mismatches,
        "seconds": round(seconds, 1),
        "machine": platform.processor() or platform.machine(),
        "date": time.strftime("%Y-%m-%d"),
    }
    print(f"{'frames':>8} {'episodes':>8} {'fps':>4} {'differing':>9} {'seconds':>8}")
    print(f"{len(dataset):>8} {result['episodes']:>8} {dataset.fps:>4} {mismatches:>9} {seconds:>8.1f}")
    RESULTS.parent.mkdir(exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
