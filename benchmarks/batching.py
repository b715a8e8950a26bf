"""Batched inference across environments: --batch-envs 1 / 4 / 8 on Meta-World MT10.

For each shipped decoder (fast_dvla, bidirectional), the same config is run in this
process at each batch size, one after the other, into its own run folder; then:

- episodes/s = episodes / sum(wall_clock_s): the loop's time (the rows' wall clocks add
  up to it, batched or not; start-up and warm-up excluded), and over the whole run;
- tokens/s = sum(action_tokens_total) / sum(policy_time_s);
- how many episodes differ from the unbatched run in success, steps or tokens ("differ"),
  how many ran the same but were charged more NFE ("more NFE": an adaptive decoder's
  batch decodes until its slowest row is done), and the
  decoded tokens of a probe: 64 observations decoded alone and in batches of 8, counting
  chunks whose tokens differ (a batched matmul sums in another order; a near-tied token
  can flip, and the episode then goes its own way).

    python benchmarks/batching.py [--tasks reach-v3,push-v3] [--episodes-per-task 16]
                                  [--sizes 1,4,8] [--json benchmarks/results/batching.json]

Target: batch 8 >= 2x the episodes/s of batch 1. The machine's load (`uptime`)
is recorded beside each figure: on a shared machine the ratios are not the idle figures.
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

import numpy as np
import pandas as pd

from harness.backends import Execution
from harness.config import ResolvedRun, build_config, resolve
from harness.episode.context import episode_context
from harness.run.runner import run
from harness.threads import apply_threads

POLICIES = ("fast_dvla", "bidirectional")
RESULTS = ["success", "steps", "action_tokens_total", "nfe_total"]
KEY = ["task", "episode_index"]


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True, check=False).stdout.strip()


def measure(resolved: ResolvedRun, batch: int, out: Path) -> dict:
    start = time.perf_counter()
    report = run(resolved, out, execution=Execution(batch_envs=batch))
    wall = time.perf_counter() - start
    rows = report.run_dir.read_episodes()
    loop = float(rows["wall_clock_s"].sum())
    return {
        "batch_envs": batch,
        "episodes": len(rows),
        "successes": int(rows["success"].sum()),
        "failed": int(rows["failure_reason"].notna().sum()),
        "run_wall_s": round(wall, 2),
        "loop_s": round(loop, 2),
        "episodes_per_s": round(len(rows) / loop, 4),
        "episodes_per_s_run": round(len(rows) / wall, 4),
        "tokens_per_s": round(float(rows["action_tokens_total"].sum() / rows["policy_time_s"].sum()), 1),
        "policy_s": round(float(rows["policy_time_s"].sum()), 2),
        "env_s": round(float(rows["env_time_s"].sum()), 2),
        "nfe_per_chunk": round(float(rows["nfe_total"].sum() / rows["chunks"].sum()), 3),
        "uptime_after": uptime(),
        "_rows": rows,
    }


def differences(base: pd.DataFrame, other: pd.DataFrame) -> dict:
    """Per result column, how many episodes differ from the unbatched run."""
    merged = base[KEY + RESULTS].merge(other[KEY + RESULTS], on=KEY, suffixes=("", "_b"))
    out = {c: int((merged[c] != merged[c + "_b"]).sum()) for c in RESULTS}
    out["episodes_any"] = int(
        (merged[RESULTS].to_numpy() != merged[[c + "_b" for c in RESULTS]].to_numpy()).any(axis=1).sum()
    )
    same_run = (
        merged[["success", "steps", "action_tokens_total"]].to_numpy()
        == merged[["success_b", "steps_b", "action_tokens_total_b"]].to_numpy()
    )
    out["episodes"] = int((~same_run.all(axis=1)).sum())  # success, steps or tokens
    out["same_actions_more_nfe"] = int(
        (same_run.all(axis=1) & (merged["nfe_total"] < merged["nfe_total_b"])).sum()
    )
    return out


def probe(resolved: ResolvedRun, observations: int = 64, batch: int = 8) -> dict:
    """Decode the same observations alone and in batches: chunks whose tokens differ."""
    policy = resolved.policies[0].policy
    rng = np.random.default_rng(0)
    pairs = []
    for task in resolved.tasks:
        env = resolved.suite.make_env(task)
        for spec in resolved.episodes(task):
            obs, _ = env.reset(seed=spec.seed, options={"episode": spec})
            context = episode_context(resolved.suite.name, task, spec, env)
            for _ in range(4):  # states along the episode, reached with random actions
                for _ in range(int(rng.integers(1, 15))):
                    obs, *_ = env.step(env.action_space.sample() * 0.3)
                pairs.append((context, obs))
        env.close()
    pairs = [pairs[i] for i in rng.permutation(len(pairs))[:observations]]  # tasks mixed
    alone = [policy.act_batch([c], [o]).actions[0] for c, o in pairs]
    together = []
    for i in range(0, len(pairs), batch):
        part = pairs[i : i + batch]
        together += list(policy.act_batch([c for c, _ in part], [o for _, o in part]).actions)
    flipped = [
        float(np.abs(a - b).max()) for a, b in zip(alone, together, strict=True) if not np.array_equal(a, b)
    ]
    return {
        "chunks": len(pairs),
        "batch": batch,
        "chunks_differing": len(flipped),
        "max_action_change": max(flipped, default=0.0),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--tasks", default="reach-v3,push-v3", help="MT10 task names or indices, comma-separated"
    )
    parser.add_argument("--episodes-per-task", type=int, default=16)
    parser.add_argument("--sizes", default="1,4,8", help="batch sizes; the first is the reference")
    parser.add_argument("--policies", default=",".join(POLICIES))
    parser.add_argument("--json", default="benchmarks/results/batching.json")
    args = parser.parse_args()
    apply_threads(1)
    sizes = [int(s) for s in args.sizes.split(",")]
    result: dict = {
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "uptime_before": uptime()},
        "suite": "metaworld/mt10",
        "tasks": args.tasks.split(","),
        "episodes_per_task": args.episodes_per_task,
        "threads": 1,
        "policies": {},
    }
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.policies.split(","):
            data = {
                "suite": "metaworld/mt10",
                "tasks": args.tasks.split(","),
                "episodes_per_task": args.episodes_per_task,
                "policy": [{"name": name}],
            }
            resolved = resolve(build_config(data))
            runs = []
            for batch in sizes:
                runs.append(measure(resolved, batch, Path(tmp) / f"{name}-{batch}"))
                r = runs[-1]
                print(
                    f"{name:13} batch {batch:2d}: {r['episodes']} episodes, loop {r['loop_s']:7.1f} s, "
                    f"{r['episodes_per_s']:.3f} ep/s, {r['tokens_per_s']:8.0f} tokens/s  [{r['uptime_after']}]",
                    flush=True,
                )
            for r in runs:
                r["x_episodes_per_s"] = round(r["episodes_per_s"] / runs[0]["episodes_per_s"], 3)
                r["x_tokens_per_s"] = round(r["tokens_per_s"] / runs[0]["tokens_per_s"], 3)
                r["differ_from_first"] = differences(runs[0]["_rows"], r["_rows"])
            result["policies"][name] = {
                "runs": [{k: v for k, v in r.items() if k != "_rows"} for r in runs],
                "probe": probe(resolved),
            }
    result["machine"]["uptime_after"] = uptime()
    print()
    print(
        f"{'policy':13} {'K':>2} {'ep/s':>7} {'x K=1':>6} {'tok/s':>8} {'x K=1':>6} {'nfe/chunk':>9} {'differ':>6} {'more NFE':>8}"
    )
    for name, p in result["policies"].items():
        for r in p["runs"]:
            print(
                f"{name:13} {r['batch_envs']:2d} {r['episodes_per_s']:7.3f} {r['x_episodes_per_s']:6.2f} "
                f"{r['tokens_per_s']:8.0f} {r['x_tokens_per_s']:6.2f} {r['nfe_per_chunk']:9.2f} "
                f"{r['differ_from_first']['episodes']:6d} {r['differ_from_first']['same_actions_more_nfe']:8d}"
            )
        print(f"{name:13} probe: {p['probe']}")
    print(f"load: before {result['machine']['uptime_before']}; after {result['machine']['uptime_after']}")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
