"""Batched inference across environments (--batch-envs K, harness/episode/loop.py).

A physics-free env whose episodes have different lengths and a fake batching policy with
a real torch module (so NFE is counted by the harness's hooks, as for a decoder).
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Sequence

import numpy as np
import pytest

from adapters.base import EpisodeSpec
from harness.backends import Execution
from harness.backends.options import check_batching
from harness.episode.nfe import NFECounter
from harness.errors import UsageError
from harness.run.folder import OpenMode
from harness.run.runner import run
from policies.base import ChunkBatch, EpisodeContext
from tests.fakes import ChunkPolicy, CountdownEnv, context, fake_resolved, run_batch

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes


def length(index: int) -> int:
    """Episode `index` succeeds on this step: lengths 2..8, never a multiple of the chunk
    alone, so slots end mid-chunk and at different steps."""
    return 2 + (index * 5) % 7


class LengthEnv(CountdownEnv):
    """Succeeds at `length(episode index)`; episode `fail_episode` raises in step 2."""

    def __init__(self, fail_episode: int | None = None):
        super().__init__(succeed_at=None)
        self.fail_episode = fail_episode
        self.seen: list[tuple[int, int]] = []  # (episode running, episode the action was for)

    def reset(self, *, seed=None, options=None):
        spec = options["episode"]
        self.succeed_at = length(spec.index)
        self.fail_at = 2 if spec.index == self.fail_episode else None
        self.episode = spec.index
        return super().reset(seed=seed, options=options)

    def step(self, action):
        self.seen.append((self.episode, round(float(action[0]) * 100)))
        return super().step(action)


class BatchPolicy:
    """A batching policy: one pass of a torch module per call whatever the batch size;
    each action is the episode's index (so the env can tell slots apart); sleeps `delay`."""

    def __init__(
        self,
        chunk: int = 3,
        delay: float = 0.0,
        nan_episode: int | None = None,
        raise_episode: int | None = None,
    ):
        import torch

        self.net = torch.nn.Linear(1, 1)
        self.chunk, self.delay, self.nan_episode = chunk, delay, nan_episode
        self.raise_episode = raise_episode
        self.calls: list[list[int]] = []  # the episode indices each call served
        self.resets: list[int] = []

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        self.resets += [e.episode_index for e in episodes]
        self.episodes = episodes

    def act(self, observations):  # the unbatched contract (the warm-up's first call)
        return self.act_batch(self.episodes, observations)

    def act_batch(self, episodes: Sequence[EpisodeContext], observations) -> ChunkBatch:
        import torch

        if self.delay:
            time.sleep(self.delay)
        with torch.no_grad():
            self.net(torch.zeros(len(episodes), 1))
        self.calls.append([e.episode_index for e in episodes])
        if any(e.episode_index == self.raise_episode for e in episodes):
            raise RuntimeError(f"cannot decode episode {self.raise_episode}'s observation")
        index = np.array([e.episode_index for e in episodes], dtype=float)
        actions = np.repeat(index[:, None, None], self.chunk, axis=1).repeat(2, axis=2) / 100
        for row, e in enumerate(episodes):
            if e.episode_index == self.nan_episode:
                actions[row, 0, 0] = np.nan
        return ChunkBatch(actions=actions, action_tokens=len(episodes) * self.chunk * 2)


def context_for(spec: EpisodeSpec, env) -> EpisodeContext:
    return dataclasses.replace(context(50), episode_index=spec.index, seed=spec.seed)


def batched(policy, episodes: int, k: int, fail_episode: int | None = None, envs=None):
    made: list[LengthEnv] = []

    def make_env():
        made.append(LengthEnv(fail_episode))
        return made[-1]

    specs = [EpisodeSpec(index=i, seed=100 + i) for i in range(episodes)]
    counter = NFECounter(policy)
    try:
        start = time.perf_counter()
        out = run_batch(specs, make_env, policy, context_for, k, envs=envs or (), counter=counter)
        elapsed = time.perf_counter() - start
    finally:
        counter.close()
    return out, made, elapsed


