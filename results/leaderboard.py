"""Leaderboards: any number of runs combined into one table per suite.

A row is a policy configuration (`policy_config_id`) measured on one machine: the same
configuration timed on two machines gets two rows, because tokens/s, Hz and wall-clock
belong to the machine. Success columns are one per task when a suite has at most
`MAX_TASK_COLUMNS` tasks in the rows (Meta-World MT10, a LIBERO suite), otherwise only
the overall column (MT50, LIBERO-90); `group_by` maps tasks to other groups.

Every number comes from the episode rows. Manifests are read only for what cannot be
in a row: which machine ran it (speedups are computed only between rows of the same
machine) and the versions and render backend that move scores (differences become
warnings, which outputs must show, not bury).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import pandas as pd
from rich.table import Table

from results.board_warnings import episode_warnings, provenance_warnings
from results.chain_table import ChainStats, chain_cells, chain_columns, chain_stats, is_chain_run
from results.labels import config_labels
from results.published import observation_regime, privileged_label
from results.render import BASELINE_NO_TOKENS, NO_TOKENS, Cell, finite_or_none, number_cell, task_keys
from results.runs import Run, combined_episodes, dedupe_episodes
from results.summary import Success
from results.table_fit import ALWAYS, Fit
from results.variant_table import (
    SIMPLERENV_AXES,
    RankingStability,
    VariantStats,
    is_variant_run,
    ranking_stability,
    variant_cells,
    variant_columns,
    variant_stats,
)

DEFAULT_BASELINE = "bidirectional"
MAX_TASK_COLUMNS = 10
OVERALL = "overall"


@dataclass(frozen=True)
class Entry:
    """One leaderboard row: a policy configuration on one machine."""

    policy: str
    label: str
    policy_config_id: str
    machine: str
    runs: tuple[str, ...]
    success: dict[str, Success]  # task group -> success
    overall: Success
    errors: int
    nfe_per_chunk: float
    tokens_per_s: float
    control_hz: float
    wall_clock_s: float
    speedup: float | None = None
    speedup_note: str = ""  # why speedup is missing ("n/a: other machine"); '' when computed
    # Instruction-chain suites only: CALVIN's numbers over all the row's chains, and per group.
    chain: ChainStats | None = None
    chain_groups: dict[str, ChainStats] = field(default_factory=dict)
    # SimplerEnv-like variant runs only: canonical, aggregated and per-axis success.
    variants: VariantStats | None = None
    # False when no row has an NFE count (a remote server that reports none): "not measured".
    nfe_measured: bool = True
    # Counted work per chunk (harness/episode/work.py), a mean over the rows that measured it;
    # None when none did: "not measured".
    flops_per_chunk: float | None = None


@dataclass(frozen=True)
class Leaderboard:
    suite: str
    groups: tuple[str, ...]
    entries: tuple[Entry, ...]
    baseline: str
    warnings: tuple[str, ...]
    # Variant runs with two or more configurations: do the variants keep their order?
    ranking: RankingStability | None = None
    # task -> "#index" (results.render.task_keys): a narrow terminal's stand-in for a task column
    short_tasks: Mapping[str, str] = field(default_factory=dict)

    @property
    def machines(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(e.machine for e in self.entries))

    @property
    def is_chain(self) -> bool:
        """An instruction-chain suite: laid out as CALVIN's table (reaching k/5, avg len)."""
        return any(e.chain is not None for e in self.entries)

    @property
    def axes(self) -> tuple[str, ...]:
        """The variant axes a SimplerEnv-like run covered; () for other runs."""
        found = [a for e in self.entries if e.variants is not None for a in e.variants.per_axis()]
        return tuple(dict.fromkeys(found))

    def frame(self) -> pd.DataFrame:
        """The numbers, one row per entry, for notebooks and CSV (rates as fractions)."""
        rows = []
        for e in self.entries:
            row: dict[str, Any] = {
                "suite": self.suite,
                "policy": e.policy,
                "label": e.label,
                "policy_config_id": e.policy_config_id,
                "machine": e.machine,
                "runs": " ".join(e.runs),
                "observations": observation_regime(self.suite),
            }
            for group, s in [*((g, e.success[g]) for g in self.groups), (OVERALL, e.overall)]:
                low, high = s.interval
                row |= {
                    f"success[{group}]": s.rate,
                    f"success_low[{group}]": low,
                    f"success_high[{group}]": high,
                    f"successes[{group}]": s.successes,
                    f"episodes[{group}]": s.episodes,
                }
            if e.chain is not None:
                row |= chain_columns(e.chain, e.chain_groups)
            if e.variants is not None:
                row |= variant_columns(e.variants)
            row |= {
                "errors": e.errors,
                "nfe_per_chunk": e.nfe_per_chunk,
                "flops_per_chunk": e.flops_per_chunk,
                "tokens_per_s": e.tokens_per_s,
                "control_hz": e.control_hz,
                "wall_clock_s": e.wall_clock_s,
                "speedup": e.speedup,
                "speedup_note": e.speedup_note,
                "baseline": self.baseline,
            }
            rows.append(row)
        return pd.DataFrame(rows)

    def cells(self) -> tuple[list[str], list[list[Cell]]]:
        """Headers and formatted cells: the one layout every output format shares. Rows
        measured on privileged state say so beside the policy ('[privileged state]').
        A chain suite gets CALVIN's columns in place of the success ones: average length
        per scene (with several), reaching 1/5 ... 5/5 and the average length overall; a
        variant run SimplerEnv's: canonical, variant-aggregated and per-axis success."""
        show_machine = len(self.machines) > 1
        regime = privileged_label([self.suite])
        headers = ["policy", *(["machine"] if show_machine else [])]
        if self.is_chain:
            k_max = max(len(e.chain.reached) for e in self.entries if e.chain is not None)
            groups = [f"{g} avg len" for g in self.groups] if len(self.groups) > 1 else []
            headers += [*groups, *(f"{k}/{k_max}" for k in range(1, k_max + 1)), "avg len (95%)"]
        elif self.axes:
            headers += [
                "canonical scene (Wilson 95%)",
                "variant-aggregated, SimplerEnv's set per task (95%)",
                "extended aggregate, every level of its axes (95%)",
            ]
            headers += [
                f"{a} (vs canonical)" if a in SIMPLERENV_AXES else f"{a} (harness axis, vs canonical)"
                for a in self.axes
            ]
        else:
            headers += [*self.groups, "success (Wilson 95%)"]
        headers += ["NFE/chunk", "GFLOP/chunk", "tokens/s", "control Hz", "wall s/episode"]
        headers += ["errors", f"speedup vs {self.baseline}"]
        rows = []
        for e in self.entries:
            row = [Cell(e.label + regime, e.label)]
            if show_machine:
                row.append(Cell(e.machine or "unknown", e.machine))
            if self.is_chain:
                row += chain_cells(e.chain, e.chain_groups, self.groups, k_max)
            elif self.axes:
                row += variant_cells(e.variants, self.axes)
            else:
                row += [Cell(e.success[g].text(), finite_or_none(e.success[g].rate)) for g in self.groups]
                row.append(Cell(e.overall.text(), finite_or_none(e.overall.rate)))
            row += [
                number_cell(e.nfe_per_chunk, ".1f") if e.nfe_measured else Cell("not measured", None),
                Cell("not measured", None)
                if e.flops_per_chunk is None
                else number_cell(e.flops_per_chunk / 1e9, ".3f"),
                number_cell(e.tokens_per_s, ".0f"),
                number_cell(e.control_hz, ".0f"),
                number_cell(e.wall_clock_s, ".2f"),
                Cell(str(e.errors), e.errors),
                Cell(f"{e.speedup:.2f}x", e.speedup) if e.speedup is not None else Cell(e.speedup_note, None),
            ]
            rows.append(row)
        return headers, rows


