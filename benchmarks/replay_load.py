"""Why the replay's paired ratio moves with load: wall time against CPU time, per call.

The replay benchmark (harness/bench.py) times fast_dvla and bidirectional decoding the
same observations, interleaved call by call, and the gate judges the ratio of their
seconds per chunk. On a loaded machine an unchanged tree read a few percent slower than
the idle baseline. This script finds out where that comes from. In one process it loads
the committed baseline's policies and recorded observations and times rounds exactly as
`bench` does, under conditions it starts and kills itself (every load has a time limit
of its own, so nothing outlives the script):

- `idle`: as the machine is;
- `busy1`, `busy2`: one or two `python -c 'while True: pass'` beside it (busy2 takes
  both cores of a 2-core machine, so the decoder waits for a core part of the time);
- `mem1`, `mem2`: one or two processes copying a 64 MB numpy array over and over,
  which take cores and also evict the shared cache and use memory bandwidth.

Conditions alternate in blocks (idle, busy1, ..., then again), so a load that other
people put on the machine meanwhile falls on all of them. Each call records its wall
time, its thread CPU time and its involuntary context switches. Per condition it
prints: the median per-round ratio (fast_dvla / bidirectional seconds per chunk) from
wall time and from CPU time, each decoder's wall/CPU factor, and preemptions per call.

    OMP_NUM_THREADS=1 python benchmarks/replay_load.py [--rounds 8] [--blocks 3]
        [--conditions idle,busy1,busy2,mem1,mem2] [--json benchmarks/results/replay_load.json]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

BASELINE = ROOT / "results/baselines/metaworld-mt10-smoke"
LOADS = {
    "idle": [],
    "busy1": ["while True: pass"],
    "busy2": ["while True: pass"] * 2,
    "mem1": ["import numpy as np\na = np.ones(1 << 23); b = np.empty_like(a)\nwhile True: np.copyto(b, a)"],
    "mem2": ["import numpy as np\na = np.ones(1 << 23); b = np.empty_like(a)\nwhile True: np.copyto(b, a)"]
    * 2,
}


def load(condition: str, limit_s: float) -> Any:
    """The condition's load processes (benchmarks/gate_stability.py's bounded_load: each
    under `timeout`, killed on the way out)."""
    from benchmarks.gate_stability import bounded_load

    return bounded_load([[sys.executable, "-c", code] for code in LOADS[condition]], limit_s, settle_s=2.0)


def baseline_figures() -> tuple[float, float]:
    """The committed baseline bench's median ratio and the reference's median s/chunk."""
    configs = {c["policy"]: c for c in json.loads((BASELINE / "replay.json").read_text())["configurations"]}
    fast, ref = configs["fast_dvla"]["round_chunk_s"], configs["bidirectional"]["round_chunk_s"]
    return statistics.median(a / b for a, b in zip(fast, ref, strict=True)), statistics.median(ref)


def pass_flop_fit(fast_ms: float, reference_ms: float) -> tuple[float, float]:
    """ms per chunk = a x passes + b x GFLOP, solved over the two decoders (the baseline
    bench's NFE and dispatcher work per chunk): a is what one pass costs beyond its
    arithmetic (dispatch, Python, reading the weights), b what a GFLOP costs."""
    import numpy as np

    configs = {c["policy"]: c for c in json.loads((BASELINE / "replay.json").read_text())["configurations"]}
    shape = [
        [configs[p]["nfe_per_chunk"], configs[p]["flops_per_chunk"] / 1e9]
        for p in ("fast_dvla", "bidirectional")
    ]
    a, b = np.linalg.solve(np.array(shape), np.array([fast_ms, reference_ms]))
    return float(a), float(b)


def preemption_fit(rounds: list[dict], policy: str) -> tuple[float, float]:
    """CPU ms per call = a + k * preemptions per call, least squares over the rounds: k is
    what one preemption costs the decoder in CPU time, a its CPU time with none."""
    import numpy as np

    cpu = np.array([r[f"{policy}_cpu"] / r["calls"] for r in rounds]) * 1e3
    pre = np.array([r[f"{policy}_preempted"] / r["calls"] for r in rounds])
    a, k = np.linalg.lstsq(np.vstack([np.ones_like(pre), pre]).T, cpu, rcond=None)[0]
    return float(a), float(k)


def setup() -> tuple[list[Any], list[Any], list[Any]]:
    from harness import bench
    from harness.commands.bench import _resolved
    from results.store import RunDir

    run = RunDir(BASELINE)
    resolved, _ = _resolved(run)
    recorded = bench.load_observations(BASELINE / "replay_observations.npz")
    contexts = bench.episode_contexts(resolved, recorded)
    timed = [p for p in resolved.policies if p.spec.name in ("fast_dvla", "bidirectional")]
    timed.sort(key=lambda p: p.spec.name != "fast_dvla")  # fast_dvla first, the reference second
    for p in timed:
        bench.warm_up_pass(p.policy, contexts, recorded.observations)
    return timed, contexts, recorded.observations


def one_round(timed: list[Any], contexts: list[Any], observations: list[Any], r: int) -> list[dict]:
    """Every observation decoded once by each policy, interleaved with a rotating start as
    harness/bench.py's time_rounds does; one record per call."""
    import gc

    from harness.bench import fresh

    calls = []
    gc.collect()
    gc.disable()
    try:
        for j, (context, obs) in enumerate(zip(contexts, observations, strict=True)):
            shift = (r + j) % len(timed)
            for p in [*timed[shift:], *timed[:shift]]:
                p.policy.reset([context])
                mine = fresh(obs)
                switches = resource.getrusage(resource.RUSAGE_THREAD).ru_nivcsw
                cpu, wall = time.thread_time(), time.perf_counter()
                p.policy.act([mine])
                wall, cpu = time.perf_counter() - wall, time.thread_time() - cpu
                switches = resource.getrusage(resource.RUSAGE_THREAD).ru_nivcsw - switches
                calls.append({"policy": p.spec.name, "wall": wall, "cpu": cpu, "preempted": switches})
    finally:
        gc.enable()
    return calls


def summarise(rounds: list[list[dict]]) -> dict[str, Any]:
    def total(calls: list[dict], policy: str, key: str) -> float:
        return sum(c[key] for c in calls if c["policy"] == policy)

    wall = [total(c, "fast_dvla", "wall") / total(c, "bidirectional", "wall") for c in rounds]
    cpu = [total(c, "fast_dvla", "cpu") / total(c, "bidirectional", "cpu") for c in rounds]
    out: dict[str, Any] = {
        "rounds": len(rounds),
        "ratio_wall": statistics.median(wall),
        "ratio_cpu": statistics.median(cpu),
        "ratio_wall_spread": statistics.pstdev(wall) / statistics.fmean(wall),
        "ratio_cpu_spread": statistics.pstdev(cpu) / statistics.fmean(cpu),
    }
    for policy in ("fast_dvla", "bidirectional"):
        calls = [c for r in rounds for c in r if c["policy"] == policy]
        out[f"{policy}_ms_wall"] = 1e3 * statistics.median(c["wall"] for c in calls)
        out[f"{policy}_ms_cpu"] = 1e3 * statistics.median(c["cpu"] for c in calls)
        out[f"{policy}_wall_over_cpu"] = sum(c["wall"] for c in calls) / sum(c["cpu"] for c in calls)
        out[f"{policy}_preempted_per_call"] = statistics.fmean(c["preempted"] for c in calls)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=8, help="rounds per condition and block")
    parser.add_argument("--blocks", type=int, default=3, help="times each condition comes round")
    parser.add_argument("--conditions", default="idle,busy1,busy2,mem1,mem2")
    parser.add_argument("--json", default=str(ROOT / "benchmarks/results/replay_load.json"))
    args = parser.parse_args(argv)
    conditions = [c for c in args.conditions.split(",") if c]
    bad = [c for c in conditions if c not in LOADS]
    if bad:
        parser.error(f"unknown condition(s) {', '.join(bad)}; valid: {', '.join(LOADS)}")
    import torch

    torch.set_num_threads(1)
    timed, contexts, observations = setup()
    by_condition: dict[str, list[list[dict]]] = {c: [] for c in conditions}
    loads: dict[str, list[float]] = {c: [] for c in conditions}
    r = 0
    for _ in range(args.blocks):
        for condition in conditions:
            with load(condition, limit_s=120 + 10 * args.rounds):
                loads[condition].append(os.getloadavg()[0])
                for _ in range(args.rounds):
                    by_condition[condition].append(one_round(timed, contexts, observations, r))
                    r += 1
                loads[condition].append(os.getloadavg()[0])
    summary = []
    base_ratio, base_reference = baseline_figures()
    per_round = [
        {
            "condition": condition,
            "calls": len(observations),
            **{
                f"{policy}_{key}": sum(c[key] for c in calls if c["policy"] == policy)
                for policy in ("fast_dvla", "bidirectional")
                for key in ("wall", "cpu", "preempted")
            },
        }
        for condition, rounds in by_condition.items()
        for calls in rounds
    ]
    print(
        f"{'condition':<9} {'load':>9} {'ratio wall':>10} {'ratio cpu':>9} {'change':>7} {'busier':>6} "
        f"{'fast w/c':>8} {'bidi w/c':>8} {'fast preempt':>12} {'bidi preempt':>12} {'fast ms cpu':>11} "
        f"{'bidi ms cpu':>11} {'ms/pass':>7} {'ms/GFLOP':>8}"
    )
    for condition in conditions:
        s = {"condition": condition, "load_1m": [min(loads[condition]), max(loads[condition])]}
        s |= summarise(by_condition[condition])
        s["busier"] = s["bidirectional_ms_cpu"] / (1e3 * base_reference)  # the verdict line's factor
        s["change_vs_baseline"] = base_ratio / s["ratio_wall"] - 1  # as the gate reads an unchanged tree
        s["ms_per_pass"], s["ms_per_gflop"] = pass_flop_fit(s["fast_dvla_ms_cpu"], s["bidirectional_ms_cpu"])
        summary.append(s)
        print(
            f"{condition:<9} {s['load_1m'][0]:>4.1f}-{s['load_1m'][1]:<4.1f} {s['ratio_wall']:>10.4f} "
            f"{s['ratio_cpu']:>9.4f} {s['change_vs_baseline']:>+7.1%} {s['busier']:>6.2f} "
            f"{s['fast_dvla_wall_over_cpu']:>8.3f} "
            f"{s['bidirectional_wall_over_cpu']:>8.3f} {s['fast_dvla_preempted_per_call']:>12.2f} "
            f"{s['bidirectional_preempted_per_call']:>12.2f} {s['fast_dvla_ms_cpu']:>11.2f} "
            f"{s['bidirectional_ms_cpu']:>11.2f} {s['ms_per_pass']:>7.2f} {s['ms_per_gflop']:>8.1f}"
        )
    fits = {policy: preemption_fit(per_round, policy) for policy in ("fast_dvla", "bidirectional")}
    for policy, (a, k) in fits.items():
        print(
            f"{policy}: CPU ms per call = {a:.2f} + {k:.3f} x preemptions per call (least squares over the rounds)"
        )
    configs = {c["policy"]: c for c in json.loads((BASELINE / "replay.json").read_text())["configurations"]}
    base_fit = pass_flop_fit(*(1e3 * configs[p]["median_chunk_s"] for p in ("fast_dvla", "bidirectional")))
    print(
        f"baseline bench (idle): ratio {base_ratio:.4f}, bidirectional {1e3 * base_reference:.2f} ms per chunk, "
        f"{base_fit[0]:.2f} ms per pass + {base_fit[1]:.1f} ms per GFLOP (wall)"
    )
    from harness.run.manifest import environment
    from results.cpu_identity import describe_cpu

    meta = {
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "cpu": describe_cpu(environment()),
        "baseline_ratio": base_ratio,
        "baseline_reference_s": base_reference,
        "preemption_fits_ms": fits,
        "baseline_ms_per_pass_and_gflop": base_fit,
        "cpus": os.cpu_count(),
        "command": "OMP_NUM_THREADS=1 python benchmarks/replay_load.py " + " ".join(argv or sys.argv[1:]),
    }
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"meta": meta, "summary": summary, "rounds": per_round}, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
