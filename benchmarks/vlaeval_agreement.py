"""This harness and vla-eval on the same LIBERO episodes, compared episode by episode.

Both harnesses claim the protocol openpi's LIBERO script runs (env seed 7 once per task,
episode j restores initial state j, 10 settle steps, the suite's step budget, success is
LIBERO's done). The same policy goes through both: the `playback` policy replaying the
scripted expert's recorded actions (it reads no observation, so both can feed it), with
the gripper as vla-eval executes it (`gripper=sign`, so both execute the same numbers).

1. the expert's episodes: `dvla-harness collect --split eval` on
   `libero/<suite>:seeding=openpi` (skipped when --demos already holds them);
2. this harness: each episode through its episode loop on
   `libero/<suite>:obs=upstream,seeding=openpi`, recording each executed action and the
   8-D state after it;
3. vla-eval: `vla-eval run --no-docker` of its LIBERO benchmark (unsharded,
   quat_no_antipodal: true) against `dvla-harness serve --protocol vla-eval` serving the
   same playback, its per-step recording (executed action, post-step state) read back.

Per episode: success, steps, the largest difference between executed actions, and
between states, and the first step where the states differ.

    python benchmarks/vlaeval_agreement.py --suite spatial --tasks 10 --episodes 5
"""

from __future__ import annotations

import argparse
import json
import pickle
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.vlaeval_runs import (
    REPO,
    fresh_output,
    machine,
    recorded_episodes,
    served,
    uptime,
    versions,
    vla_eval_config,
    vla_eval_run,
)
from policies.playback import PlaybackParams, PlaybackPolicy


def collect(suite_key: str, tasks: int, episodes: int, demos: Path) -> None:
    if (demos / "steps.parquet").is_file():
        return
    command = [sys.executable, "-m", "harness", "collect", "--suite", f"libero/{suite_key}:seeding=openpi"]
    command += ["--split", "eval", "--policy", "libero_scripted", "--tasks", ",".join(map(str, range(tasks)))]
    command += ["--episodes-per-task", str(episodes), "--out", str(demos), "--quiet"]
    subprocess.run(command, cwd=REPO, check=True)


class Recording(gym.Wrapper):
    """The env, keeping each executed action and the 8-D state after it."""

    def reset(self, **kwargs: Any):
        self.actions: list[np.ndarray] = []
        self.states: list[np.ndarray] = []
        return self.env.reset(**kwargs)

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.actions.append(np.asarray(action, np.float32))
        self.states.append(np.asarray(obs["state"], np.float32))
        return obs, reward, terminated, truncated, info


def here(args: argparse.Namespace, params: PlaybackParams, saved: Path) -> tuple[list[dict[str, Any]], float]:
    """This harness's episodes, through its own loop (what `run` runs per episode), kept in
    `saved` after each one."""
    from adapters.registry import load_suite
    from harness.episode.context import episode_context
    from harness.episode.loop import run_episode

    size = "" if args.image_size == 256 else f",image_size={args.image_size}"
    suite = load_suite(f"libero/{args.suite}:obs=upstream,seeding=openpi{size}")
    tasks, episodes = args.tasks, args.episodes
    out, start = [], time.perf_counter()
    for task in suite.tasks[args.first_task : tasks]:
        env = Recording(suite.make_env(task))
        try:
            for episode in task.episodes[:episodes]:
                context = episode_context(suite.name, task, episode, env)
                outcome = run_episode(env, PlaybackPolicy(params), context, episode)
                out.append(
                    {
                        "task_idx": task.index,
                        "episode": episode.index,
                        "success": bool(outcome.success),
                        "steps": int(outcome.steps),
                        "failure": outcome.failure_reason,
                        "actions": np.array(env.actions),
                        "states": np.array(env.states),
                    }
                )
                saved.write_bytes(pickle.dumps((out, time.perf_counter() - start)))
                print(
                    f"  task {task.index} episode {episode.index}: {outcome.steps} steps, "
                    f"success {outcome.success}",
                    flush=True,
                )
        finally:
            env.close()
    return out, time.perf_counter() - start


def run_here(args: argparse.Namespace, demos: Path, saved: Path) -> tuple[list[dict[str, Any]], float]:
    print(f"this harness: {args.tasks} tasks x {args.episodes} episodes of libero/{args.suite}")
    return here(args, PlaybackParams(str(demos), gripper=args.gripper), saved)


