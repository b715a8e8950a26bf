"""Harness overhead on Meta-World: the harness's episode path against a bare loop.

Both sides drive the same env object with Meta-World's expert on the same episode
specs, interleaved (the order alternates every round) so that both see the same
machine noise. The harness side is everything a real run does per episode: the timed
loop, NFE hooks, building the row and writing it durably as a Parquet part.

    python benchmarks/overhead.py [--episodes 5] [--tasks reach-v3,push-v3] [--json PATH]

Target: overhead <= 3% of wall-clock (the median over paired episodes; the total is
printed too).
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import tempfile
import time
from pathlib import Path

from adapters.registry import load_suite
from harness.config import RunConfig, resolve
from harness.episode import run_episode
from harness.nfe import NFECounter
from harness.runner import EpisodeJob, episode_context, make_row
from results.store import RunDir

TARGET_PERCENT = 3.0


def bare_episode(env, task, spec) -> tuple[float, int]:
    """The loop a user would write by hand: no timing splits, no hooks, no rows."""
    from metaworld.policies import ENV_POLICY_MAP

    start = time.perf_counter()
    obs, _ = env.reset(options={"episode": spec})
    expert = ENV_POLICY_MAP[task.name]()
    steps = 0
    while steps < task.max_steps:
        obs, _, terminated, truncated, info = env.step(expert.get_action(obs))
        steps += 1
        if info["success"] or terminated or truncated:
            break
    return time.perf_counter() - start, steps


def harness_episode(resolved, run_dir, env, task, spec, counter) -> tuple[float, int, float]:
    prun = resolved.policies[0]
    start = time.perf_counter()
    context = episode_context(resolved.suite.name, task, spec, env)
    outcome = run_episode(env, prun.policy, counter, context, spec, 0)
    run_dir.append_episode(make_row("bench", resolved, EpisodeJob(prun, task, spec), outcome))
    return (
        time.perf_counter() - start,
        outcome.steps,
        outcome.wall_clock_s - outcome.policy_time_s - outcome.env_time_s,
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--episodes", type=int, default=5, help="episodes per task (default 5)")
    parser.add_argument("--tasks", default="", help="comma-separated MT10 tasks (default: all ten)")
    parser.add_argument("--json", default="benchmarks/results/overhead.json", help="where to write the JSON")
    args = parser.parse_args()

    suite = load_suite("metaworld/mt10")
    names = [t for t in args.tasks.split(",") if t] or [t.name for t in suite.tasks]
    config = RunConfig(suite=suite.name, policies=(), tasks=tuple(names), episodes_per_task=args.episodes)
    from harness.config import PolicyChoice

    resolved = resolve(RunConfig(**{**config.to_dict(), "policies": (PolicyChoice("scripted"),)}))
    counter = NFECounter(resolved.policies[0].policy)
    totals = {"harness_s": 0.0, "bare_s": 0.0, "steps": 0, "in_loop_overhead_s": 0.0}
    mismatched = 0
    paired_percent: list[float] = []  # per episode spec: (harness - bare) / harness
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = RunDir(tmp)
        run_dir.create()
        for task in resolved.tasks:
            env = suite.make_env(task)
            for round_, spec in enumerate(resolved.episodes(task)):
                sides = ["harness", "bare"] if round_ % 2 == 0 else ["bare", "harness"]
                steps, seconds = {}, {}
                for side in sides:
                    if side == "bare":
                        seconds["bare"], steps["bare"] = bare_episode(env, task, spec)
                    else:
                        seconds["harness"], steps["harness"], loop_overhead = harness_episode(
                            resolved, run_dir, env, task, spec, counter
                        )
                        totals["in_loop_overhead_s"] += loop_overhead
                totals["bare_s"] += seconds["bare"]
                totals["harness_s"] += seconds["harness"]
                paired_percent.append(100 * (seconds["harness"] - seconds["bare"]) / seconds["harness"])
                mismatched += steps["bare"] != steps["harness"]
                totals["steps"] += steps["harness"]
            env.close()
    overhead = totals["harness_s"] - totals["bare_s"]
    result = {
        "benchmark": "overhead",
        "suite": suite.name,
        "tasks": names,
        "episodes_per_task": args.episodes,
        "steps": totals["steps"],
        "episodes_with_different_step_counts": mismatched,
        "bare_s": round(totals["bare_s"], 4),
        "harness_s": round(totals["harness_s"], 4),
        "overhead_s": round(overhead, 4),
        "overhead_us_per_step": round(1e6 * overhead / totals["steps"], 2),
        # The median of per-episode paired differences resists the shared machine's
        # bursts, which land on one side of a pair at random; the total does not.
        "overhead_percent_of_wall_clock": round(statistics.median(paired_percent), 3),
        "overhead_percent_total": round(100 * overhead / totals["harness_s"], 3),
        "in_loop_overhead_percent": round(100 * totals["in_loop_overhead_s"] / totals["harness_s"], 3),
        "target_percent": TARGET_PERCENT,
        "machine": {"cpu": platform.processor() or platform.machine(), "python": platform.python_version()},
    }
    print(f"{'':32}{'value':>12}")
    for key in (
        "steps",
        "bare_s",
        "harness_s",
        "overhead_us_per_step",
        "overhead_percent_of_wall_clock",
        "overhead_percent_total",
        "in_loop_overhead_percent",
        "episodes_with_different_step_counts",
    ):
        print(f"{key:32}{result[key]:>12}")
    verdict = "PASS" if result["overhead_percent_of_wall_clock"] <= TARGET_PERCENT else "FAIL"
    print(f"target <= {TARGET_PERCENT}% of wall-clock: {verdict}")
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
