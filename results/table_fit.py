"""Tables that fit the terminal they print to.

At its natural width the main job's summary is 171 columns and a LIBERO leaderboard
about 240; squeezed evenly into a narrower terminal, rich breaks names mid-word
("pick-pla/ce-v3") and a ten-row table runs to 85 lines. Here a table keeps the columns
that fit in order of importance (the others are named beneath it, one flag away), each
at a width where every word stays whole, and task names too long to sit beside the
always-shown columns give way to their task indices (what `--tasks` accepts) with a
legend. A table written to a pipe or a file is printed whole (harness/console.py).
"""

from __future__ import annotations

import copy
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

from rich.cells import cell_len
from rich.console import RenderableType
from rich.table import Column, Table
from rich.text import Text

ALWAYS = 0  # the rank of a column shown at any width
# Where an identifier longer than its column may break, as a last resort: after one of
# its own separators ("pick_up_the_black_bowl_" / "on_the_plate"), never inside a word.
_BREAKS = re.compile(r"(?<=[_\-/.,=])")


@dataclass(frozen=True)
class Fit:
    """How a table gives way to a narrow terminal.

    ranks: header -> importance (0 always shown; larger is hidden first); a header not
    listed ranks after every listed one, in table order, except the first column, which
    is always shown. keys: a long name (a task) -> the short key (its index) shown in its
    place, cells and headers alike, when the names do not fit beside the always-shown
    columns; a legend beneath the table then says which is which. notes: header -> what
    the column means; given, the caption is the notes of the columns shown."""

    ranks: Mapping[str, int] = field(default_factory=dict)
    keys: Mapping[str, str] = field(default_factory=dict)
    key_name: str = "task"
    notes: Mapping[str, str] = field(default_factory=dict)
    prose: frozenset[str] = frozenset()


@dataclass(frozen=True)
class Fitted:
    table: Table
    hidden: tuple[str, ...]  # headers of the columns left out, in table order
    legend: tuple[tuple[str, str], ...]  # (key, name) of every key the table shows


def plain(cell: RenderableType) -> str:
    """A cell's text as the terminal shows it (markup stripped)."""
    if isinstance(cell, Text):
        return cell.plain
    if isinstance(cell, str):
        return Text.from_markup(cell).plain
    return str(cell)


def _natural(texts: Iterable[str]) -> int:
    return max((cell_len(line) for t in texts for line in t.splitlines()), default=0)


def _longest_word(texts: Iterable[str]) -> int:
    return max((cell_len(word) for t in texts for word in t.split()), default=0)


def _longest_piece(texts: Iterable[str]) -> int:
    """The narrowest a column can be with identifiers broken only after their separators."""
    pieces = (p for t in texts for word in t.split() for p in _BREAKS.split(word))
    return max((cell_len(p) for p in pieces), default=0)


@dataclass(frozen=True)
class _Col:
    index: int
    header: str
    cells: list[str]
    rank: int
    keyed: bool = False  # names in it are shown by their keys
    prose: bool = False  # running text: wraps at spaces wherever it is shown

    @property
    def texts(self) -> list[str]:
        return [self.header, *self.cells]

    @property
    def natural(self) -> int:
        return max(1, _natural(self.texts))

    @property
    def minimum(self) -> int:
        return max(1, _longest_word(self.texts))

    @property
    def unwrapped(self) -> int:
        """The width at which no cell wraps (a header may, at its spaces; prose may too)."""
        if self.prose:
            return self.minimum
        return max(1, _natural(self.cells), _longest_word([self.header]))

    def with_keys(self, keys: Mapping[str, str]) -> _Col:
        header, cells = keys.get(self.header, self.header), [keys.get(x, x) for x in self.cells]
        if header == self.header and cells == self.cells:
            return self
        return _Col(self.index, header, cells, self.rank, keyed=True, prose=self.prose)


def _ranked(table: Table, fit: Fit) -> list[_Col]:
    listed = max(fit.ranks.values(), default=0) + 1
    cols = []
    for i, column in enumerate(table.columns):
        header = plain(column.header)
        rank = ALWAYS if i == 0 else fit.ranks.get(header, listed + i)
        cols.append(_Col(i, header, [plain(c) for c in column.cells], rank, prose=header in fit.prose))
    return cols


def _overhead(table: Table, count: int) -> int:
    """Borders and padding of `count` columns."""
    _, right, _, left = table.padding
    lines = (count + 1 if table.show_edge else count - 1) if table.box else 0
    return count * (left + right) + max(lines, 0)


def _shrink(widths: dict[int, int], cols: Sequence[_Col], budget: int) -> None:
    """Narrow the widest columns first until they fit: down to their longest word, and
    where that is not enough, down to the longest piece of an identifier between its
    separators (a LIBERO task name in an 80-column terminal)."""
    for floor in (lambda c: c.minimum, lambda c: max(1, _longest_piece(c.texts))):
        while sum(widths.values()) > budget:
            shrinkable = [c for c in cols if widths[c.index] > floor(c)]
            if not shrinkable:
                break
            widest = max(shrinkable, key=lambda c: widths[c.index])
            widths[widest.index] -= 1


