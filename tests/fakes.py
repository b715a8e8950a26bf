"""A physics-free environment and policies for unit tests of the runner (no simulator)."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from adapters.base import EpisodeSpec, Suite, TaskSpec
from harness.config import PolicyRun, ResolvedRun, RunConfig
from harness.episode.envs import TaskEnvs
from harness.episode.loop import Episode, EpisodeLoop, run_episode
from harness.episode.nfe import NFECounter
from harness.episode.outcome import EpisodeOutcome
from harness.episode.plan import ExecutionPlan
from harness.episode.timed import TimedPolicy
from policies.base import ChunkBatch, EpisodeContext
from policies.registry import NoParams, PolicySpec


class CountdownEnv(gym.Env):
    """Succeeds on step `succeed_at` (never if None); each step sleeps `step_delay` s.

    Its action space is wide, so that ChunkPolicy's numbered actions (0, 1, 2 ...) lie
    inside it; tests of the out-of-space rule narrow it (tests/test_action_space.py)."""

    observation_space = gym.spaces.Box(-np.inf, np.inf, (1,))
    action_space = gym.spaces.Box(-1000.0, 1000.0, (2,))

    def __init__(self, succeed_at: int | None, step_delay: float = 0.0, fail_at: int | None = None):
        self.succeed_at, self.step_delay, self.fail_at = succeed_at, step_delay, fail_at
        self.t = 0
        self.actions: list[np.ndarray] = []
        self.closed = False

    def close(self):
        self.closed = True

    def reset(self, *, seed=None, options=None):
        if self.closed:
            raise RuntimeError("reset after close")
        self.t = 0
        return np.zeros(1), {"success": False}

    def step(self, action):
        if self.step_delay:
            time.sleep(self.step_delay)
        self.t += 1
        self.actions.append(np.asarray(action))
        if self.fail_at is not None and self.t == self.fail_at:
            raise RuntimeError("simulator exploded")
        success = self.succeed_at is not None and self.t >= self.succeed_at
        return np.array([self.t], dtype=float), 0.0, False, False, {"success": success}


class ChunkPolicy:
    """Returns chunks of `chunk` actions numbered 0, 1, 2 ...; sleeps `delay` s per call."""

    def __init__(self, chunk: int = 4, delay: float = 0.0, dim: int = 2):
        self.chunk, self.delay, self.dim = chunk, delay, dim
        self.calls = 0

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        self.calls = 0

    def act(self, observations: Sequence[object]) -> ChunkBatch:
        if self.delay:
            time.sleep(self.delay)
        start = self.calls * self.chunk
        self.calls += 1
        steps = np.arange(start, start + self.chunk, dtype=float)
        actions = np.repeat(steps[:, None], self.dim, axis=1)[None]
        return ChunkBatch(actions=actions, action_tokens=self.chunk * self.dim)


def context(max_steps: int = 50) -> EpisodeContext:
    return EpisodeContext(
        suite="fake/countdown",
        task="count",
        instruction="count to n",
        action_space=CountdownEnv.action_space,
        observation_space=CountdownEnv.observation_space,
        max_steps=max_steps,
        episode_index=0,
    )


def fake_resolved(
    policy: object,
    episodes: int = 3,
    max_steps: int = 20,
    succeed_at: int | None = 5,
    fail_episode: int | None = None,
    tasks: int = 1,
) -> ResolvedRun:
    """A ResolvedRun over the fake env; episode `fail_episode` raises inside step 2."""
    specs = tuple(EpisodeSpec(index=i, seed=100 + i) for i in range(episodes))
    all_tasks = tuple(
        TaskSpec("count" if t == 0 else f"count{t}", "count to n", max_steps, specs, index=t)
        for t in range(tasks)
    )
    made: list[CountdownEnv] = []

    class PerEpisodeEnv(CountdownEnv):
        def reset(self, *, seed=None, options=None):
            spec = options["episode"]
            self.fail_at = 2 if spec.index == fail_episode else None
            return super().reset(seed=seed, options=options)

    def make_env(_task: TaskSpec) -> gym.Env:
        env = PerEpisodeEnv(succeed_at)
        env.open_when_made = sum(not e.closed for e in made)  # type: ignore[attr-defined]
        made.append(env)
        return env

    suite = Suite("fake/countdown", "1", all_tasks, make_env)
    spec = PolicySpec("fake", "test policy", NoParams, lambda _p: policy)
    run = PolicyRun(spec, NoParams(), "{}", "", "", "fakeconfig01", policy)  # type: ignore[arg-type]
    config = RunConfig(suite=suite.name, policies=())
    resolved = ResolvedRun(config, suite, all_tasks, [run])
    resolved.made_envs = made  # type: ignore[attr-defined]
    return resolved


def tiny_model(pattern: str, state_dim: int = 6, **kw):
    """A small random action-token model: 4-D actions, chunks of 4 (16 tokens), 32 bins."""
    import torch

    from policies.dvla.model import ActionTokenModel, ModelConfig

    torch.manual_seed(0)
    cfg = ModelConfig(
        action_dim=4,
        chunk_len=4,
        state_dim=state_dim,
        bins=32,
        vocab_words=20,
        max_words=5,
        width=32,
        layers=2,
        heads=4,
        ffn=64,
        pattern=pattern,
        **kw,
    )
    return ActionTokenModel(cfg).eval()


# The smallest training setup that still learns: tests check the path, not the skill.
TINY_TRAIN = {
    "steps": 40,
    "batch_size": 64,
    "lr": 3e-3,
    "warmup": 5,
    "chunk_len": 4,
    "width": 32,
    "layers": 2,
    "heads": 4,
    "ffn": 64,
    "bins": 64,
}


# Faults a worker can be made to suffer at chosen episodes (tests of harness/backends/).
FAULTS = ("exit", "sigkill", "segfault", "hang")


def suffer(kind: str) -> None:
    """Die (or hang) the way a worker does when a simulator or the kernel ends it."""
    import ctypes
    import os
    import signal

    if kind == "exit":
        os._exit(3)
    elif kind == "sigkill":
        os.kill(os.getpid(), signal.SIGKILL)  # what the out-of-memory killer sends
    elif kind == "segfault":
        ctypes.string_at(0)  # reads address 0: SIGSEGV, as a simulator's bad pointer
    elif kind == "hang":
        time.sleep(3600)
    else:
        raise ValueError(f"unknown fault {kind!r}; choose one of {', '.join(FAULTS)}")


class FaultPolicy(ChunkPolicy):
    """ChunkPolicy that suffers `faults[episode_index]` when that episode starts (keep
    episode 0 clean: the runner warms policies up on it in the writing process).

    A fault written "KIND:once" strikes only the first time its episode starts (a file
    in the folder `marks` remembers it across worker processes), so a retry succeeds.
    A fault's key is an episode index (in every task) or "TASK/INDEX" (that task's only),
    so one run can suffer different faults in different tasks. "KIND@N" strikes at the
    episode's N-th act call instead, after N - 1 chunks have run.
    """

    def __init__(
        self, faults: dict[int | str, str], marks: str | None = None, chunk: int = 2, delay: float = 0.0
    ):
        super().__init__(chunk=chunk, delay=delay)
        self.faults, self.marks = faults, marks
        self.later: tuple[int, str] | None = None  # (act call, fault) of a "KIND@N"

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        super().reset(episodes)
        self.later = None
        self.strike(episodes[0])

    def act(self, observations: Sequence[object]) -> ChunkBatch:
        if self.later is not None and self.calls + 1 == self.later[0]:
            suffer(self.later[1])
        return super().act(observations)

    def strike(self, ep: EpisodeContext) -> None:
        """Suffer the fault set for `ep`, if any (and not already suffered, for KIND:once)."""
        kind = self.faults.get(f"{ep.task}/{ep.episode_index}", self.faults.get(ep.episode_index))
        if kind is None:
            return
        kind, at, call = kind.partition("@")
        if at:
            self.later = (int(call), kind)
            return
        kind, _, once = kind.partition(":")
        if once:
            from pathlib import Path

            assert self.marks is not None, "a KIND:once fault needs a marks folder"

            mark = Path(self.marks) / f"{ep.task}-{ep.episode_index}"
            if mark.exists():
                return
            mark.touch()
        suffer(kind)


class BatchFaultPolicy(FaultPolicy):
    """FaultPolicy that declares act_batch (so --batch-envs K serves it): an episode's fault
    strikes in the first call that decodes for it, so in a batch it takes down every
    episode in flight. Chunks depend only on the episode (a batchable policy keeps no state
    between calls), and one pass of a tiny torch module per call makes NFE counted."""

    def __init__(
        self, faults: dict[int | str, str], marks: str | None = None, chunk: int = 2, delay: float = 0.0
    ):
        import torch

        super().__init__(faults, marks, chunk=chunk, delay=delay)
        self.net = torch.nn.Linear(1, 1)
        self.episode: EpisodeContext | None = None
        self.sizes: list[int] = []  # episodes decoded per call

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        self.episode = episodes[0]

    def act(self, observations: Sequence[object]) -> ChunkBatch:
        assert self.episode is not None
        return self.act_batch([self.episode] * len(observations), observations)

    def act_batch(self, episodes: Sequence[EpisodeContext], observations: Sequence[object]) -> ChunkBatch:
        import torch

        for ep in episodes:
            self.strike(ep)
        self.sizes.append(len(episodes))
        if self.delay:
            time.sleep(self.delay)
        with torch.no_grad():
            self.net(torch.zeros(len(episodes), 1))
        index = np.array([ep.episode_index for ep in episodes], dtype=float) / 100
        actions = np.repeat(index[:, None, None], self.chunk, axis=1).repeat(self.dim, axis=2)
        return ChunkBatch(actions=actions, action_tokens=len(episodes) * self.chunk * self.dim)


@dataclass(frozen=True)
class FakeBuild:
    """Builds the fake run in a worker process (an Execution's `rebuild`): picklable,
    so a spawned process or a Ray actor makes the same ResolvedRun as the test."""

    faults: tuple[tuple[int | str, str], ...] = ()  # (episode index or "TASK/INDEX", fault)
    marks: str | None = None
    episodes: int = 3
    tasks: int = 1
    succeed_at: int | None = 5
    delay: float = 0.0  # seconds per policy call
    batch: bool = False  # a policy that declares act_batch (BatchFaultPolicy)
    max_steps: int = 20

    def __call__(self) -> ResolvedRun:
        kind = BatchFaultPolicy if self.batch else FaultPolicy
        policy = kind(dict(self.faults), self.marks, delay=self.delay)
        return fake_resolved(
            policy,
            episodes=self.episodes,
            tasks=self.tasks,
            succeed_at=self.succeed_at,
            max_steps=self.max_steps,
        )


def run_one(
    env: gym.Env,
    policy: Any,
    ctx: EpisodeContext,
    spec: EpisodeSpec,
    replan_every: int = 0,
    latency: Any = None,
    out_of_space: str = "fail",
    counter: NFECounter | None = None,
    name: str = "fake",
) -> EpisodeOutcome:
    """One episode through the episode loop on a given env (harness/episode/loop.py
    run_episode); `name`: the policy's registered name (a latency profile's key)."""
    timed = TimedPolicy(policy, name, counter)
    try:
        return run_episode(env, timed, ctx, spec, ExecutionPlan(replan_every, out_of_space, latency))
    finally:
        if counter is None:
            timed.close_counter()


def run_batch(
    specs: Sequence[EpisodeSpec],
    make_env: Callable[[], gym.Env],
    policy: Any,
    context_for: Callable[[EpisodeSpec, Any], EpisodeContext],
    k: int,
    replan_every: int = 0,
    latency: Any = None,
    out_of_space: str = "fail",
    envs: Sequence[gym.Env] = (),
    counter: NFECounter | None = None,
    name: str = "fake",
) -> list[tuple[int, EpisodeOutcome]]:
    """Every episode of `specs` (one task, one policy) through the loop's `k` slots:
    (position in `specs`, outcome) in the order they end. `envs`: envs already built,
    taken before any is made."""
    plan = ExecutionPlan(replan_every, out_of_space, latency, batch_envs=k)
    task = TaskSpec("task-0", "do the task", 50, tuple(specs))
    pool = TaskEnvs(lambda _task: make_env(), out_of_space)
    for env in reversed(list(envs)):  # the first given is taken first
        pool.adopt(task.name, env)
    timed = TimedPolicy(policy, name, counter)
    loop = EpisodeLoop("fake/suite", plan, pool)
    episodes = [Episode(task, spec, timed, context_for(spec, None)) for spec in specs]
    try:
        return list(loop.run(episodes, alone=k == 1))
    finally:
        pool.idle.clear()  # the caller's envs stay open, as the test made them
        if counter is None:
            timed.close_counter()