def test_every_episode_runs_once_in_k_slots_that_are_reused():
    policy = BatchPolicy(chunk=3, delay=0.002)
    out, made, _ = batched(policy, episodes=10, k=4)
    assert sorted(i for i, _ in out) == list(range(10))  # each exactly once
    by_index = dict(out)
    for i, o in by_index.items():
        assert o.success and o.failure_reason is None and o.batch_envs == 4
        assert o.steps == length(i)  # its own length, whatever the other slots did
        assert o.chunks == -(-length(i) // 3)  # a chunk is asked for only when used up
    assert len(made) == 4  # four envs, reused by the ten episodes
    assert sorted(policy.resets) == list(range(10))  # one reset per episode, as it starts
    # batching happened: at most K per call, K at the start, fewer calls than chunks
    assert max(map(len, policy.calls)) == 4 and policy.calls[0] == [0, 1, 2, 3]
    assert sum(map(len, policy.calls)) == sum(o.chunks for o in by_index.values())
    assert len(policy.calls) < sum(o.chunks for o in by_index.values())
    # a freed slot takes the next episode of the queue at once: episode 0 (2 steps) ends
    # mid-chunk and episode 4 is decoded while episode 1 (7 steps) still runs
    first_with_4 = next(n for n, call in enumerate(policy.calls) if 4 in call)
    last_with_1 = max(n for n, call in enumerate(policy.calls) if 1 in call)
    assert first_with_4 < last_with_1
    # each slot executed its own episode's actions (the policy's actions name the episode)
    seen = [pair for env in made for pair in env.seen]
    assert len(seen) == sum(map(length, range(10))) and all(a == b for a, b in seen)


def test_nfe_counts_a_batched_pass_once_for_each_episode_and_time_is_shared():
    policy = BatchPolicy(chunk=3, delay=0.01)
    out, _, elapsed = batched(policy, episodes=7, k=3)
    calls = len(policy.calls)
    outcomes = [o for _, o in out]
    for o in outcomes:
        assert o.nfe_total == o.chunks  # one pass per call that served it, not 1/K
        assert o.action_tokens_total == o.chunks * 3 * 2  # the call's tokens split per row
    assert sum(o.nfe_total for o in outcomes) == sum(map(len, policy.calls))
    # each call's ~10 ms is shared among its episodes: the shares add up to the calls
    total_policy = sum(o.policy_time_s for o in outcomes)
    assert calls * 0.01 <= total_policy < calls * 0.01 + 0.05 + 0.01 * calls
    # wall clocks add up to the loop's time (policy + env + each slot's share of the rest)
    assert sum(o.wall_clock_s for o in outcomes) == pytest.approx(elapsed, rel=0.05, abs=0.005)
    for o in outcomes:
        assert o.wall_clock_s >= o.policy_time_s + o.env_time_s - 1e-9


def test_a_failing_env_or_action_fails_only_its_episode_and_the_slot_goes_on():
    policy = BatchPolicy(chunk=3, nan_episode=5)
    out, made, _ = batched(policy, episodes=8, k=3, fail_episode=2)
    by_index = dict(out)
    assert sorted(by_index) == list(range(8))
    assert "simulator exploded" in by_index[2].failure_reason and by_index[2].steps == 1
    assert "non-finite" in by_index[5].failure_reason and by_index[5].steps == 0
    assert [i for i, o in by_index.items() if o.failure_reason] == [2, 5]
    assert all(by_index[i].success for i in (0, 1, 3, 4, 6, 7))
    assert len(made) == 5  # the failed episodes' envs were closed and rebuilt
    assert sum(e.closed for e in made) == 2


def test_a_policy_that_cannot_batch_is_refused_naming_what_it_must_declare():
    resolved = fake_resolved(ChunkPolicy())
    with pytest.raises(UsageError, match=r"policy fake cannot batch.*act_batch"):
        check_batching(resolved.policies, 4)
    check_batching(resolved.policies, 1)  # unbatched: any policy
    with pytest.raises(UsageError, match="--batch-envs must be at least 1, got 0"):
        check_batching(resolved.policies, 0)


def test_runner_rows_record_the_batch_size_and_resume_may_change_it(tmp_path):
    policy = BatchPolicy(chunk=2)
    resolved = fake_resolved(policy, episodes=5, succeed_at=3, tasks=2)
    out = tmp_path / "r"
    report = run(resolved, out, execution=Execution(batch_envs=3))
    rows = report.run_dir.read_episodes()
    assert len(rows) == 10 and rows["success"].all()
    assert set(rows["batch_envs"]) == {3} and set(rows["worker_id"]) == {"main"}
    assert rows.groupby("task").size().eq(5).all()
    assert (rows["nfe_total"] == rows["chunks"]).all()
    manifest = json.loads((out / "manifest.json").read_text())
    assert [s["batch_envs"] for s in manifest["execution"]] == [3]
    # the warm-up paid a batch of 3's first call too, outside every row
    assert policy.calls[:2] == [[0], [0, 0, 0]] and manifest["warm_up"][0]["policies"][0]["error"] is None
    # a larger protocol resumed unbatched: only the new episodes run, at batch size 1
    bigger = fake_resolved(ChunkPolicy(chunk=2), episodes=6, succeed_at=3, tasks=2)
    report = run(bigger, out, OpenMode.RESUME, execution=Execution(batch_envs=1))
    rows = report.run_dir.read_episodes()
    assert report.executed == 2 and len(rows) == 12
    assert sorted(rows[rows["batch_envs"] == 1]["episode_index"]) == [5, 5]
    manifest = json.loads((out / "manifest.json").read_text())
    assert [s["batch_envs"] for s in manifest["execution"]] == [3, 1]


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--batch-envs", "0"], "--batch-envs must be an integer of at least 1, got 0"),
        (["--batch-envs", "2", "--policy", "scripted"], "policy scripted cannot batch"),
    ],
)
def test_bad_batch_flags_exit_2_and_write_nothing(cli, tmp_path, flags, message):
    out = tmp_path / "r"
    code, _, err = cli(
        "run", "--suite", "metaworld/mt1/reach-v3", "--episodes-per-task", "1", "--out", str(out), *flags
    )
    assert code == 2, err
    assert message in " ".join(err.split())
    assert not out.exists()


