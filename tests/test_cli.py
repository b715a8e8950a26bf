"""The command line: help, listings, and one clear line + exit 2 for every bad input."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

REPO = Path(__file__).resolve().parent.parent
MT1 = ["--suite", "metaworld/mt1/reach-v3"]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["run", "--suite", "nope/x"], "unknown suite 'nope/x'; valid suites: metaworld/mt10"),
        (["run", "--suite", "metaworld/mt1/nope-v3"], "unknown Meta-World task 'nope-v3'"),
        (["run", "--tasks", "nope"], "has no task 'nope'; valid tasks (or 0..9): reach-v3"),
        (["run", "--tasks", "99"], "has no task '99'"),
        (
            ["run", "--policy", "nope"],
            "unknown policy 'nope'; valid policies: autoregressive, bidirectional, block_diffusion, fast_dllm, fast_dvla, lerobot, libero_scripted, maniskill_scripted, playback, random, remote, scripted, vlaeval",
        ),
        (
            ["run", *MT1, "--policy", "random:bogus=1"],
            "has no parameter 'bogus'; valid parameters: seed, chunk_length",
        ),
        (["run", *MT1, "--policy", "random:seed=abc"], "parameter 'seed' must be int, got 'abc'"),
        (
            ["run", *MT1, "--policy", "random:chunk_length=0"],
            "chunk_length=0 is out of range; valid range [1, 64]",
        ),
        (["run", *MT1, "--policy", "random:seed"], "expected NAME:key=value"),
        (["run", *MT1, "--episodes-per-task", "0"], "--episodes-per-task must be >= 1, got 0"),
        (["run", *MT1, "--episodes-per-task", "-3"], "--episodes-per-task must be >= 1, got -3"),
        (["run", *MT1, "--episodes-per-task", "51"], "defines 50 episodes; valid range 1..50"),
        (["run", *MT1, "--episodes-per-task", "two"], "invalid int value: 'two'"),
        (["run", *MT1, "--replan-every", "-1"], "--replan-every must be >= 0, got -1"),
        (["run", "--config", "missing.toml"], "config file 'missing.toml' does not exist"),
        (["run", "--resume"], "is not a dvla-harness run folder"),
        (["run", "--retry-failed"], "--retry-failed only makes sense with --resume"),
        (["run", "--resume", "--overwrite"], "not allowed with argument"),
        (["list", "tasks"], "needs a suite"),
        (["list", "widgets"], "invalid choice: 'widgets'"),
        (["show", "no/such/run"], "not a run folder (no manifest.json)"),
    ],
)
def test_bad_input_exits_2_with_a_clear_message_and_writes_nothing(cli, tmp_path, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    if argv[0] == "run" and "--out" not in argv:
        argv = [*argv, "--out", str(tmp_path / "out")]
    code, _out, err = cli(*argv)
    assert code == 2
    assert message in err
    assert list(tmp_path.iterdir()) == []  # no output folder, no runs/ folder


def test_bad_config_file_is_refused(cli, tmp_path):
    cfg = tmp_path / "run.toml"
    cfg.write_text('suite = "metaworld/mt10"\nepisodes = 3\n')
    code, _, err = cli("run", "--config", str(cfg), "--out", str(tmp_path / "out"))
    assert code == 2 and "unknown key 'episodes'; valid keys: suite, tasks" in err
    cfg.write_text('suite = "metaworld/mt10"\n[[policy]]\nname = "random"\nparams = { seed = "x" }\n')
    code, _, err = cli("run", "--config", str(cfg), "--out", str(tmp_path / "out"))
    assert code == 2 and "parameter 'seed' must be int" in err
    assert not (tmp_path / "out").exists()


def test_unwritable_output_folder_is_refused(cli, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    code, _, err = cli("run", *MT1, "--out", str(blocker / "sub"))
    assert code == 2 and "is not writable" in err
    code, _, err = cli("run", *MT1, "--out", str(blocker))
    assert code == 2 and "exists and is not a folder" in err
    assert blocker.read_text() == "x"


def test_overwrite_refuses_a_folder_that_is_not_a_run(cli, tmp_path):
    (tmp_path / "precious").mkdir()
    (tmp_path / "precious" / "thesis.tex").write_text("keep me")
    code, _, err = cli("run", *MT1, "--out", str(tmp_path / "precious"), "--overwrite")
    assert code == 2 and "refusing to delete it" in err
    assert (tmp_path / "precious" / "thesis.tex").read_text() == "keep me"


def test_config_file_lists_several_policies(cli, tmp_path):
    cfg = tmp_path / "run.toml"
    cfg.write_text(
        'suite = "metaworld/mt1/drawer-close-v3"\nepisodes_per_task = 1\n'
        '[[policy]]\nname = "scripted"\n[[policy]]\nname = "random"\nparams = { seed = 4 }\n'
    )
    code, out, _ = cli("run", "--config", str(cfg), "--out", str(tmp_path / "out"), "--quiet")
    assert code == 0
    assert "scripted" in out and "random" in out
    code, out, _ = cli("show", str(tmp_path / "out"))
    assert code == 0 and "drawer-close-v3" in out and "finished" in out


def test_listings(cli):
    code, out, _ = cli("list", "suites")
    assert code == 0 and "metaworld/mt10" in out and "metaworld/mt50" in out
    code, out, _ = cli("list", "policies")
    assert code == 0 and "action_noise: float = 0.0 in [0.0, inf]" in out
    code, out, _ = cli("list", "tasks", "metaworld/mt10")
    assert code == 0 and "open the drawer" in out and "peg-insert-side-v3" in out


def test_list_policies_prints_what_a_person_reads(cli):
    from policies.registry import SHIPPED_CHECKPOINTS

    code, out, _ = cli("list", "policies")
    assert code == 0
    assert "tau_add: float = 0.2857 (2/7) in [0.0, 1.0]" in out and "0.2857142857142857" not in out
    assert "seed: int = 0, any integer >= 0" in out and "9223372036854775807" not in out
    assert "checkpoint: str = metaworld-mt10 (shipped set)" in out
    assert str(SHIPPED_CHECKPOINTS) not in out  # no install path (site-packages) as a default


@pytest.mark.parametrize("sub", ["", "run", "list", "show", "collect", "train"])
def test_help_everywhere_and_python_dash_m(sub):
    argv = [sys.executable, "-m", "harness", *([sub] if sub else []), "--help"]
    done = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0
    assert "usage: dvla-harness" in done.stdout and "example" in done.stdout


def test_listing_suites_does_not_import_simulators():
    code = "import sys; from harness.cli import main; main(['list','suites']); print('metaworld' in sys.modules, 'torch' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.stdout.strip().endswith("False False")


def test_an_unforeseen_exception_prints_its_traceback_and_exits_3(monkeypatch, capsys):
    """`entry` (the console script) turns a bug, anything but the harness's own errors,
    into exit 3 (a harness error), never 1, which means some episode failed."""
    import harness.commands.listing
    from harness.cli import entry
    from harness.errors import EXIT_HARNESS

    def broken(args: object) -> int:
        raise RuntimeError("a bug in a command")

    monkeypatch.setattr(harness.commands.listing, "cmd_list", broken)
    monkeypatch.setattr(sys, "argv", ["dvla-harness", "list", "suites"])
    with pytest.raises(SystemExit) as exited:
        entry()
    assert exited.value.code == EXIT_HARNESS == 3
    err = capsys.readouterr().err
    assert "Traceback" in err and "RuntimeError: a bug in a command" in err
    assert err.rstrip().splitlines()[-1] == "dvla-harness: internal error (traceback above); exit status 3"


def test_install_hints_give_the_clone_form_and_the_index_form(monkeypatch, tmp_path):
    from harness import plugins

    hint = plugins.install_hint("libero")  # these tests run from a clone
    assert (
        'pip install -c constraints.txt ".[libero]"' in hint and "pip install 'dvla-harness[libero]'" in hint
    )
    assert plugins.install_hint("linesim", "dvla-line-plugin") == "pip install 'dvla-line-plugin[linesim]'"
    monkeypatch.setattr(plugins, "_CLONE", tmp_path)  # installed from an index: no clone around it
    assert plugins.install_hint("libero") == "pip install 'dvla-harness[libero]'"