def compare(ours: dict[str, Any], theirs: dict[str, Any]) -> dict[str, Any]:
    a, b = ours["actions"], np.asarray(theirs["actions"], np.float32)
    s, t = ours["states"], np.asarray(theirs["states"], np.float32)
    n = min(len(a), len(b))
    state_diff = np.abs(s[:n] - t[:n]).max(axis=1) if n else np.zeros(0)
    differs = np.flatnonzero(state_diff > 0)
    return {
        "task_idx": ours["task_idx"],
        "episode": ours["episode"],
        "success": [ours["success"], theirs["success"]],
        "steps": [ours["steps"], theirs["steps"]],
        "max_action_diff": float(np.abs(a[:n] - b[:n]).max()) if n else 0.0,
        "max_state_diff": float(state_diff.max()) if n else 0.0,
        "first_state_difference": int(differs[0]) if len(differs) else None,
        "agree": ours["success"] == theirs["success"]
        and ours["steps"] == theirs["steps"]
        and not len(differs),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--suite", default="spatial", choices=("spatial", "object", "goal", "10"))
    parser.add_argument("--tasks", type=int, default=10, help="the suite's first N tasks (default 10)")
    parser.add_argument("--episodes", type=int, default=5, help="episodes (initial states 0..N-1) per task")
    parser.add_argument("--demos", default="", help="the expert's episodes (default demos/vlaeval-<suite>)")
    parser.add_argument("--gripper", default="sign", choices=("sign", "as_recorded"))
    parser.add_argument(
        "--image-size",
        type=int,
        default=256,
        help="this harness's camera size (default 256, vla-eval's); playback reads no image and the "
        "cameras move no physics, so a small one only saves rendering",
    )
    parser.add_argument("--vla-eval-python", default=sys.executable, help="an interpreter with vla-eval")
    parser.add_argument(
        "--work", default="", help="where vla-eval writes (default runs/vlaeval-agreement-<suite>)"
    )
    parser.add_argument(
        "--json", default="", help="default benchmarks/results/vlaeval-agreement-<suite>.json"
    )
    parser.add_argument(
        "--first-task", type=int, default=0, help="this harness's side from task N (with --here-only)"
    )
    parser.add_argument("--here-only", action="store_true", help="run this harness's side only (saved)")
    parser.add_argument(
        "--compare-only",
        action="store_true",
        help="compare the saved side here with what vla-eval recorded in --work so far",
    )
    args = parser.parse_args()

    demos = Path(args.demos or REPO / "demos" / f"vlaeval-{args.suite}").resolve()
    work = Path(args.work or REPO / "runs" / f"vlaeval-agreement-{args.suite}").resolve()
    load_before = uptime()
    collect(args.suite, args.tasks, args.episodes, demos)
    playback = f"playback:demos={demos},gripper={args.gripper}"
    suite = f"libero/{args.suite}:obs=upstream,seeding=openpi"
    work.mkdir(parents=True, exist_ok=True)
    saved = work / "here.pkl"  # ours, so a vla-eval run stopped early still compares (--compare-only)
    there_s = None
    if args.compare_only:
        ours, here_s = pickle.loads(saved.read_bytes())
    elif args.here_only:
        ours, here_s = run_here(args, demos, saved)
    else:
        with served(playback, suite, work / "serve.log") as url, ThreadPoolExecutor(1) as pool:
            # vla-eval runs in its own processes while this one runs ours: the two share no
            # state, and on a shared machine the pair takes about the time of the slower one
            print("vla-eval: its LIBERO benchmark against dvla-harness serve --protocol vla-eval")
            config = vla_eval_config(
                url, args.suite, args.episodes, args.tasks, fresh_output(work / "results")
            )
            there = pool.submit(vla_eval_run, args.vla_eval_python, config, work)
            ours, here_s = run_here(args, demos, saved)
            there_s = round(there.result()[0], 1)
    if args.here_only:
        print(f"wrote {saved}")
        return
    theirs = {(e["task_idx"], e["episode"]): e for e in recorded_episodes(work / "results")}
    rows = [
        compare(o, theirs[(o["task_idx"], o["episode"])])
        for o in ours
        if (o["task_idx"], o["episode"]) in theirs
    ]
    missing = [(o["task_idx"], o["episode"]) for o in ours if (o["task_idx"], o["episode"]) not in theirs]

    print(
        f"\n{'task':>4} {'ep':>3} {'success here/vla-eval':>22} {'steps':>10} {'max |d action|':>15} {'max |d state|':>14}"
    )
    for r in rows:
        s, n = r["success"], r["steps"]
        print(
            f"{r['task_idx']:>4} {r['episode']:>3} {str(s[0]) + ' / ' + str(s[1]):>22} {f'{n[0]}/{n[1]}':>10} "
            f"{r['max_action_diff']:>15.3g} {r['max_state_diff']:>14.3g}"
            + ("" if r["agree"] else f"  DIFFERS from step {r['first_state_difference']}")
        )
    agree = sum(r["agree"] for r in rows)
    print(f"\nagree on {agree} of {len(rows)} episodes (success, steps, every post-step state bit for bit)")
    if missing:
        print(f"vla-eval recorded no episode for {missing}")
    result = {
        "benchmark": "vlaeval_agreement",
        "suite": f"libero/{args.suite}",
        "tasks": args.tasks,
        "episodes_per_task": args.episodes,
        "policy": playback.replace(str(REPO) + "/", ""),
        "image_size_here": args.image_size,
        "command": " ".join(["python", "benchmarks/vlaeval_agreement.py", *sys.argv[1:]]),
        "agree": agree,
        "compared": len(rows),
        "missing": missing,
        "success_here": sum(r["success"][0] for r in rows),
        "success_vla_eval": sum(r["success"][1] for r in rows),
        "seconds_here": round(here_s, 1),
        "seconds_vla_eval": there_s,
        "episodes": rows,
        "versions_here": versions(sys.executable),
        "versions_vla_eval": versions(args.vla_eval_python),
        "machine": machine() | {"uptime_before": load_before, "uptime_after": uptime()},
    }
    path = Path(args.json or REPO / "benchmarks" / "results" / f"vlaeval-agreement-{args.suite}.json")
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
