"""`dvla-harness run`: evaluate policies on a suite into a run folder.

The flags and the run-with-progress-and-summary step are shared with `sweep`, which
is a run whose policy list is a grid.
"""

from __future__ import annotations

import argparse
import signal
from pathlib import Path
from typing import TYPE_CHECKING, Any

from harness.console import console, episode_progress, err_console, print_table, raise_interrupt
from harness.errors import EXIT_STATUS_HELP, UsageError

if TYPE_CHECKING:
    import pandas as pd

EXAMPLES = (
    """\
examples:
  dvla-harness run                                   # the main job (embedded default config)
  dvla-harness run --suite metaworld/mt10 --policy scripted --episodes-per-task 10 --out runs/demo
  dvla-harness run --suite metaworld/mt1/reach-v3 --policy random:seed=3 --episodes-per-task 2
  dvla-harness run --suite metaworld/mt10 --policy fast_dvla --policy bidirectional --traces
  dvla-harness run --suite metaworld/mt10 --policy fast_dvla --batch-envs 8   # 8 envs, one batched decode per step
  dvla-harness run --out runs/demo --resume          # finish an interrupted run (its recorded config)
  dvla-harness run --out runs/demo --resume --episodes-per-task 50   # extend it: only the new episodes run

one process writes a run folder at a time (OUT/writer.lock names it); a second run,
--resume, --overwrite or sweep on it is refused while it runs

"""
    + EXIT_STATUS_HELP
)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="evaluate policies on a suite into a run folder",
        description=(
            "Evaluate one or more policies on a suite. Every finished episode is appended to "
            "OUT/pending.jsonl at once and compacted into OUT/episodes.parquet at the end; "
            "OUT/manifest.json holds the resolved config and provenance. With no arguments, "
            "runs the embedded default config (the README's main job). Flags override "
            "--config, which overrides the embedded default; naming another suite runs its "
            "whole protocol (every task, every episode spec) unless --tasks or "
            "--episodes-per-task cut it to a prefix."
        ),
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_run_arguments(p)
    p.set_defaults(func=cmd_run)


def add_run_arguments(p: argparse.ArgumentParser) -> None:
    """The flags of `run`, shared with `sweep` (a sweep is a run over a grid of policies),
    in three groups: what is evaluated, the run folder, where it computes."""
    _what_arguments(p.add_argument_group("what to evaluate (the config; --config FILE holds the same keys)"))
    _folder_arguments(p.add_argument_group("the run folder"))
    _compute_arguments(p.add_argument_group("where and how episodes run (not part of the config)"))


def _what_arguments(p: Any) -> None:
    p.add_argument(
        "--config",
        metavar="FILE",
        help="TOML file with keys: suite, tasks, episodes_per_task, replan_every, batch_envs, "
        "out_of_space, inference_latency, execution, [[policy]] name/params",
    )
    p.add_argument("--suite", help="suite name (see `dvla-harness list suites`)")
    p.add_argument(
        "--variants",
        metavar="SPEC",
        help="simpler/ suites: canonical (ManiSkill3's canonical scene alone, the default), all "
        "(every level of every axis), or axes/levels joined by + (lighting+camera.left); the same "
        "as the suite option :variants=SPEC (docs/simpler.md)",
    )
    p.add_argument(
        "--tasks",
        metavar="NAME_OR_INDEX,...",
        help="only these tasks of the suite (names or 0-based indices)",
    )
    p.add_argument(
        "--policy",
        action="append",
        metavar="NAME[:k=v,...]",
        help="policy to evaluate, with parameters; repeat to compare several (see `dvla-harness list policies`)",
    )
    p.add_argument(
        "--episodes-per-task",
        type=int,
        metavar="N",
        help="the first N episode specs of each task (default: the config's, else the whole protocol)",
    )
    p.add_argument(
        "--replan-every",
        type=int,
        metavar="K",
        help="execute K actions of each chunk before asking again; 0 = the whole chunk (default 0)",
    )
    from harness.episode.actions import OUT_OF_SPACE_RULES, RULES_HELP

    p.add_argument("--out-of-space", choices=OUT_OF_SPACE_RULES, metavar="RULE", help=RULES_HELP)
    p.add_argument(
        "--inference-latency",
        metavar="MODE",
        help="simulated decoding time per chunk: none (default; the world waits), passes:MS[+FIXED_MS], "
        "profile:NAME (`dvla-harness list latency-profiles`) or measured (docs/latency.md)",
    )
    p.add_argument(
        "--execution",
        choices=("sync", "async"),
        help="under an inference latency: sync (the robot holds still while a chunk decodes; "
        "default) or async (it keeps executing the current chunk)",
    )


