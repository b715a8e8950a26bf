"""Episodes per hour and CPU seconds per episode: vla-eval and this harness, the same
policy on the same LIBERO episodes, on this machine, back to back.

The policy is `playback` of the scripted expert's recorded episodes (the agreement
benchmark's, benchmarks/vlaeval_agreement.py, which shows both harnesses execute the
same actions to the same states on them), so the figures measure the harnesses and the
simulator, not a model. Each side runs at its best settings for one machine:

- vla-eval 0.8.0: `vla-eval run --no-docker` of its LIBERO benchmark, `--shards` shard
  processes sharing one eval id (its queue hands out episodes as shards free up), against
  the playback as a `PredictModelServer` of its own (benchmarks/vlaeval_playback_server.py),
  which asks for nothing beyond its default observation (the agentview image, PNG-encoded).
- this harness: `dvla-harness run --workers N` on `libero/<suite>:obs=upstream,seeding=openpi`,
  which renders the same two 256 px cameras vla-eval's LIBERO renders every step.
  `--also-state` adds a run on `obs=state`, which renders nothing: all a policy that reads
  no image needs, and not what vla-eval can do.

CPU seconds count every process each side starts (shards, model server, workers).

    python benchmarks/vlaeval_throughput.py --suite spatial --tasks 10 --episodes 5 --shards 2 --workers 2
"""

from __future__ import annotations

import argparse
import json
import resource
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.vlaeval_runs import (
    REPO,
    environment,
    fresh_output,
    machine,
    recorded_episodes,
    uptime,
    versions,
    vla_eval_config,
)


def children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_healthy(port: int, server: subprocess.Popen, seconds: float = 600) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if server.poll() is not None:
            raise SystemExit("the vla-eval model server exited before it was ready")
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=5):
                return
        except OSError:
            time.sleep(0.5)
    raise SystemExit("the vla-eval model server never answered /health")


def through_vla_eval(args: argparse.Namespace, demos: Path, work: Path) -> dict[str, Any]:
    port = free_port()
    env = environment()
    load, cpu = uptime(), children_cpu()
    server_cmd = [
        args.vla_eval_python,
        str(REPO / "benchmarks" / "vlaeval_playback_server.py"),
        "--demos",
        str(demos),
    ]
    server_cmd += ["--suite", f"libero/{args.suite}:seeding=openpi", "--port", str(port)]
    log = (work / "server.log").open("w")
    server = subprocess.Popen(server_cmd, stdout=log, stderr=subprocess.STDOUT, env=env)
    try:
        wait_healthy(port, server)
        config = vla_eval_config(
            f"ws://127.0.0.1:{port}", args.suite, args.episodes, args.tasks, fresh_output(work / "results")
        )
        config["benchmarks"][0]["params"].pop("quat_no_antipodal")  # its default: what its users run
        (work / "eval.yaml").write_text(json.dumps(config))
        command = [
            args.vla_eval_python,
            "-m",
            "vla_eval.cli.main",
            "run",
            "--no-docker",
            "-c",
            str(work / "eval.yaml"),
        ]
        command += ["--eval-id", "throughput"]
        start = time.perf_counter()
        shards = [
            subprocess.Popen(
                [*command, "--shard-id", str(i), "--num-shards", str(args.shards)],
                stdout=(work / f"shard{i}.log").open("w"),
                stderr=subprocess.STDOUT,
                env=env,
            )
            for i in range(args.shards)
        ]
        codes = [shard.wait() for shard in shards]
        wall = time.perf_counter() - start
    finally:
        server.terminate()
        server.wait(timeout=60)
        log.close()
    if any(codes):
        raise SystemExit(f"a vla-eval shard failed ({codes}); see {work}")
    episodes = recorded_episodes(work / "results")
    if len(episodes) != args.tasks * args.episodes:
        raise SystemExit(
            f"vla-eval recorded {len(episodes)} episodes, not {args.tasks * args.episodes}; see {work}"
        )
    return {
        "harness": f"vla-eval, {args.shards} shards, its own PredictModelServer",
        "episodes": len(episodes),
        "success": sum(e["success"] for e in episodes),
        "steps": sum(e["steps"] for e in episodes),
        "wall_s": round(wall, 1),
        "cpu_s": round(children_cpu() - cpu, 1),  # server start-up included, as a run includes it
        "uptime_before": load,
        "uptime_after": uptime(),
    }