def test_batching_is_accepted_with_workers_and_an_episode_timeout():
    from harness.backends.options import execution_from_args
    from harness.cli import build_parser

    flags = ["--batch-envs", "3", "--workers", "2", "--episode-timeout", "30"]
    args = build_parser().parse_args(["run", "--suite", "metaworld/mt10", "--policy", "fast_dvla", *flags])
    execution = execution_from_args(args)  # once refused (exit 2): batching ran in this process only
    assert (execution.batch_envs, execution.workers, execution.episode_timeout) == (3, 2, 30.0)
    assert not execution.in_process


def test_batch_envs_in_a_config_file_is_read_and_validated(cli, tmp_path):
    config = tmp_path / "c.toml"
    config.write_text('suite = "metaworld/mt1/reach-v3"\nbatch_envs = 0\n[[policy]]\nname = "fast_dvla"\n')
    code, _, err = cli("run", "--config", str(config), "--out", str(tmp_path / "r"))
    assert code == 2 and "--batch-envs must be an integer of at least 1, got 0" in " ".join(err.split())
    config.write_text('suite = "metaworld/mt1/reach-v3"\nbatch_envs = 4\n[[policy]]\nname = "scripted"\n')
    code, _, err = cli("run", "--config", str(config), "--out", str(tmp_path / "r"))
    assert code == 2 and "policy scripted cannot batch across environments (--batch-envs 4)" in " ".join(
        err.split()
    )
    assert not (tmp_path / "r").exists()


def test_leaderboard_warns_when_rows_of_different_batch_sizes_are_compared(tmp_path):
    from results.leaderboard import leaderboards
    from results.runs import load_run
    from tests.test_leaderboard import BIDI, FAST, episodes, write_run

    unbatched = episodes("bidirectional", BIDI, "bidi000001", [1, 1])  # no batch_envs: older rows
    batched8 = [r | {"batch_envs": 8} for r in episodes("fast_dvla", FAST, "fast000001", [1, 0])]
    (board,) = leaderboards([load_run(write_run(tmp_path / "mixed", unbatched + batched8))])
    text = " ".join(board.warnings)
    assert "rows ran at different batch sizes (--batch-envs 1, 8)" in text and "speedups" in text
    one = [r | {"batch_envs": 1} for r in episodes("fast_dvla", FAST, "fast000001", [1, 0])]
    (board,) = leaderboards([load_run(write_run(tmp_path / "same", unbatched + one))])
    assert not any("batch sizes" in w for w in board.warnings)


def test_gate_warns_when_baseline_and_candidate_ran_at_different_batch_sizes(cli, tmp_path):
    from tests.test_gate import with_reference, write_run

    base = write_run(tmp_path / "base", with_reference(2000.0, 1000.0), calibration=5000.0)
    batched4 = with_reference(2000.0, 1000.0).assign(batch_envs=4)
    cand = write_run(tmp_path / "cand", batched4, calibration=5000.0)
    code, out, err = cli("gate", "--baseline", str(base), "--candidate", str(cand))
    assert code == 0, out + err
    text = " ".join(out.split())
    assert "batch sizes differ (--batch-envs: baseline [1], candidate [4])" in text
    code, out, _ = cli("gate", "--baseline", str(base), "--candidate", str(base))
    assert "batch sizes differ" not in out


