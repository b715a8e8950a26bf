"""Inference latency with --batch-envs K (harness/episode/plan.py): each slot keeps its
own clock and chunks in flight, so deterministic modes give the rows of --batch-envs 1.

Episodes of different lengths put the slots at different phases, so some calls serve
several slots and others one; a recording policy's actions name the step their chunk
was requested at, so each env's log says which chunk ran when."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np
import pytest

from adapters.base import EpisodeSpec
from harness.backends import Execution
from harness.episode.latency import LatencyPlan, parse_latency
from harness.episode.nfe import NFECounter
from harness.run.runner import run
from policies.base import ChunkBatch, EpisodeContext
from tests.fakes import CountdownEnv, context, fake_resolved, run_batch, run_one
from tests.test_latency import rows_of
from tests.test_remote import serve_process  # noqa: F401  (a fixture)

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

HZ = 10.0  # 100 ms a control step
MAX_STEPS = 24
EPISODES = 7


def length(index: int) -> int | None:
    """Episode `index` succeeds on this step (7 to 17); episode 4 never does (the budget)."""
    return None if index == 4 else 7 + (index * 5) % 11


class SlotEnv(CountdownEnv):
    """Observation: the step count. Logs per episode what each step executed: the code of
    a chunk's action (1 + 10 x request step + index) or "H" for a hold (zero first dim);
    with `switch_at`, a chain whose second instruction is in force from that step."""

    def __init__(self, log: dict[int, list], switch_at: Callable[[int], int] | None = None):
        super().__init__(succeed_at=None)
        self.log, self.switch_at = log, switch_at

    def _info(self) -> dict:
        if self.switch_at is None:
            return {"success": self.succeed_at is not None and self.t >= self.succeed_at}
        k = int(self.t >= self.switch_at(self.episode))
        return {"success": False, "instruction": ("first", "second")[k], "subtask_index": k}

    def reset(self, *, seed=None, options=None):
        self.episode = options["episode"].index
        self.succeed_at = length(self.episode)
        obs, _ = super().reset(seed=seed, options=options)
        self.log[self.episode] = []
        return obs, self._info()

    def step(self, action):
        self.log[self.episode].append("H" if action[0] == 0 else round(float(action[0])))
        obs, r, term, trunc, info = super().step(action)
        return obs, r, term, trunc, {**info, **self._info()}


class RecordingBatchPolicy:
    """A batching policy: `passes` forward passes of a real module per call, whatever the
    batch size, or with `need` the most any row of the call needs (an adaptive decoder
    decodes until its slowest row is done). Records each row's observation and each reset's
    instruction by episode."""

    def __init__(
        self,
        chunk: int = 4,
        passes: int = 2,
        need: Callable[[int, float], int] | None = None,
        reset_passes: int = 0,
    ):
        import torch

        self.net = torch.nn.Linear(1, 1)
        self.chunk, self.passes, self.need, self.reset_passes = chunk, passes, need, reset_passes
        self.seen: dict[int, list[float]] = {}
        self.instructions: dict[int, list[str]] = {}
        self.sizes: list[int] = []

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        for e in episodes:
            self.instructions.setdefault(e.episode_index, []).append(e.instruction)
        self.episodes = episodes
        import torch

        with torch.no_grad():
            for _ in range(self.reset_passes):
                self.net(torch.zeros(len(episodes), 1))

    def act(self, observations):  # unbatched: run_episode's call
        return self.act_batch(self.episodes, observations)

    def act_batch(self, episodes: Sequence[EpisodeContext], observations) -> ChunkBatch:
        import torch

        obs = np.array([float(np.asarray(o)[0]) for o in observations])
        passes = self.passes
        if self.need is not None:
            passes = max(self.need(e.episode_index, o) for e, o in zip(episodes, obs, strict=True))
        with torch.no_grad():
            for _ in range(passes):
                self.net(torch.zeros(len(episodes), 1))
        for e, o in zip(episodes, obs, strict=True):
            self.seen.setdefault(e.episode_index, []).append(o)
        self.sizes.append(len(episodes))
        codes = 1 + 10 * obs[:, None] + np.arange(self.chunk)
        return ChunkBatch(
            actions=np.repeat(codes[:, :, None], 2, axis=2), action_tokens=len(episodes) * self.chunk * 2
        )


def context_for(spec: EpisodeSpec, _env=None) -> EpisodeContext:
    return dataclasses.replace(context(MAX_STEPS), episode_index=spec.index, seed=spec.seed)


SPECS = [EpisodeSpec(index=i, seed=100 + i) for i in range(EPISODES)]
FIELDS = ("success", "steps", "chunks", "nfe_total", "action_tokens_total", "delay_steps_mean",
          "delay_steps_max", "late_chunks", "hold_steps", "failure_reason")  # fmt: skip


def unbatched(plan: LatencyPlan, replan_every: int, policy, switch_at=None):
    """Each episode alone (one slot): outcomes and env logs by episode."""
    log: dict[int, list] = {}
    counter = NFECounter(policy)
    try:
        outcomes = {
            spec.index: run_one(
                SlotEnv(log, switch_at),
                policy,
                context_for(spec),
                spec,
                replan_every,
                latency=plan,
                counter=counter,
                name="fast_dvla",
            )
            for spec in SPECS
        }
    finally:
        counter.close()
    return outcomes, log


def batched(plan: LatencyPlan, replan_every: int, policy, k: int, switch_at=None):
    log: dict[int, list] = {}
    counter = NFECounter(policy)
    try:
        make_env = lambda: SlotEnv(log, switch_at)  # noqa: E731
        out = run_batch(
            SPECS,
            make_env,
            policy,
            context_for,
            k,
            replan_every,
            latency=plan,
            counter=counter,
            name="fast_dvla",
        )
        outcomes = {SPECS[i].index: o for i, o in out}
    finally:
        counter.close()
    return outcomes, log


def plan(mode: str, execution: str) -> LatencyPlan:
    return LatencyPlan(parse_latency(mode), execution, HZ)


@pytest.mark.parametrize("k", [2, 3])
@pytest.mark.parametrize("replan_every", [0, 2])
@pytest.mark.parametrize("execution", ["sync", "async"])
@pytest.mark.parametrize("mode", ["passes:150", "passes:60+20", "profile:fast-dvla-ddvla"])
def test_deterministic_modes_give_each_slot_the_episode_it_has_alone(mode, execution, replan_every, k):
    # 2 passes a call: passes:150 is d = 3, passes:60+20 and the profile's 139.1 ms d = 2
    p = plan(mode, execution)
    alone_policy, batch_policy = RecordingBatchPolicy(), RecordingBatchPolicy()
    alone, alone_log = unbatched(p, replan_every, alone_policy)
    together, together_log = batched(p, replan_every, batch_policy, k)
    assert max(batch_policy.sizes) > 1 and min(batch_policy.sizes) == 1  # slots met, and did not always
    assert sorted(together) == sorted(alone)
    for i in alone:
        assert [getattr(together[i], f) for f in FIELDS] == [getattr(alone[i], f) for f in FIELDS], i
        assert together[i].batch_envs == k
    assert together_log == alone_log  # every step's action or hold, per episode
    assert batch_policy.seen == alone_policy.seen  # each request from its own slot's observation
    assert sum(o.hold_steps for o in alone.values()) > 0 and all(
        o.delay_steps_max >= 2 for o in alone.values()
    )


@pytest.mark.parametrize("execution", ["sync", "async"])
def test_a_chain_switch_in_one_slot_drops_only_that_slots_chunks(execution):
    switch_at = lambda episode: 3 + episode % 4  # noqa: E731  (mid-delay for some, not others)
    p = plan("passes:100", execution)
    alone_policy, batch_policy = RecordingBatchPolicy(), RecordingBatchPolicy()
    alone, alone_log = unbatched(p, 2, alone_policy, switch_at)
    together, together_log = batched(p, 2, batch_policy, 3, switch_at)
    for i in alone:
        assert [getattr(together[i], f) for f in FIELDS] == [getattr(alone[i], f) for f in FIELDS], i
    assert together_log == alone_log and batch_policy.seen == alone_policy.seen
    assert batch_policy.instructions == alone_policy.instructions
    assert all(v == ["first", "second"] for v in batch_policy.instructions.values())


def test_an_instruction_on_the_budgets_last_step_ends_the_episode_without_a_reset():
    switch_at = lambda episode: MAX_STEPS if episode % 2 else 5  # noqa: E731
    p = plan("passes:100", "async")
    alone_policy, batch_policy = RecordingBatchPolicy(), RecordingBatchPolicy()
    unbatched(p, 2, alone_policy, switch_at)
    batched(p, 2, batch_policy, 2, switch_at)
    for policy in (alone_policy, batch_policy):
        assert policy.instructions[1] == ["first"] and policy.instructions[0] == ["first", "second"]


@pytest.mark.parametrize("execution", ["sync", "async"])
def test_a_resets_passes_delay_the_next_chunk_alone_and_batched(execution):
    # passes:100 at 10 Hz: a pass is a step; the reset's pass makes the first chunk d = 3
    p = plan("passes:100", execution)
    alone, _ = unbatched(p, 2, RecordingBatchPolicy(reset_passes=1))
    together, _ = batched(p, 2, RecordingBatchPolicy(reset_passes=1), 3)
    for i, o in alone.items():
        assert o.delay_steps_max == 3 and o.delay_steps_mean == (3 + 2 * (o.chunks - 1)) / o.chunks
        assert [getattr(together[i], f) for f in FIELDS] == [getattr(o, f) for f in FIELDS], i


def test_an_adaptive_decoders_slot_waits_for_its_batchs_slowest_row():
    # passes:100 at 10 Hz: a pass is a step, so a chunk's d is the passes its call ran
    need = lambda episode, obs: 1 + (episode + int(obs)) % 3  # noqa: E731
    policy = RecordingBatchPolicy(need=need)
    together, _ = batched(plan("passes:100", "async"), 2, policy, 3)
    for o in together.values():
        assert o.delay_steps_mean * o.chunks == o.nfe_total  # its delays are its charged passes
    alone, _ = unbatched(plan("passes:100", "async"), 2, RecordingBatchPolicy(need=need))
    assert any(together[i].nfe_total > alone[i].nfe_total for i in alone)  # it did wait for others


def test_measured_gives_a_slot_its_batch_calls_wall_clock():
    import time

    class Slow(RecordingBatchPolicy):
        def act_batch(self, episodes, observations):
            time.sleep(0.12)  # at 10 Hz: at least 2 steps a call, however many rows
            return super().act_batch(episodes, observations)

    together, _ = batched(plan("measured", "sync"), 0, Slow(), 3)
    assert all(o.delay_steps_max >= 2 and o.hold_steps >= 2 for o in together.values())


@dataclasses.dataclass(frozen=True)
class BatchedBuild:
    """The fake run with episodes of different lengths, at a latency."""

    mode: str
    execution: str

    def __call__(self):
        resolved = fake_resolved(RecordingBatchPolicy(), episodes=5, max_steps=MAX_STEPS, tasks=2)
        config = dataclasses.replace(
            resolved.config, inference_latency=self.mode, execution=self.execution, replan_every=2
        )
        make_env = lambda _task: SlotEnv({})  # noqa: E731
        suite = dataclasses.replace(resolved.suite, control_hz=HZ, make_env=make_env)
        return dataclasses.replace(resolved, config=config, suite=suite)


@pytest.mark.parametrize("execution", ["sync", "async"])
def test_runner_rows_at_a_latency_are_the_same_at_every_batch_size(tmp_path, execution):
    build = BatchedBuild("passes:60+20", execution)
    rows = {
        k: rows_of(run(build(), tmp_path / f"k{k}", execution=Execution(batch_envs=k))) for k in (1, 2, 3)
    }
    assert set(rows[3]["batch_envs"]) == {3}
    assert (rows[1]["hold_steps"] > 0).all() and rows[1]["delay_steps_max"].max() == 2
    assert rows[1]["success"].sum() == 8  # episode 4 of each task runs out of budget
    same = [c for c in rows[1].columns if c != "batch_envs"]
    for k in (2, 3):
        pd_equal(rows[1][same], rows[k][same])


def pd_equal(a, b) -> None:
    import pandas as pd

    pd.testing.assert_frame_equal(a.reset_index(drop=True), b.reset_index(drop=True))


def test_batched_workers_give_the_rows_of_one_unbatched_process(tmp_path):
    build = BatchedBuild("passes:60+20", "async")
    one = rows_of(run(build(), tmp_path / "one"))
    workers = rows_of(
        run(build(), tmp_path / "w", execution=Execution(workers=2, batch_envs=2, rebuild=build))
    )
    assert set(workers["batch_envs"]) == {2}
    same = [c for c in one.columns if c != "batch_envs"]
    pd_equal(one[same], workers[same])


def test_a_remote_policy_batched_is_charged_the_servers_passes_like_the_local_one_alone(
    cli,
    tmp_path,
    serve_process,  # noqa: F811
):
    import pandas as pd

    url = serve_process("--policy", "bidirectional", "--suite", "metaworld/mt10", "--task", "reach-v3")
    argv = ["run", "--suite", "metaworld/mt10", "--tasks", "reach-v3", "--episodes-per-task", "2",
            "--replan-every", "4", "--inference-latency", "passes:4", "--execution", "async", "--quiet"]  # fmt: skip
    code, _, err = cli(
        *argv, "--policy", f"remote:url={url}", "--batch-envs", "2", "--out", str(tmp_path / "r")
    )
    assert code == 0, err
    code, _, err = cli(*argv, "--policy", "bidirectional", "--out", str(tmp_path / "l"))
    assert code == 0, err
    remote = pd.read_parquet(tmp_path / "r" / "episodes.parquet").set_index("episode_index").sort_index()
    local = pd.read_parquet(tmp_path / "l" / "episodes.parquet").set_index("episode_index").sort_index()
    assert (
        set(remote["batch_envs"]) == {2} and (local["delay_steps_max"] == 4).all()
    )  # 12 passes x 4 ms at 80 Hz
    for column in ("success", "steps", "chunks", "nfe_total", "delay_steps_mean", "delay_steps_max",
                   "late_chunks", "hold_steps"):  # fmt: skip
        assert list(remote[column]) == list(local[column]), column


def test_a_batch_call_that_raises_fails_its_episode_and_its_batch_mates_wait_for_it():
    class Raising(RecordingBatchPolicy):
        def act_batch(self, episodes, observations):
            out = super().act_batch(episodes, observations)  # its passes run, then it raises
            rows = zip(episodes, observations, strict=True)
            if any(e.episode_index == 2 and float(np.asarray(o)[0]) >= 6 for e, o in rows):
                raise RuntimeError("cannot decode episode 2's observation")
            return out

    policy = Raising()
    together, _ = batched(plan("passes:100", "async"), 2, policy, 3)  # a pass is a step: d = 2 alone
    assert "cannot decode episode 2" in together[2].failure_reason
    assert all(o.failure_reason is None for i, o in together.items() if i != 2)
    # a batch-mate asked again alone waited for the failed call's 2 passes and its own 2
    assert max(o.delay_steps_max for i, o in together.items() if i != 2) == 4