# --- speedups ---------------------------------------------------------------------


@dataclass(frozen=True)
class Timed:
    policy: str
    config_id: str
    label: str
    machine: str
    runs: tuple[str, ...]
    tokens_per_s: float


def _same_machine(a: Timed, b: Timed) -> bool:
    if a.machine or b.machine:
        return a.machine == b.machine
    return len(a.runs) == 1 and a.runs == b.runs  # no manifest: only rows of one run are known to match


def speedups(items: Sequence[Timed], baseline: str) -> tuple[list[tuple[float | None, str]], list[str]]:
    """Tokens/s over the baseline's on the same machine, or why there is none."""
    bases = [b for b in items if baseline in (b.policy, b.config_id)]
    warnings = []
    out: list[tuple[float | None, str]] = []
    for item in items:
        mine = [b for b in bases if _same_machine(item, b)]
        if not bases:
            out.append((None, f"n/a: no {baseline} row"))
            continue
        if not mine:
            unknown = not item.machine or all(not b.machine for b in bases)
            out.append((None, "n/a: machine unknown" if unknown else "n/a: other machine"))
            continue
        base = next((b for b in mine if b.label == b.policy), mine[0])
        if len(mine) > 1:
            msg = (
                f"baseline {baseline!r} has {len(mine)} configurations on one machine; speedups use "
                f"{base.label} (pass --baseline CONFIG_ID to choose)"
            )
            if msg not in warnings:
                warnings.append(msg)
        if math.isnan(item.tokens_per_s):
            out.append((None, NO_TOKENS))
        elif math.isnan(base.tokens_per_s) or base.tokens_per_s <= 0:
            out.append((None, BASELINE_NO_TOKENS))
        else:
            out.append((item.tokens_per_s / base.tokens_per_s, ""))
    return out, warnings


