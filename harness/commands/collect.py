"""`dvla-harness collect`: demonstrations through the ordinary episode loop (docs/demonstrations.md)."""

from __future__ import annotations

import argparse
import signal
from pathlib import Path
from typing import Any

from rich.table import Table

from harness.console import console, episode_progress, err_console, raise_interrupt
from harness.errors import EXIT_INTERRUPTED


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "collect",
        help="record demonstrations (successful episodes) of a policy",
        description=(
            "Run one policy through the ordinary episode loop and keep its successful "
            "episodes as demonstrations for `dvla-harness train` (format: "
            "docs/demonstrations.md). By default episodes come from the suite's train "
            "split, which never shares a layout with evaluation; for LIBERO that means fresh "
            "initial states drawn from each task's BDDL distribution and checked against the "
            "evaluation ones (suite option initial_states=fresh|evaluation, states_seed=N)."
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
        "--episodes-per-task",
        type=int,
        metavar="N",
        help="episodes attempted per task (default: all of the split; Meta-World's train split has 1,000 layouts per task)",
    )
    p.add_argument(
        "--split", default="train", choices=("train", "eval"), help="which episode specs (default train)"
    )
    p.add_argument(
        "--replan-every", type=int, metavar="K", help="actions executed per chunk; 0 = whole chunk"
    )
    p.add_argument(
        "--action-noise",
        type=float,
        default=0.0,
        metavar="SIGMA",
        help="DART-style collection: the env executes the demonstrator's action plus Gaussian "
        "noise of std SIGMA x half the action range (all dimensions but the gripper, the last); "
        "the demonstrator's own action is recorded, so the demonstrations show recoveries "
        "(default 0: none; try 0.1)",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=1,
        metavar="N",
        help="worker processes on this machine (default 1); the folder is the same for any N, "
        "since episodes are merged in the suite's order and noise is seeded per episode",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="demonstrations folder")
    p.add_argument("--overwrite", action="store_true", help="replace an existing demonstrations folder")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_collect)


def cmd_collect(args: argparse.Namespace) -> int:
    """Ctrl-C or SIGTERM (as CI cancels a job) at any point: the workers are stopped, one
    line, exit 130; nothing is written (the folder is written once, at the end)."""
    signal.signal(signal.SIGTERM, raise_interrupt)
    try:
        return _collect(args)
    except KeyboardInterrupt:
        err_console.print(
            f"interrupted; nothing was written to {args.out} (collect writes its folder once, at the "
            "end): run the same command again",
            soft_wrap=True,
            highlight=False,
        )
        return EXIT_INTERRUPTED


def _collect(args: argparse.Namespace) -> int:
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
    progress, start = episode_progress(args.quiet)
    total = sum(len(resolved.episodes(t)) for t in resolved.tasks)
    with progress:
        report = collect(resolved, out, args.overwrite, start(total, 0), args.action_noise, args.workers)
    chains = bool(report.subtasks_kept)
    columns = ["task", "kept / attempted", *(["subtasks kept"] if chains else [])]
    table = Table(*columns, title=f"demonstrations in {out}")
    for task, attempted in report.attempted.items():
        extra = [str(report.subtasks_kept.get(task, 0))] if chains else []
        table.add_row(task, f"{report.kept[task]} / {attempted}", *extra)
    console.print(table)
    console.print(f"{sum(report.kept.values())} episodes, {report.steps} steps")
    if chains:
        console.print(
            "instruction chains: every chain keeps the steps of the subtasks it completed, up to "
            "its first failure, each under its own instruction (docs/chains.md, Demonstrations)",
            soft_wrap=True,
        )
    if report.fresh_states:
        closest = min(report.closest_to_evaluation.values())
        console.print(
            f"initial states: {sum(report.fresh_states.values())} fresh draws from each task's BDDL "
            f"distribution ({resolved.suite.name}); none equals an evaluation state (sha256 checked); "
            f"the closest is {closest * 1000:.1f} mm from one (largest object displacement)",
            soft_wrap=True,
        )
    return 0