def choose_columns(table: Table, width: int, fit: Fit) -> tuple[list[_Col], dict[int, int]]:
    """The columns to show and their widths. The always-shown columns come at their
    natural widths if they fit (with names keyed, if they do not), else wrapped at
    spaces; then, in order of importance, every other rank whose columns all fit beside
    them without wrapping a cell (names keyed if that is what makes them fit): a rank is
    shown whole or not at all (a leaderboard's task columns). The room left widens
    wrapped columns, the most important first."""
    cols = _ranked(table, fit)
    always = [c for c in cols if c.rank == ALWAYS]
    if fit.keys and sum(c.natural for c in always) + _overhead(table, len(always)) > width:
        always = [c.with_keys(fit.keys) for c in always]
    widths = {c.index: c.natural for c in always}
    _shrink(widths, always, width - _overhead(table, len(always)))
    chosen = list(always)
    ranks = sorted({c.rank for c in cols} - {ALWAYS})
    for rank in ranks:
        group = [c for c in cols if c.rank == rank]
        for form in (group, [c.with_keys(fit.keys) for c in group]):
            used = sum(widths.values()) + _overhead(table, len(chosen) + len(form))
            if used + sum(c.unwrapped for c in form) <= width:
                widths |= {c.index: c.unwrapped for c in form}
                chosen += form
                break
    spare = width - sum(widths.values()) - _overhead(table, len(chosen))
    for col in sorted(chosen, key=lambda c: (c.rank, c.index)):
        grow = min(spare, col.natural - widths[col.index])
        if grow > 0:
            widths[col.index] += grow
            spare -= grow
    return sorted(chosen, key=lambda c: c.index), widths


def break_name(text: str, width: int) -> str:
    """`text` with every line that is longer than `width` broken after its separators
    (never inside a word; a word longer than `width` alone is left for the terminal)."""
    lines = []
    for line in text.splitlines() or [""]:
        current = ""
        for piece in (p for word in re.split(r"(\s+)", line) for p in _BREAKS.split(word)):
            if current and cell_len(current + piece) > width:
                lines.append(current.rstrip())
                current = piece.lstrip()
            else:
                current += piece
        lines.append(current)
    return "\n".join(lines)


def fit_table(table: Table, width: int, fit: Fit | None = None) -> Fitted:
    """`table` cut to `width` terminal columns (see the module docstring)."""
    fit = fit or Fit()
    if not table.columns:
        return Fitted(table, (), ())
    chosen, widths = choose_columns(table, width, fit)
    out = copy.copy(table)
    out.columns, out.rows = [], []
    originals: list[Column] = list(table.columns)
    cells: list[list[RenderableType]] = []
    for col in chosen:
        source = originals[col.index]
        w = widths[col.index]
        long_word = col.minimum > w
        header: RenderableType = break_name(col.header, w) if col.keyed or long_word else source.header
        out.add_column(
            header,
            justify=source.justify,
            style=source.style,
            header_style=source.header_style,
            width=w,
            overflow="fold",
        )
        column_cells: list[RenderableType] = []
        for text, original in zip(col.cells, source.cells, strict=True):
            changed = col.keyed and text != plain(original)
            column_cells.append(break_name(text, w) if changed or long_word else original)
        cells.append(column_cells)
    for r, row in enumerate(table.rows):
        out.add_row(*(c[r] for c in cells), style=row.style, end_section=row.end_section)
    shown = {c.index for c in chosen}
    hidden = tuple(plain(c.header) for i, c in enumerate(originals) if i not in shown)
    if fit.notes:
        kept = [fit.notes[h] for h in (plain(originals[i].header) for i in sorted(shown)) if h in fit.notes]
        out.caption = "; ".join(kept) or None
    shown_keys = {t for c in chosen if c.keyed for t in c.texts}
    legend = tuple((key, name) for name, key in fit.keys.items() if key in shown_keys)
    return Fitted(out, hidden, legend)


def hidden_note(hidden: Sequence[str], keys: Mapping[str, str], how: str) -> str:
    """One line naming what a narrow terminal left out (task columns counted, not listed)."""
    tasks = [h for h in hidden if h in keys]
    named = [h for h in hidden if h not in keys]
    parts = [*named, *([f"{len(tasks)} task column(s)"] if tasks else [])]
    return f"not shown at this width: {', '.join(parts)}; {how}"


def legend_lines(legend: Sequence[tuple[str, str]], key_name: str, width: int) -> list[str]:
    """The keys a table shows and the names they stand for, one per line, each line
    broken (after its separators) to `width` under a hanging indent."""
    if not legend:
        return []
    pad = max(cell_len(k) for k, _ in legend) + 1
    lines = [f"{key_name}s:"]
    for key, name in legend:
        body = break_name(name, max(10, width - pad - 2)).splitlines()
        lines.append(f"  {key.ljust(pad)}{body[0]}")
        lines += [" " * (pad + 2) + rest for rest in body[1:]]
    return lines
