"""`dvla-harness bench`: the replay benchmark of a finished run, for the gate's speed verdict.

A command of its own rather than a step of `run`: it adds figures to any run folder (an
old one, a resumed one, one benched again with more rounds) without re-running episodes,
its flags (rounds, observations) are about timing only and change no row, and the CI job
stays three plain commands: run, bench, gate. The work is harness/bench.py; the figures'
meaning and the verdict are results/replay.py.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from harness.errors import UsageError

DEFAULT_ROUNDS = 30
DEFAULT_MIN_ROUNDS = 10
DEFAULT_PER_TASK = 4

DESCRIPTION = """\
Time every configuration of a run decoding a fixed set of recorded observations, many
rounds, interleaved, and write the figures to RUN_DIR/replay.json; `dvla-harness gate`
then judges speed on them (a 95% bootstrap interval over the rounds) instead of on the
closed-loop episodes, which are few, of different lengths and timed once each.

Observations: RUN_DIR/replay_observations.npz when it exists; else --observations SOURCE
(another run's recorded set, copied in: the CI job decodes exactly what the committed
baseline decoded); else recorded now: the --record-from decoder (default bidirectional)
plays the first episode of each task of the run again, and K observations per task
(--observations-per-task, evenly spaced over the episode) are kept.

Timing: each configuration decodes every observation once untimed (warm-up; its
tokens, forward passes and work are counted: the FLOPs of every torch product, seen at
torch's dispatcher wherever the decoder calls it), then rounds: observation by
observation, every configuration in turn (reset untimed, act timed), starting from a
different configuration each time, so a load that comes and goes hits all alike.
Reported per configuration: median and minimum seconds per chunk over the rounds, the
median's 95% bootstrap interval, and its ratio to the reference in the same rounds.
Configurations that decode no action tokens (scripted) are not timed.

Rounds: --rounds at most. When the observations come from a benched run (the CI job's
--observations BASELINE_DIR), bench judges each configuration against that baseline as
the gate will (--reference, --max-slowdown: give it the gate's) after --min-rounds and
every 5 rounds after, and stops as soon as every verdict is settled: more rounds only
while an interval straddles the allowed slowdown. replay.json records the rounds used
and why timing stopped. --min-rounds N --rounds N times exactly N rounds.

Exit status: 0 benched; 2 unusable input (not a run folder, a run whose policies no
longer resolve, a foreign observations file, bad flags), nothing written.
"""

EXAMPLES = """\
examples:
  # the CI job: the smoke run, benched on the committed baseline's observations, gated
  OMP_NUM_THREADS=1 dvla-harness run --config results/baselines/metaworld-mt10-smoke.toml \\
      --out runs/ci --quiet
  OMP_NUM_THREADS=1 dvla-harness bench runs/ci \\
      --observations results/baselines/metaworld-mt10-smoke --quiet
  dvla-harness gate --baseline results/baselines/metaworld-mt10-smoke --candidate runs/ci

  # more rounds on a noisy machine (the gate said "inconclusive")
  dvla-harness bench runs/ci --observations results/baselines/metaworld-mt10-smoke --rounds 100

  # exactly 30 rounds, no early stop (a baseline's own bench)
  dvla-harness bench runs/base --min-rounds 30 --rounds 30

  # a run without bidirectional: record from another decoder
  dvla-harness bench runs/sweep --record-from fast_dvla

  # from Python
  from results.replay import load_replay; load_replay("runs/ci")["configurations"]
"""


def _positive(minimum: int) -> Any:
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {value}")
        return value

    return parse


def _fraction(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a fraction such as 0.10, got {text!r}") from None
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1), got {value}")
    return value


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "bench",
        help="time every configuration of a run on recorded observations (the gate's speed figures)",
        description=DESCRIPTION,
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="a finished run folder (`dvla-harness run --out`)")
    p.add_argument(
        "--rounds",
        type=_positive(2),
        default=DEFAULT_ROUNDS,
        metavar="N",
        help=f"timed rounds over the observations, at most (default {DEFAULT_ROUNDS}; more: a narrower "
        "interval); all of them unless a baseline bench lets the verdict settle sooner",
    )
    p.add_argument(
        "--min-rounds",
        type=_positive(2),
        metavar="M",
        help=f"rounds before the first look at the verdict (default {DEFAULT_MIN_ROUNDS}, or --rounds if fewer)",
    )
    p.add_argument(
        "--max-slowdown",
        type=_fraction,
        default=0.10,
        metavar="FRACTION",
        help="the slowdown the gate will allow (its --max-slowdown, default 0.10): the limit the "
        "verdict settles against",
    )
    p.add_argument(
        "--reference",
        default="bidirectional",
        metavar="POLICY|CONFIG_ID",
        help="the decoder the gate measures speed against (its --reference, default bidirectional)",
    )
    p.add_argument(
        "--observations",
        metavar="RUN_DIR|NPZ",
        help="decode the observations another run recorded (its replay_observations.npz), copied in",
    )
    p.add_argument(
        "--observations-per-task",
        type=_positive(1),
        default=DEFAULT_PER_TASK,
        metavar="K",
        help=f"when recording: observations kept per task (default {DEFAULT_PER_TASK})",
    )
    p.add_argument(
        "--record-from",
        default="bidirectional",
        metavar="POLICY|CONFIG_ID",
        help="when recording: the configuration whose episode is replayed (default bidirectional)",
    )
    from harness.threads import parse_threads

    p.add_argument(
        "--threads",
        type=parse_threads,
        metavar="N",
        help="torch CPU threads (default: OMP_NUM_THREADS if set, else the run's default); the gate "
        "compares benches of equal thread counts only",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_bench)


def _source_file(text: str) -> Path:
    from results.store import REPLAY_OBSERVATIONS

    path = Path(text)
    if path.is_dir():
        path = path / REPLAY_OBSERVATIONS
    if not path.is_file():
        raise UsageError(
            f"--observations: {str(path)!r} does not exist (pass a benched run folder or its "
            f"{REPLAY_OBSERVATIONS})"
        )
    return path


def _identity(policy: str, params_json: str, sha256: str | None) -> str:
    """A configuration as the gate pairs it: name, params and checkpoint hash, not its path."""
    params = json.loads(params_json or "{}")
    if sha256:
        params.pop("checkpoint", None)
    return json.dumps([policy, params, sha256 or ""], sort_keys=True)


def _resolved(run_dir: Any) -> Any:
    """The run's config resolved again, refusing one whose policies are no longer the run's."""
    from harness.config import build_config, resolve
    from harness.run.resume import config_data
    from results.store import ResultsFileError

    try:
        manifest = run_dir.read_manifest(required=("config",))
        episodes = run_dir.read_episodes()
    except ResultsFileError as exc:
        raise UsageError(str(exc)) from None
    try:
        resolved = resolve(build_config(config_data(manifest["config"])))
    except UsageError as exc:
        raise UsageError(f"{run_dir.path}: its recorded config does not resolve: {exc}") from None
    recorded = {_identity(r.policy, r.policy_params, r.checkpoint_sha256): r.policy_config_id
                for r in episodes.drop_duplicates("policy_config_id").itertuples()}  # fmt: skip
    changed = []
    for p in resolved.policies:
        found = recorded.get(_identity(p.spec.name, p.params_json, p.checkpoint_sha256))
        if found is None:
            changed.append(p.spec.name)
        else:
            p.config_id = found  # the run's id: its checkpoint path may be another clone's
    if changed:
        raise UsageError(
            f"{run_dir.path}: {', '.join(changed)} no longer resolve(s) to a configuration the run "
            "recorded (a checkpoint or the policy's parameters changed since); bench a fresh run instead"
        )
    return resolved, manifest


def _pick(resolved: Any, name: str) -> Any:
    found = [p for p in resolved.policies if name in (p.spec.name, p.config_id)]
    if len(found) != 1:
        choices = ", ".join(f"{p.spec.name} ({p.config_id})" for p in resolved.policies)
        how = "none" if not found else f"{len(found)} configurations"
        raise UsageError(f"--record-from {name!r}: {how} of the run match; choices: {choices}")
    return found[0]


def cmd_bench(args: argparse.Namespace) -> int:
    from harness.threads import apply_threads

    apply_threads(args.threads)  # once, before torch does any work
    from harness.bench import load_observations
    from harness.run.folder import acquire
    from results.lock import RunLock
    from results.store import REPLAY_OBSERVATIONS, RunDir

    run_dir = RunDir(args.run_dir)
    if not run_dir.is_run():
        raise UsageError(
            f"{args.run_dir!r} is not a run folder (no manifest.json; make one with `dvla-harness run`)"
        )
    if args.min_rounds is None:
        args.min_rounds = min(DEFAULT_MIN_ROUNDS, args.rounds)
    elif args.min_rounds > args.rounds:
        raise UsageError(f"--min-rounds {args.min_rounds} is more than --rounds {args.rounds}")
    source = _source_file(args.observations) if args.observations else None
    given = load_observations(source) if source else None  # a foreign file refused before any work
    baseline = _baseline_bench(source)
    lock = RunLock(run_dir.path)
    acquire(lock)  # a run still writing the folder is refused, naming it
    try:
        return _bench(args, run_dir, (source, given, baseline), run_dir.path / REPLAY_OBSERVATIONS)
    finally:
        lock.release()


def _baseline_bench(source: Path | None) -> dict[str, Any] | None:
    """The replay.json beside the observations file, when it came from a benched run: the
    baseline the stopping rule judges against. A broken one is refused before any work."""
    from results.replay import ReplayFileError, load_replay

    if source is None:
        return None
    try:
        return load_replay(source.parent)
    except ReplayFileError as exc:
        raise UsageError(f"--observations: {exc}") from None


def _bench(args: argparse.Namespace, run_dir: Any, sources: tuple, own: Path) -> int:
    from harness import bench
    from harness.console import console, err_console
    from harness.threads import threads_record

    source, given, baseline = sources
    resolved, manifest = _resolved(run_dir)
    started = time.perf_counter()
    if given is not None:
        recorded, how = given, f"from {source}"
    elif own.is_file():
        recorded, how = bench.load_observations(own), f"from {own}"
    else:
        origin = _pick(resolved, args.record_from)
        if not args.quiet:
            err_console.print(f"recording observations: {origin.spec.name} replays each task's first episode")
        recorded = bench.record_observations(resolved, origin, args.observations_per_task)
        how = f"recorded from {origin.spec.name} ({origin.config_id}), {args.observations_per_task} per task"
    if not recorded.observations:
        raise UsageError(
            f"{run_dir.path}: no observations to decode (the run has no episodes to record from)"
        )
    digest = recorded.digest()
    contexts = bench.episode_contexts(resolved, recorded)
    timed, not_timed, decodes = [], [], {}
    for p in resolved.policies:
        d = bench.warm_up_pass(p.policy, contexts, recorded.observations)
        if d.error or d.action_tokens == 0:
            not_timed.append({"policy": p.spec.name, "policy_config_id": p.config_id,
                              "reason": d.error or "decodes no action tokens"})  # fmt: skip
        else:
            timed.append(p)
            decodes[p.config_id] = d
    if not timed:
        raise UsageError(
            f"{run_dir.path}: no configuration of the run decodes action tokens; nothing to time"
        )
    rule = bench.stopping_rule(
        baseline, timed, args.reference, (args.max_slowdown, args.min_rounds, args.rounds)
    )
    rounds = _timed_rounds(args, timed, (contexts, recorded.observations), rule)
    configurations = _configurations(timed, decodes, rounds, len(recorded.observations))
    observations = {
        "file": "replay_observations.npz",
        "count": len(recorded.observations),
        "tasks": sorted({c["task"] for c in recorded.contexts}),
        "sha256": None,  # set below from the observations as loaded, before any decode
        "how": how,
        "source": str(source) if source else None,
    }
    payload = _payload(args, manifest, observations, configurations, not_timed)
    payload["rounds"] = len(next(iter(rounds.wall.values())))
    payload["sequential"] = rule.record(rounds.wall) if rule else None
    payload["observations"]["sha256"] = digest
    payload["elapsed_s"] = time.perf_counter() - started
    payload["torch_threads"] = threads_record().get("torch_intra_op")
    _write(run_dir, own, recorded, payload)
    console.print(_table(payload, len(recorded.observations)))
    for entry in not_timed:
        console.print(f"not timed: {entry['policy']} ({entry['policy_config_id']}): {entry['reason']}")
    console.print(_rounds_line(payload))
    console.print(f"replay figures: {run_dir.path / 'replay.json'} ({payload['elapsed_s']:.1f} s)")
    return 0


def _timed_rounds(args: argparse.Namespace, timed: list, decoded: tuple, rule: Any) -> Any:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from harness import bench
    from harness.console import err_console

    progress = Progress(
        TextColumn("[bold]rounds"), BarColumn(), MofNCompleteColumn(), TextColumn("ETA"),
        TimeRemainingColumn(), console=err_console, disable=args.quiet,
    )  # fmt: skip
    every = max(1, math.ceil(args.rounds / 4))
    done = [0]

    def tick() -> None:
        done[0] += 1
        progress.update(task, advance=1)
        if not args.quiet and not err_console.is_terminal and (done[0] % every == 0):
            err_console.print(f"rounds {done[0]}/{args.rounds}")

    with progress:
        task = progress.add_task("rounds", total=args.rounds)
        contexts, observations = decoded
        stop = rule.settled if rule else None
        return bench.time_rounds(timed, contexts, observations, args.rounds, tick, stop)


def _configurations(timed: list, decodes: dict, rounds: Any, n: int) -> list[dict[str, Any]]:
    """Each timed configuration's figures per chunk, from its decodes and rounds."""
    from harness.bench import portable_params
    from results.replay import chunk_figures

    configurations = []
    for p in timed:
        d = decodes[p.config_id]
        configurations.append(
            {
                "policy": p.spec.name,
                "policy_config_id": p.config_id,
                "policy_params": portable_params(p),
                "action_tokens_per_chunk": d.action_tokens / n,
                "nfe_per_chunk": None if d.nfe is None else d.nfe / n,
                # every torch product, at the dispatcher (the gate compares this), and the
                # counted modules' products, by the hooks the episodes are counted with
                "flops_per_chunk": None if d.flops is None else d.flops / n,
                "module_flops_per_chunk": None if d.module_flops is None else d.module_flops / n,
                **chunk_figures(rounds.wall[p.config_id]),
                "round_chunk_s": rounds.wall[p.config_id],
                # the same calls' CPU time: how long the rounds waited for a core (null: a GPU policy)
                "round_cpu_chunk_s": rounds.cpu[p.config_id],
            }
        )
    return configurations


def _payload(
    args: argparse.Namespace,
    manifest: dict[str, Any],
    observations: dict[str, Any],
    configurations: list[dict[str, Any]],
    not_timed: list,
) -> dict[str, Any]:
    from results.replay import REPLAY_VERSION

    return {
        "replay_version": REPLAY_VERSION,
        "run_id": manifest.get("run_id"),
        "at": datetime.now(UTC).isoformat(),
        "definition": (
            "per round, every observation decoded once by every configuration, interleaved "
            "observation by observation with a rotating start; round_chunk_s = mean seconds of "
            "act per observation in that round (reset untimed); one untimed warm-up pass first"
        ),
        "rounds": None,  # the rounds timed, set once they are
        "max_rounds": args.rounds,
        "observations": observations,
        "configurations": configurations,
        "not_timed": not_timed,
    }


def _rounds_line(payload: dict[str, Any]) -> str:
    """How many rounds were timed, and why no more."""
    rule = payload["sequential"]
    if rule is None:
        return f"rounds: {payload['rounds']} (fixed: no baseline bench to judge against)"
    verdicts = ", ".join(f"{k} {v}" for k, v in rule["verdicts"].items())
    if rule["stopped"] == "settled":
        return (
            f"rounds: {rule['rounds']} of at most {rule['max_rounds']}: settled against the baseline "
            f"bench at {rule['look_confidence']:.1%} ({verdicts}; allowed -{rule['max_slowdown']:.0%})"
        )
    return (
        f"rounds: {rule['rounds']}, the cap: not settled sooner against the baseline bench ({verdicts} "
        f"at {rule['look_confidence']:.1%}; allowed -{rule['max_slowdown']:.0%})"
    )


def _write(run_dir: Any, own: Path, recorded: Any, payload: dict[str, Any]) -> None:
    from harness.bench import observations_bytes
    from harness.run.folder import io_error
    from results.store import REPLAY, atomic_write

    try:
        if not own.is_file() or payload["observations"]["source"]:
            atomic_write(own, observations_bytes(recorded))
        atomic_write(run_dir.path / REPLAY, (json.dumps(payload, indent=1, allow_nan=False) + "\n").encode())
    except OSError as exc:
        raise io_error(run_dir.path, "writing the replay figures", exc) from None


def _table(payload: dict[str, Any], n: int) -> Any:
    from rich.table import Table

    configs = payload["configurations"]
    reference = next((c for c in configs if c["policy"] == "bidirectional"), None)
    table = Table(
        "configuration", "tokens/chunk", "NFE/chunk", "GFLOP/chunk", "median ms/chunk [95%]",
        "min ms/chunk", "vs bidirectional",
        title=f"replay: {n} observations x {payload['rounds']} rounds",
        caption="seconds per chunk over the rounds; GFLOP/chunk: every torch product, counted at the "
        "dispatcher; vs bidirectional: median of the per-round ratio of its time",
    )  # fmt: skip
    for c in configs:
        low, high = c["median_chunk_s_interval"]
        ratio = ""
        if reference is not None:
            import numpy as np

            per_round = np.asarray(c["round_chunk_s"]) / np.asarray(reference["round_chunk_s"])
            ratio = f"{float(np.median(per_round)):.3f}x time"
        table.add_row(
            f"{c['policy']} ({c['policy_config_id']})",
            f"{c['action_tokens_per_chunk']:.1f}",
            "-" if c["nfe_per_chunk"] is None else f"{c['nfe_per_chunk']:.2f}",
            "-" if c.get("flops_per_chunk") is None else f"{c['flops_per_chunk'] / 1e9:.4f}",
            f"{c['median_chunk_s'] * 1e3:.2f} [{low * 1e3:.2f}, {high * 1e3:.2f}]",
            f"{c['min_chunk_s'] * 1e3:.2f}",
            ratio,
        )
    return table
