"""Runs laid out like Fast-dVLA's LIBERO table: methods x suites, average, tokens/s,
speedup, with the published rows beneath, labelled with their source.

Built from the per-suite leaderboards, so the same rows, labels, machine rule for
speedups and warnings apply; only the layout differs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from results.leaderboard import (
    DEFAULT_BASELINE,
    Block,
    Cell,
    Entry,
    Leaderboard,
    Success,
    finite_or_none,
    leaderboards,
    markdown_table,
    number_cell,
)
from results.published import (
    CALVIN,
    LIBERO,
    PRIVILEGED,
    PUBLISHED,
    SIMPLERENV,
    PublishedTable,
    check_comparable,
    is_libero,
    libero_column,
    privileged_label,
    tables_for,
)
from results.runs import Run


@dataclass(frozen=True)
class PaperRow:
    label: str
    policy_config_id: str
    machine: str
    success: dict[str, Success]  # suite -> success
    average: float | None  # mean of the suite success rates; None unless every suite was run
    tokens_per_s: float
    speedup: float | None
    speedup_note: str
    runs: tuple[str, ...] = ()


@dataclass(frozen=True)
class PaperTable:
    """Fast-dVLA's LIBERO layout: methods x suites, average, tokens/s, speedup; and its
    CALVIN layout, one table per instruction-chain suite (`chain_boards`)."""

    suites: tuple[str, ...]
    rows: tuple[PaperRow, ...]
    baseline: str
    warnings: tuple[str, ...]
    chain_boards: tuple[Leaderboard, ...] = ()
    variant_boards: tuple[Leaderboard, ...] = ()  # SimplerEnv-like suites: their own layout


def paper_table(runs: Sequence[Run], baseline: str | None = None) -> PaperTable:
    """LIBERO suites in the paper's layout, the chain and SimplerEnv-like suites in
    theirs; other suites (Meta-World, plugins) have only their leaderboards.

    Speedups are taken within each suite (its own leaderboard: the baseline's rows of
    that suite, on the same machine) and averaged over the suites a row has, never
    across suites: a LIBERO row is not measured against a Meta-World teacher. Tokens/s
    is the mean over those suites likewise, so each suite counts once."""
    every = leaderboards(runs, baseline)
    chain_boards = tuple(b for b in every if b.is_chain)  # CALVIN's layout: not averaged with LIBERO's
    variant_boards = tuple(b for b in every if is_simpler(b))  # SimplerEnv's: canonical vs aggregated
    # Only LIBERO suites take LIBERO's layout: a Meta-World or plugin suite has no published
    # row to stand beside, and its own leaderboard already shows it.
    boards = [b for b in every if not b.is_chain and not is_simpler(b) and is_libero(b.suite)]
    baseline = baseline or DEFAULT_BASELINE
    keys = list(dict.fromkeys((e.policy_config_id, e.machine) for b in boards for e in b.entries))
    out = []
    for cid, machine in keys:
        mine = {
            b.suite: e for b in boards for e in b.entries if (e.policy_config_id, e.machine) == (cid, machine)
        }
        success = {suite: e.overall for suite, e in mine.items()}
        average = (
            sum(100 * v.rate for v in success.values()) / len(boards) if len(success) == len(boards) else None
        )
        speedup, note = _suite_mean_speedup(mine)
        first = next(iter(mine.values()))
        tokens = (
            float(np.nanmean([e.tokens_per_s for e in mine.values()]))
            if any(np.isfinite(e.tokens_per_s) for e in mine.values())
            else float("nan")
        )
        runs_of = tuple(dict.fromkeys(r for e in mine.values() for r in e.runs))
        out.append(PaperRow(first.label, cid, machine, success, average, tokens, speedup, note, runs_of))
    warnings = [f"{b.suite}: {w}" for b in every for w in b.warnings]
    return PaperTable(
        tuple(b.suite for b in boards),
        tuple(out),
        baseline,
        tuple(dict.fromkeys(warnings)),
        chain_boards,
        variant_boards,
    )


def is_simpler(board: Leaderboard) -> bool:
    """A SimplerEnv-like suite (simpler/*, or any run with variant rows)."""
    return board.suite.lower().startswith("simpler/") or any(e.variants is not None for e in board.entries)


def _suite_mean_speedup(entries: dict[str, Entry]) -> tuple[float | None, str]:
    """The mean of a row's per-suite speedups, or why there is none; names the suites
    left out when only some have one."""
    have = {suite: e.speedup for suite, e in entries.items() if e.speedup is not None}
    if not have:
        return None, next(iter(entries.values())).speedup_note
    if len(have) < len(entries):
        missing = ", ".join(s for s in entries if s not in have)
        return sum(have.values()) / len(have), f"without {missing}"
    return sum(have.values()) / len(have), ""


def measured_speed_headers(baseline: str) -> list[str]:
    """A measured table's speed columns, named apart from a published table's: this
    machine's tokens/s and a speedup over this run's own baseline."""
    return ["tokens/s (measured)", f"speedup vs {baseline} (measured)"]


def published_block(table: PublishedTable, title: str, tag: str, notes: Sequence[str]) -> Block:
    """A published table in a section of its own beneath the measured one: its tokens/s
    were timed on the paper's hardware and its speedups are over the paper's own baseline
    (`table.baseline`), so they never share a column with figures measured here."""
    speed = [f"tokens/s ({PUBLISHED})"]
    if table.baseline:
        speed.append(f"speedup vs {table.baseline} ({PUBLISHED})")
    headers = ["method", *table.columns, *speed, "source"]
    rows = []
    for p in table.rows:
        cells = [Cell(table.text("tokens/s", p.tokens_per_s), p.tokens_per_s)]
        if table.baseline:
            cells.append(Cell("-" if p.speedup is None else f"{p.speedup:.1f}x", p.speedup))
        rows.append(
            [
                Cell(f"{p.method} ({tag})", p.method),
                *(Cell(table.text(c, p.values.get(c)), p.values.get(c)) for c in table.columns),
                *cells,
                Cell(f"{PUBLISHED}: {p.source}", p.source),
            ]
        )
    return Block(title, headers, rows, tuple(notes), 0)


def paper_blocks(pt: PaperTable, allow_privileged: bool = False) -> list[Block]:
    """The measured rows in the paper's layout, then each published table in a section of
    its own, labelled with its source: success columns carry the paper's names in both,
    while tokens/s and speedups (the paper's hardware and baseline, or this machine's and
    this run's) stay in their own sections.

    The published LIBERO rows read camera images; a LIBERO suite measured on privileged
    state (obs=state or obs=images) raises PrivilegedRowsError unless `allow_privileged`,
    and such rows are labelled '[privileged state]' either way."""
    privileged = check_comparable(pt.suites, allow_privileged)
    columns = {s: libero_column(s) for s in pt.suites}
    aligned = bool(columns) and all(columns.values()) and len(set(columns.values())) == len(columns)
    suites = list(pt.suites)
    if aligned:
        suites.sort(key=lambda s: LIBERO.columns.index(columns[s]))  # type: ignore[arg-type]
    names = [f"{columns[s]} ({s})" if aligned else s for s in suites]
    headers = ["method", *names, "Avg", *measured_speed_headers(pt.baseline), "source"]
    rows = []
    for r in pt.rows:
        rows.append(
            [
                Cell(
                    r.label
                    + (f" @ {r.machine}" if len({x.machine for x in pt.rows}) > 1 else "")
                    + privileged_label(list(r.success)),
                    r.label,
                ),
                *(
                    Cell(r.success[s].text(), finite_or_none(r.success[s].rate))
                    if s in r.success
                    else Cell("-", None)
                    for s in suites
                ),
                Cell(f"{r.average:.1f}", r.average)
                if r.average is not None
                else Cell("n/a: not every suite", None),
                number_cell(r.tokens_per_s, ".0f"),
                Cell(f"{r.speedup:.2f}x", r.speedup) if r.speedup is not None else Cell(r.speedup_note, None),
                Cell("measured: " + ", ".join(r.runs), "measured"),
            ]
        )
    notes = pt.warnings
    if privileged:
        notes = (
            *notes,
            f"rows marked [{PRIVILEGED}] were measured on object and fixture poses "
            f"({', '.join(privileged)}); the published rows on camera images: not the same task",
        )
    blocks = [Block("measured", headers, rows, notes)] if pt.suites else []
    for table in tables_for(list(pt.suites)) if pt.suites else ():
        note = f"{table.name}, {PUBLISHED}: {table.source}; {table.note}; not measured here"
        blocks.append(published_block(table, f"{PUBLISHED}: {table.name}", PUBLISHED, (note,)))
    return (
        blocks
        + [b for board in pt.chain_boards for b in calvin_blocks(board, pt.baseline)]
        + [b for board in pt.variant_boards for b in simpler_blocks(board, pt.baseline)]
    )


NOT_CALVIN = "CALVIN-like: CALVIN's protocol on LIBERO scenes, not CALVIN's scene or tasks (docs/chains.md)"


def _entry_row(e: Entry, machines: bool, cells: Sequence[Cell]) -> list[Cell]:
    """A measured row of a benchmark's own layout: label, the layout's cells, tokens/s,
    speedup and where it was measured."""
    return [
        Cell(e.label + (f" @ {e.machine}" if machines else ""), e.label),
        *cells,
        number_cell(e.tokens_per_s, ".0f"),
        Cell(f"{e.speedup:.2f}x", e.speedup) if e.speedup is not None else Cell(e.speedup_note, None),
        Cell("measured: " + ", ".join(e.runs), "measured"),
    ]


def calvin_blocks(board: Leaderboard, baseline: str) -> list[Block]:
    """One chain suite in Fast-dVLA's CALVIN layout (reaching 1/5 ... 5/5, avg len,
    tokens/s), then the published CALVIN rows in a section of their own, labelled as a
    different benchmark: the same protocol and metrics, but CALVIN's own scene, tasks and
    training data, so no number of ours can be read against theirs."""
    headers = ["method", *CALVIN.columns, *measured_speed_headers(baseline), "source"]
    rows = []
    machines = len(board.machines) > 1
    for e in board.entries:
        assert e.chain is not None
        reach = [Cell(e.chain.reach_text(k), finite_or_none(e.chain.reach(k))) for k in range(1, 6)]
        rows.append(
            _entry_row(e, machines, [*reach, Cell(e.chain.length_text(), finite_or_none(e.chain.avg_len))])
        )
    notes = (
        f"{board.suite}: {NOT_CALVIN}",
        "measured: % of chains reaching k of 5 subtasks (Wilson 95%); avg len: subtasks completed "
        "per chain (bootstrap 95%)",
    )
    note = f"{CALVIN.name}, {PUBLISHED}: {CALVIN.source}; {CALVIN.note}; not measured here, and not the same benchmark"
    return [
        Block(f"{board.suite} (CALVIN layout)", headers, rows, notes),
        published_block(CALVIN, f"{PUBLISHED}: {CALVIN.name}", "published, CALVIN: not comparable", (note,)),
    ]


NOT_SIMPLERENV = (
    "SimplerEnv-like: SimplerEnv's protocol (a reference scene, variant aggregation) on ManiSkill3 "
    "tasks, not SimplerEnv's scenes, real-to-sim assets or robots; the canonical scene is "
    "ManiSkill3's default scene, not SimplerEnv's visual matching (docs/simpler.md)"
)


def simpler_blocks(board: Leaderboard, baseline: str) -> list[Block]:
    """One SimplerEnv-like suite as SimplerEnv reports it: the canonical scene (in the
    place of SimplerEnv's visual matching, which it is not) and the variant aggregation
    side by side, never pooled into one rate; then the published SimplerEnv rows in a
    section of their own, labelled as a different benchmark."""
    headers = [
        "method",
        "canonical scene (Wilson 95%)",
        "variant aggregation, SimplerEnv's set per task (bootstrap 95%)",
        *measured_speed_headers(baseline),
        "source",
    ]
    rows = []
    machines = len(board.machines) > 1
    for e in board.entries:
        canonical = e.variants.canonical if e.variants is not None else e.overall
        aggregated = (
            Cell(e.variants.aggregated_text(), finite_or_none(e.variants.aggregated))
            if e.variants is not None
            else Cell("-", None)
        )
        rows.append(
            _entry_row(e, machines, [Cell(canonical.text(), finite_or_none(canonical.rate)), aggregated])
        )
    notes = [f"{board.suite}: {NOT_SIMPLERENV}"]
    if board.ranking is not None:
        notes.append(board.ranking.text())
    note = (
        f"{SIMPLERENV.name}, {PUBLISHED}: {SIMPLERENV.source}; {SIMPLERENV.note}; not measured here, "
        "and not the same benchmark"
    )
    return [
        Block(f"{board.suite} (SimplerEnv layout)", headers, rows, tuple(notes)),
        published_block(
            SIMPLERENV, f"{PUBLISHED}: {SIMPLERENV.name}", "published, SimplerEnv: not comparable", (note,)
        ),
    ]


NO_PUBLISHED_TABLE = (
    "no LIBERO, CALVIN-like or SimplerEnv-like suite in these runs: no published table to lay "
    "them out beside (`dvla-harness leaderboard` shows them)"
)


def blocks_markdown(blocks: Sequence[Block]) -> str:
    if not blocks:
        return NO_PUBLISHED_TABLE[0].upper() + NO_PUBLISHED_TABLE[1:] + ".\n"
    parts = []
    for b in blocks:
        parts.append(f"### {b.title}\n\n" + markdown_table(b.headers, [[c.text for c in r] for r in b.rows]))
        if b.notes:
            parts.append("\n".join(f"- {n}" for n in b.notes))
    return "\n\n".join(parts) + "\n"
