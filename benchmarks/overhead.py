"""Harness overhead: the harness's episode path against a bare loop over the same env.

Both sides drive the same env object with the suite's scripted expert (Meta-World's
own policies, or `libero_scripted` for LIBERO) on the same episode specs, interleaved
(the order alternates every round) so that both see the same machine noise. The
harness side is everything a real run does per episode: the timed loop, NFE hooks,
building the row and appending it to pending.jsonl, flushed, as a run does.

    python benchmarks/overhead.py [--episodes 5] [--tasks reach-v3,push-v3] [--json PATH]
    python benchmarks/overhead.py --suite libero/object [--episodes 3] [--tasks 0,1,2]
    python benchmarks/overhead.py --suite simpler/all [--episodes 5]

Targets: overhead <= 3% of wall-clock on Meta-World, <= 5% on LIBERO and on the
SimplerEnv-like ManiSkill3 suites (state observations), as the median over paired
episodes; the total is printed too. LIBERO and ManiSkill3 results go to
benchmarks/results/overhead-libero.json and overhead-simpler.json unless --json says otherwise.
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
from harness.backends.jobs import EpisodeJob
from harness.config import RunConfig, resolve
from harness.episode.context import episode_context
from harness.episode.loop import run_episode
from harness.episode.timed import TimedPolicy
from harness.run.rows import make_row
from results.store import RunDir

TARGET_PERCENT = 3.0  # Meta-World
LIBERO_TARGET_PERCENT = 5.0  # LIBERO with state observations
SIMPLER_TARGET_PERCENT = 5.0  # simpler/* with state observations


def metaworld_expert(suite_name: str, task):
    from metaworld.policies import ENV_POLICY_MAP

    return ENV_POLICY_MAP[task.name]().get_action


def libero_expert(suite_name: str, task):
    """What a hand-written LIBERO loop would use: the scripted expert's state machine."""
    from types import SimpleNamespace

    from policies.experts.libero_pick import LiberoScriptedParams, PickPlaceExpert
    from policies.experts.libero_select import plan_for

    plan = plan_for(SimpleNamespace(suite=suite_name, task=task.name))
    return PickPlaceExpert(plan, LiberoScriptedParams(), None).act


def maniskill_expert(suite_name: str, task):
    """The scripted expert's per-task state machine, as a hand-written loop would call it."""
    from adapters.simpler import TASKS, state_layout
    from policies.experts.maniskill_scripted import TaskExpert

    return TaskExpert(task.name, 1.0, layout=state_layout(TASKS[task.name])).act


def bare_episode(env, suite_name, task, spec, make_expert) -> tuple[float, int]:
    """The loop a user would write by hand: no timing splits, no hooks, no rows."""
    start = time.perf_counter()
    obs, _ = env.reset(options={"episode": spec})
    act = make_expert(suite_name, task)
    steps = 0
    while steps < task.max_steps:
        obs, _, terminated, truncated, info = env.step(act(obs))
        steps += 1
        if info["success"] or terminated or truncated:
            break
    return time.perf_counter() - start, steps


def harness_episode(resolved, run_dir, env, task, spec, policy: TimedPolicy) -> tuple[float, int, float]:
    prun = resolved.policies[0]
    start = time.perf_counter()
    context = episode_context(resolved.suite.name, task, spec, env)
    outcome = run_episode(env, policy, context, spec)
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
    parser.add_argument(
        "--suite", default="metaworld/mt10", help="metaworld/mt10 (default), a libero/ or a simpler/ suite"
    )
    parser.add_argument("--episodes", type=int, default=None, help="episodes per task (default 5; LIBERO 3)")
    parser.add_argument(
        "--tasks", default="", help="comma-separated task names or indices (default: all; LIBERO 0,1,2)"
    )
    parser.add_argument("--json", default="", help="where to write the JSON (default benchmarks/results/...)")
    args = parser.parse_args()

    libero = args.suite.startswith("libero/")
    if libero:
        policy, make_expert, target = "libero_scripted", libero_expert, LIBERO_TARGET_PERCENT
        default_tasks, default_episodes, default_json = "0,1,2", 3, "overhead-libero.json"
    elif args.suite.startswith("simpler/"):
        policy, make_expert, target = "maniskill_scripted", maniskill_expert, SIMPLER_TARGET_PERCENT
        default_tasks, default_episodes, default_json = "", 5, "overhead-simpler.json"
    else:
        policy, make_expert, target = "scripted", metaworld_expert, TARGET_PERCENT
        default_tasks, default_episodes, default_json = "", 5, "overhead.json"
    episodes = args.episodes or default_episodes
    suite = load_suite(args.suite)
    names = [t for t in (args.tasks or default_tasks).split(",") if t] or [t.name for t in suite.tasks]
    config = RunConfig(suite=suite.name, policies=(), tasks=tuple(names), episodes_per_task=episodes)
    from harness.config import PolicyChoice

    resolved = resolve(RunConfig(**{**config.to_dict(), "policies": (PolicyChoice(policy),)}))
    names = [t.name for t in resolved.tasks]
    policy = TimedPolicy(resolved.policies[0].policy, resolved.policies[0].spec.name)
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
                        seconds["bare"], steps["bare"] = bare_episode(
                            env, suite.name, task, spec, make_expert
                        )
                    else:
                        seconds["harness"], steps["harness"], loop_overhead = harness_episode(
                            resolved, run_dir, env, task, spec, policy
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
        "episodes_per_task": episodes,
        "observations": "state (Meta-World's 39-D vector)" if policy == "scripted" else "state",
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
        "target_percent": target,
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
    verdict = "PASS" if result["overhead_percent_of_wall_clock"] <= target else "FAIL"
    print(f"target <= {target}% of wall-clock: {verdict}")
    path = Path(args.json or f"benchmarks/results/{default_json}")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
