"""Tables written to a pipe or a file are never cut short: no `fast_…`, no `(24/3…`."""

from __future__ import annotations

import io
import subprocess
import sys
from pathlib import Path

from tests.test_html_fit import _mt10_rows
from tests.test_leaderboard import write_run

REPO = Path(__file__).resolve().parent.parent


def test_leaderboard_to_a_pipe_prints_full_names_and_counts(tmp_path):
    run = write_run(tmp_path / "mt10", _mt10_rows())  # ten task columns: wider than 160
    out = subprocess.run(
        [sys.executable, "-m", "harness", "leaderboard", str(run)],
        cwd=REPO,
        capture_output=True,  # stdout a pipe, as `dvla-harness leaderboard RUN | less`
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert "…" not in out.stdout
    assert "fast_dvla (tau_conf=0.3)" in out.stdout and "fast_dvla (tau_conf=0.5)" in out.stdout
    assert "button-press-topdown-v3" in out.stdout and "speedup vs bidirectional" in out.stdout
    assert "(472/500)" in out.stdout and "(43/50)" in out.stdout and "(50/50)" in out.stdout


def test_run_and_leaderboard_say_the_same_when_there_is_no_bidirectional_row(tmp_path):
    from rich.console import Console

    from results.leaderboard import leaderboards
    from results.render import summary_table
    from results.runs import load_run
    from results.summary import summarize
    from tests.test_leaderboard import FAST, episodes

    run = load_run(write_run(tmp_path / "r", episodes("fast_dvla", FAST, "fast000001", [1, 0, 1])))
    (board,) = leaderboards([run])
    (entry,) = board.entries
    console = Console(width=300, record=True, file=io.StringIO())
    console.print(summary_table(summarize(run.episodes)))
    text = console.export_text()
    assert entry.speedup_note == "n/a: no bidirectional row"
    all_row = next(line for line in text.splitlines() if "ALL" in line)
    assert all_row.rstrip(" │").endswith(entry.speedup_note)


def test_run_and_leaderboard_say_the_same_for_a_policy_without_tokens(tmp_path):
    """A scripted expert beside bidirectional: no `-x` in the run summary, the leaderboard's reason."""
    from rich.console import Console

    from results.leaderboard import leaderboards
    from results.render import summary_table
    from results.runs import load_run
    from results.summary import summarize
    from tests.test_leaderboard import BIDI, episodes

    rows = episodes("bidirectional", BIDI, "bidi000001", [1, 0, 1])
    rows += episodes("scripted", "{}", "scri000001", [1, 1, 1], tokens_per_s=None)
    run = load_run(write_run(tmp_path / "r", rows))
    (board,) = leaderboards([run])
    note = next(e.speedup_note for e in board.entries if e.policy == "scripted")
    console = Console(width=300, record=True, file=io.StringIO())
    console.print(summary_table(summarize(run.episodes)))
    text = console.export_text()
    assert note == "n/a: no tokens" and "-x" not in text
    scripted_all = [line for line in text.splitlines() if "ALL" in line][1]
    assert scripted_all.rstrip(" │").endswith(note)
