"""Actions outside the env's action space (harness/episode/actions.py): failed by default,
clipped or recorded by choice, counted in every row, held fixed across --resume, and
caught by `check policy` on any call of any episode, not only the first."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import gymnasium as gym
import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from adapters.base import EpisodeSpec, Suite, TaskSpec
from harness.conformance import check_policy
from harness.errors import UsageError
from harness.run.folder import OpenMode
from harness.run.runner import run
from policies.base import ChunkBatch, EpisodeContext
from policies.registry import NoParams, PolicySpec
from results import schema
from results.board_warnings import out_of_space_warnings
from results.store import RunDir, read_table, rows_to_table
from tests.fakes import CountdownEnv, fake_resolved, run_batch
from tests.test_plugins import installed_plugin  # noqa: F401  (the fixture)

UNIT = gym.spaces.Box(-1.0, 1.0, (2,))  # the [-1, 1] space of most robot suites


class ValuePolicy:
    """Chunks of `chunk` actions of 0.5, except on act call `at` (1-based) of episode
    `episode` (1-based, counted by resets), where every action is `value`; `at` None:
    every call. Batchable (no state between calls but the counters)."""

    def __init__(self, value: float, chunk: int = 3, at: int | None = None, episode: int | None = None):
        self.value, self.chunk, self.at, self.episode = value, chunk, at, episode
        self.resets = self.calls = 0

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        self.resets, self.calls = self.resets + 1, 0

    def act(self, observations: Sequence[object]) -> ChunkBatch:
        return self.act_batch([], observations)

    def act_batch(self, episodes: Sequence[EpisodeContext], observations: Sequence[object]) -> ChunkBatch:
        self.calls += 1
        hit = (self.at is None or self.calls == self.at) and (self.episode in (None, self.resets))
        value = self.value if hit else 0.5
        return ChunkBatch(actions=np.full((len(observations), self.chunk, 2), value))


def unit_resolved(policy: object, rule: str | None = None, episodes: int = 2, succeed_at: int | None = 4):
    """fake_resolved whose envs have the [-1, 1] action space, under `rule` (None: the default)."""
    resolved = fake_resolved(policy, episodes=episodes, succeed_at=succeed_at)
    make = resolved.suite.make_env

    def unit_env(task):
        env = make(task)
        env.action_space = UNIT
        return env

    resolved.suite = dataclasses.replace(resolved.suite, make_env=unit_env)
    if rule is not None:
        resolved.config = dataclasses.replace(resolved.config, out_of_space=rule)
    return resolved


def executed(resolved) -> np.ndarray:
    """Every action any of the run's envs received, in order of the envs' making."""
    actions = [a for env in resolved.made_envs for a in env.actions]
    return np.array(actions).reshape(-1, 2)


def rows(out) -> list[dict]:
    return RunDir(out).read_episodes().sort_values("episode_index").to_dict("records")


def test_the_default_fails_the_episode_naming_step_value_and_bounds_and_the_env_gets_nothing(tmp_path):
    resolved = unit_resolved(ValuePolicy(5.0))
    report = run(resolved, tmp_path / "r")
    assert report.failed == 2
    for row in rows(tmp_path / "r"):
        assert row["failure_reason"].startswith("ActionOutOfSpace: the action for env step 0 ")
        assert "element 0 is 5, bounds [-1, 1]" in row["failure_reason"]
        assert "--out-of-space clip or record" in row["failure_reason"]
        assert not row["success"] and row["steps"] == 0
        assert row["out_of_space_rule"] == "fail"
        assert row["actions_out_of_space"] == 3 and row["max_action_excess"] == pytest.approx(4.0)
    assert executed(resolved).size == 0
    manifest = RunDir(tmp_path / "r").read_manifest()
    assert manifest["config"]["out_of_space"] == "fail"


def test_a_later_chunk_out_of_space_names_its_step(tmp_path):
    run(unit_resolved(ValuePolicy(-1.5, chunk=2, at=2), succeed_at=None, episodes=1), tmp_path / "r")
    (row,) = rows(tmp_path / "r")
    assert "the action for env step 2 (0-based; action 0 of its chunk)" in row["failure_reason"]
    assert "element 0 is -1.5, bounds [-1, 1]" in row["failure_reason"]
    assert row["steps"] == 2 and row["actions_out_of_space"] == 2


def test_clip_gives_the_env_clipped_actions_and_counts_them(tmp_path):
    resolved = unit_resolved(ValuePolicy(5.0), "clip")
    report = run(resolved, tmp_path / "r")
    assert report.failed == 0
    seen = executed(resolved)
    assert len(seen) == 8 and (seen == 1.0).all()  # 2 episodes x 4 steps, each element clipped to 1
    for row in rows(tmp_path / "r"):
        assert pd.isna(row["failure_reason"]) and row["success"]
        assert row["out_of_space_rule"] == "clip"
        # two chunks of 3 returned, all outside: the action past success counts too
        assert row["actions_out_of_space"] == 6 and row["max_action_excess"] == pytest.approx(4.0)
    assert RunDir(tmp_path / "r").read_manifest()["config"]["out_of_space"] == "clip"


def test_record_passes_actions_unclipped_and_counts_them(tmp_path):
    resolved = unit_resolved(ValuePolicy(1e6), "record")
    assert run(resolved, tmp_path / "r").failed == 0
    assert (executed(resolved) == 1e6).all()
    for row in rows(tmp_path / "r"):
        assert pd.isna(row["failure_reason"]) and row["actions_out_of_space"] == 6
        assert row["max_action_excess"] == pytest.approx(1e6 - 1)
    (warning,) = out_of_space_warnings(RunDir(tmp_path / "r").read_episodes())
    assert "12 action(s) outside the action space in 2 of 2 episode(s)" in warning
    assert "--out-of-space record; 0 episode(s) failed for it" in warning


def test_in_space_actions_count_zero(tmp_path):
    run(unit_resolved(ValuePolicy(1.0)), tmp_path / "r")
    for row in rows(tmp_path / "r"):
        assert pd.isna(row["failure_reason"]) and row["actions_out_of_space"] == 0
        assert row["max_action_excess"] == 0.0
    assert out_of_space_warnings(RunDir(tmp_path / "r").read_episodes()) == []


@pytest.mark.parametrize("rule", ["clip", "record"])
def test_non_finite_actions_fail_under_every_rule(tmp_path, rule):
    resolved = unit_resolved(ValuePolicy(float("nan")), rule)
    assert run(resolved, tmp_path / "r").failed == 2
    assert all("non-finite" in row["failure_reason"] for row in rows(tmp_path / "r"))
    assert executed(resolved).size == 0


def _context(max_steps: int = 10) -> EpisodeContext:
    return EpisodeContext(
        "fake/countdown", "count", "count", UNIT, CountdownEnv.observation_space, max_steps, 0
    )


@pytest.mark.parametrize(
    ("rule", "failed", "seen"), [("fail", 3, None), ("clip", 0, 1.0), ("record", 0, 5.0)]
)
def test_batched_episodes_follow_the_rule(rule, failed, seen):
    policy = ValuePolicy(5.0, chunk=2)
    envs: list = []

    def make_env():
        env = CountdownEnv(succeed_at=3)
        env.action_space = UNIT
        envs.append(env)
        return env

    specs = [EpisodeSpec(i) for i in range(3)]
    out = dict(run_batch(specs, make_env, policy, lambda _s, _e: _context(), 2, out_of_space=rule))
    assert sum(o.failure_reason is not None for o in out.values()) == failed
    assert all(o.actions_out_of_space == (2 if rule == "fail" else 4) for o in out.values())
    actions = np.array([a for env in envs for a in env.actions])
    if seen is None:
        assert actions.size == 0
        assert all(o.failure_reason.startswith("ActionOutOfSpace: ") for o in out.values())
    else:
        assert actions.size and (actions == seen).all()
    for env in envs:
        env.close()


def test_resume_refuses_another_rule_and_reads_an_older_manifest_as_fail(tmp_path):
    from harness.run.recorded import fingerprint_of

    out = tmp_path / "r"
    run(unit_resolved(ValuePolicy(1.0), episodes=1), out)
    with pytest.raises(UsageError, match=r'out_of_space: "fail" -> "clip"'):
        run(unit_resolved(ValuePolicy(1.0), "clip", episodes=2), out, OpenMode.RESUME)
    # a manifest written before the rule existed: its runs resume under the default
    manifest = RunDir(out).read_manifest()
    del manifest["config"]["out_of_space"]
    manifest["config_fingerprint"] = fingerprint_of(manifest["config"])  # as the older harness took it
    RunDir(out).write_manifest(manifest)
    with pytest.raises(UsageError, match=r'out_of_space: "fail" -> "record"'):
        run(unit_resolved(ValuePolicy(1.0), "record", episodes=2), out, OpenMode.RESUME)
    report = run(unit_resolved(ValuePolicy(1.0), episodes=2), out, OpenMode.RESUME)
    assert (report.skipped, report.executed) == (1, 1)


def test_a_bad_rule_exits_2_naming_the_choices(cli, tmp_path):
    code, _, err = cli("run", "--out-of-space", "ignore")
    assert code == 2 and "invalid choice: 'ignore'" in err
    assert "'fail', 'clip', 'record'" in err
    config = tmp_path / "c.toml"
    config.write_text('out_of_space = "ignore"\n')
    code, _, err = cli("run", "--config", str(config), "--out", str(tmp_path / "r"))
    assert code == 2 and "out_of_space 'ignore' is not a rule; choose one of fail, clip, record" in err
    assert not (tmp_path / "r").exists()
    code, out, _ = cli("run", "--help")
    assert code == 0 and "--out-of-space RULE" in out


def test_show_warns_about_out_of_space_actions(cli, tmp_path):
    run(unit_resolved(ValuePolicy(5.0), "clip"), tmp_path / "r")
    code, _, err = cli("show", str(tmp_path / "r"))
    assert code == 0 and "outside the action space in 2 of 2" in err and "--out-of-space clip" in err


def test_a_version_3_table_reads_the_new_columns_as_null(tmp_path):
    from tests.test_leaderboard import row  # one valid row of the episode table

    new = ["out_of_space_rule", "actions_out_of_space", "max_action_excess"]
    counted = {"out_of_space_rule": "clip", "actions_out_of_space": 2, "max_action_excess": 0.5}
    pq.write_table(rows_to_table([row() | counted]), tmp_path / "v4.parquet")
    back = read_table(tmp_path / "v4.parquet").to_pylist()[0]
    assert {name: back[name] for name in new} == counted
    old = rows_to_table([row()]).drop_columns(new)
    old = old.replace_schema_metadata({schema.SCHEMA_VERSION_KEY: b"3"})
    pq.write_table(old, tmp_path / "v3.parquet")
    table = read_table(tmp_path / "v3.parquet")
    assert all(table.column(name).null_count == 1 for name in new)
    assert schema.SCHEMA_VERSION == "5" and "3" in schema.READABLE_VERSIONS


# --- check policy: every call of more than one episode ---------------------------------


def _check(policy: ValuePolicy) -> tuple[bool, str]:
    specs = tuple(EpisodeSpec(i, seed=i) for i in range(3))
    task = TaskSpec("count", "count to n", 50, specs)

    def make_env(_task):
        env = CountdownEnv(succeed_at=None)
        env.action_space = UNIT
        return env

    suite = Suite("fake/countdown", "1", (task,), make_env)
    spec = PolicySpec("fake", "test policy", NoParams, lambda _p: policy)
    findings = {f.rule: f for f in check_policy(spec, {}, suite)}
    (act,) = [f for rule, f in findings.items() if rule.startswith("reset + act")]
    return act.ok, act.detail


def test_check_policy_catches_a_break_on_step_3_of_episode_2():
    ok, detail = _check(ValuePolicy(5.0, chunk=1, at=3, episode=2))
    assert not ok
    assert detail.startswith("episode 1 (spec 1 of count), chunk 2 (env step 2): the action for env step 2")
    assert "element 0 is 5, bounds [-1, 1]" in detail
    ok, detail = _check(ValuePolicy(0.5, chunk=1))
    assert ok and detail == "8 chunk(s) over 2 episodes, 8 env step(s)"


def test_check_policy_names_the_call_of_a_bad_shape():
    class Shrinking(ValuePolicy):
        def act_batch(self, episodes, observations):
            batch = super().act_batch(episodes, observations)
            return ChunkBatch(actions=batch.actions[:, :, :1] if self.calls == 2 else batch.actions)

    ok, detail = _check(Shrinking(0.5, chunk=2))
    assert not ok and detail.startswith("episode 0 (spec 0 of count), chunk 1 (env step 2): actions of shape")


def test_leaderboard_and_gate_warn_about_rules_and_out_of_space_actions(cli, tmp_path):
    from results.board_warnings import out_of_space_gate_warnings

    run(unit_resolved(ValuePolicy(1.0)), tmp_path / "a")
    clipped = unit_resolved(ValuePolicy(5.0), "clip")
    clipped.policies[0].params_json, clipped.policies[0].config_id = '{"value":5}', "fakeconfig05"
    run(clipped, tmp_path / "b")
    code, _, err = cli("leaderboard", str(tmp_path / "a"), str(tmp_path / "b"))
    assert code == 0 and "rows differ in --out-of-space rule: ['clip', 'fail']" in err
    assert "12 action(s) outside the action space in 2 of 2 episode(s)" in err
    a, b = (RunDir(tmp_path / name).read_episodes() for name in "ab")
    baseline_rule, candidate_counts = out_of_space_gate_warnings(a, b)
    assert baseline_rule.startswith("--out-of-space rules differ (baseline fail, candidate clip)")
    assert candidate_counts.startswith("candidate fake: 12 action(s) outside the action space")
    assert out_of_space_gate_warnings(a, a) == ()


def test_a_plain_resume_keeps_the_recorded_rule_and_a_flag_for_another_is_refused(
    installed_plugin,  # noqa: F811
    cli,
    tmp_path,
):
    out = str(tmp_path / "r")
    base = ("run", "--suite", "line/walk", "--policy", "constant:value=1.0", "--out", out, "--quiet")
    assert cli(*base, "--episodes-per-task", "1", "--out-of-space", "record")[0] == 0
    code, _, err = cli("run", "--out", out, "--resume", "--episodes-per-task", "2", "--quiet")
    assert code == 0, err
    assert set(RunDir(out).read_episodes()["out_of_space_rule"]) == {"record"}
    code, _, err = cli("run", "--out", out, "--resume", "--out-of-space", "fail", "--quiet")
    assert code == 2 and 'out_of_space: "record" -> "fail"' in err