def _folder_arguments(p: Any) -> None:
    p.add_argument(
        "--out", metavar="DIR", help="run folder (default: runs/<UTC date and time>, printed with the table)"
    )
    mode = p.add_mutually_exclusive_group()
    mode.add_argument(
        "--resume",
        action="store_true",
        help="run only the episodes OUT does not have yet, of the config OUT recorded (other flags "
        "are optional); refuses flags that change what is evaluated, except a larger "
        "--episodes-per-task, which extends the run",
    )
    mode.add_argument("--overwrite", action="store_true", help="replace an existing run folder")
    p.add_argument(
        "--retry-failed",
        action="store_true",
        help="with --resume, also re-run episodes recorded with a failure_reason",
    )
    p.add_argument(
        "--traces",
        action="store_true",
        help="also write which action positions each forward pass committed to OUT/traces.jsonl "
        "(for `dvla-harness plot decoding-order`)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _compute_arguments(p: Any) -> None:
    from harness.backends.options import add_backend_arguments

    add_backend_arguments(p)
    from harness.threads import DEFAULT_THREADS_PER_WORKER, parse_threads

    p.add_argument(
        "--threads",
        type=parse_threads,
        metavar="N",
        help=f"torch CPU threads for the policies (default: OMP_NUM_THREADS if set, else "
        f"{DEFAULT_THREADS_PER_WORKER}: more threads spin against other jobs on a busy machine; "
        "recorded in the manifest)",
    )
    from harness.device import DEFAULT_DEVICE, DEVICES

    p.add_argument(
        "--device",
        choices=DEVICES,
        default=DEFAULT_DEVICE,
        help="where model policies decode: cpu (default: what every baseline was measured on), "
        "cuda (refused without a GPU), auto (cuda when a GPU is visible); recorded in the manifest; "
        "with --backend ray each worker resolves it on its node (see --ray-num-gpus)",
    )


def config_from_args(args: argparse.Namespace) -> Any:
    """The RunConfig the flags ask for (harness/config.py `merge_config` applies the
    precedence); the batch size they or --config ask for goes to `args.batch_envs`, which
    the backend flags read."""
    from harness.config import merge_config, parse_policy_arg
    from harness.run.resume import recorded_config_data

    # --resume continues the folder's recorded config; flags change it (and are checked)
    recorded = recorded_config_data(Path(args.out)) if args.resume and args.out else None
    tasks = None
    if args.tasks is not None:
        tasks = [t.strip() for t in args.tasks.split(",") if t.strip()]
        if not tasks:
            raise UsageError("--tasks is empty; give task names or indices, comma-separated")
    flags = {
        "suite": args.suite,
        "variants": getattr(args, "variants", None),
        "tasks": tasks,
        "policy": [parse_policy_arg(p) for p in args.policy] if args.policy else None,
        "episodes_per_task": args.episodes_per_task,
        "replan_every": args.replan_every,
        "out_of_space": getattr(args, "out_of_space", None),
        "inference_latency": getattr(args, "inference_latency", None),
        "execution": getattr(args, "execution", None),
        "batch_envs": getattr(args, "batch_envs", None),
    }
    config, args.batch_envs = merge_config(recorded, args.config, flags)
    return config


def prepare_compute(args: argparse.Namespace) -> None:
    """Before the policies are built: torch's threads set once for this process (harness/
    threads.py applies them to torch whenever it loads), and a device that cannot be had
    refused (exit 2) before any model is loaded. Under --backend ray the workers resolve
    --device on their nodes (this machine may have no GPU); only a GPU no Ray worker could
    be given is refused here."""
    from harness.device import resolve_device
    from harness.threads import apply_threads

    apply_threads(args.threads)
    if getattr(args, "backend", "local") == "ray":
        from harness.backends.ray import check_ray_device

        check_ray_device(args.device, args.ray_num_gpus)
    else:
        resolve_device(args.device)


def cmd_run(args: argparse.Namespace) -> int:
    from harness.config import resolve
    from harness.run.folder import OpenMode

    mode = OpenMode.from_flags(
        args.resume, args.overwrite, args.retry_failed
    )  # refused before anything loads
    prepare_compute(args)
    resolved = resolve(config_from_args(args))
    return execute_run(resolved, args, mode, "dvla-harness run --out {out} --resume")


def print_out_of_space(episodes: pd.DataFrame, labels: dict[str, str] | None = None) -> None:
    """A warning line per configuration whose actions left the action space (harness/episode/actions.py)."""
    from results.board_warnings import out_of_space_warnings

    for line in out_of_space_warnings(episodes, labels):
        err_console.print(f"[yellow]warning:[/yellow] {line}", markup=True, highlight=False, soft_wrap=True)


def print_latency_table(episodes: pd.DataFrame, labels: dict[str, str] | None = None) -> None:
    """Delays, late chunks and hold steps beside success, for runs at an inference latency."""
    from results.latency_table import has_latency, latency_summary, latency_table

    if has_latency(episodes):
        console.print(latency_table(latency_summary(episodes), labels))


def print_chain_table(episodes: pd.DataFrame, labels: dict[str, str] | None = None) -> None:
    """CALVIN's table beneath the summary, for instruction-chain runs (docs/chains.md)."""
    from results.chain_table import chain_summary, chain_table, is_chain_run

    if is_chain_run(episodes):
        print_table(
            chain_table(chain_summary(episodes), title="instruction chains (CALVIN-like)", labels=labels)
        )


def print_speed_warning(run_dir: Any) -> None:
    """The run's own speed verdict, as `show` prints it: a CI log that shows only `run`
    says its timings are not comparable (calibration drift, starved episodes)."""
    from results.runs import speed_warning

    try:
        warning = speed_warning(run_dir.read_manifest())
    except (OSError, ValueError):  # an unreadable manifest: the run's own error says so
        return
    if warning:
        err_console.print(
            f"[yellow]warning[/yellow]: speed figures of this run are unreliable: {warning}",
            highlight=False,
            soft_wrap=True,
        )


def execute_run(resolved: Any, args: argparse.Namespace, mode: Any, again: str) -> int:
    """Run `resolved` with the progress bar, print the summary, return the exit status.

    mode: how the folder opens (harness/run/folder.py OpenMode, from --resume,
    --overwrite, --retry-failed); again: the command that continues an interrupted run
    ({out} is filled in). Every table names a configuration by the config_label its rows
    hold (a sweep's grid points too).
    """
    from harness.backends.options import check_batching, execution_from_args
    from harness.device import apply_device
    from harness.run.runner import run

    # under Ray each worker places its own policies; this process only records the request
    apply_device(resolved.policies, args.device, per_worker=getattr(args, "backend", "local") == "ray")
    execution = execution_from_args(args)  # Ray not installed or unreachable: exit 2 here
    check_batching(resolved.policies, execution.batch_envs)  # a policy that cannot batch: exit 2
    out = Path(args.out) if args.out else default_out()
    progress, start = episode_progress(args.quiet)
    # CI cancels with SIGTERM: stop like Ctrl-C, keeping every finished episode.
    signal.signal(signal.SIGTERM, raise_interrupt)
    with progress:
        report = run(resolved, out, mode, execution=execution, traces=args.traces, progress=start)
    print_run(resolved, report)
    if report.interrupted:
        err_console.print(f"interrupted; continue with: {again.format(out=out)}")
        return 130
    if report.failed:
        err_console.print(
            f"[red]{report.failed} episode(s) raised an exception[/red]; see failure_reason in the rows "
            f"and tracebacks in {report.run_dir.path / 'events.jsonl'}"
        )
        return 1
    return 0


def default_out() -> Path:
    """runs/<UTC date and time>: a new folder for a run given no --out (printed with the table)."""
    from datetime import UTC, datetime

    return Path("runs") / datetime.now(UTC).strftime("%Y%m%d-%H%M%S")


def print_run(resolved: Any, report: Any) -> None:
    """The run's summary tables (chains, latency, out-of-space warnings beneath), where
    its rows and manifest are, and its speed verdict."""
    from results.labels import row_labels
    from results.render import summary_table
    from results.summary import summarize

    episodes = report.run_dir.read_episodes()
    if len(episodes):
        labels = row_labels(episodes)
        print_table(
            summary_table(
                summarize(episodes),
                title=f"{resolved.suite.name} - {report.run_dir.path}",  # the name the user typed or was shown
                labels=labels,
            )
        )
        print_chain_table(episodes, labels)
        print_latency_table(episodes, labels)
        print_out_of_space(episodes, labels)
    console.print(
        f"rows: {report.run_dir.path / 'episodes.parquet'}  manifest: {report.run_dir.manifest_path}"
    )
    print_speed_warning(report.run_dir)
