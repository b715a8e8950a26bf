"""The runner on the fake env: rows, durability, failure isolation, resume bookkeeping."""

from __future__ import annotations

import json

import pyarrow.parquet as pq
import pytest

import harness.run.runner
from harness.errors import UsageError
from harness.run.folder import OpenMode
from harness.run.runner import run
from results.schema import COLUMN_NAMES
from results.store import RunDir
from tests.fakes import ChunkPolicy, fake_resolved

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes


def test_rows_are_written_one_per_episode(tmp_path):
    resolved = fake_resolved(ChunkPolicy(chunk=2), episodes=3, succeed_at=5)
    report = run(resolved, tmp_path / "run")
    assert report.executed == 3 and report.failed == 0
    df = RunDir(tmp_path / "run").read_episodes()
    assert list(df.columns) == list(COLUMN_NAMES)
    assert df["episode_index"].tolist() == [0, 1, 2]
    assert df["success"].all() and (df["steps"] == 5).all() and (df["chunks"] == 3).all()
    assert (df["action_tokens_total"] == 12).all()
    assert (df["tokens_per_s"] > 0).all()
    assert not (tmp_path / "run" / "pending.jsonl").exists()  # compacted
    assert pq.read_table(tmp_path / "run" / "episodes.parquet").num_rows == 3
    manifest = json.loads((tmp_path / "run" / "manifest.json").read_text())
    assert manifest["status"] == "finished" and manifest["finished_at"]


def test_an_episode_exception_is_a_row_and_the_run_goes_on(tmp_path):
    resolved = fake_resolved(ChunkPolicy(chunk=2), episodes=3, succeed_at=5, fail_episode=1)
    report = run(resolved, tmp_path / "run")
    assert report.executed == 3 and report.failed == 1
    df = RunDir(tmp_path / "run").read_episodes()
    failed = df[df["episode_index"] == 1].iloc[0]
    assert not failed["success"] and failed["failure_reason"] == "RuntimeError: simulator exploded"
    assert df[df["episode_index"] != 1]["success"].all()
    assert len(resolved.made_envs) == 2  # the env that raised was rebuilt, not reused
    events = [json.loads(line) for line in (tmp_path / "run" / "events.jsonl").read_text().splitlines()]
    failures = [e for e in events if e["event"] == "episode_failed"]
    assert len(failures) == 1 and "simulator exploded" in failures[0]["traceback"]


def test_each_episode_is_durable_before_the_next_starts(tmp_path):
    """When episode i starts, a separate reader already sees every earlier episode."""
    seen_parts: list[int] = []
    out = tmp_path / "run"

    class Watching(ChunkPolicy):
        def reset(self, episodes):
            seen_parts.append(len(RunDir(out).read_episodes()))
            super().reset(episodes)

    run(fake_resolved(Watching(chunk=2), episodes=4), out)
    assert seen_parts == [
        0,
        0,
        1,
        2,
        3,
    ]  # the warm-up's reset (harness/backends/warmup.py), then one per episode


def test_resume_runs_only_missing_episodes_and_retry_failed_reruns_failures(tmp_path):
    out = tmp_path / "run"
    run(fake_resolved(ChunkPolicy(chunk=2), episodes=3, fail_episode=1), out)
    again = run(fake_resolved(ChunkPolicy(chunk=2), episodes=3), out, OpenMode.RESUME)
    assert again.executed == 0 and again.skipped == 3
    retried = run(fake_resolved(ChunkPolicy(chunk=2), episodes=3), out, OpenMode.RETRY_FAILED)
    assert retried.executed == 1
    df = RunDir(out).read_episodes()
    assert len(df) == 3 and df["success"].all() and df["failure_reason"].isna().all()


def test_a_row_cut_short_by_a_kill_is_dropped_and_others_kept(tmp_path):
    out = tmp_path / "run"
    run(fake_resolved(ChunkPolicy(chunk=2), episodes=2), out)
    run_dir = RunDir(out)
    rows = run_dir.read_episodes()
    (out / "episodes.parquet").unlink()
    for row in rows.to_dict("records"):
        run_dir.append_episode({k: (None if v != v else v) for k, v in row.items()})
    with open(out / "pending.jsonl", "a") as fh:
        fh.write('{"run_id": "half a ro')  # SIGKILL mid-write
    assert len(run_dir.read_episodes()) == 2


def test_summary_lists_policies_in_the_order_they_ran(cli, tmp_path):
    from results.summary import summarize

    out = tmp_path / "run"
    args = ["run", "--suite", "metaworld/mt1/reach-v3", "--episodes-per-task", "1", "--quiet"]
    assert cli(*args, "--policy", "scripted", "--policy", "random", "--out", str(out))[0] == 0
    summary = summarize(RunDir(out).read_episodes())
    assert summary["policy"].drop_duplicates().tolist() == ["scripted", "random"]


