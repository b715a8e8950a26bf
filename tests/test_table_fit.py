"""Tables fit the terminal they print to (results/table_fit.py): at 80, 120 and 200
columns no line is wider than the terminal, no name is broken inside a word, the
columns left out are named beneath the table, and a pipe still gets every column whole."""

from __future__ import annotations

import io
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from rich.console import Console
from rich.table import Table

from harness.console import print_note, print_table
from results.leaderboard import board_fit, leaderboards, rich_table
from results.render import summary_fit, summary_table
from results.runs import load_run
from results.summary import summarize
from results.table_fit import ALWAYS, Fit, break_name, fit_table
from tests.test_html_fit import MT10, _mt10_rows
from tests.test_leaderboard import write_run

REPO = Path(__file__).resolve().parent.parent
WIDTHS = (80, 120, 200)
LIBERO_SPATIAL = [
    "pick_up_the_black_bowl_between_the_plate_and_the_ramekin_and_place_it_on_the_plate",
    "pick_up_the_black_bowl_next_to_the_ramekin_and_place_it_on_the_plate",
    "pick_up_the_black_bowl_from_table_center_and_place_it_on_the_plate",
]


def _terminal(width: int) -> Console:
    return Console(file=io.StringIO(), width=width, force_terminal=True, color_system=None)


def _text(console: Console) -> str:
    return console.file.getvalue()  # type: ignore[attr-defined]


def _mt10() -> pd.DataFrame:
    return pd.DataFrame(_mt10_rows())


def _libero() -> pd.DataFrame:
    rows = _mt10_rows()
    names = {task: LIBERO_SPATIAL[i % 3] for i, task in enumerate(MT10)}
    kept = [r | {"task": names[r["task"]], "task_index": r["task_index"] % 3} for r in rows]
    return pd.DataFrame([r for r in kept if r["task"] in LIBERO_SPATIAL])


def _print_summary(episodes: pd.DataFrame, width: int, wide: bool = False) -> str:
    console = _terminal(width)
    summary = summarize(episodes)
    print_table(summary_table(summary), console, summary_fit(summary, episodes), wide=wide)
    return _text(console)


@pytest.mark.parametrize("width", WIDTHS)
def test_the_summary_fits_the_terminal_with_names_whole(width):
    text = _print_summary(_mt10(), width)
    assert max(len(line) for line in text.splitlines()) <= width
    for task in MT10:  # never "pick-pla" / "ce-v3"
        assert task in text
    assert "fast_dvla (tau_conf=0.3)" in text or "fast_dvla" in text
    assert "success (Wilson 95%)" in text
    if width == 200:
        assert "not shown" not in text and "GFLOP/chunk" in text  # the whole table fits
    else:
        note = next(line for line in text.splitlines() if "not shown at this width" in line)
        assert "GFLOP/chunk" in note  # the least important column goes first
        assert "speedup" in text  # the speedup is kept before the Hz and work columns


def test_a_narrow_terminal_keeps_the_columns_in_order_of_importance():
    narrow, middle = _print_summary(_mt10(), 80), _print_summary(_mt10(), 120)
    header = next(line for line in middle.splitlines() if "policy" in line)
    assert "tokens/s" in header and "control Hz" not in header
    assert "tokens/s" not in next(line for line in narrow.splitlines() if "policy" in line)
    assert len(narrow.splitlines()) < 60  # one line per row, not three or four


@pytest.mark.parametrize("width", WIDTHS)
def test_long_task_names_give_way_to_their_indices_with_a_legend(width):
    text = _print_summary(_libero(), width)
    lines = text.splitlines()
    assert max(len(line) for line in lines) <= width
    if width == 200:  # room for the whole names
        assert all(name in text for name in LIBERO_SPATIAL) and "tasks:" not in text
        return
    assert "#0" in text and "#2" in text
    start = next(i for i, line in enumerate(lines) if line.startswith("tasks:"))
    end = next(i for i, line in enumerate(lines) if line.startswith("not shown at this width"))
    legend = lines[start:end]
    joined = "".join(line.strip() for line in legend)
    for name in LIBERO_SPATIAL:  # broken only after an underscore, so the pieces join up
        assert name in joined
    for line in legend[1:]:
        piece = line.split()[-1]
        assert piece.endswith("_") or any(name.endswith(piece) for name in LIBERO_SPATIAL)


