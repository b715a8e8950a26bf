"""The main job at --threads 1 and --threads 2, on an idle machine and under a CPU load.

Why: torch's intra-op threads spin while they wait, so on a machine with other jobs a
second thread can cost far more than it gains for the shipped models (the
main job took 56 minutes beside other jobs and 2 minutes idle). `run` therefore
defaults to 1 thread per worker; this benchmark checks that choice, idle and beside N
busy loops (`python -c 'while True: pass'`, started here and always killed here).

In each condition the same config runs at 1 and at 2 threads, one after the other (the
order alternates between conditions), each through the CLI (`python -m harness run
--threads N --quiet --out DIR`) in its own process and temporary run folder: torch's
inter-op pool is fixed once per process, and a run past its time box is stopped with
SIGTERM (the harness keeps its finished episodes). 2-thread runs under load can take
10x longer, so the comparison is over the episodes both runs finished:

- wall-clock and policy time summed over those episodes, per thread count, and their
  ratio (2 threads / 1 thread: above 1 means the second thread costs time);
- tokens/s = sum(action_tokens_total) / sum(policy_time_s) over them;
- whether successes and steps are identical, and how many episodes differ in any
  column that is not timing or provenance (results.schema);
- the 1-minute load average before and after each run, the CPU model, torch's version.

    python benchmarks/threads.py [--config FILE] [--tasks 0,1] [--episodes-per-task 3]
                                 [--conditions idle,load] [--load-procs 2] [--time-box 900]
                                 [--json benchmarks/results/threads.json]

With no --config it is the README's main job (harness/defaults/main.toml: MT10, five
decoders, 3 episodes per task): run it on an otherwise idle machine, or the "idle"
condition is not idle (its load average says so).
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import pandas as pd

from harness.threads import physical_cores
from results.schema import PROVENANCE_COLUMNS, TIMING_COLUMNS
from results.store import RunDir

ROOT = Path(__file__).resolve().parent.parent
THREADS = (1, 2)
CONDITIONS = ("idle", "load")
KEY = ["task", "episode_index", "policy_config_id"]
NOT_RESULTS = TIMING_COLUMNS | PROVENANCE_COLUMNS  # when, where or how fast: not what happened
GRACE_S = 60.0  # after SIGTERM, time to write what finished before SIGKILL


def _die_with_parent() -> None:
    """In a child, before exec: Linux sends it SIGKILL when this script dies, however it dies."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass  # not Linux: the finally blocks still kill the children on a normal exit


def load1() -> float:
    return round(os.getloadavg()[0], 2)


def start_load(n: int) -> list[subprocess.Popen]:
    return [
        subprocess.Popen([sys.executable, "-c", "while True: pass"], preexec_fn=_die_with_parent)
        for _ in range(n)
    ]


