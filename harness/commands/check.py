"""`dvla-harness check`: conformance checks for a suite or a policy (a plugin's first test)."""

from __future__ import annotations

import argparse

from harness.errors import UsageError

EPILOG = """\
examples:
  dvla-harness check suite line/walk                         # a plugin suite's contract
  dvla-harness check policy constant:value=1 --suite line/walk
  dvla-harness check suite metaworld/mt1/reach-v3 --steps 20

One line per rule (ok / FAIL and what was seen); exit 1 if any rule failed, 2 for an
unknown suite or policy. Nothing is written. The rules: docs/plugins.md.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "check",
        help="check a suite or a policy against the harness's contract (for plugin authors)",
        description="Conformance checks in the spirit of Gymnasium's check_env.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("what", choices=("suite", "policy"))
    p.add_argument("name", help="a suite name, or a policy as NAME[:k=v,...]")
    p.add_argument("--suite", help="with `policy`: the suite to act in")
    p.add_argument("--steps", type=int, default=5, help="env steps per task to check (default 5)")
    p.set_defaults(func=cmd_check)


def cmd_check(args: argparse.Namespace) -> int:
    from harness.config import RunConfig, parse_policy_arg, resolve_suite
    from harness.conformance import check_policy, check_suite
    from harness.console import console

    if args.steps < 1:
        raise UsageError(f"--steps must be >= 1, got {args.steps}")
    if args.what == "suite":
        suite, _ = resolve_suite(RunConfig(suite=args.name, policies=()))
        findings = check_suite(suite, args.steps)
    else:
        if not args.suite:
            raise UsageError("`check policy` needs --suite SUITE to act in")
        from policies.registry import UnknownPolicyError, get_policy

        choice = parse_policy_arg(args.name)
        try:
            spec = get_policy(choice.name)
        except UnknownPolicyError as exc:
            raise UsageError(str(exc)) from None
        suite, _ = resolve_suite(RunConfig(suite=args.suite, policies=()))
        findings = check_policy(spec, dict(choice.params), suite)
    failed = 0
    for f in findings:
        failed += not f.ok
        mark = "[green]ok[/green]  " if f.ok else "[red]FAIL[/red]"
        console.print(f"{mark} {f.rule}" + (f": {f.detail}" if f.detail else ""), highlight=False)
    console.print(f"{failed} rule(s) failed" if failed else "all rules hold")
    return 1 if failed else 0
