"""`lerobot-eval`'s eval_info.json, cut to what docs/lerobot.md quotes: per task and overall
success, with the command, package versions, machine, load and date beside it.

LeRobot's own file keeps every episode's reward and seed (tens of kB for MT10); this keeps
the per-task counts, LeRobot's `pc_success` figures and a Wilson 95%
interval per figure (the one docs/ quotes for this harness's own runs). Run it with the
LeRobot environment's python, which has the versions it records:

    .venv-lerobot/bin/python benchmarks/lerobot_eval_summary.py OUT/eval_info.json \\
        --command "lerobot-eval ..." --load "9.2-11.0" --started ... --finished ... \\
        --out benchmarks/results/lerobot_eval_mt10.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from importlib import metadata
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from harness.run.manifest import cpu_model
from results.summary import wilson_interval

PACKAGES = ("lerobot", "metaworld", "mujoco", "torch", "gymnasium", "numpy")


def summarise(info: dict) -> dict:
    tasks = {}
    for entry in info["per_task"]:
        episodes = entry["metrics"]["successes"]
        wins = sum(bool(s) for s in episodes)
        low, high = wilson_interval(wins, len(episodes))
        tasks[entry["task_group"]] = {
            "successes": wins,
            "episodes": len(episodes),
            "pc_success": 100.0 * wins / len(episodes),
            "wilson95": [round(100 * low, 1), round(100 * high, 1)],
        }
    wins = sum(t["successes"] for t in tasks.values())
    n = sum(t["episodes"] for t in tasks.values())
    low, high = wilson_interval(wins, n)
    overall = info["overall"]
    return {
        "tasks": tasks,
        "overall": {
            "successes": wins,
            "episodes": n,
            "pc_success": overall["pc_success"],
            "wilson95": [round(100 * low, 1), round(100 * high, 1)],
            "eval_s": overall["eval_s"],
        },
    }


def versions() -> dict[str, str | None]:
    out: dict[str, str | None] = {"python": platform.python_version()}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("eval_info", type=Path, help="lerobot-eval's OUTPUT_DIR/eval_info.json")
    parser.add_argument("--command", required=True, help="the lerobot-eval command line")
    parser.add_argument("--load", required=True, help="uptime's load averages during the run")
    parser.add_argument("--started", required=True, help="UTC start")
    parser.add_argument("--finished", required=True, help="UTC end")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    try:
        info = json.loads(args.eval_info.read_text())
        summary = summarise(info)
    except (OSError, ValueError, KeyError, TypeError) as error:
        print(f"error: {args.eval_info}: not a lerobot-eval eval_info.json ({error})", file=sys.stderr)
        return 2
    record = {
        "what": "lerobot-eval on LeRobot's Meta-World env through the metaworld_state plugin",
        "command": args.command,
        "started_utc": args.started,
        "finished_utc": args.finished,
        "load": args.load,
        "machine": {"cpu": cpu_model(), "cpu_count": os.cpu_count(), "platform": platform.platform()},
        "versions": versions(),
        **summary,
    }
    print(f"{'task':28s} {'success':>9s} {'Wilson 95%':>14s}")
    for task, row in [*summary["tasks"].items(), ("overall", summary["overall"])]:
        low, high = row["wilson95"]
        ratio = f"{row['successes']}/{row['episodes']}"
        print(f"{task:28s} {ratio:>9s} {row['pc_success']:6.1f}% [{low:.0f}, {high:.0f}]")
    args.out.write_text(json.dumps(record, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
