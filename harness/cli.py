"""The `dvla-harness` command line (also `python -m harness`).

Exit status: 0 success; 1 some episodes raised (recorded with a failure_reason);
2 bad input (nothing written); 130 interrupted (what finished is kept; use --resume).
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from harness.errors import UsageError

EXAMPLES = """\
examples:
  dvla-harness run                                   # the main job (embedded default config)
  dvla-harness run --suite metaworld/mt10 --policy scripted --episodes-per-task 10 --out runs/demo
  dvla-harness run --suite metaworld/mt1/reach-v3 --policy random:seed=3 --episodes-per-task 2
  dvla-harness run --out runs/demo --resume          # finish an interrupted run
  dvla-harness list suites | policies | tasks metaworld/mt10
  dvla-harness show runs/demo
  dvla-harness collect --suite metaworld/mt10 --policy scripted --episodes-per-task 50 --out demos/mt10
"""

# Pipes and CI logs get wide tables instead of rich's 80-column default.
console = Console(width=None if sys.stdout.isatty() else 160)
err_console = Console(stderr=True, width=None if sys.stderr.isatty() else 140)


def _run_parser(sub: argparse._SubParsersAction) -> None:
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
    """The flags of `run`, shared with `sweep` (a sweep is a run over a grid of policies)."""
    p.add_argument(
        "--config",
        metavar="FILE",
        help="TOML file with keys: suite, tasks, episodes_per_task, replan_every, [[policy]] name/params",
    )
    p.add_argument("--suite", help="suite name (see `dvla-harness list suites`)")
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
    p.add_argument("--out", metavar="DIR", help="run folder (default: runs/<run id>)")
    mode = p.add_mutually_exclusive_group()
    mode.add_argument(
        "--resume",
        action="store_true",
        help="run only the episodes OUT does not have yet; refuses a folder made by another config",
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


def _list_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "list",
        help="list suites, policies, or a suite's tasks",
        description="List what can be evaluated. Suites whose simulator is missing show the pip extra to install.",
        epilog="examples:\n  dvla-harness list suites\n  dvla-harness list policies\n  dvla-harness list tasks metaworld/mt10",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("what", choices=("suites", "policies", "tasks"))
    p.add_argument("suite", nargs="?", help="with `tasks`: the suite whose tasks to list")
    p.set_defaults(func=cmd_list)


def _show_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "show",
        help="re-print a run's summary from its Parquet rows",
        description="Summarise a run folder (finished or interrupted) from its episode rows.",
        epilog="example:\n  dvla-harness show runs/demo",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("run_dir", metavar="RUN_DIR")
    p.set_defaults(func=cmd_show)


def _collect_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "collect",
        help="record demonstrations (successful episodes) of a policy",
        description=(
            "Run one policy through the ordinary episode loop and keep its successful "
            "episodes as demonstrations for `dvla-harness train` (format: "
            "docs/demonstrations.md). By default episodes come from the suite's train "
            "split, which never shares a layout with evaluation."
        ),
        epilog="example:\n  dvla-harness collect --suite metaworld/mt10 --policy scripted --episodes-per-task 50 --out demos/mt10",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--suite", required=True, help="suite name (see `dvla-harness list suites`)")
    p.add_argument(
        "--policy", required=True, metavar="NAME[:k=v,...]", help="the demonstrator, e.g. scripted"
    )
    p.add_argument("--tasks", metavar="NAME_OR_INDEX,...", help="only these tasks")
    p.add_argument(
        "--episodes-per-task", type=int, metavar="N", help="episodes attempted per task (default: all specs)"
    )
    p.add_argument(
        "--split", default="train", choices=("train", "eval"), help="which episode specs (default train)"
    )
    p.add_argument(
        "--replan-every", type=int, metavar="K", help="actions executed per chunk; 0 = whole chunk"
    )
    p.add_argument("--out", required=True, metavar="DIR", help="demonstrations folder")
    p.add_argument("--overwrite", action="store_true", help="replace an existing demonstrations folder")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_collect)


def _train_parser(sub: argparse._SubParsersAction) -> None:
    from policies.recipes import NOISE_SCHEDULES, RECIPES, SAMPLING, TrainConfig

    d = TrainConfig(recipe="bidirectional")
    p = sub.add_parser(
        "train",
        help="train an action-token model from demonstrations",
        description=(
            "Train the action-token transformer on a demonstrations folder (from `dvla-harness "
            "collect`) with one recipe, deterministically for a given --seed. Writes OUT "
            "(safetensors; its header holds the model shape, attention pattern, tokenizer, "
            "instruction vocabulary, normalisation, recipe and data hash), OUT.json (the same "
            "header, readable) and the loss curve as OUT.loss.csv and OUT.loss.png."
        ),
        epilog=(
            "examples:\n"
            "  dvla-harness train --demos demos/mt10 --recipe bidirectional --out ckpt/teacher.safetensors\n"
            "  dvla-harness train --demos demos/mt10 --recipe distill --teacher ckpt/teacher.safetensors "
            "--out ckpt/fast_dvla.safetensors"
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--demos", required=True, metavar="DIR", help="demonstrations folder")
    p.add_argument("--recipe", required=True, choices=RECIPES)
    p.add_argument("--out", required=True, metavar="FILE.safetensors", help="checkpoint to write")
    p.add_argument("--teacher", metavar="FILE", help="distill: the bidirectional teacher checkpoint")
    p.add_argument(
        "--init",
        metavar="FILE",
        help="continue training this checkpoint (its pattern must fit the recipe; tokenizer and "
        "normalisation are kept)",
    )
    p.add_argument(
        "--sampling",
        choices=SAMPLING,
        default=d.sampling,
        help="task: each instruction equally often in a batch (default); step: each demonstration step",
    )
    p.add_argument(
        "--warmup-steps", type=int, metavar="N", help=f"learning-rate warm-up (default {d.warmup})"
    )
    p.add_argument(
        "--noise-schedule",
        choices=NOISE_SCHEDULES,
        default=d.noise_schedule,
        help="per-block mask ratios (block_diffusion, distill)",
    )
    for name, kind in (
        ("steps", int),
        ("batch_size", int),
        ("lr", float),
        ("seed", int),
        ("chunk_len", int),
        ("width", int),
        ("layers", int),
        ("heads", int),
        ("ffn", int),
        ("block_size", int),
    ):
        p.add_argument(
            "--" + name.replace("_", "-"),
            type=kind,
            default=getattr(d, name),
            help=f"default {getattr(d, name)}",
        )
    p.add_argument("--overwrite", action="store_true", help="replace an existing checkpoint")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_train)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dvla-harness",
        description=(
            "Benchmark and evaluation harness for robot policies that decode discrete action "
            "tokens: success, NFE, control Hz and tokens/s per episode, into Parquet."
        ),
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    from harness import __version__

    parser.add_argument("--version", action="version", version=f"dvla-harness {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    _run_parser(sub)
    _list_parser(sub)
    _show_parser(sub)
    _collect_parser(sub)
    _train_parser(sub)
    from harness.commands import register_all

    register_all(sub)
    return parser


def _config_from_args(args: argparse.Namespace):
    from harness.config import build_config, default_config_data, load_config_file, parse_policy_arg

    data = default_config_data()
    overrides = load_config_file(args.config) if args.config else {}
    if args.suite:
        overrides["suite"] = args.suite
    if overrides.get("suite", data["suite"]) != data["suite"]:
        # The default's task subset and episode count are the main job's, not the protocol's.
        data.pop("tasks", None)
        data.pop("episodes_per_task", None)
    data |= overrides
    if args.tasks is not None:
        data["tasks"] = [t.strip() for t in args.tasks.split(",") if t.strip()]
        if not data["tasks"]:
            raise UsageError("--tasks is empty; give task names or indices, comma-separated")
    if args.policy:
        data["policy"] = [parse_policy_arg(p) for p in args.policy]
    if args.episodes_per_task is not None:
        data["episodes_per_task"] = args.episodes_per_task
    if args.replan_every is not None:
        data["replan_every"] = args.replan_every
    return build_config(data)


def _progress_factory(quiet: bool) -> tuple[Progress, Callable[[int, int], Callable[[bool], None]]]:
    progress = Progress(
        TextColumn("[bold]episodes"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[success]}"),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        console=err_console,
        disable=quiet,
    )
    state = {"done": 0, "ok": 0}

    def start(total: int, skipped: int) -> Callable[[bool], None]:
        if skipped:
            err_console.print(f"resuming: {skipped} episode(s) already recorded, {total} to run")
        task_id = progress.add_task("episodes", total=total, success="success -")

        def tick(success: bool) -> None:
            state["done"] += 1
            state["ok"] += int(success)
            rate = 100 * state["ok"] / state["done"]
            progress.update(
                task_id, advance=1, success=f"success {rate:.0f}% ({state['ok']}/{state['done']})"
            )

        return tick

    return progress, start


def _raise_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def cmd_run(args: argparse.Namespace) -> int:
    from harness.config import resolve

    if args.retry_failed and not args.resume:
        raise UsageError("--retry-failed only makes sense with --resume")
    resolved = resolve(_config_from_args(args))
    return execute_run(resolved, args, "dvla-harness run --out {out} --resume")


def execute_run(
    resolved: Any, args: argparse.Namespace, again: str, labels: dict[str, str] | None = None
) -> int:
    """Run `resolved` with the progress bar, print the summary, return the exit status.

    again: the command that continues an interrupted run ({out} is filled in); labels:
    display names per policy_config_id for the summary (a sweep's grid points).
    """
    from harness.runner import run
    from results.render import summary_table
    from results.summary import summarize

    out = Path(args.out) if args.out else None
    if out is None:
        from datetime import UTC, datetime

        out = Path("runs") / datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
    progress, start = _progress_factory(args.quiet)
    # CI cancels with SIGTERM: stop like Ctrl-C, keeping every finished episode.
    signal.signal(signal.SIGTERM, _raise_interrupt)
    with progress:
        report = run(
            resolved,
            out,
            resume=args.resume,
            overwrite=args.overwrite,
            retry_failed=args.retry_failed,
            progress=start,
            traces=args.traces,
        )
    episodes = report.run_dir.read_episodes()
    if labels and len(episodes):
        episodes["policy"] = episodes["policy_config_id"].map(labels).fillna(episodes["policy"])
    if len(episodes):
        console.print(
            summary_table(summarize(episodes), title=f"{resolved.suite.name} - run {report.run_id}")
        )
    console.print(
        f"rows: {report.run_dir.path / 'episodes.parquet'}  manifest: {report.run_dir.manifest_path}"
    )
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


def cmd_collect(args: argparse.Namespace) -> int:
    from harness.collect import collect
    from harness.config import build_config, parse_policy_arg, resolve

    data: dict[str, Any] = {
        "suite": args.suite,
        "policy": [parse_policy_arg(args.policy)],
        "split": args.split,
    }
    if args.tasks is not None:
        data["tasks"] = [t.strip() for t in args.tasks.split(",") if t.strip()]
    if args.episodes_per_task is not None:
        data["episodes_per_task"] = args.episodes_per_task
    if args.replan_every is not None:
        data["replan_every"] = args.replan_every
    resolved = resolve(build_config(data))
    out = Path(args.out)
    progress, start = _progress_factory(args.quiet)
    total = sum(len(resolved.episodes(t)) for t in resolved.tasks)
    with progress:
        report = collect(resolved, out, args.overwrite, start(total, 0))
    table = Table("task", "kept / attempted", title=f"demonstrations in {out}")
    for task, attempted in report.attempted.items():
        table.add_row(task, f"{report.kept[task]} / {attempted}")
    console.print(table)
    console.print(f"{sum(report.kept.values())} episodes, {report.steps} steps")
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from policies.checkpoint import CheckpointError
    from policies.recipes import TrainConfig
    from policies.training import train

    out = Path(args.out)
    if out.suffix != ".safetensors":
        raise UsageError(f"--out {args.out!r}: a checkpoint file name must end in .safetensors")
    if out.exists() and not args.overwrite:
        raise UsageError(f"checkpoint {args.out!r} exists; pass --overwrite to replace it")
    if not Path(args.demos).is_dir():
        raise UsageError(f"--demos {args.demos!r} is not a folder (make one with `dvla-harness collect`)")
    cfg = TrainConfig(
        recipe=args.recipe,
        steps=args.steps,
        batch_size=args.batch_size,
        lr=args.lr,
        seed=args.seed,
        chunk_len=args.chunk_len,
        width=args.width,
        layers=args.layers,
        heads=args.heads,
        ffn=args.ffn,
        block_size=args.block_size,
        noise_schedule=args.noise_schedule,
        teacher=args.teacher or "",
        init=args.init or "",
        warmup_steps=args.warmup_steps,
        sampling=args.sampling,
    )
    try:
        cfg.validate()
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    progress = Progress(
        TextColumn("[bold]training"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("loss {task.fields[loss]}"),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        console=err_console,
        disable=args.quiet,
    )
    task = progress.add_task("train", total=cfg.steps, loss="-")

    every = max(1, cfg.steps // 20)
    started = time.monotonic()

    def on_step(step: int, loss: float) -> None:
        progress.update(task, advance=1, loss=f"{loss:.4f}")
        # A log file or CI has no live bar: a line every 5% instead.
        if not err_console.is_terminal and not args.quiet and (step + 1) % every == 0:
            elapsed = time.monotonic() - started
            eta = elapsed / (step + 1) * (cfg.steps - step - 1)
            err_console.print(
                f"step {step + 1}/{cfg.steps}  loss {loss:.4f}  {elapsed:.0f} s, ETA {eta:.0f} s"
            )

    try:
        with progress:
            report = train(cfg, args.demos, out, on_step)
    except (ValueError, CheckpointError) as exc:
        raise UsageError(str(exc)) from None
    console.print(
        f"wrote {out} ({cfg.recipe}, {cfg.steps} steps, {report.seconds:.0f} s, "
        f"final loss {sum(report.losses[-50:]) / len(report.losses[-50:]):.4f}); curve: {out.with_suffix('.loss.png')}"
    )
    from policies.checkpoint import load

    error = load(out).meta.get("tokenizer_round_trip_error")
    console.print(f"action tokenizer round-trip error on the training actions: {error:.5f} (mean |a - a'|)")
    return 0


def cmd_list(args: argparse.Namespace) -> int:
    if args.what == "suites":
        from adapters.registry import list_suites

        table = Table("suite", "tasks", "episodes/task", "description", "needs extra")
        for info in list_suites():
            extra = (
                "-"
                if not info.extra
                else (
                    f"{info.extra} (installed)"
                    if info.installed
                    else f"[yellow]pip install 'dvla-harness[{info.extra}]'[/yellow]"
                )
            )
            table.add_row(
                info.name, str(info.num_tasks), str(info.episodes_per_task), info.description, extra
            )
        console.print(table)
    elif args.what == "policies":
        import dataclasses

        from policies.registry import all_policies, describe_param, param_types

        for spec in all_policies().values():
            where = ", ".join(p + "*" for p in spec.suites) or "any suite"
            console.print(f"[bold]{spec.name}[/bold]  {spec.summary}  [dim](suites: {where})[/dim]")
            types = param_types(spec.params)
            for f in dataclasses.fields(spec.params):
                console.print("    " + describe_param(f, types[f.name].__name__), markup=False)
    else:
        if not args.suite:
            raise UsageError("`list tasks` needs a suite, e.g. dvla-harness list tasks metaworld/mt10")
        from harness.config import RunConfig, resolve_suite

        suite, tasks = resolve_suite(RunConfig(suite=args.suite, policies=()))
        table = Table(
            "#", "task", "instruction", "max steps", "episodes", title=f"{suite.name} (v{suite.version})"
        )
        for task in tasks:
            table.add_row(
                str(task.index), task.name, task.instruction, str(task.max_steps), str(len(task.episodes))
            )
        console.print(table)
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    from results.render import summary_table
    from results.store import ResultsFileError, RunDir
    from results.summary import summarize

    run_dir = RunDir(args.run_dir)
    try:
        manifest = run_dir.read_manifest()
        episodes = run_dir.read_episodes()
    except ResultsFileError as exc:
        raise UsageError(str(exc)) from None
    env = manifest.get("environment", {})
    console.print(
        f"run {manifest.get('run_id')} ({manifest.get('status')}), suite {manifest['suite']['name']}, "
        f"{len(episodes)} episodes; started {manifest.get('started_at')}; "
        f"{env.get('cpu')}, GPU {env.get('gpu') or 'none'}; git {env.get('git_commit') or 'n/a'}"
    )
    if len(episodes):
        console.print(summary_table(summarize(episodes)))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except UsageError as exc:
        print(f"dvla-harness {args.command}: error: {exc}", file=sys.stderr)  # one unwrapped line
        return 2


def entry() -> Any:
    sys.exit(main())
