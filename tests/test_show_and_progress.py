"""What a person reading a log or a killed run sees: progress lines without a terminal,
errors without a blank line before them, and `show` telling a killed run from a running one."""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path

import pytest

from harness.console import episode_progress
from policies.dvla.checkpoint import load, save
from results.lock import RunLock
from tests.test_dvla_policies import make_checkpoint

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


def test_a_long_run_off_a_terminal_names_its_folder_first_and_reports_every_ten_episodes(capsys):
    progress, start = episode_progress(quiet=False, folder=Path("runs/long"))
    with progress:
        tick = start(400, 0)
        for _ in range(25):
            tick(True)
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == "run folder: runs/long"
    assert [line.split(" (")[0] for line in lines[1:]] == ["episodes 10/400", "episodes 20/400"]


def test_progress_written_to_a_file_ends_with_one_last_frame(capsys):
    """Off a terminal the plain lines are the display: no rich frame repeats the last one."""
    progress, start = episode_progress(quiet=False)
    with progress:
        tick = start(4, 0)
        for _ in range(4):
            tick(True)
    err = capsys.readouterr().err
    assert err.count("episodes 4/4") == 1 and err.count("4/4") == 2 and "━" not in err


def test_quiet_prints_no_progress_lines(capsys):
    progress, start = episode_progress(quiet=True)
    with progress:
        tick = start(10, 0)
        for _ in range(10):
            tick(True)
    assert "episodes 10/10" not in capsys.readouterr().err


MT1 = ["run", "--suite", "metaworld/mt1/reach-v3", "--episodes-per-task", "1"]
Cli = Callable[..., tuple[int, str, str]]
Setup = Callable[[Cli, Path, pytest.FixtureRequest], list[str]]


def _existing_folder(cli: Cli, out: Path, request: pytest.FixtureRequest) -> list[str]:
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    return [*MT1, "--policy", "random", "--out", str(out)]


def _another_config(cli: Cli, out: Path, request: pytest.FixtureRequest) -> list[str]:
    assert cli(*MT1, "--policy", "random", "--out", str(out), "--quiet")[0] == 0
    return [*MT1, "--policy", "random:seed=1", "--out", str(out), "--resume"]


def _lock_held(cli: Cli, out: Path, request: pytest.FixtureRequest) -> list[str]:
    assert cli(*MT1, "--policy", "random", "--out", str(out), "--quiet")[0] == 0
    lock = RunLock(out)
    lock.acquire()  # flock is per open file: this process's own run is refused too
    request.addfinalizer(lock.release)
    return [*MT1, "--policy", "random", "--out", str(out), "--resume"]


def _changed_checkpoint(cli: Cli, out: Path, request: pytest.FixtureRequest) -> list[str]:
    ckpt = make_checkpoint(out.parent / "m.safetensors", "bidirectional")
    args = [*MT1, "--policy", f"bidirectional:checkpoint={ckpt},steps=1", "--out", str(out)]
    assert cli(*args, "--quiet")[0] == 0
    other = load(ckpt)
    other.meta = {"recipe": "another model"}
    save(other, ckpt)
    return [*args, "--resume"]


@pytest.mark.parametrize(
    ("setup", "says"),
    [
        (_existing_folder, "exists and is not empty"),
        (_another_config, "belongs to a different config"),
        (_lock_held, "being written by another process"),
        (_changed_checkpoint, "had sha256"),
    ],
)
def test_an_error_opening_the_run_folder_is_stderrs_first_line_with_the_progress_bar_on(
    cli: Cli, tmp_path: Path, request: pytest.FixtureRequest, setup: Setup, says: str
) -> None:
    """Without --quiet (the progress display on), as a user types it."""
    args = setup(cli, tmp_path / "run", request)
    code, _, err = cli(*args)
    assert code == 2
    assert err.splitlines()[0].startswith("dvla-harness run: error: "), repr(err)
    assert says in err.splitlines()[0] and len(err.splitlines()) == 1


def test_show_calls_a_run_nobody_writes_interrupted_or_killed(cli, tmp_path):
    out = tmp_path / "run"
    args = ["run", "--suite", "metaworld/mt1/reach-v3", "--episodes-per-task", "1", "--policy", "random"]
    assert cli(*args, "--out", str(out), "--quiet")[0] == 0
    manifest = json.loads((out / "manifest.json").read_text())
    (out / "manifest.json").write_text(json.dumps(manifest | {"status": "running"}))  # as a SIGKILL leaves it
    code, text, _ = cli("show", str(out))
    assert code == 0 and "interrupted or killed" in text and "--resume" in text


def test_run_and_show_tell_two_configurations_of_one_policy_apart(cli, tmp_path):
    out = tmp_path / "r"
    code, text, err = cli(
        "run", "--suite", "metaworld/mt1/reach-v3", "--policy", "random:seed=1", "--policy", "random:seed=2",
        "--episodes-per-task", "1", "--out", str(out),
    )  # fmt: skip
    assert code == 0, err
    assert "random (seed=1)" in text and "random (seed=2)" in text
    code, text, _ = cli("show", str(out))
    assert code == 0 and "random (seed=1)" in text and "random (seed=2)" in text
