"""`dvla-harness export lerobot`: demonstrations as a LeRobotDataset v3 (docs/demonstrations.md)."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from harness.errors import UsageError

EPILOG = """\
examples:
  dvla-harness collect --suite metaworld/mt10 --policy scripted --episodes-per-task 50 --out demos/mt10
  dvla-harness export lerobot demos/mt10 --out datasets/mt10
  dvla-harness collect --suite libero/spatial:obs=images --policy libero_scripted --out demos/spatial
  dvla-harness export lerobot demos/spatial --out datasets/spatial --video   # cameras as MP4
  # then, in the LeRobot environment (docs/lerobot.md):
  lerobot-train --dataset.repo_id=local/mt10 --dataset.root=datasets/mt10 --policy.type=act ...

Writes LeRobot's v3 layout with pyarrow (no lerobot import): data/, meta/info.json,
meta/stats.json, meta/tasks.parquet, meta/episodes/, camera images in image mode (PNG
in the parquet, lossless) or with --video as AV1 MP4 under videos/ (LeRobot's video
mode: lossy, much smaller), and meta/dvla_harness.json (suite, split, demonstrator,
steps_sha256: what v3 has no slot for). fps is the suite's control rate. A run folder
cannot be exported: its rows hold outcomes and timings, not the observations and actions
a dataset needs.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export",
        help="write demonstrations in another tool's format (lerobot: LeRobotDataset v3)",
        description="Write a `collect` folder as a LeRobotDataset v3, for LeRobot's trainers and tools.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("format", choices=("lerobot",), help="the format to write")
    p.add_argument("source", type=Path, help="a demonstrations folder written by `dvla-harness collect`")
    p.add_argument("--out", type=Path, required=True, help="the dataset folder to create (must not exist)")
    p.add_argument(
        "--repo-id",
        default=None,
        help="the dataset's name in LeRobot (recorded in the sidecar; default local/<folder name>)",
    )
    p.add_argument(
        "--video",
        action="store_true",
        help="camera images as MP4 video (LeRobot's video mode: videos/<key>/chunk-000/file-000.mp4, AV1 "
        "with LeRobot's default encoder settings): 11x smaller than image mode's PNGs on LIBERO's 128 px "
        "cameras, and lossy (2.3-2.6 levels of 255 on average; docs/lerobot.md); needs cameras in the "
        "source and the `video` extra (imageio-ffmpeg)",
    )
    p.set_defaults(func=cmd_export)


def cmd_export(args: argparse.Namespace) -> int:
    from harness.console import console
    from harness.export_lerobot import export_demos

    repo_id = args.repo_id or f"local/{args.out.name}"
    if not re.fullmatch(r"[\w.-]+/[\w.-]+", repo_id):
        raise UsageError(f"--repo-id {repo_id!r}: expected OWNER/NAME (letters, digits, '.', '_', '-')")
    if (args.source / "episodes.parquet").is_file() or (args.source / "pending.jsonl").is_file():
        raise UsageError(
            f"{args.source} is a run folder: its rows hold outcomes and timings, not the observations "
            "and actions a dataset needs; record demonstrations with `dvla-harness collect`"
        )
    summary = export_demos(args.source, args.out, repo_id, video=args.video)
    console.print(
        f"wrote {args.out}: LeRobotDataset {summary['codebase_version']}, {summary['total_episodes']} episodes, "
        f"{summary['total_frames']} frames, {summary['total_tasks']} tasks at {summary['fps']} fps"
    )
    return 0