def stop(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        p.kill()
    for p in procs:
        p.wait()


def timed_run(args: argparse.Namespace, threads: int, out: Path, time_box: float) -> dict[str, Any]:
    """One run through the CLI at `threads`, stopped at `time_box` seconds; its rows in `_rows`."""
    command = [
        sys.executable,
        "-m",
        "harness",
        "run",
        "--threads",
        str(threads),
        "--quiet",
        "--out",
        str(out),
    ]
    if args.config:
        command += ["--config", args.config]
    if args.tasks:
        command += ["--tasks", args.tasks]
    if args.episodes_per_task is not None:
        command += ["--episodes-per-task", str(args.episodes_per_task)]
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    log = out.with_suffix(".log")
    before, start, stopped = load1(), time.perf_counter(), False
    with log.open("w") as sink:
        proc = subprocess.Popen(
            command, cwd=ROOT, env=env, stdout=sink, stderr=subprocess.STDOUT, preexec_fn=_die_with_parent
        )
        try:
            proc.wait(timeout=time_box)
        except subprocess.TimeoutExpired:
            stopped = True
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=GRACE_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        finally:
            if proc.poll() is None:  # this script interrupted: leave no run behind
                proc.kill()
                proc.wait()
    wall = time.perf_counter() - start
    run_dir = RunDir(out)
    rows = run_dir.read_episodes() if run_dir.is_run() else pd.DataFrame(columns=KEY)
    manifest = json.loads(run_dir.manifest_path.read_text()) if run_dir.is_run() else {}
    per_task = manifest.get("config", {}).get("episodes_per_task")
    planned = (
        len(manifest["suite"]["tasks"]) * per_task * len(manifest["policies"])
        if manifest and per_task
        else None
    )
    if proc.returncode not in (0, 130) and not stopped:
        print(f"  threads {threads}: exit {proc.returncode}; last lines of {log}:", file=sys.stderr)
        print("\n".join(log.read_text().splitlines()[-15:]), file=sys.stderr)
    return {
        "threads": threads,
        "exit_status": proc.returncode,
        "stopped_at_time_box": stopped,
        "episodes": len(rows),
        "episodes_planned": planned,
        "run_wall_s": round(wall, 2),
        "load1_before": before,
        "load1_after": load1(),
        "torch_threads": {k: manifest.get("threads", {}).get(k) for k in ("torch_intra_op", "torch_interop")},
        "_rows": rows,
        "_environment": manifest.get("environment", {}),
    }


def compare(a: pd.DataFrame, b: pd.DataFrame) -> dict[str, Any]:
    """Over the episodes both runs finished: time per run, ratio b/a, and what differs."""
    if a.empty or b.empty:
        return {"common_episodes": 0}
    merged = a.merge(b, on=KEY, suffixes=("_a", "_b"))
    out: dict[str, Any] = {"common_episodes": len(merged)}
    for column, name in (("wall_clock_s", "wall_clock"), ("policy_time_s", "policy_time")):
        sa, sb = float(merged[column + "_a"].sum()), float(merged[column + "_b"].sum())
        out[f"{name}_s"] = [round(sa, 2), round(sb, 2)]
        out[f"{name}_ratio"] = round(sb / sa, 3) if sa > 0 else None
    tokens = [float(merged[f"action_tokens_total_{s}"].sum()) for s in "ab"]
    policy = out["policy_time_s"]
    out["tokens_per_s"] = [round(t / p, 1) if p > 0 else None for t, p in zip(tokens, policy, strict=True)]
    out["same_successes_and_steps"] = bool(
        (merged["success_a"] == merged["success_b"]).all() and (merged["steps_a"] == merged["steps_b"]).all()
    )
    columns = [c for c in a.columns if c in b.columns and c not in NOT_RESULTS and c not in KEY]
    left, right = (
        merged[[c + "_a" for c in columns]].to_numpy(),
        merged[[c + "_b" for c in columns]].to_numpy(),
    )
    same = (left == right) | (pd.isna(left) & pd.isna(right))
    out["episodes_differing"] = int((~same.all(axis=1)).sum())
    return out


def fmt_pair(values: list | None, ratio: float | None = None, unit: str = "") -> str:
    if not values:
        return "-"
    text = " / ".join("-" if v is None else f"{v:,.{1 if abs(v) < 100 else 0}f}{unit}" for v in values)
    return text + (f" ({ratio:.1f}x)" if ratio is not None else "")


def table(result: dict[str, Any]) -> str:
    lines = [
        "| condition | episodes finished (1 thread / 2 threads) | common episodes | wall-clock over the "
        "common episodes | policy time | tokens/s | same successes and steps | 1-min load before -> after |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, c in result["conditions"].items():
        runs = {r["threads"]: r for r in c["runs"]}
        cmp = c["comparison"]
        finished = " / ".join(str(runs[t]["episodes"]) for t in THREADS)
        loads = "; ".join(f"{t}t {runs[t]['load1_before']} -> {runs[t]['load1_after']}" for t in THREADS)
        label = name + (f" ({c['load_procs']} busy loops)" if c["load_procs"] else "")
        lines.append(
            f"| {label} | {finished} | {cmp['common_episodes']} | "
            f"{fmt_pair(cmp.get('wall_clock_s'), cmp.get('wall_clock_ratio'), ' s')} | "
            f"{fmt_pair(cmp.get('policy_time_s'), cmp.get('policy_time_ratio'), ' s')} | "
            f"{fmt_pair(cmp.get('tokens_per_s'))} | {cmp.get('same_successes_and_steps', '-')} | {loads} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--config", metavar="FILE", help="run config TOML (default: the embedded main job)")
    parser.add_argument(
        "--tasks", metavar="NAME_OR_INDEX,...", help="only these tasks (passed to `run --tasks`)"
    )
    parser.add_argument(
        "--episodes-per-task", type=int, metavar="N", help="default: the config's (main job: 3)"
    )
    parser.add_argument("--conditions", default=",".join(CONDITIONS), help="comma-separated: idle, load")
    parser.add_argument(
        "--load-procs", type=int, default=2, metavar="N", help="busy loops in 'load' (default 2)"
    )
    parser.add_argument(
        "--time-box",
        type=float,
        default=900.0,
        metavar="SECONDS",
        help="stop a run after this long (SIGTERM; its finished episodes are kept) (default 900)",
    )
    parser.add_argument("--json", default="benchmarks/results/threads.json")
    args = parser.parse_args()
    conditions = [c.strip() for c in args.conditions.split(",") if c.strip()]
    if unknown := set(conditions) - set(CONDITIONS):
        parser.error(f"unknown condition(s) {sorted(unknown)}; choose from {', '.join(CONDITIONS)}")
    # SIGTERM to this script: unwind through the finally blocks, so no busy loop outlives it.
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    result: dict[str, Any] = {
        "machine": {
            "cpus": os.cpu_count(),
            "physical_cores": physical_cores(),
            "platform": platform.platform(),
            "load1_before": load1(),
        },
        "config": args.config or "embedded main job (harness/defaults/main.toml)",
        "tasks": args.tasks,
        "episodes_per_task": args.episodes_per_task,
        "time_box_s": args.time_box,
        "conditions": {},
        "load_pids": [],
    }
    with tempfile.TemporaryDirectory(prefix="threads-bench-") as tmp:
        for i, name in enumerate(conditions):
            n = args.load_procs if name == "load" else 0
            order = THREADS if i % 2 == 0 else THREADS[::-1]
            load = start_load(n)
            result["load_pids"] += [p.pid for p in load]
            try:
                time.sleep(2.0 if n else 0.0)  # let the busy loops get going
                runs = []
                for threads in order:
                    runs.append(timed_run(args, threads, Path(tmp) / f"{name}-t{threads}", args.time_box))
                    r = runs[-1]
                    print(
                        f"{name:5} threads {threads}: {r['episodes']} episodes in {r['run_wall_s']:.1f} s"
                        f"{' (time box)' if r['stopped_at_time_box'] else ''}, exit {r['exit_status']}, "
                        f"load {r['load1_before']} -> {r['load1_after']}",
                        flush=True,
                    )
            finally:
                stop(load)
            env = runs[0]["_environment"]
            result["machine"].setdefault("cpu", env.get("cpu"))
            result["machine"].setdefault("torch", env.get("packages", {}).get("torch"))
            runs.sort(key=lambda r: r["threads"])
            result["conditions"][name] = {
                "load_procs": n,
                "order": list(order),
                "runs": [{k: v for k, v in r.items() if not k.startswith("_")} for r in runs],
                "comparison": compare(runs[0]["_rows"], runs[1]["_rows"]),
            }
    result["machine"]["load1_after"] = load1()
    print()
    print(table(result))
    m = result["machine"]
    print(f"\nCPU: {m.get('cpu')} ({m['physical_cores']} physical cores); torch {m.get('torch')}")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
