"""How often the CI gate cries wolf, and how often it catches a real slowdown, under load.

Why: a gate that fails an unchanged tree whenever the runner is busy gets switched off.
This benchmark runs the CI job of docs/ci-gate.md (`CI_COMMANDS`: the smoke run, its
replay benchmark, then the gate against the committed baseline) N times for each
candidate under each load condition, every command in its own process through the CLI,
and counts the gate's verdicts:

- candidates: `unchanged` (this tree); `slow15` (`fast_dvla` that spins, on the CPU, for
  a fixed fraction of every forward pass: NFE and counted work unchanged, only time);
  `morework` (`fast_dvla` that decodes every observation twice in one batch and keeps
  one copy: the same actions and NFE, twice the counted work per pass); `rawmatmul`
  (`fast_dvla`'s decoder running a `torch.matmul` on bare tensors after every forward
  pass, outside any module: about 16% more FLOPs per pass that the module hooks do not
  see, the same actions and NFE). The test policies live here, not in the product: the
  child process that runs the CLI swaps them in for the shipped `fast_dvla` (same name,
  params and checkpoint), so the gate pairs them with the baseline's `fast_dvla`
  exactly as it would a changed decoder;
- conditions: `idle`; `busyN` (N `python -c 'while True: pass'` beside it: busy2 takes
  both cores of a 2-core machine, busy8 makes a load average of about 10 there);
  `tests` (the test suite running beside it, restarted when it ends). Every load is
  started and killed here, also on Ctrl-C, and runs under `timeout` (--time-box times
  the trials of its condition), so none outlives the benchmark.

Printed: per condition and candidate, how many trials passed, failed and were
inconclusive, the false-alarm rate (unchanged: failures / N) or detection rate (the
others: failures / N), the median seconds of one CI job and the mean 1-minute load
average. Written: every trial's exit codes, verdict, failing lines and timings as JSON.

    python benchmarks/gate_stability.py [--n 10] [--conditions idle,busy2,tests]
        [--candidates unchanged,slow15,morework] [--slowdown 0.15]
        [--tests-command 'tox -e test'] [--tests-log FILE]
        [--json benchmarks/results/gate_stability.json]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shlex
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))  # run as a script from anywhere: the harness is this tree

BASELINE = "results/baselines/metaworld-mt10-smoke"
CONFIG = "results/baselines/metaworld-mt10-smoke.toml"
# The CI job of docs/ci-gate.md, command by command ({out}: the trial's run folder).
# tests/test_gate_stability.py checks that the docs' job runs exactly these.
CI_COMMANDS: tuple[tuple[str, ...], ...] = (
    ("run", "--config", CONFIG, "--out", "{out}", "--quiet"),
    ("bench", "{out}", "--observations", BASELINE, "--quiet"),
    ("gate", "--baseline", BASELINE, "--candidate", "{out}", "--max-slowdown", "0.10"),
)
CANDIDATES = ("unchanged", "slow15", "morework", "rawmatmul")
CONDITIONS = ("idle", "busy2", "busy8", "tests")  # and any busyN: N busy loops
BUSY_LOOP = "while True: pass"


# --- the test policies (child process only) -------------------------------------------


def spin_after_each_pass(model: Any, fraction: float) -> None:
    """Make every forward pass of `model` take `fraction` longer, on the CPU.

    The spin runs inside the pass (between the model's own pre- and post-hooks), so the
    harness charges it to the policy like real work, the counted passes and their work
    stay the same, and a loaded machine slows the spin as much as the pass it follows.
    """
    started: list[float] = []

    def before(module: Any, args: Any) -> None:
        started.append(time.perf_counter())

    def after(module: Any, args: Any, output: Any) -> None:
        t0 = started.pop()
        end = time.perf_counter() + fraction * (time.perf_counter() - t0)
        while time.perf_counter() < end:
            pass

    model.register_forward_pre_hook(before)
    model.register_forward_hook(after)


class DoubledBatch:
    """A policy that decodes each observation twice in one batch and keeps one copy:
    the same actions and forward passes, twice the work inside every pass."""

    def __init__(self, inner: Any):
        self.inner = inner

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def reset(self, episodes: Sequence[Any]) -> None:
        self.inner.reset(list(episodes) * 2)

    def act(self, observations: Sequence[Any]) -> Any:
        import dataclasses

        k = len(observations)
        batch = self.inner.act(list(observations) * 2)
        trace = batch.trace[:k] if batch.trace is not None else None
        return dataclasses.replace(
            batch, actions=batch.actions[:k], action_tokens=batch.action_tokens // 2, trace=trace
        )

    def act_batch(self, episodes: Sequence[Any], observations: Sequence[Any]) -> Any:
        self.inner._instructions = [ep.instruction for ep in episodes] * 2
        return self.act(observations)


class ProductAfterEachPass:
    """A decoder's model with a raw product after every forward pass: `torch.matmul` of a
    (16, width) by a (width, 6.5 width) tensor, held by no module (about 3.4 MFLOP at the
    shipped width 128, 16% of a fast_dvla pass's counted FLOPs). The decoder sees the
    model it had: same outputs, same passes."""

    def __init__(self, model: Any):
        import torch

        self.model = model
        width = model.cfg.width
        self.left, self.right = torch.ones(16, width), torch.ones(width, int(6.5 * width))

    def __getattr__(self, name: str) -> Any:
        return getattr(self.model, name)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        import torch

        out = self.model(*args, **kwargs)
        torch.matmul(self.left, self.right)
        return out


def with_raw_product(decode: Any) -> Any:
    """A decoder (`decode_fast_dvla`) whose step runs ProductAfterEachPass's extra product."""

    def decode_with_product(model: Any, *args: Any, **kwargs: Any) -> Any:
        return decode(ProductAfterEachPass(model), *args, **kwargs)

    return decode_with_product


def install_candidate(candidate: str, slowdown: float) -> None:
    """Swap the test policy in for the shipped `fast_dvla` in this process's registry."""
    import dataclasses

    from policies.dvla import policy as dvla

    if candidate == "unchanged":
        return
    if candidate == "rawmatmul":
        from policies.dvla import fast_dvla

        fast_dvla.decode_fast_dvla = with_raw_product(fast_dvla.decode_fast_dvla)
        return
    index = next(i for i, spec in enumerate(dvla.SPECS) if spec.name == "fast_dvla")
    shipped_build = dvla.SPECS[index].build

    def build(params: Any) -> Any:
        policy = shipped_build(params)
        if candidate == "slow15":
            spin_after_each_pass(policy.model, slowdown)
            return policy
        return DoubledBatch(policy)

    dvla.SPECS[index] = dataclasses.replace(dvla.SPECS[index], build=build)


def child_main(candidate: str, slowdown: float, argv: list[str]) -> int:
    install_candidate(candidate, slowdown)
    from harness.cli import main

    return main(argv)


# --- loads ----------------------------------------------------------------------------


def busy_loops(condition: str) -> int | None:
    """How many busy loops a `busyN` condition names (None: not one)."""
    count = condition.removeprefix("busy")
    return int(count) if condition.startswith("busy") and count.isdigit() and int(count) > 0 else None


@contextlib.contextmanager
def bounded_load(commands: list[list[str]], limit_s: float, settle_s: float = 5.0) -> Iterator[None]:
    """Run `commands` as a load, each in its own process group under `timeout limit_s` (so
    none outlives its time even if this process is killed), and kill them on the way out."""
    procs = [
        subprocess.Popen(["timeout", str(int(limit_s)), *command], cwd=ROOT, start_new_session=True)
        for command in commands
    ]
    try:
        if procs:
            time.sleep(settle_s)  # let the load reach the cores before the first trial
        yield
    finally:
        for proc in procs:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def load(condition: str, tests_command: str, tests_log: str, limit_s: float) -> Any:
    """The condition's load (idle: none), bounded in time and always killed on the way out."""
    if condition == "tests":  # the suite, restarted when it ends; its output kept for reading
        loop = f"while true; do {tests_command} >>{shlex.quote(tests_log)} 2>&1; done"
        return bounded_load([["bash", "-c", loop]], limit_s)
    loops = busy_loops(condition)
    if loops is None and condition != "idle":
        raise ValueError(f"unknown condition {condition!r}; valid: {', '.join(CONDITIONS)}")
    return bounded_load([[sys.executable, "-c", BUSY_LOOP]] * (loops or 0), limit_s)


# --- trials ---------------------------------------------------------------------------


def verdict(gate_code: int, gate_out: str) -> str:
    if gate_code == 1:
        return "fail"
    if gate_code != 0:
        return f"error (exit {gate_code})"
    return "inconclusive" if "inconclusive" in gate_out.lower() else "pass"


def failing_lines(gate_out: str) -> list[str]:
    """The gate's failure lines (after its table), for the JSON: which check failed."""
    lines = gate_out.splitlines()
    start = next((i for i, line in enumerate(lines) if line.lower().startswith("gate failed")), None)
    return [line.strip() for line in lines[start:]][:12] if start is not None else []


def bench_rounds(path: Path) -> dict[str, Any]:
    """How many rounds the bench took and why it stopped (its replay.json)."""
    if not path.is_file():
        return {}
    data = json.loads(path.read_text())
    return {"rounds": data.get("rounds"), "stopped": (data.get("sequential") or {}).get("stopped", "fixed")}


def verdict_lines(gate_out: str) -> list[str]:
    """The gate's `verdict:` lines (the replay figure and how far it can be trusted), each
    joined again where the console wrapped it."""
    out: list[str] = []
    for line in gate_out.splitlines():
        if line.startswith("verdict: "):
            out.append(line)
        elif out and not line.startswith(("note:", "warning:", "gate ", "paired ")) and out[-1]:
            out[-1] += " " + line.strip()
        elif out:
            out.append("")
    return [line for line in out if line]


def replay_ratios(path: Path) -> dict[str, float]:
    """Each timed configuration's median per-round seconds per chunk over the reference's
    (bidirectional), from a bench's replay.json: how far a passing trial was from failing."""
    if not path.is_file():
        return {}
    configs = json.loads(path.read_text())["configurations"]
    reference = next((c for c in configs if c["policy"] == "bidirectional"), None)
    if reference is None:
        return {}
    return {
        c["policy"]: round(
            statistics.median(
                a / b for a, b in zip(c["round_chunk_s"], reference["round_chunk_s"], strict=True)
            ),
            4,
        )
        for c in configs
        if c is not reference
    }


def trial(candidate: str, slowdown: float, time_box: float) -> dict[str, Any]:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    with tempfile.TemporaryDirectory(prefix="gate-stability-") as tmp:
        out = str(Path(tmp) / "ci")
        record: dict[str, Any] = {"candidate": candidate, "load_1m_before": os.getloadavg()[0]}
        started = time.perf_counter()
        codes, gate_out, steps = [], "", []
        for command in CI_COMMANDS:
            argv = [arg.replace("{out}", out) for arg in command]
            child = [sys.executable, __file__, "--child", candidate, "--slowdown", str(slowdown), "--", *argv]
            steps.append(time.perf_counter())
            try:
                done = subprocess.run(
                    child, cwd=ROOT, env=env, capture_output=True, text=True, timeout=time_box
                )
            except subprocess.TimeoutExpired:
                codes.append(124)
                break
            codes.append(done.returncode)
            if command[0] == "gate":
                gate_out = done.stdout + done.stderr
            elif done.returncode != 0:
                gate_out = done.stdout[-2000:] + done.stderr[-2000:]
                break
        ended = time.perf_counter()
        record.update(
            replay_ratios=replay_ratios(Path(out) / "replay.json"),
            **bench_rounds(Path(out) / "replay.json"),
            seconds=round(ended - started, 1),
            step_seconds=[round(b - a, 1) for a, b in zip(steps, [*steps[1:], ended], strict=True)],
            verdict_lines=verdict_lines(gate_out),
            exit_codes=codes,
            verdict=verdict(codes[-1], gate_out) if len(codes) == len(CI_COMMANDS) else "error (did not run)",
            failing=failing_lines(gate_out),
            load_1m_after=os.getloadavg()[0],
        )
        return record


def summarise(trials: list[dict[str, Any]]) -> dict[str, Any]:
    n = len(trials)
    counts = {v: sum(t["verdict"] == v for t in trials) for v in ("pass", "fail", "inconclusive")}
    errors = n - sum(counts.values())
    rate_name = "false_alarm_rate" if trials[0]["candidate"] == "unchanged" else "detection_rate"
    return {
        "n": n,
        **counts,
        "errors": errors,
        rate_name: counts["fail"] / n if n else None,
        "median_seconds": statistics.median(t["seconds"] for t in trials) if trials else None,
        "max_seconds": max(t["seconds"] for t in trials) if trials else None,
        "median_rounds": statistics.median(t.get("rounds") or 0 for t in trials) if trials else None,
        "mean_load_1m": statistics.fmean((t["load_1m_before"] + t["load_1m_after"]) / 2 for t in trials),
    }


def print_table(summary: list[dict[str, Any]]) -> None:
    header = (
        f"{'condition':<9} {'candidate':<10} {'n':>3} {'pass':>4} {'fail':>4} {'inconcl':>7} {'err':>3}  "
        f"{'rate':<22} {'s/job':>6} {'max s':>6} {'rounds':>6} {'load':>5}"
    )
    print(header)
    print("-" * len(header))
    for row in summary:
        if "false_alarm_rate" in row:
            rate = f"false alarms {row['false_alarm_rate']:.0%}"
        else:
            rate = f"detected {row['detection_rate']:.0%}"
        print(
            f"{row['condition']:<9} {row['candidate']:<10} {row['n']:>3} {row['pass']:>4} {row['fail']:>4} "
            f"{row['inconclusive']:>7} {row['errors']:>3}  {rate:<22} {row['median_seconds']:>6.1f} "
            f"{row['max_seconds']:>6.1f} {row['median_rounds']:>6.1f} {row['mean_load_1m']:>5.1f}"
        )


def refuse_another_cpu() -> None:
    """The gate compares speed only on the baseline's CPU (docs/ci-gate.md), so on
    another every trial would pass untimed and the rates would mean nothing."""
    from harness.run.manifest import environment
    from results.cpu_identity import cpu_difference

    manifest = json.loads((ROOT / BASELINE / "manifest.json").read_text())
    theirs, ours = manifest.get("environment") or {}, environment()
    differ = cpu_difference(theirs, ours)
    if differ:
        raise SystemExit(
            f"error: this machine's CPU ({ours.get('cpu')}) is not the committed baseline's "
            f"({theirs.get('cpu')}: {differ}); the gate does not compare speed across CPUs, so every "
            "trial would pass untimed. Regenerate the baseline here first (results/baselines/README.md), "
            "and do not commit it"
        )


def choices(text: str, valid: tuple[str, ...], what: str) -> list[str]:
    picked = [c.strip() for c in text.split(",") if c.strip()]
    bad = [c for c in picked if c not in valid and not (what == "conditions" and busy_loops(c))]
    if bad or not picked:
        raise SystemExit(f"error: --{what}: {', '.join(bad) or 'none given'}; valid: {', '.join(valid)}")
    return picked


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child"]:  # one CI command with a candidate's policy swapped in
        sep = argv.index("--")
        return child_main(argv[1], float(argv[3]), argv[sep + 1 :])
    parser = argparse.ArgumentParser(
        description="False-alarm and detection rates of the CI gate under load (docs/ci-gate.md)."
    )
    parser.add_argument("--n", type=int, default=10, help="trials per condition and candidate (default 10)")
    parser.add_argument(
        "--conditions", default="idle,busy2", help=f"comma-separated: {', '.join(CONDITIONS)}"
    )
    parser.add_argument(
        "--candidates", default="unchanged,slow15,morework", help=f"comma-separated: {', '.join(CANDIDATES)}"
    )
    parser.add_argument(
        "--slowdown", type=float, default=0.15, help="slow15's extra time per pass (default 0.15)"
    )
    parser.add_argument("--time-box", type=float, default=600.0, help="seconds before one command is stopped")
    parser.add_argument(
        "--tests-command",
        default=f"{sys.executable} -m pytest -q -p no:cacheprovider tests",
        help="the `tests` condition's load, restarted when it ends (e.g. 'tox -e test')",
    )
    parser.add_argument("--tests-log", default=os.devnull, help="where the tests load's output goes")
    parser.add_argument("--json", default=str(ROOT / "benchmarks/results/gate_stability.json"))
    args = parser.parse_args(argv)
    if args.n < 1 or not 0 < args.slowdown < 10:
        parser.error("--n must be at least 1 and --slowdown in (0, 10)")
    conditions = choices(args.conditions, CONDITIONS, "conditions")
    candidates = choices(args.candidates, CANDIDATES, "candidates")
    refuse_another_cpu()
    results: list[dict[str, Any]] = []
    summary: list[dict[str, Any]] = []
    for condition in conditions:
        bound = args.time_box * len(CI_COMMANDS) * args.n * len(candidates) + 60
        with load(condition, args.tests_command, args.tests_log, bound):
            for candidate in candidates:
                trials = []
                for i in range(args.n):
                    t = trial(candidate, args.slowdown, args.time_box)
                    t["condition"] = condition
                    trials.append(t)
                    print(
                        f"  {condition} {candidate} {i + 1}/{args.n}: {t['verdict']} in {t['seconds']} s "
                        f"{t['step_seconds']}, {t.get('rounds')} rounds ({t.get('stopped')}), load "
                        f"{t['load_1m_before']:.1f}; {'; '.join(t['failing'][1:3] or t['verdict_lines'])}",
                        flush=True,
                    )
                results.extend(trials)
                summary.append({"condition": condition, "candidate": candidate, **summarise(trials)})
    print_table(summary)
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    from harness.run.manifest import environment
    from results.cpu_identity import describe_cpu

    meta = {
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "machine": describe_cpu(environment()),
        "cpus": os.cpu_count(),
        "command": " ".join(["python benchmarks/gate_stability.py", *argv]),
        "commands": [" ".join(("dvla-harness", *c)) for c in CI_COMMANDS],
        "slowdown": args.slowdown,
        "tests_command": args.tests_command if "tests" in conditions else None,
    }
    out.write_text(
        json.dumps({"meta": meta, "summary": summary, "trials": results}, indent=1, allow_nan=False)
    )
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
