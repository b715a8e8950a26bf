"""`dvla-harness gate`: fail CI when a candidate run regresses against a baseline run.

The verdict comes from results/gate.py (usable from notebooks); this module only turns
flags into a call, the result into a table, and the verdict into an exit status.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from rich.table import Table

from harness.errors import UsageError
from results.table_fit import ALWAYS, Fit

if TYPE_CHECKING:  # pandas and the gate load only when the command runs, not for every CLI call
    from results.gate import GateResult, TaskDiff
    from results.gate_speed import SpeedDiff
    from results.replay import ReplaySpeed

DESCRIPTION = """\
Compare a candidate run with a baseline run of the same episodes and exit 1 on a
regression, so CI can run a short evaluation and then this command.

What fails the gate:
  success   a drop that is significant at --alpha by McNemar's exact test (one-sided)
            on the paired episodes: overall at alpha, per task at alpha / tasks.
            A drop that could be chance (e.g. 1 of 9 episodes) passes.
  chain length  (instruction-chain suites) a drop in subtasks completed per chain,
            chains paired, by the exact sign test; it and full-chain success are each
            tested at alpha / 2, so a policy that stops earlier is caught even when
            its 5/5 chains hold.
  NFE       any increase of NFE per chunk (forward passes are counted, not timed,
            so they are exact for deterministic decoders), unless --allow-nfe-increase.
  work      any increase of counted work per chunk (FLOPs of the passes' matrix
            products, read from tensor shapes by the same hooks: exact on any machine
            under any load), unless --allow-work-increase. Not measured on either side
            (a remote server that reports none, rows from before it was recorded):
            not compared, said in a note.
  tokens/s  a slowdown beyond --max-slowdown of each configuration's tokens/s relative
            to a reference decoder's (--reference, default bidirectional) timed in the
            same run, episode by episode, against the same ratio in the baseline run:
            the machine's speed and load cancel out, its CPU model does not. Where no
            such reference exists (not in both runs, changed, different torch thread
            counts) or the manifests name different CPUs (family, model, stepping,
            microcode, caches, flags; the model name for older manifests) (unless
            --speed-across-cpus), the table says "not comparable" with the reason, and
            speed does not fail the gate.
  replay    when both runs were benched (`dvla-harness bench`, replay.json), speed is
            judged on the replay benchmark instead: the same ratio, round by round
            over recorded observations, with a 95% bootstrap interval. It fails only
            when the whole interval lies beyond --max-slowdown; when the interval
            straddles it the gate passes with a warning ("inconclusive"), or fails
            with --inconclusive fail. The closed-loop ratio is then reported, not
            judged, and the verdict line says how far the replay's figure can be
            trusted (rounds, waiting for a core, the machine's speed).
  replay work  when both runs were benched, any increase of the work their
            decodes ran, counted at torch's dispatcher: the FLOPs of every torch
            product, wherever the decoder's code calls it (the module hooks behind
            `work` see only the counted modules' products), unless
            --allow-work-increase.

Episodes pair by (suite, task, episode_index, seed, init_state_id). Policy
configurations pair by name + params + checkpoint hash; then by name alone when that
is unambiguous; then, if one is left on each side, those two (so a run of policy A can
gate a run of policy B). Runs whose episodes or configurations do not match are refused.

Exit status: 0 the candidate holds; 1 regression; 2 unusable input (missing or foreign
files, another schema version, mismatched episodes). Details: docs/ci-gate.md.
"""

EXAMPLES = """\
examples:
  # the committed CI baseline: a fresh short run (its bidirectional rows are the
  # reference), the replay benchmark on the baseline's recorded observations, then the gate
  OMP_NUM_THREADS=1 dvla-harness run --config results/baselines/metaworld-mt10-smoke.toml \\
      --out runs/ci --quiet
  OMP_NUM_THREADS=1 dvla-harness bench runs/ci \\
      --observations results/baselines/metaworld-mt10-smoke --quiet
  dvla-harness gate --baseline results/baselines/metaworld-mt10-smoke --candidate runs/ci \\
      --max-slowdown 0.10

  # yesterday's run against today's, stricter, NFE allowed to grow
  dvla-harness gate --baseline runs/old/episodes.parquet --candidate runs/new \\
      --alpha 0.01 --allow-nfe-increase

  # from Python
  from results.runs import load_run; from results.gate import gate_runs
  gate_runs(load_run("runs/old"), load_run("runs/new")).failures
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "gate",
        help="exit 1 if a candidate run regresses against a baseline (success, NFE, speed)",
        description=DESCRIPTION,
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--baseline", required=True, metavar="RUN_DIR|PARQUET", help="the reference run")
    p.add_argument("--candidate", required=True, metavar="RUN_DIR|PARQUET", help="the run under test")
    p.add_argument(
        "--alpha",
        type=float,
        default=0.05,
        help="significance level of a success drop (default 0.05; smaller = fewer false alarms)",
    )
    p.add_argument(
        "--max-slowdown",
        type=float,
        default=0.10,
        metavar="FRACTION",
        help="largest allowed drop of tokens/s relative to the reference, e.g. 0.10 = 10%% (default 0.10)",
    )
    p.add_argument(
        "--reference",
        default="bidirectional",
        metavar="POLICY|CONFIG_ID",
        help="the decoder in both runs that speed is measured against (default bidirectional)",
    )
    p.add_argument(
        "--speed-across-cpus",
        action="store_true",
        help="judge speed even when the runs' manifests name different CPUs (by default not "
        "comparable: the CPU alone moves a decoder's speed over its reference)",
    )
    p.add_argument(
        "--inconclusive",
        choices=("pass", "fail"),
        default="pass",
        help="what a replay speed verdict whose interval straddles --max-slowdown does: pass with a "
        "warning (default), or fail the gate, for a team that wants such a change to block a merge",
    )
    p.add_argument(
        "--allow-nfe-increase", action="store_true", help="report NFE/chunk increases but do not fail"
    )
    p.add_argument(
        "--allow-work-increase",
        action="store_true",
        help="report counted work (GFLOP/chunk) increases but do not fail",
    )
    from harness.console import add_wide_argument

    add_wide_argument(p)
    p.set_defaults(func=cmd_gate)


# What a narrow terminal keeps first (results/table_fit.py): which row, its verdict and
# the evidence behind a success verdict, then speed and work.
GATE_RANKS = {
    "configuration": ALWAYS,
    "task": ALWAYS,
    "verdict": ALWAYS,
    "successes": 10,
    "p (drop)": 20,
    "subtasks/chain (shorter/longer, p)": 30,
    "tokens/s vs ref.": 40,
    "replay vs ref. [95%]": 50,
    "NFE/chunk": 60,
    "GFLOP/chunk": 70,
    "drops/gains": 80,
    "episodes": 90,
}


def _fmt(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def render(result: GateResult, title: str) -> Table:
    chains = any(t.length_p is not None for t in result.tasks)
    # counted work: a column when either run measured it (a note says when it is not compared)
    work = any(t.baseline_work is not None or t.candidate_work is not None for t in result.tasks)
    columns = ["configuration", "task", "episodes", "successes", "drops/gains", "p (drop)"]
    columns += ["subtasks/chain (shorter/longer, p)"] if chains else []
    replay = {r.pair: r for r in result.replay}
    more_work = {w.pair for w in result.replay_work if w.increased and w.gated}
    table = Table(
        *columns,
        "NFE/chunk",
        *(["GFLOP/chunk"] if work else []),
        "tokens/s vs ref. (closed loop, not judged)" if replay else "tokens/s vs ref.",
        *(["replay vs ref. [95%]"] if replay else []),
        "verdict",
        title=title,
        caption=(
            "successes, NFE/chunk and GFLOP/chunk (counted work): baseline -> candidate; "
            "* = significant drop; tokens/s vs ref.: "
            "change of tokens/s over the reference decoder's in the same run"
            + ("; subtasks/chain: mean subtasks completed, chains paired" if chains else "")
            + (
                "; replay: the same ratio over the bench's rounds, with its bootstrap interval "
                "(judged in place of tokens/s)"
                if replay
                else ""
            )
        ),
    )
    skipped = dict(result.not_comparable)
    speed = {s.pair: s for s in result.speed}
    short = {p.label: p.short for p in result.pairs}
    previous = None
    for t in result.tasks:
        s = speed.get(t.pair) if t.task == "ALL" else None
        r = replay.get(t.pair) if t.task == "ALL" else None
        bad = [
            name
            for name, hit in (
                ("success", t.success_regressed),
                ("chain length", t.length_regressed),
                ("NFE", t.nfe_increased and t.nfe_gated),
                ("work", (t.work_increased and t.work_gated) or (t.task == "ALL" and t.pair in more_work)),
                ("speed", r.verdict == "fail" if r is not None else s is not None and s.regressed),
            )
            if hit
        ]
        nfe = f"{_fmt(t.baseline_nfe)} -> {_fmt(t.candidate_nfe)}"
        table.add_row(
            short[t.pair] if t.pair != previous else "",
            t.task,
            str(t.episodes),
            f"{t.baseline_successes} -> {t.candidate_successes}",
            f"{t.drops} / {t.gains}",
            f"{t.p_value:.3g}" + (" *" if t.success_regressed else ""),
            *([_length_cell(t)] if chains else []),
            nfe + (" (up)" if t.nfe_increased else ""),
            *([_work_cell(t)] if work else []),
            _speed_cell(t.task, t.pair, s, skipped, result.reference),
            *([_replay_cell(r, t.task == "ALL" and t.pair == result.reference)] if replay else []),
            "[red]FAIL " + ", ".join(bad) + "[/red]" if bad else "[green]ok[/green]",
            end_section=t.task == "ALL",
        )
        previous = t.pair
    return table


def _work_cell(t: TaskDiff) -> str:
    if t.baseline_work is None or t.candidate_work is None:
        return "-"
    text = f"{t.baseline_work / 1e9:.3f} -> {t.candidate_work / 1e9:.3f}"
    return text + (" (up)" if t.work_increased else "")


def _length_cell(t: TaskDiff) -> str:
    if t.length_p is None:
        return ""
    return (
        f"{_fmt(t.baseline_length)} -> {_fmt(t.candidate_length)} ({t.length_drops}/{t.length_gains}, "
        f"p {t.length_p:.3g}{' *' if t.length_regressed else ''})"
    )


def _speed_cell(task: str, pair: str, s: SpeedDiff | None, skipped: dict[str, str], reference: str) -> str:
    if task != "ALL":
        return ""
    if s is not None:
        return f"{s.change:+.1%}"
    if pair == reference:
        return "reference"
    return "not comparable" if pair in skipped else ""


def _replay_cell(r: ReplaySpeed | None, is_reference: bool) -> str:
    if r is None:
        return "reference" if is_reference else ""
    shown = f"{r.change:+.1%} [{r.low:+.1%}, {r.high:+.1%}]"
    return shown + (" inconclusive" if r.verdict == "inconclusive" else "")


def cmd_gate(args: argparse.Namespace) -> int:
    from harness.console import console, err_console, print_note, print_table
    from results.gate import GateInputError, gate_runs
    from results.gate_inputs import check_gate_inputs
    from results.render import task_keys
    from results.replay import ReplayFileError
    from results.runs import load_run
    from results.store import ResultsFileError

    if not 0 < args.alpha < 1:
        raise UsageError(f"--alpha must be between 0 and 1, got {args.alpha}")
    if not args.max_slowdown >= 0:
        raise UsageError(f"--max-slowdown must be >= 0, got {args.max_slowdown}")
    runs = {}
    for side in ("baseline", "candidate"):
        try:
            runs[side] = load_run(getattr(args, side))
            check_gate_inputs(runs[side].episodes, getattr(args, side))  # a NaN success, a negative NFE
        except ResultsFileError as exc:
            raise UsageError(f"--{side}: {exc}") from None
    try:
        result = gate_runs(
            runs["baseline"],
            runs["candidate"],
            alpha=args.alpha,
            max_slowdown=args.max_slowdown,
            allow_nfe_increase=args.allow_nfe_increase,
            allow_work_increase=args.allow_work_increase,
            reference=args.reference,
            speed_across_cpus=args.speed_across_cpus,
            inconclusive=args.inconclusive,
        )
    except GateInputError as exc:
        raise UsageError(f"cannot compare {args.baseline} with {args.candidate}: {exc}") from None
    except ReplayFileError as exc:
        raise UsageError(str(exc)) from None
    title = f"gate: {args.candidate} vs baseline {args.baseline}"
    fit = Fit(GATE_RANKS, task_keys(runs["candidate"].episodes))
    print_table(render(result, title), fit=fit, wide=args.wide)
    for pair in result.pairs:
        if pair.rule != "same policy and params":
            print_note("paired", f"{pair.label}: {pair.rule}", console)
    for note in result.notes:
        print_note("note:", note, console)
    for warning in result.warnings:
        print_note("[yellow]warning:[/yellow]", warning, console)
    for r in result.replay:  # the figure that decided speed, and how far it can be trusted
        console.print(f"verdict: {r.trust()}")
    if result.passed:
        unsure = [r.pair for r in result.replay if r.verdict == "inconclusive"]
        speed = f"speed inconclusive for {', '.join(unsure)} (warning above)" if unsure else "no slowdown"
        if not result.speed and not result.replay:
            speed = "speed not compared (the note above says why)"
        console.print(
            "[green]gate passed[/green]: no significant success drop, no NFE or counted work increase, "
            f"{speed}"
        )
        return 0
    err_console.print("[red]gate failed[/red]:\n  " + "\n  ".join(result.failures))
    return 1