# --- building ---------------------------------------------------------------------


def prepare_rows(episodes: pd.DataFrame) -> tuple[pd.DataFrame, int]:
    """Rows as every output counts them (results.runs.dedupe_episodes), for frames that
    did not come through combined_episodes; the count includes what it dropped."""
    return dedupe_episodes(episodes)


def leaderboard(
    episodes: pd.DataFrame,
    baseline: str | None = None,
    group_by: Callable[[str], str] | None = None,
    provenance: Mapping[str, Mapping[str, Any]] | None = None,
    labels: Mapping[str, str] | None = None,
) -> Leaderboard:
    """The leaderboard of one suite's rows (optionally with `run`/`machine` columns, as
    from results.runs.combined_episodes; `provenance` maps run -> manifest)."""
    df, duplicates = prepare_rows(episodes)
    suites = df["suite"].unique()
    if len(suites) != 1:
        raise ValueError(f"one suite per leaderboard, got {sorted(suites)}; use leaderboards()")
    labels = dict(labels or config_labels(df))
    baseline = baseline or DEFAULT_BASELINE
    tasks = list(df.sort_values("task_index", kind="stable")["task"].unique())
    if group_by is None:
        group_of = {t: t for t in tasks} if len(tasks) <= MAX_TASK_COLUMNS else {}
    else:
        group_of = {t: group_by(t) for t in tasks}
    groups = tuple(dict.fromkeys(group_of[t] for t in tasks if t in group_of))
    first = df.sort_values("started_at", kind="stable") if "started_at" in df else df
    keys = list(dict.fromkeys(zip(first["policy_config_id"], first["machine"], strict=True)))
    grouped = {k: g for k, g in df.groupby(["policy_config_id", "machine"], sort=False)}
    chains = is_chain_run(df)
    variants = is_variant_run(df)
    drafts = []
    for key in keys:
        rows = grouped[key]
        per_group = {g: Success(0, 0) for g in groups}
        chain_groups = {}
        for group in groups:
            mine = rows[rows["task"].map(group_of) == group]
            per_group[group] = Success(int(mine["success"].sum()), len(mine))
            if chains:
                chain_groups[group] = chain_stats(mine["subtasks_completed"].fillna(0))
        drafts.append(
            Entry(
                policy=str(rows["policy"].iloc[0]),
                label=labels[key[0]],
                policy_config_id=key[0],
                machine=key[1],
                runs=tuple(dict.fromkeys(rows["run"])),
                success=per_group,
                overall=Success(int(rows["success"].sum()), len(rows)),
                errors=int(rows["failure_reason"].notna().sum()),
                nfe_per_chunk=float(rows["nfe_per_chunk"].mean()),
                tokens_per_s=float(rows["tokens_per_s"].mean()),
                control_hz=float(rows["control_hz"].mean()),
                wall_clock_s=float(rows["wall_clock_s"].mean()),
                chain=chain_stats(rows["subtasks_completed"].fillna(0)) if chains else None,
                chain_groups=chain_groups,
                variants=variant_stats(rows) if variants else None,
                nfe_measured=bool(rows["nfe_total"].notna().any()),
                flops_per_chunk=_flops_per_chunk(rows),
            )
        )
    timed = [Timed(e.policy, e.policy_config_id, e.label, e.machine, e.runs, e.tokens_per_s) for e in drafts]
    ratios, warnings = speedups(timed, baseline)
    entries = tuple(
        Entry(**{**e.__dict__, "speedup": s, "speedup_note": note})
        for e, (s, note) in zip(drafts, ratios, strict=True)
    )
    warnings = episode_warnings(df, keys, labels) + warnings
    if provenance is not None:
        warnings = provenance_warnings(list(dict.fromkeys(df["run"])), provenance) + warnings
    if duplicates:
        warnings.append(f"{duplicates} episode(s) appear in more than one run; the latest is counted")
    ranking = None
    if variants:
        ranking = ranking_stability({f"{e.label}@{e.machine}": e.variants for e in entries if e.variants})
    return Leaderboard(str(suites[0]), groups, entries, baseline, tuple(warnings), ranking, task_keys(df))


