"""The generalization-gap table: success on a standard suite and under each LIBERO-PRO
perturbation, and the drop with a 95% interval, per suite and policy configuration.

A perturbed run's suite name carries the perturbation (`libero/spatial:perturb=swap,
seeding=openvla`); without that option the name is its standard suite's, so the two pair
by name. Columns follow LIBERO-PRO's paper (Zhou et al., 2025): the original suite, then
object (Obj.), position/swap (Pos.), language (Sem.), task and environment (Env.).

The drop is standard minus perturbed success (positive: the policy got worse). Episodes
pair when both sides ran exactly the same (task, episode index) keys: episode j of a task
runs initial state j of its own suite under the same seed on both. Every LIBERO-PRO
folder, `_lan` included, ships its own draw of initial states, so a pair shares task,
seed and index, not the layout: Newcombe's score interval for paired proportions
(Statistics in Medicine 17:2635, 1998, method 10) estimates the pairs' correlation from
the outcomes, so it is narrower than the unpaired one only as far as the outcomes are
correlated, and the cell gives McNemar's discordant counts (standard-only successes /
perturbed-only successes), what the drop is made of. Where one side ran a prefix of the
other's episodes (the usual case: the standard suite at 50 a task, a perturbation at 2),
the drop pairs on the keys both ran and the cell says how many; the success columns keep
every episode of their own side. Where neither side's keys contain the other's (other
tasks) the episodes are treated as independent and the interval is Newcombe's hybrid
score interval for a difference of proportions (method 10), built from the two Wilson
intervals. Each cell says which it used.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from results.published import PublishedGapRow, libero_pro_label, libero_pro_rows
from results.render import Cell, finite_or_none
from results.summary import Success

STANDARD = "standard"
# LIBERO-PRO's paper order and names; combinations (swap+lan...) follow, in the order seen.
COLUMNS = {"object": "Obj.", "swap": "Pos.", "lan": "Sem.", "task": "Task", "env": "Env."}


# The instruction source LIBERO-PRO's published table was made with (docs/libero-pro.md):
# a perturbed column under it carries the bare perturbation's name, under another it says so.
PUBLISHED_INSTRUCTION = "filename"


def split_perturbation(suite: str) -> tuple[str, str]:
    """(standard suite name, perturbation) of a suite name; perturbation 'standard' when
    none. A perturbed run's instruction source is part of its perturbation (`lan` under
    the published `filename` source, `lan (instruction=bddl)` under the other), so both
    pair with the same standard run. A perturbed name without one heard the BDDL's words
    under lan and task and the standard instruction under the scene perturbations."""
    base, sep, options = suite.partition(":")
    items = [i.partition("=") for i in options.split(",")] if sep else []
    values = {key.strip(): value.strip() for key, _, value in items}
    perturb = values.get("perturb", STANDARD)
    dropped = ("perturb", "instruction") if "perturb" in values else ()
    kept = [f"{key}{eq}{value}" for key, eq, value in items if key.strip() not in dropped]
    if perturb != STANDARD:
        legacy = "bddl" if {"lan", "task"} & set(perturb.split("+")) else PUBLISHED_INSTRUCTION
        instruction = values.get("instruction", legacy)
        if instruction != PUBLISHED_INSTRUCTION:
            perturb = f"{perturb} (instruction={instruction})"
    return (f"{base}:{','.join(kept)}" if kept else base), perturb


@dataclass(frozen=True)
class Drop:
    """Standard minus perturbed success, with its interval and how it was computed."""

    drop: float
    low: float
    high: float
    paired: bool
    standard_only: int = 0  # paired: keys the standard suite solved and the perturbed did not
    perturbed_only: int = 0
    shared: str = ""  # paired on part of one side: "20 of 500 standard episodes"

    def text(self) -> str:
        if math.isnan(self.drop):
            return "-"
        on = f" on {self.shared}" if self.shared else ""
        how = (
            f"paired{on}, {self.standard_only}/{self.perturbed_only} discordant"
            if self.paired
            else "unpaired"
        )
        return f"{100 * self.drop:+.1f} pts [{100 * self.low:+.0f}, {100 * self.high:+.0f}] ({how})"


def newcombe_drop(standard: Success, perturbed: Success) -> Drop:
    """Newcombe's hybrid score interval for p_standard - p_perturbed, independent samples."""
    if not standard.episodes or not perturbed.episodes:
        return Drop(math.nan, math.nan, math.nan, False)
    p1, p2 = standard.rate, perturbed.rate
    (l1, u1), (l2, u2) = standard.interval, perturbed.interval
    d = p1 - p2
    low = d - math.sqrt((p1 - l1) ** 2 + (u2 - p2) ** 2)
    high = d + math.sqrt((u1 - p1) ** 2 + (p2 - l2) ** 2)
    return Drop(d, low, high, False)


