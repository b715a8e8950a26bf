"""Remote vs local: the shipped fast_dvla on MT10, in this process and served over loopback.

`dvla-harness serve` runs the decoder in a second process; one `dvla-harness run` then
interleaves the `remote` policy (through the server) and the local decoder episode by
episode, on the same episodes, so both see the same machine load. Reported: control Hz
of each, the transport share of wall-clock and per call (the remote call's time minus the
server's own policy time), and whether success, steps and NFE are identical per episode.

    python benchmarks/remote.py [--episodes 3] [--tasks reach-v3,push-v3] [--batch-envs K] [--json PATH]

With --batch-envs K both policies step K envs in lockstep (one `dvla/batch` message per
call for the remote one); transport is then reported per observation served (a call
serves up to K), the amortised figure.

Targets: transport <= 1 ms per call on loopback with state observations, and
the remote path's success and NFE identical to the local path's.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import pandas as pd

REPO = Path(__file__).resolve().parent.parent
TARGET_MS = 1.0


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--episodes", type=int, default=3, help="episodes per task (default 3)")
    parser.add_argument("--tasks", default="", help="comma-separated MT10 tasks (default: all ten)")
    parser.add_argument("--batch-envs", type=int, default=1, help="envs per policy call (default 1)")
    parser.add_argument("--json", default="", help="default benchmarks/results/remote[-batchK].json")
    args = parser.parse_args()
    env = os.environ | {"OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    server = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "harness",
            "serve",
            "--policy",
            "fast_dvla",
            "--suite",
            "metaworld/mt10",
            "--port",
            "0",
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env | {"COLUMNS": "200"},
    )
    try:
        line = server.stdout.readline()
        match = re.search(r"on (ws://[0-9.]+:[0-9]+)", line)
        if not match:
            raise SystemExit(f"the server did not start: {line}{server.stdout.read()}")
        with tempfile.TemporaryDirectory() as tmp:
            command = [sys.executable, "-m", "harness", "run", "--suite", "metaworld/mt10"]
            command += ["--policy", f"remote:url={match.group(1)}", "--policy", "fast_dvla"]
            command += ["--episodes-per-task", str(args.episodes), "--out", f"{tmp}/run", "--quiet"]
            command += ["--tasks", args.tasks] if args.tasks else []
            command += ["--batch-envs", str(args.batch_envs)]
            subprocess.run(command, cwd=REPO, env=env, check=False)
            rows = pd.read_parquet(f"{tmp}/run/episodes.parquet")
    finally:
        server.terminate()
        server.wait(timeout=30)
    key = ["task", "episode_index"]
    remote = rows[rows["policy"] == "remote"].set_index(key).sort_index()
    local = rows[rows["policy"] == "fast_dvla"].set_index(key).sort_index()
    same = {c: bool((remote[c] == local[c]).all()) for c in ("success", "steps", "nfe_total")}
    # act calls (observations served, when batched) and one reset per episode
    calls = int(remote["chunks"].sum()) + len(remote)
    transport = float(remote["transport_time_s"].sum())
    result = {
        "benchmark": "remote",
        "suite": "metaworld/mt10",
        "episodes": len(remote),
        "batch_envs": args.batch_envs,
        "identical": same,
        "success_remote": int(remote["success"].sum()),
        "success_local": int(local["success"].sum()),
        "control_hz_remote": round(float(remote["steps"].sum() / remote["policy_time_s"].sum()), 1),
        "control_hz_local": round(float(local["steps"].sum() / local["policy_time_s"].sum()), 1),
        "calls": calls,
        # per call when unbatched; per observation served when batched (a call serves up to K)
        "transport_ms_per_call": round(1000 * transport / calls, 3),
        "transport_share_of_wall_clock": round(transport / float(remote["wall_clock_s"].sum()), 4),
        "target_ms_per_call": TARGET_MS,
        "machine": {"cpu": platform.processor() or platform.machine(), "python": platform.python_version()},
    }
    for name, value in result.items():
        if name not in ("machine", "benchmark"):
            print(f"{name:32}{value}")
    if args.batch_envs == 1:
        ok = result["transport_ms_per_call"] <= TARGET_MS and all(same.values())
        verdict = "PASS" if ok else "FAIL"
        print(f"target: transport <= {TARGET_MS} ms per call and identical outcomes: {verdict}")
    else:  # the target is per call, unbatched; a batch's figure is per observation served
        print(
            f"identical outcomes: {'PASS' if all(same.values()) else 'FAIL'} (the transport target is judged unbatched)"
        )
    path = Path(
        args.json
        or f"benchmarks/results/remote{'' if args.batch_envs == 1 else f'-batch{args.batch_envs}'}.json"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