def _flops_per_chunk(rows: pd.DataFrame) -> float | None:
    measured = rows["flops_per_chunk"].dropna() if "flops_per_chunk" in rows else rows.iloc[:0]
    return float(measured.mean()) if len(measured) else None


def leaderboards(
    runs: Sequence[Run], baseline: str | None = None, group_by: Callable[[str], str] | None = None
) -> list[Leaderboard]:
    """One leaderboard per suite found in the runs, in the order the suites appear."""
    episodes = combined_episodes(runs)
    provenance = {r.label: r.manifest for r in runs}
    labels = config_labels(episodes)
    return [
        leaderboard(episodes[episodes["suite"] == suite], baseline, group_by, provenance, labels)
        for suite in episodes["suite"].unique()
    ]


# --- text outputs -----------------------------------------------------------------


def _md_escape(text: str) -> str:
    return text.replace("|", "\\|")


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    lines = ["| " + " | ".join(map(_md_escape, headers)) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(_md_escape(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def to_markdown(boards: Sequence[Leaderboard]) -> str:
    parts = []
    for b in boards:
        headers, rows = b.cells()
        parts.append(f"## {b.suite}\n\n" + markdown_table(headers, [[c.text for c in r] for r in rows]))
        if b.ranking is not None:
            parts.append(b.ranking.text())
        if b.warnings:
            parts.append("Warnings:\n\n" + "\n".join(f"- {w}" for w in b.warnings))
    return "\n\n".join(parts) + "\n"


def to_csv(boards: Sequence[Leaderboard]) -> str:
    return pd.concat([b.frame() for b in boards], ignore_index=True).to_csv(index=False)


def rich_table(board: Leaderboard) -> Table:
    headers, rows = board.cells()
    table = Table(title=board.suite, caption=board.ranking.text() if board.ranking else None)
    for i, h in enumerate(headers):
        table.add_column(h, justify="left" if i == 0 or h == "machine" else "right", overflow="fold")
    for row in rows:
        table.add_row(*(c.text for c in row))
    return table


# What a narrow terminal keeps first (results/table_fit.py): the row's name and its overall
# result (success, CALVIN's average length, SimplerEnv's canonical and aggregate), then speed,
# then the per-task and per-axis breakdown; headers not listed go last, in table order.
BOARD_RANKS = {
    "policy": ALWAYS,
    "success (Wilson 95%)": ALWAYS,
    "avg len (95%)": ALWAYS,
    "canonical scene (Wilson 95%)": ALWAYS,
    "variant-aggregated, SimplerEnv's axes (95%)": ALWAYS,
    "machine": 10,
    "tokens/s": 30,
    "NFE/chunk": 40,
    "errors": 50,
    "wall s/episode": 70,
    "control Hz": 80,
    "GFLOP/chunk": 90,
}
TASK_COLUMNS_RANK = 60  # shared: a leaderboard's task columns are shown all or none


def board_fit(board: Leaderboard) -> Fit:
    """How a leaderboard gives way to a narrow terminal: its speedup column beside the
    overall result, task columns (keyed by index where names do not fit) after speed."""
    ranks = dict(BOARD_RANKS) | {f"speedup vs {board.baseline}": 20}
    if any(e.errors for e in board.entries):
        ranks["errors"] = 15  # its own rank (a rank is shown whole or not at all)
    ranks |= {group: TASK_COLUMNS_RANK for group in board.groups}
    return Fit(ranks, board.short_tasks)


@dataclass(frozen=True)
class Block:
    """A titled table of cells, as paper-table and the HTML report lay them out."""

    title: str
    headers: list[str]
    rows: list[list[Cell]]
    notes: tuple[str, ...] = ()
    published_from: int | None = None  # rows from here on are published reference rows