def paired_drop(standard: np.ndarray, perturbed: np.ndarray) -> Drop:
    """Newcombe's score interval for a difference of paired proportions (1998b, method 10):
    the two Wilson intervals combined with the pairs' phi correlation. It stays wide where
    a bootstrap collapses (every pair concordant gives a zero-width bootstrap interval)."""
    a_, b_ = np.asarray(standard, dtype=bool), np.asarray(perturbed, dtype=bool)
    n = len(a_)
    if n == 0:
        return Drop(math.nan, math.nan, math.nan, True)
    both = int((a_ & b_).sum())
    only_std = int((a_ & ~b_).sum())
    only_pert = int((~a_ & b_).sum())
    neither = n - both - only_std - only_pert
    s1, s2 = Success(both + only_std, n), Success(both + only_pert, n)
    p1, p2 = s1.rate, s2.rate
    (l1, u1), (l2, u2) = s1.interval, s2.interval
    margins = (both + only_std) * (only_pert + neither) * (both + only_pert) * (only_std + neither)
    phi = (both * neither - only_std * only_pert) / math.sqrt(margins) if margins else 0.0
    d = p1 - p2
    low = d - math.sqrt(max(0.0, (p1 - l1) ** 2 - 2 * phi * (p1 - l1) * (u2 - p2) + (u2 - p2) ** 2))
    high = d + math.sqrt(max(0.0, (u1 - p1) ** 2 - 2 * phi * (u1 - p1) * (p2 - l2) + (p2 - l2) ** 2))
    return Drop(d, low, high, True, only_std, only_pert)


def drop(standard_rows: pd.DataFrame, perturbed_rows: pd.DataFrame) -> Drop:
    """Paired where both sides ran the same (task, episode index) keys, or one side's keys
    contain the other's (paired on those); else unpaired."""
    keys = ["task", "episode_index"]
    a = standard_rows.drop_duplicates(keys, keep="last").set_index(keys)["success"]
    b = perturbed_rows.drop_duplicates(keys, keep="last").set_index(keys)["success"]
    keys_a, keys_b = set(a.index), set(b.index)
    if len(a) and len(b) and (keys_a <= keys_b or keys_b <= keys_a):
        common = a.index.intersection(b.index)
        paired = paired_drop(a.loc[common].to_numpy(bool), b.loc[common].to_numpy(bool))
        if keys_a == keys_b:
            return paired
        side, total = ("standard", len(a)) if len(a) > len(b) else ("perturbed", len(b))
        return dataclasses.replace(paired, shared=f"{len(common)} of {total} {side} episodes")
    return newcombe_drop(_success(standard_rows), _success(perturbed_rows))


def _success(rows: pd.DataFrame) -> Success:
    return Success(int(rows["success"].sum()), len(rows))


@dataclass(frozen=True)
class GapRow:
    label: str
    policy_config_id: str
    standard: Success
    perturbed: dict[str, tuple[Success, Drop]]  # perturbation -> its success and drop


def _published_cells(row: PublishedGapRow, perturbations: tuple[str, ...], label: str) -> list[Cell]:
    """A published row in the table's columns: its success values as printed and the drop
    where both sides are published (no interval: the sources give no episode counts)."""
    standard = row.values.get("standard")
    cells = [Cell(f"{row.method} [{row.table}] {label}", row.method), _percent(standard)]
    for p in perturbations:
        value = row.values.get(p)
        cells.append(_percent(value))
        if value is None or standard is None:
            cells.append(Cell("-", None))
        else:
            cells.append(Cell(f"{standard - value:+.1f} pts (published)", (standard - value) / 100))
    return cells


def _percent(value: float | None) -> Cell:
    return Cell("-", None) if value is None else Cell(f"{value:.0f}%", value / 100)