def through_harness(args: argparse.Namespace, demos: Path, obs: str) -> dict[str, Any]:
    load, cpu = uptime(), children_cpu()
    with tempfile.TemporaryDirectory() as tmp:
        command = [
            sys.executable,
            "-m",
            "harness",
            "run",
            "--suite",
            f"libero/{args.suite}:obs={obs},seeding=openpi",
        ]
        command += [
            "--policy",
            f"playback:demos={demos},gripper=sign",
            "--tasks",
            ",".join(map(str, range(args.tasks))),
        ]
        command += [
            "--episodes-per-task",
            str(args.episodes),
            "--workers",
            str(args.workers),
            "--out",
            f"{tmp}/run",
        ]
        start = time.perf_counter()
        subprocess.run([*command, "--quiet"], cwd=REPO, env=environment(), check=False)
        wall = time.perf_counter() - start
        rows = pd.read_parquet(f"{tmp}/run/episodes.parquet")
    return {
        "harness": f"dvla-harness, --workers {args.workers}, obs={obs}",
        "episodes": len(rows),
        "success": int(rows.success.sum()),
        "steps": int(rows.steps.sum()),
        "wall_s": round(wall, 1),
        "cpu_s": round(children_cpu() - cpu, 1),
        "env_s": round(float(rows.env_time_s.sum()), 1),
        "policy_s": round(float(rows.policy_time_s.sum()), 1),
        "overhead_s": round(float(rows.overhead_s.sum()), 1),
        "uptime_before": load,
        "uptime_after": uptime(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--suite", default="spatial", choices=("spatial", "object", "goal", "10"))
    parser.add_argument("--tasks", type=int, default=10)
    parser.add_argument("--episodes", type=int, default=5, help="episodes per task")
    parser.add_argument("--shards", type=int, default=2, help="vla-eval shard processes (default 2)")
    parser.add_argument("--workers", type=int, default=2, help="this harness's worker processes (default 2)")
    parser.add_argument("--also-state", action="store_true", help="also run this harness on obs=state")
    parser.add_argument(
        "--demos", default="", help="default demos/vlaeval-<suite> (the agreement benchmark's)"
    )
    parser.add_argument("--vla-eval-python", default=sys.executable)
    parser.add_argument("--work", default="", help="default runs/vlaeval-throughput-<suite>")
    parser.add_argument(
        "--json", default="", help="default benchmarks/results/vlaeval-throughput-<suite>.json"
    )
    args = parser.parse_args()
    demos = Path(args.demos or REPO / "demos" / f"vlaeval-{args.suite}").resolve()
    if not (demos / "steps.parquet").is_file():
        raise SystemExit(f"{demos} holds no demonstrations: run benchmarks/vlaeval_agreement.py first")
    work = Path(args.work or REPO / "runs" / f"vlaeval-throughput-{args.suite}").resolve()
    work.mkdir(parents=True, exist_ok=True)
    runs = [through_vla_eval(args, demos, work)]
    runs.append(through_harness(args, demos, "upstream"))
    if args.also_state:
        runs.append(through_harness(args, demos, "state"))
    print(f"\n{'':52} {'episodes':>8} {'success':>7} {'episodes/h':>10} {'CPU s/episode':>13}")
    for run in runs:
        run["episodes_per_hour"] = round(3600 * run["episodes"] / run["wall_s"], 1)
        run["cpu_s_per_episode"] = round(run["cpu_s"] / run["episodes"], 2)
        print(
            f"{run['harness']:52} {run['episodes']:>8} {run['success']:>7} {run['episodes_per_hour']:>10} "
            f"{run['cpu_s_per_episode']:>13}   [{run['uptime_before'].split('load average:')[-1].strip()}]"
        )
    result = {
        "benchmark": "vlaeval_throughput",
        "suite": f"libero/{args.suite}",
        "command": " ".join(["python", "benchmarks/vlaeval_throughput.py", *sys.argv[1:]]),
        "runs": runs,
        "speedup_episodes_per_hour": round(runs[1]["episodes_per_hour"] / runs[0]["episodes_per_hour"], 2),
        "versions": versions(sys.executable),
        "machine": machine(),
    }
    path = Path(args.json or REPO / "benchmarks" / "results" / f"vlaeval-throughput-{args.suite}.json")
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"this harness / vla-eval, episodes per hour: {result['speedup_episodes_per_hour']}x\nwrote {path}")


if __name__ == "__main__":
    main()
