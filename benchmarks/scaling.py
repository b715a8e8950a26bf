"""Episodes per second with 1 worker, 2 local worker processes and 2 Ray actors, and
(for a model policy) with 8 environments batched per worker.

Two workloads: LIBERO spatial with state observations and the scripted expert (the
simulator is the cost) and Meta-World MT10 with the shipped fast_dvla (the policy is a
large part). Each mode runs the same config into its own run folder, one mode after the
other; the unbatched modes' rows must agree on every column that is not timing or place
(success, steps, chunks, NFE, tokens, failure reason): that is checked and printed. The
batched modes (`b8`: `--batch-envs 8`, MT10 only: the scripted expert cannot batch) are
compared on the same columns less NFE and batch size, since a batched row is charged
the passes its batch ran (docs/results-schema.md); how many episodes' NFE differs is
printed beside.

    python benchmarks/scaling.py [--episodes-per-task 2] [--tasks 0,1,...] [--workloads libero,mt10]
                                 [--json benchmarks/results/scaling.json]

Figures: episodes/s over the whole run (worker start-up, Ray start-up and env builds
included, as a user waits for them) and over the episodes alone (from the first
episode's start to the run's end). Targets: 2 workers >= 1.8x one worker on
LIBERO; Ray >= 0.9x the local pool. The machine's load (`uptime`) is recorded beside
them: on a shared machine the ratios are not the idle figures.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import tempfile
import time
from pathlib import Path

import pandas as pd

from harness.backends import Execution
from harness.config import build_config, resolve
from harness.run.runner import run
from harness.threads import apply_threads
from results.schema import PROVENANCE_COLUMNS, TIMING_COLUMNS

WORKLOADS = {
    "libero": ("libero/spatial", "libero_scripted"),
    "mt10": ("metaworld/mt10", "fast_dvla"),
}
MODES = {
    "local x1": Execution(),
    "local x2": Execution(workers=2),
    "ray x2": Execution(backend="ray", workers=2),
    "local x1 b8": Execution(batch_envs=8),
    "local x2 b8": Execution(workers=2, batch_envs=8),
}
# Workloads whose policy cannot batch (scripted experts) skip the batched modes.
BATCHES = {"libero": False, "mt10": True}
# What batching changes by definition (NFE charged per batch, a batched pass's counted work
# shared among the episodes it served), left out of `differing`.
BATCH_DEFINED = frozenset(
    {
        "nfe_total",
        "nfe_per_chunk",
        "batch_envs",
        "flops_total",
        "flops_per_chunk",
        "query_tokens_total",
        "kv_tokens_total",
        "kv_cached_tokens_total",
    }
)
# Columns that say when, where or how fast, not what happened.
NOT_RESULTS = TIMING_COLUMNS | PROVENANCE_COLUMNS
KEY = ["task", "episode_index", "policy_config_id"]


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True, check=False).stdout.strip()


def measure(suite: str, policy: str, tasks: list[str] | None, episodes: int, mode: str, out: Path) -> dict:
    data: dict = {"suite": suite, "policy": [{"name": policy}], "episodes_per_task": episodes}
    if tasks:
        data["tasks"] = tasks
    resolved = resolve(build_config(data))
    start = time.perf_counter()
    started = pd.Timestamp.now(tz="UTC")
    report = run(resolved, out, execution=MODES[mode])
    wall = time.perf_counter() - start
    rows = report.run_dir.read_episodes()
    first = (rows["started_at"].min() - started).total_seconds()
    return {
        "mode": mode,
        "episodes": len(rows),
        "failed": int(rows["failure_reason"].notna().sum()),
        "successes": int(rows["success"].sum()),
        "wall_s": round(wall, 2),
        "start_up_s": round(first, 2),
        "episodes_per_s": round(len(rows) / wall, 4),
        "episodes_per_s_running": round(len(rows) / max(1e-9, wall - first), 4),
        "workers": sorted(set(rows["worker_id"])),
        "uptime_after": uptime(),
        "_rows": rows,
    }


def differing(a: pd.DataFrame, b: pd.DataFrame, ignore: frozenset[str] = frozenset()) -> int:
    """Episodes whose non-timing columns (less `ignore`) differ between two runs of one config."""
    columns = [c for c in a.columns if c not in NOT_RESULTS | ignore]
    left = a[columns].sort_values(KEY).reset_index(drop=True)
    right = b[columns].sort_values(KEY).reset_index(drop=True)
    if len(left) != len(right):
        return abs(len(left) - len(right)) + min(len(left), len(right))
    same = (left == right) | (left.isna() & right.isna())
    return int((~same.all(axis=1)).sum())


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--episodes-per-task", type=int, default=2)
    parser.add_argument("--tasks", help="task names or indices, comma-separated (default: all ten)")
    parser.add_argument("--workloads", default="libero,mt10", help="comma-separated: libero, mt10")
    parser.add_argument("--modes", default=",".join(MODES), help="comma-separated: " + ", ".join(MODES))
    parser.add_argument("--json", default="benchmarks/results/scaling.json")
    args = parser.parse_args()
    for option, given, valid in (("--modes", args.modes, MODES), ("--workloads", args.workloads, WORKLOADS)):
        unknown = [x for x in given.split(",") if x not in valid]
        if unknown:
            parser.error(f"{option}: unknown {', '.join(map(repr, unknown))}; valid: {', '.join(valid)}")
    apply_threads(1)
    tasks = [t.strip() for t in args.tasks.split(",")] if args.tasks else None
    result: dict = {
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "uptime_before": uptime()},
        "episodes_per_task": args.episodes_per_task,
        "workloads": {},
    }
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.workloads.split(","):
            suite, policy = WORKLOADS[name]
            runs = []
            for mode in args.modes.split(","):
                if MODES[mode].batch_envs > 1 and not BATCHES[name]:
                    continue
                out = Path(tmp) / f"{name}-{mode.replace(' ', '')}"
                runs.append(measure(suite, policy, tasks, args.episodes_per_task, mode, out))
                r = runs[-1]
                print(
                    f"{name:7} {mode:11} {r['episodes']:4d} episodes {r['wall_s']:8.1f} s  "
                    f"{r['episodes_per_s']:.3f} ep/s ({r['episodes_per_s_running']:.3f} running)  "
                    f"start-up {r['start_up_s']:.1f} s  {r['uptime_after']}",
                    flush=True,
                )
            if not runs:
                print(f"{name}: no mode applies ({policy} cannot batch)", flush=True)
                continue
            base = runs[0]
            for r in runs:
                r["ratio_vs_first"] = round(r["episodes_per_s"] / base["episodes_per_s"], 3)
                r["ratio_running_vs_first"] = round(
                    r["episodes_per_s_running"] / base["episodes_per_s_running"], 3
                )
                batched = MODES[r["mode"]].batch_envs > 1
                ignore = BATCH_DEFINED if batched else frozenset()
                r["episodes_differing_from_first"] = differing(base["_rows"], r["_rows"], ignore)
                if batched:
                    r["episodes_nfe_differing_from_first"] = differing(
                        base["_rows"][[*KEY, "nfe_total"]], r["_rows"][[*KEY, "nfe_total"]]
                    )
            result["workloads"][name] = {
                "suite": suite,
                "policy": policy,
                "runs": [{k: v for k, v in r.items() if k != "_rows"} for r in runs],
            }
    result["machine"]["uptime_after"] = uptime()
    print()
    print(
        f"{'workload':8} {'mode':11} {'ep/s':>7} {'x first':>8} {'ep/s run':>9} {'x first':>8} {'differ':>6} "
        f"{'NFE differ':>10}"
    )
    for name, w in result["workloads"].items():
        for r in w["runs"]:
            print(
                f"{name:8} {r['mode']:11} {r['episodes_per_s']:7.3f} {r['ratio_vs_first']:8.2f} "
                f"{r['episodes_per_s_running']:9.3f} {r['ratio_running_vs_first']:8.2f} "
                f"{r['episodes_differing_from_first']:6d} {r.get('episodes_nfe_differing_from_first', '-'):>10}"
            )
    print(f"load: before {result['machine']['uptime_before']}; after {result['machine']['uptime_after']}")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
