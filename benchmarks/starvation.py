"""Policy wall time / policy CPU time per episode, idle and beside busy loops.

Where harness/episode/cpu_time.py's STARVED_FACTOR comes from: "episodes" of a fixed torch
workload at one thread (the calibration block, harness/run/manifest.py; `--calls` policy
calls of `--passes` passes each, about 0.1 s of policy time per episode, like a short
Meta-World episode of the shipped decoders) are timed as the episode loop times them,
with perf_counter and the CPU clock harness/episode/cpu_time.py picks, once as the machine is and
once beside `--busy` busy loops (`python -c 'while True: pass'`, started here and killed
on the way out, whatever happens). Prints the ratio distribution of each condition,
how many episodes each factor would flag, and the load average beside it.

    OMP_NUM_THREADS=1 python benchmarks/starvation.py [--episodes 40] [--busy 2]
                                                      [--json benchmarks/results/starvation.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from harness.episode.cpu_time import STARVED_FACTOR, cpu_clock

FACTORS = (1.1, 1.25, 1.5, 2.0)


def workload() -> Any:
    """One forward pass of the calibration block (x + attention, + MLP; 1x16x64)."""
    torch.manual_seed(0)
    attn = torch.nn.MultiheadAttention(64, 4, batch_first=True).eval()
    mlp = torch.nn.Sequential(torch.nn.Linear(64, 256), torch.nn.GELU(), torch.nn.Linear(256, 64)).eval()
    x = torch.randn(1, 16, 64)

    def block() -> None:
        with torch.inference_mode():
            h = x + attn(x, x, x, need_weights=False)[0]
            h + mlp(h)

    return block


def episode_ratios(episodes: int, calls: int, passes: int) -> list[float]:
    """policy wall / policy CPU time of each episode, summed over its calls as the loop does."""
    block = workload()
    for _ in range(20):
        block()
    cpu = cpu_clock(None)
    ratios = []
    for _ in range(episodes):
        wall = used = 0.0
        for _ in range(calls):
            c, t = cpu(), time.perf_counter()
            for _ in range(passes):
                block()
            wall += time.perf_counter() - t
            used += cpu() - c
        ratios.append(wall / used)
    return ratios


def summary(ratios: list[float]) -> dict[str, Any]:
    r = np.asarray(ratios)
    return {
        "episodes": len(r),
        "min": round(float(r.min()), 3),
        "median": round(float(np.median(r)), 3),
        "p90": round(float(np.quantile(r, 0.9)), 3),
        "max": round(float(r.max()), 3),
        "flagged": {str(f): int((r > f).sum()) for f in FACTORS},
    }


def measure(label: str, busy: int, args: argparse.Namespace) -> dict[str, Any]:
    loops = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(busy)]
    try:
        time.sleep(1.0 if busy else 0.0)
        load_before = os.getloadavg()[0]
        ratios = episode_ratios(args.episodes, args.calls, args.passes)
        load_after = os.getloadavg()[0]
    finally:
        for loop in loops:
            loop.kill()
            loop.wait()
    out = {"condition": label, "busy_loops": busy, "load_1min": [load_before, load_after]}
    out |= summary(ratios) | {"ratios": [round(x, 3) for x in ratios]}
    print(
        f"{label:>16}: episodes {out['episodes']}, ratio min {out['min']} median {out['median']} "
        f"p90 {out['p90']} max {out['max']}; flagged at factor {out['flagged']}; "
        f"load {load_before:.1f} -> {load_after:.1f}"
    )
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--episodes", type=int, default=40)
    p.add_argument("--calls", type=int, default=10, help="policy calls per episode")
    p.add_argument("--passes", type=int, default=40, help="forward passes per call")
    p.add_argument("--busy", type=int, default=2, help="busy loops beside the second condition")
    p.add_argument("--json", type=Path)
    args = p.parse_args()
    for name in ("episodes", "calls", "passes", "busy"):
        if getattr(args, name) < 1:
            p.error(f"--{name} must be at least 1, got {getattr(args, name)}")
    torch.set_num_threads(1)
    print(f"CPU clock: {cpu_clock(None).__name__}; STARVED_FACTOR {STARVED_FACTOR}; {os.cpu_count()} CPUs")
    results = [measure("as it is", 0, args), measure(f"{args.busy} busy loops", args.busy, args)]
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"factor": STARVED_FACTOR, "conditions": results}, indent=1) + "\n")


if __name__ == "__main__":
    main()