@dataclass(frozen=True)
class GapTable:
    suite: str  # the standard suite's name
    perturbations: tuple[str, ...]
    rows: tuple[GapRow, ...]
    published: tuple[PublishedGapRow, ...] = ()  # LIBERO-PRO's own rows for this suite

    def notes(self) -> tuple[str, ...]:
        """The table's note, and where its published rows come from and why they are apart."""
        if not self.published:
            return (NOTE,)
        sources = sorted({f"[{r.table}] {r.source.rsplit(', row ', 1)[0]}" for r in self.published})
        label = libero_pro_label(self.suite)
        why = (
            "they read camera images, and the measured rows above read privileged state"
            if "not comparable" in label
            else "other checkpoints, simulator versions and episodes"
        )
        return (
            NOTE,
            f"Rows marked {label} are the LIBERO-PRO authors' numbers, not measured here ({why}); "
            f"'-' where the source prints none. Sources: {'; '.join(sources)}.",
        )

    def cells(self) -> tuple[list[str], list[list[Cell]]]:
        headers = ["policy", "standard (Wilson 95%)"]
        for p in self.perturbations:
            name = f"{p} ({COLUMNS[p]})" if p in COLUMNS else p
            headers += [name, f"{p}: drop (95%)"]
        rows = []
        for r in self.rows:
            row = [Cell(r.label, r.label), Cell(r.standard.text(), finite_or_none(r.standard.rate))]
            for p in self.perturbations:
                if p not in r.perturbed:
                    row += [Cell("-", None), Cell("-", None)]
                    continue
                success, d = r.perturbed[p]
                row += [
                    Cell(success.text(), finite_or_none(success.rate)),
                    Cell(d.text(), finite_or_none(d.drop)),
                ]
            rows.append(row)
        label = libero_pro_label(self.suite)
        rows += [_published_cells(r, self.perturbations, label) for r in self.published]
        return headers, rows

    def frame(self) -> pd.DataFrame:
        """One row per (configuration, perturbation), rates as fractions, for CSV."""
        out = []
        for r in self.rows:
            for p, (success, d) in r.perturbed.items():
                out.append(
                    {
                        "suite": self.suite,
                        "policy_config_id": r.policy_config_id,
                        "label": r.label,
                        "perturbation": p,
                        "standard": r.standard.rate,
                        "standard_episodes": r.standard.episodes,
                        "perturbed": success.rate,
                        "perturbed_episodes": success.episodes,
                        "drop": d.drop,
                        "drop_low": d.low,
                        "drop_high": d.high,
                        "paired": d.paired,
                    }
                )
        return pd.DataFrame(out)


def gap_tables(episodes: pd.DataFrame, labels: dict[str, str] | None = None) -> list[GapTable]:
    """One table per standard suite that has perturbed rows; configurations in order seen.
    A configuration with no standard rows gets '-' for its drops, not a made-up baseline."""
    df = episodes.copy()
    split = df["suite"].map(split_perturbation)
    df["_base"], df["_perturb"] = split.str[0], split.str[1]
    labels = labels or {}
    tables = []
    for base in df["_base"].unique():
        mine = df[df["_base"] == base]
        seen = [p for p in mine["_perturb"].unique() if p != STANDARD]
        if not seen:
            continue
        order = [p for p in COLUMNS if p in seen] + [p for p in seen if p not in COLUMNS]
        rows = []
        for cid, rows_of in mine.groupby("policy_config_id", sort=False):
            standard = rows_of[rows_of["_perturb"] == STANDARD]
            perturbed = {}
            for p in order:
                these = rows_of[rows_of["_perturb"] == p]
                if len(these):
                    perturbed[p] = (_success(these), drop(standard, these))
            label = labels.get(str(cid), str(rows_of["policy"].iloc[0]))
            rows.append(GapRow(label, str(cid), _success(standard), perturbed))
        tables.append(GapTable(str(base), tuple(order), tuple(rows), libero_pro_rows(str(base))))
    return tables


NOTE = (
    "Drop = standard - perturbed success, in points, with a 95% interval: paired (matching "
    "task and episode index, on the episodes both ran when one run has more; Newcombe's paired "
    "score interval; n/m = pairs only the standard / only the perturbed run solved) or unpaired "
    "(Newcombe's score interval). LIBERO-PRO perturbations "
    "(Zhou et al., 2025): Obj. appearance, Pos. object positions, Sem. the paraphrase folder, "
    "Task new goals, Env. another table; the policy hears the standard instruction (task.language, "
    "as in LIBERO-PRO's published table) unless a column says instruction=bddl (each BDDL's own "
    "words: the paraphrase, the new goal's)."
)


def gap_markdown(tables: list[GapTable]) -> str:
    from results.leaderboard import markdown_table

    parts = []
    for t in tables:
        headers, rows = t.cells()
        parts.append(
            f"## {t.suite}: generalization gaps (LIBERO-PRO)\n\n"
            + markdown_table(headers, [[c.text for c in r] for r in rows])
            + "".join(f"\n\n{n}" for n in t.notes()[1:])
        )
    return "\n\n".join(parts) + f"\n\n{NOTE}\n" if parts else ""


def gap_rich(table: GapTable):
    from rich.table import Table

    headers, rows = table.cells()
    out = Table(title=f"{table.suite}: generalization gaps (LIBERO-PRO)", caption=" ".join(table.notes()))
    for i, h in enumerate(headers):
        out.add_column(h, justify="left" if i == 0 else "right")
    for row in rows:
        out.add_row(*(c.text for c in row))
    return out


def gap_blocks(tables: list[GapTable]) -> list:
    """The tables as the HTML report's titled blocks."""
    from results.leaderboard import Block

    return [
        Block(
            f"{t.suite}: generalization gaps (LIBERO-PRO)",
            *t.cells(),
            t.notes(),
            published_from=len(t.rows) if t.published else None,
        )
        for t in tables
    ]
