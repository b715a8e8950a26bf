"""What a person reading a log or a killed run sees: progress lines without a terminal,
and `show` telling a killed run from a running one."""

from __future__ import annotations

import json
import re

import pytest

from harness.console import episode_progress

pytestmark = pytest.mark.metaworld


def test_progress_prints_a_line_every_five_percent_without_a_terminal(capsys):
    progress, start = episode_progress(quiet=False)
    with progress:
        tick = start(40, 0)
        for i in range(40):
            tick(i % 2 == 0)
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if re.match(r"episodes \d+/40 \(\d+%\)", line)]
    assert len(lines) == 20  # 2 of 40 each: every 5%
    assert lines[-1].startswith("episodes 40/40 (100%), success 50% (20/40)")


def test_quiet_prints_no_progress_lines(capsys):
    progress, start = episode_progress(quiet=True)
    with progress:
        tick = start(10, 0)
        for _ in range(10):
            tick(True)
    assert "episodes 10/10" not in capsys.readouterr().err


def test_show_calls_a_run_nobody_writes_interrupted_or_killed(cli, tmp_path):
    out = tmp_path / "run"
    args = ["run", "--suite", "metaworld/mt1/reach-v3", "--episodes-per-task", "1", "--policy", "random"]
    assert cli(*args, "--out", str(out), "--quiet")[0] == 0
    manifest = json.loads((out / "manifest.json").read_text())
    (out / "manifest.json").write_text(json.dumps(manifest | {"status": "running"}))  # as a SIGKILL leaves it
    code, text, _ = cli("show", str(out))
    assert code == 0 and "interrupted or killed" in text and "--resume" in text
