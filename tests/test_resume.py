"""A run killed with SIGKILL loses at most the episode in flight and resumes exactly;
--resume continues the recorded config, extends it, and survives a policy upgrade."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from harness.errors import UsageError
from harness.run.folder import OpenMode
from harness.run.runner import run
from results.store import RunDir
from tests.fakes import ChunkPolicy, fake_resolved

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

REPO = Path(__file__).resolve().parent.parent
ARGS = [
    "run",
    "--suite",
    "metaworld/mt1/reach-v3",
    "--policy",
    "random",
    "--episodes-per-task",
    "10",
    "--quiet",
]


def _wait_for_rows(out, n: int) -> None:
    """Until the running process has recorded n episodes (or two minutes pass)."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        pending = out / "pending.jsonl"
        if pending.is_file() and pending.read_text().count("\n") >= n:
            return
        time.sleep(0.02)


def test_sigkill_then_resume_records_each_episode_once(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, "-m", "harness", *ARGS, "--out", str(out)],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    _wait_for_rows(out, 3)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    before = RunDir(out).read_episodes()  # every complete row parses; a cut line is dropped
    assert 3 <= len(before) < 10, "the run must be killed mid-way"
    assert not (out / "episodes.parquet").exists()

    done = subprocess.run(
        [sys.executable, "-m", "harness", *ARGS, "--out", str(out), "--resume"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    # the killed process's lock died with it; its record is reported stale and taken over
    assert f"taking over a stale writer lock (pid {proc.pid} " in done.stderr
    assert not (out / "writer.lock").exists()
    df = RunDir(out).read_episodes()
    assert sorted(df["episode_index"]) == list(range(10))
    raw = pq.read_table(out / "episodes.parquet").to_pandas()
    assert len(raw) == 10 and raw["episode_index"].is_unique
    assert set(df["run_id"]) == set(before["run_id"])  # the same run, continued
    kept = df.set_index("episode_index").loc[before["episode_index"], "started_at"]
    assert list(kept) == list(before["started_at"])  # recorded episodes were not re-run


def test_resume_refuses_a_folder_of_another_config(cli, tmp_path):
    out = tmp_path / "run"
    base = ["run", "--suite", "metaworld/mt1/reach-v3", "--episodes-per-task", "1", "--out", str(out)]
    assert cli(*base, "--policy", "random", "--quiet")[0] == 0
    before = sorted(p.name for p in out.rglob("*"))
    code, _, err = cli(*base, "--policy", "random:seed=1", "--resume")
    assert code == 2 and "belongs to a different config" in err and "seed" in err
    code, _, err = cli(*base, "--policy", "random")
    assert code == 2 and "--resume" in err and "--overwrite" in err
    assert sorted(p.name for p in out.rglob("*")) == before


def test_sigterm_stops_cleanly_and_compacts(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, "-m", "harness", *ARGS, "--out", str(out)],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    _wait_for_rows(out, 2)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130
    assert "--resume" in err
    assert not (out / "pending.jsonl").exists()
    rows = pq.read_table(out / "episodes.parquet").num_rows
    assert 2 <= rows < 10


# --- resume that users can type ----------------------------------------------

MT1 = ["run", "--suite", "metaworld/mt1/reach-v3", "--quiet"]


def _rows(out):
    return RunDir(out).read_episodes().sort_values("episode_index").reset_index(drop=True)


def test_resume_with_no_other_flags_continues_the_recorded_config_of_any_run(cli, tmp_path):
    out = tmp_path / "run"
    code, _, err = cli(
        *MT1, "--tasks", "0", "--policy", "random:seed=3", "--episodes-per-task", "2", "--out", str(out)
    )
    assert code == 0, err
    before = _rows(out)
    code, _, err = cli("run", "--out", str(out), "--resume", "--quiet")  # not the embedded default's config
    assert code == 0, err
    assert _rows(out)["started_at"].tolist() == before["started_at"].tolist()  # nothing ran again


def test_flags_restating_the_recorded_config_are_no_difference_and_a_real_one_is_named_alone(cli, tmp_path):
    out, config = tmp_path / "run", tmp_path / "run.toml"
    config.write_text(
        'suite = "metaworld/mt1/reach-v3"\ntasks = [0]\nepisodes_per_task = 1\n'
        '[[policy]]\nname = "random"\nparams = {seed = 3}\n'
    )
    assert cli("run", "--config", str(config), "--out", str(out), "--quiet")[0] == 0
    # a task by name instead of index, a parameter as a flag's string instead of TOML's int
    code, _, err = cli(
        *MT1, "--tasks", "reach-v3", "--policy", "random:seed=3", "--out", str(out), "--resume"
    )
    assert code == 0, err
    code, _, err = cli("run", "--out", str(out), "--resume", "--policy", "random:seed=4", "--quiet")
    assert code == 2 and "belongs to a different config (policies: " in err and err.count("\n") == 1
    for key in ("tasks", "suite", "episodes_per_task", "replan_every", "split"):
        assert f"{key}:" not in err


def test_more_episodes_per_task_extend_a_finished_run_and_fewer_are_refused(cli, tmp_path):
    out = tmp_path / "run"
    assert cli(*MT1, "--policy", "random", "--episodes-per-task", "2", "--out", str(out))[0] == 0
    first = _rows(out)
    code, _, err = cli("run", "--out", str(out), "--resume", "--episodes-per-task", "4", "--quiet")
    assert code == 0 and "extending the run from 2 to 4 episodes per task" in err
    rows = _rows(out)
    assert rows["episode_index"].tolist() == [0, 1, 2, 3] and set(rows["run_id"]) == set(first["run_id"])
    assert rows["started_at"][:2].tolist() == first["started_at"].tolist()  # the first two were kept
    manifest = RunDir(out).read_manifest()
    assert manifest["config"]["episodes_per_task"] == 4 and manifest["extended"][0]["episodes_per_task"] == [
        2,
        4,
    ]
    code, _, err = cli("run", "--out", str(out), "--resume", "--quiet")  # the recorded config is now 4
    assert (
        code == 0
        and "extending" not in err
        and _rows(out)["started_at"].tolist() == rows["started_at"].tolist()
    )
    code, _, err = cli("run", "--out", str(out), "--resume", "--episodes-per-task", "3", "--quiet")
    assert code == 2 and "episodes_per_task: 4 -> 3 (fewer than recorded" in err


def test_a_policy_upgrade_adding_a_defaulted_parameter_does_not_run_recorded_episodes_again(
    cli, tmp_path, monkeypatch
):
    import policies.registry
    from policies.experts.scripted import RANDOM, RandomParams, RandomPolicy

    @dataclasses.dataclass(frozen=True)
    class OldRandomParams:  # the package before it gained chunk_length (default 1)
        seed: int = policies.registry.param(0, "seed", low=0)

    old = dataclasses.replace(
        RANDOM, params=OldRandomParams, build=lambda p: RandomPolicy(RandomParams(seed=p.seed))
    )
    upgraded = policies.registry.all_policies()
    monkeypatch.setattr(policies.registry, "all_policies", lambda: upgraded | {"random": old})
    out = tmp_path / "run"
    assert cli(*MT1, "--policy", "random", "--episodes-per-task", "2", "--out", str(out))[0] == 0
    recorded = _rows(out)
    assert recorded["policy_params"].unique().tolist() == ['{"seed":0}']

    monkeypatch.undo()  # upgraded: random now has chunk_length=1
    code, _, err = cli(*MT1, "--policy", "random", "--episodes-per-task", "2", "--out", str(out), "--resume")
    assert code == 0, err
    assert _rows(out)["started_at"].tolist() == recorded["started_at"].tolist()  # none ran again
    assert "policy 'random' has parameters its recorded rows predate (chunk_length=1)" in err
    code, _, err = cli("run", "--out", str(out), "--resume", "--episodes-per-task", "3", "--quiet")
    rows = _rows(out)
    assert code == 0 and rows["started_at"][:2].tolist() == recorded["started_at"].tolist()
    assert len(rows) == 3 and rows["policy_config_id"].nunique() == 1 and rows["policy_params"].nunique() == 1
    assert any(
        e["event"] == "policy_params_matched_at_defaults" for e in map(json.loads, open(out / "events.jsonl"))
    )
    # a value other than the default is another configuration
    code, _, err = cli("run", "--out", str(out), "--resume", "--policy", "random:chunk_length=2", "--quiet")
    assert code == 2 and "belongs to a different config (policies:" in err


def test_ctrl_c_while_compacting_stops_in_one_line_and_loses_no_row(cli, tmp_path, monkeypatch):
    import results.store

    out = tmp_path / "run"

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt  # the second Ctrl-C, while episodes.parquet is written

    monkeypatch.setattr(results.store.pq, "write_table", interrupted)
    code, _, err = cli(*MT1, "--policy", "random", "--episodes-per-task", "3", "--out", str(out))
    assert code == 130 and err.count("\n") == 1 and "Traceback" not in err
    assert "interrupted while saving; every recorded episode is safe" in err and "--resume" in err
    assert RunDir(out).read_manifest()["status"] == "interrupted"
    assert sorted(p.name for p in out.iterdir()) == ["events.jsonl", "manifest.json", "pending.jsonl"]
    assert len(RunDir(out).read_episodes()) == 3
    monkeypatch.undo()
    code, _, err = cli("run", "--out", str(out), "--resume", "--quiet")
    assert code == 0 and pq.read_table(out / "episodes.parquet").num_rows == 3


def resolving_to(name: str, config_suite: str, episodes: int):
    """A fake run whose suite resolved to `name` from `--suite config_suite`."""
    resolved = fake_resolved(ChunkPolicy(chunk=2), episodes=episodes)
    resolved.suite = dataclasses.replace(resolved.suite, name=name)
    resolved.config = dataclasses.replace(resolved.config, suite=config_suite)
    return resolved


def test_a_suite_default_that_changed_is_named_and_naming_the_recorded_protocol_resumes(tmp_path):
    """The suite is compared by the name it resolved to: the same --suite resolving to
    another protocol (LIBERO's seeding default) is refused with the fix, and naming the
    recorded protocol explicitly is the same suite."""

    out = tmp_path / "run"
    run(resolving_to("fake/countdown:seeding=old", "fake/countdown", 2), out)
    with pytest.raises(
        UsageError,
        match=r"suite: \"fake/countdown:seeding=old\" -> \"fake/countdown:seeding=new\" \(the same --suite now resolves to another protocol",
    ):
        run(resolving_to("fake/countdown:seeding=new", "fake/countdown", 3), out, OpenMode.RESUME)
    report = run(
        resolving_to("fake/countdown:seeding=old", "fake/countdown:seeding=old", 3), out, OpenMode.RESUME
    )
    assert (report.skipped, report.executed) == (2, 1)


def test_a_libero_pro_lan_folder_named_before_the_instruction_option_gets_a_hint_that_works(tmp_path):
    """A lan/task folder recorded before `instruction=` heard the BDDL's words; no --suite
    resolves to its old name any more, so the refusal must not say "name the recorded one"
    but name the suite that runs that protocol now (instruction=bddl) and say to start anew."""

    out = tmp_path / "run"
    legacy = "libero/object:perturb=lan,seeding=openvla"
    run(resolving_to(legacy, "libero/object:perturb=lan", 2), out)
    now = "libero/object:perturb=lan,instruction=filename,seeding=openvla"
    with pytest.raises(UsageError) as refused:
        run(resolving_to(now, "libero/object:perturb=lan", 3), out, OpenMode.RESUME)
    message = str(refused.value)
    assert "name the recorded one" not in message
    assert "before the `instruction=` suite option" in message
    assert "--suite libero/object:perturb=lan,instruction=bddl,seeding=openvla" in message
    assert "instruction=filename for LIBERO-PRO's published path" in message
    # a swap folder's name never changed meaning: the general hint stands
    run(
        resolving_to("libero/object:perturb=swap,seeding=openvla", "libero/object:perturb=swap", 2),
        tmp_path / "s",
    )
    with pytest.raises(UsageError, match="name the recorded one in --suite"):
        run(
            resolving_to("libero/object:perturb=swap,seeding=openpi", "libero/object:perturb=swap", 3),
            tmp_path / "s",
            OpenMode.RESUME,
        )


def test_a_suite_whose_version_changed_is_not_resumed(tmp_path):
    """A suite's version says its episodes or scoring changed (the chain suites' credit
    rule): rows of two versions in one folder would not compare, so the resume is refused."""

    def versioned(version: str, episodes: int):
        resolved = fake_resolved(ChunkPolicy(chunk=2), episodes=episodes)
        resolved.suite = dataclasses.replace(resolved.suite, version=version)
        return resolved

    out = tmp_path / "run"
    run(versioned("1", 2), out)
    with pytest.raises(
        UsageError, match=r'suite version: "1" -> "2" \(the suite\'s episodes or scoring changed'
    ):
        run(versioned("2", 3), out, OpenMode.RESUME)
    assert run(versioned("1", 3), out, OpenMode.RESUME).executed == 1