def test_a_tasks_env_is_closed_when_the_next_task_starts(tmp_path):
    # LIBERO envs hold ~0.5 GB each: a 90-task suite must not keep them all open.
    resolved = fake_resolved(ChunkPolicy(chunk=2), episodes=2, succeed_at=3, tasks=3)
    report = run(resolved, tmp_path / "run")
    assert report.executed == 6 and report.failed == 0
    envs = resolved.made_envs
    assert len(envs) == 3  # one per task, reused across that task's episodes
    assert [env.open_when_made for env in envs] == [0, 0, 0]  # the previous task's was closed first
    assert all(env.closed for env in envs)
    assert [len(env.actions) for env in envs] == [6, 6, 6]


def test_the_env_built_for_the_pre_flight_check_is_the_one_the_episodes_use(tmp_path):
    checked: list[object] = []

    class Checking(ChunkPolicy):
        def check_spaces(self, observation_space, action_space):
            checked.append(action_space)

    resolved = fake_resolved(Checking(chunk=2), episodes=2, tasks=2)
    run(resolved, tmp_path / "run")
    assert len(checked) == 1
    assert len(resolved.made_envs) == 2  # one per task: the checked env was not rebuilt
    assert all(env.closed for env in resolved.made_envs)


def test_a_run_that_stops_before_its_episodes_closes_the_pre_flight_env(tmp_path, monkeypatch):
    class Checking(ChunkPolicy):
        def check_spaces(self, observation_space, action_space):
            pass

    def refuse(*_args):
        raise UsageError("the recorded run has another configuration")

    monkeypatch.setattr(harness.run.runner.RunFolder, "open", refuse)
    resolved = fake_resolved(Checking(chunk=2), episodes=1)
    with pytest.raises(UsageError):
        run(resolved, tmp_path / "run")
    assert len(resolved.made_envs) == 1 and resolved.made_envs[0].closed


def test_a_policy_calling_sys_exit_fails_its_episode_and_the_run_goes_on(tmp_path):
    class Exits(ChunkPolicy):
        episode = -1

        def reset(self, episodes):
            super().reset(episodes)
            self.episode = episodes[0].episode_index

        def act(self, observations):
            if self.episode == 1:
                raise SystemExit(3)
            return super().act(observations)

    report = run(fake_resolved(Exits(chunk=2), episodes=4, succeed_at=5), tmp_path / "run")
    assert report.executed == 4 and report.failed == 1
    df = RunDir(tmp_path / "run").read_episodes()
    assert df.set_index("episode_index").loc[1, "failure_reason"] == "SystemExit: 3"
    assert json.loads((tmp_path / "run" / "manifest.json").read_text())["status"] == "finished"


def test_a_policy_calling_sys_exit_through_the_cli_exits_1_with_a_finished_run(cli, tmp_path, monkeypatch):
    """What a user sees: the run is not ended by the policy's exit status (3 here), but
    finishes, with that episode a failure row and exit 1 (some episode failed)."""
    from policies.experts.scripted import RandomPolicy

    act = RandomPolicy.act

    def exits_in_episode_1(self: RandomPolicy, observations: object) -> object:
        if self._episodes[0].episode_index == 1:  # not 0: the warm-up runs on episode 0
            raise SystemExit(3)
        return act(self, observations)

    monkeypatch.setattr(RandomPolicy, "act", exits_in_episode_1)
    out = tmp_path / "run"
    code, _, err = cli(
        "run", "--suite", "metaworld/mt1/reach-v3", "--policy", "random", "--episodes-per-task", "3",
        "--out", str(out), "--quiet",
    )  # fmt: skip
    assert code == 1, err
    assert "1 episode(s) raised an exception" in err
    assert json.loads((out / "manifest.json").read_text())["status"] == "finished"
    df = RunDir(out).read_episodes().set_index("episode_index")
    assert df.index.tolist() == [0, 1, 2]
    assert df.loc[1, "failure_reason"] == "SystemExit: 3" and not df.loc[1, "success"]
    assert df.loc[[0, 2], "failure_reason"].isna().all()


def test_resume_refuses_rows_of_a_suite_the_config_no_longer_resolves_to(tmp_path):
    """A default that changes the suite's canonical name (LIBERO's seeding) must not let
    --resume add rows of the new protocol to a folder of the old one."""
    resolved = fake_resolved(ChunkPolicy(chunk=2), episodes=3, succeed_at=5)
    run(resolved, tmp_path / "run")
    rows = RunDir(tmp_path / "run").read_episodes()
    rows = rows.assign(suite="fake/countdown:seeding=old")
    import pyarrow as pa

    from results.schema import arrow_schema

    table = pa.Table.from_pandas(rows, schema=arrow_schema(), preserve_index=False)
    pq.write_table(
        table.replace_schema_metadata(arrow_schema().metadata), tmp_path / "run" / "episodes.parquet"
    )
    with pytest.raises(UsageError, match="holds rows of suite 'fake/countdown:seeding=old'"):
        run(fake_resolved(ChunkPolicy(chunk=2), episodes=4, succeed_at=5), tmp_path / "run", OpenMode.RESUME)