def test_shipped_bidirectional_decodes_the_same_episodes_batched(tmp_path):
    """MT10 with the shipped bidirectional checkpoint: batch 4 gives the unbatched rows.

    Greedy decoding of each row is independent of the others in the batch (no cross-row
    op); only a batched matmul's summation order could flip a near-tied token. Measured
    (benchmarks/batching.py): no flip on these episodes, so any difference here is a bug
    or a new CPU's rounding (then measure it there and say so in README)."""
    pytest.importorskip("metaworld")
    from harness.config import build_config, resolve

    data = {"suite": "metaworld/mt10", "tasks": ["reach-v3"], "episodes_per_task": 4}
    resolved = resolve(build_config(data | {"policy": [{"name": "bidirectional"}]}))
    one = run(resolved, tmp_path / "one").run_dir.read_episodes()
    four = run(resolved, tmp_path / "four", execution=Execution(batch_envs=4)).run_dir.read_episodes()
    columns = ["success", "steps", "chunks", "action_tokens_total", "nfe_total", "failure_reason"]
    columns += ["flops_total", "query_tokens_total", "kv_tokens_total", "kv_cached_tokens_total"]
    a = one.sort_values("episode_index").reset_index(drop=True)
    b = four.sort_values("episode_index").reset_index(drop=True)
    assert a[columns].equals(b[columns])
    assert set(a["batch_envs"]) == {1} and set(b["batch_envs"]) == {4}
    assert (b["nfe_total"] == 12 * b["chunks"]).all()  # 12 passes per chunk, each charged to every row
    assert (b["flops_total"] > 0).all()  # and each row its own row's counted work, as unbatched


def test_a_config_files_batch_envs_is_used_unless_the_flag_says_otherwise(tmp_path):
    from harness.backends.options import execution_from_args
    from harness.cli import build_parser
    from harness.commands.run import config_from_args

    config = tmp_path / "c.toml"
    config.write_text('suite = "metaworld/mt10"\nbatch_envs = 4\n[[policy]]\nname = "fast_dvla"\n')
    for flags, want in (([], 4), (["--batch-envs", "2"], 2)):
        args = build_parser().parse_args(["run", "--config", str(config), *flags])
        run_config = config_from_args(args)
        assert execution_from_args(args).batch_envs == want
        assert "batch_envs" not in run_config.to_dict()  # how to run, not what: not fingerprinted
    plain = build_parser().parse_args(["run", "--suite", "metaworld/mt10", "--policy", "fast_dvla"])
    config_from_args(plain)
    assert execution_from_args(plain).batch_envs == 1


def test_a_policy_call_that_raises_fails_only_the_episode_that_made_it_raise():
    policy = BatchPolicy(chunk=3, raise_episode=1)
    out, _, _ = batched(policy, episodes=6, k=3)
    by_index = dict(out)
    assert sorted(by_index) == list(range(6))
    assert [i for i, o in by_index.items() if o.failure_reason] == [1]
    assert "cannot decode episode 1" in by_index[1].failure_reason and by_index[1].steps == 0
    assert all(by_index[i].success and by_index[i].steps == length(i) for i in (0, 2, 3, 4, 5))
    # the failed call [0, 1, 2] was followed by each episode alone; the others went on
    assert policy.calls[:4] == [[0, 1, 2], [0], [1], [2]]
    # its passes stay charged: episode 0 paid the failed call and its own retry
    assert by_index[0].nfe_total == by_index[0].chunks + 1


def test_the_benchmark_tells_a_changed_episode_from_one_charged_more_passes():
    import importlib.util
    from pathlib import Path

    import pandas as pd

    path = Path(__file__).resolve().parent.parent / "benchmarks" / "batching.py"
    spec = importlib.util.spec_from_file_location("batching_benchmark", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    base = pd.DataFrame(
        {
            "task": ["a"] * 3,
            "episode_index": [0, 1, 2],
            "success": [True, False, True],
            "steps": [40, 500, 60],
            "action_tokens_total": [256, 2016, 320],
            "nfe_total": [80, 600, 100],
        }
    )
    batched = base.copy()
    batched.loc[1, "nfe_total"] = 640  # same actions, charged its batch's extra passes
    batched.loc[2, ["success", "steps"]] = [False, 500]  # a flipped token changed the episode
    got = bench.differences(base, batched)
    assert got["episodes"] == 1 and got["same_actions_more_nfe"] == 1 and got["episodes_any"] == 2
    assert got["success"] == 1 and got["nfe_total"] == 1