def test_wide_and_pipes_print_every_column_and_whole_names():
    wide = _print_summary(_libero(), 80, wide=True)
    piped = Console(file=io.StringIO(), width=80)  # not a terminal
    summary = summarize(_libero())
    print_table(summary_table(summary), piped, summary_fit(summary, _libero()))
    for text in (wide, _text(piped)):
        assert "not shown" not in text and "GFLOP/chunk" in text and "loop Hz" in text
        assert all(name in text for name in LIBERO_SPATIAL)


@pytest.mark.parametrize("width", WIDTHS)
def test_a_leaderboard_shows_task_columns_all_or_none(width, tmp_path):
    (board,) = leaderboards([load_run(write_run(tmp_path / "mt10", _mt10_rows()))])
    console = _terminal(width)
    print_table(rich_table(board), console, board_fit(board))
    text = _text(console)
    assert max(len(line) for line in text.splitlines()) <= width
    header = "\n".join(text.splitlines()[:4])
    shown = [t for t in MT10 if t in header]
    assert shown == [] or shown == MT10
    assert "speedup" in header and "success (Wilson 95%)" in header  # the headline, at any width
    assert "fast_dvla (tau_conf=0.3)" in text and "bidirectional" in text


def test_a_rank_is_shown_whole_or_not_at_all():
    table = Table("name", "a", "b", "c")
    table.add_row("x", "1" * 10, "2" * 10, "3" * 5)
    fitted = fit_table(table, 32, Fit({"name": ALWAYS, "a": 1, "b": 1, "c": 2}))
    assert fitted.hidden == ("a", "b")  # a and b together need 26: c alone fits
    wider = fit_table(table, 60, Fit({"name": ALWAYS, "a": 1, "b": 1, "c": 2}))
    assert wider.hidden == ()


def test_identifiers_break_only_after_their_separators():
    name = LIBERO_SPATIAL[0]
    broken = break_name(name, 30).splitlines()
    assert "".join(broken) == name
    assert all(len(line) <= 30 and line.endswith("_") for line in broken[:-1])
    assert break_name("fast_dvla (block_size=4)", 12).splitlines() == ["fast_dvla", "(block_size=", "4)"]


def test_notes_wrap_at_words_in_a_terminal_and_stay_one_line_in_a_pipe():
    text = "rows differ in " + ", ".join(f"setting_{i}" for i in range(40))
    terminal = _terminal(80)
    print_note("warning:", text, terminal)
    lines = _text(terminal).splitlines()
    assert len(lines) > 3 and max(len(line) for line in lines) <= 80
    assert all(line.startswith(" " * 9) for line in lines[1:])  # a hanging indent
    assert all(re.search(r"setting_\d+,?$", line.strip()) for line in lines[1:-1])  # whole words
    piped = Console(file=io.StringIO(), width=80)
    print_note("warning:", text, piped)
    assert _text(piped) == f"warning: {text}\n"


@pytest.mark.skipif(shutil.which("script") is None, reason="needs util-linux script for a pseudo-terminal")
@pytest.mark.parametrize("width", (80, 120))
def test_show_and_list_suites_in_a_real_terminal(width, tmp_path):
    run = write_run(tmp_path / "mt10", _mt10_rows())
    env = {**os.environ, "TERM": "dumb", "NO_COLOR": "1"}
    for command in (f"show {run}", "list suites"):
        shell = f"stty cols {width}; {sys.executable} -m harness {command}"
        out = subprocess.run(
            ["script", "-qc", shell, "/dev/null"],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=120,
            env=env,
        )
        text = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", out.stdout).replace("\r", "")
        lines = text.splitlines()
        assert lines and max(len(line) for line in lines) <= width, text
        if command.startswith("show"):
            assert all(task in text for task in MT10) and "not shown at this width" in text
        else:  # the names a user types are whole
            assert "libero/spatial:perturb=object" in text and "metaworld/mt1/<task>" in text


def test_errors_move_up_on_their_own_when_an_episode_raised():
    episodes = _mt10()
    episodes.loc[episodes.index[:3], "failure_reason"] = "ValueError: boom"
    raised, clean = _print_summary(episodes, 90), _print_summary(_mt10(), 90)  # room for one more
    raised_header, clean_header = ("\n".join(t.splitlines()[:4]) for t in (raised, clean))
    assert "errors" in raised_header and "speedup" not in raised_header  # errors first when any
    assert "speedup" in clean_header and "errors" not in clean_header  # else the speedup
