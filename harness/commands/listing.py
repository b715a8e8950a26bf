"""`dvla-harness list`: suites, policies and a suite's tasks, without importing simulators."""

from __future__ import annotations

import argparse

from rich.markup import escape
from rich.table import Table

from harness.console import add_wide_argument, console, print_table
from harness.errors import UsageError
from harness.plugins import install_hint
from results.table_fit import ALWAYS, Fit


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "list",
        help="list suites, policies, a suite's tasks, or latency profiles",
        description="List what can be evaluated. Suites whose simulator is missing show the pip extra to install.",
        epilog="examples:\n  dvla-harness list suites\n  dvla-harness list policies\n  dvla-harness list tasks metaworld/mt10",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("what", choices=("suites", "policies", "tasks", "latency-profiles"))
    p.add_argument("suite", nargs="?", help="with `tasks`: the suite whose tasks to list")
    add_wide_argument(p)
    p.set_defaults(func=cmd_list)


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
                    else f"[yellow]{escape(install_hint(info.extra, info.package))}[/yellow]"
                )
            )
            table.add_row(
                info.name, str(info.num_tasks), str(info.episodes_per_task), info.description, extra
            )
        # the names a user types stay whole: the suite and the install command first
        ranks = {"needs extra": ALWAYS, "description": 10, "tasks": 20, "episodes/task": 30}
        print_table(table, fit=Fit(ranks, prose=frozenset({"description"})), wide=args.wide)
    elif args.what == "latency-profiles":
        from harness.episode.latency import profile_rows

        table = Table(
            "profile", "chunk latency per decoder", "source", title="--inference-latency profile:NAME"
        )
        for name, chunks, source in profile_rows():
            table.add_row(name, chunks, source)
        print_table(table, wide=args.wide)
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
        print_table(table, fit=Fit({"task": ALWAYS}, prose=frozenset({"instruction"})), wide=args.wide)
    return 0
