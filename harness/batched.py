"""Batched inference across environments (`--batch-envs K`): K envs of one task in lockstep.

Each control step, every running slot executes one action of its chunk; the slots whose
chunk is used up (a new episode, or the last action executed) are served by one
`policy.act_batch` call for all of them, so a decoder runs one forward pass per step for
up to K episodes. An episode that ends frees its slot at once for the next episode of
the queue (same task, same policy), so the batch stays full until the queue runs dry.

What each episode is charged, so that its row means what an unbatched row means:
- NFE: every forward pass of a call counts 1 for each episode the call served (a pass
  over K episodes is K episode-passes, never 1/K). An adaptive decoder (fast_dvla,
  fast_dllm's threshold) runs until its slowest row is decoded, so a row may be charged
  more passes than it needed alone: the passes it waited for.
- Policy time: a call's time is shared equally among the slots it served, and so is
  its CPU time (harness/cpu_time.py), so a slot's ratio of the two is its calls'.
- Env time: the slot's own env.reset and env.step calls, timed one by one.
- Wall clock: policy share + env time + an equal share of the loop's own bookkeeping in
  each step among the slots running in it. The rows' wall clocks therefore add up to the
  time the loop ran, and episodes/s = rows / sum(wall_clock_s) as for unbatched rows.
- Tokens: a call's action_tokens split equally among its slots (the shipped decoders
  decode the same number of tokens per row).
- Counted work (FLOPs, query and KV positions; harness/work.py): a call's work split
  equally among its slots, in integers adding up to it. A batched pass's rows have one
  shape, so each episode is charged its own row's work: for a decoder with a fixed
  number of passes the same as unbatched, whatever the batch size; an adaptive one is
  also charged its row of the passes it waited for, as with NFE.

Failures stay with their episode: an env that raises, or an action of one slot that is
non-finite, absurd or (under `--out-of-space fail`) outside the action space, fails that slot's episode (its env is rebuilt for the next one).
When the policy call itself raises, each episode it served is asked for again alone, so
only the one whose observation makes the policy raise fails; the failed call's time and
passes stay charged to all of them (they waited for it). Only KeyboardInterrupt stops
the loop.

The loop runs in the writing process (`execute_batched`) or inside each worker process
and Ray actor (`BatchedRunner`, driven by harness/backends/local.py's `Worker`), so a
row means the same wherever its batch ran; both, and the refusal of a policy that cannot
batch, are harness/batch_runner.py.
"""

from __future__ import annotations

import time
import traceback
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

import gymnasium as gym
import numpy as np

from adapters.base import EpisodeSpec
from harness.action_space import DEFAULT_OUT_OF_SPACE, ActionCheck
from harness.cpu_time import cpu_clock
from harness.episode import EpisodeOutcome, chain_fields, check_chunk, in_force, remote_policy
from harness.latency import LatencyPlan
from harness.nfe import NFECounter
from harness.work import Work
from policies.base import EpisodeContext

clock = time.perf_counter


@dataclass
class _Slot:
    """One running episode: its env, its unexecuted actions and what it is charged."""

    index: int  # position of its spec in the queue given to run_batched
    spec: EpisodeSpec
    context: EpisodeContext
    started_at: datetime
    obs: Any = None
    actions: deque = field(default_factory=deque)
    steps: int = 0
    chunks: int = 0
    nfe: int | None = 0  # None once a remote server did not report its passes
    work: Work = field(default_factory=Work)
    tokens: int = 0
    policy_time: float = 0.0
    cpu_time: float = 0.0  # CPU time of its share of the policy calls
    server_time: float = 0.0  # remote policies: the server's own share of policy_time
    env_time: float = 0.0
    overhead: float = 0.0  # its share of the loop's own time (wall = policy + env + this)
    success: bool = False
    done: bool = False
    failure: str | None = None
    trace: str | None = None
    traces: list[dict[str, Any]] | None = None
    info: dict[str, Any] = field(default_factory=dict)  # the env's last info (chains read it)
    space: ActionCheck | None = None  # the action space's bounds and the --out-of-space rule
    schedule: Any = None  # under an inference latency: its chunks in flight (harness/batched_latency.py)

    def fail(self, exc: BaseException) -> None:
        self.failure, self.trace = f"{type(exc).__name__}: {exc}", traceback.format_exc()
        self.success, self.done = False, True

    def outcome(self, batch_envs: int, remote: bool, cpu_measured: bool) -> EpisodeOutcome:
        return EpisodeOutcome(
            success=self.success,
            steps=self.steps,
            chunks=self.chunks,
            nfe_total=self.nfe,
            work=self.work,
            action_tokens_total=self.tokens,
            policy_time_s=self.policy_time,
            policy_cpu_time_s=self.cpu_time if cpu_measured else None,
            env_time_s=self.env_time,
            wall_clock_s=self.policy_time + self.env_time + self.overhead,
            started_at=self.started_at,
            failure_reason=self.failure,
            traceback=self.trace,
            traces=self.traces,
            batch_envs=batch_envs,
            transport_time_s=max(0.0, self.policy_time - self.server_time) if remote else None,
            **(self.space.columns() if self.space is not None else {}),
            **chain_fields(self.info),
            **(
                self.schedule.tally.latency_columns()
                if self.schedule is not None  # at `none` every chunk's d is 0
                else {
                    "delay_steps_mean": 0.0 if self.chunks else None,
                    "delay_steps_max": 0 if self.chunks else None,
                }
            ),
        )

    def charge(self, passes: int | None, server_time: float, work: Work, connect_wait: float = 0.0) -> None:
        """Count a call's passes, server time and counted work; a remote policy's wait to
        connect again (a server restart) moves from policy time to overhead, as in
        run_episode."""
        self.nfe = None if passes is None or self.nfe is None else self.nfe + passes
        self.server_time += server_time
        self.work += work
        moved = min(connect_wait, self.policy_time)
        self.policy_time -= moved
        self.overhead += moved


def _shares(total: int, parts: int) -> list[int]:
    """`total` split into `parts` integers that differ by at most 1 and add up to it."""
    base, extra = divmod(total, parts)
    return [base + (i < extra) for i in range(parts)]


class _Loop:
    """The state of one batched queue: slots, envs, the policy and its NFE counter."""

    def __init__(self, envs, make_env, policy, nfe, context_for, replan_every, traces, out_of_space):
        self.envs, self.make_env, self.policy, self.nfe = envs, make_env, policy, nfe
        self.context_for, self.replan_every, self.record_traces = context_for, replan_every, traces
        self.out_of_space = out_of_space
        self.finished: list[tuple[int, _Slot | EpisodeOutcome]] = []
        self.remote = remote_policy(policy)
        cpu_now = None if self.remote is not None else cpu_clock(policy)
        self.cpu_measured = cpu_now is not None
        self.cpu = cpu_now or (lambda: 0.0)  # unmeasured: read as 0 and recorded as None

    def passes(self) -> tuple[int | None, float, Work, float]:
        """Forward passes since the last take, here and (remote policies) on the server,
        with the server's own policy time, the passes' counted work and the client's wait
        to connect again (the order `charge` takes them in); passes None when the server reports none."""
        local, work = self.nfe.take(), self.nfe.take_work()
        if self.remote is None:
            return local, 0.0, work, 0.0
        totals = self.remote.take_remote()
        passes = None if totals.nfe is None else local + totals.nfe
        return passes, totals.server_time_s, work + totals.work, totals.connect_wait_s

    def close_env(self, i: int) -> None:
        env, self.envs[i] = self.envs[i], None
        if env is not None:
            env.close()

    def start(self, i: int, index: int, spec: EpisodeSpec) -> _Slot | None:
        """Begin episode `spec` in slot i (env built if needed, reset, policy reset); None
        if it failed before its first step (its outcome is already in `finished`)."""
        started_at, t0 = datetime.now(UTC), clock()
        try:
            if self.envs[i] is None:
                self.envs[i] = self.make_env()
        except Exception as exc:
            slot = _Slot(index, spec, None, started_at)  # type: ignore[arg-type]
            slot.fail(exc)
            slot.overhead = clock() - t0
            self.finished.append((index, slot))
            return None
        env = self.envs[i]
        slot = _Slot(index, spec, self.context_for(spec, env), started_at)
        slot.traces = [] if self.record_traces else None
        slot.space = ActionCheck.for_space(slot.context.action_space, self.out_of_space)
        try:
            slot.obs, slot.info = env.reset(seed=spec.seed, options={"episode": spec})
            t = clock()
            slot.env_time += t - t0
            slot.context = in_force(slot.context, slot.info)
            self.passes()
            c = self.cpu()
            try:
                with self.nfe.counting():
                    self.policy.reset([slot.context])
            finally:
                slot.policy_time += clock() - t
                slot.cpu_time += self.cpu() - c
                slot.charge(*self.passes())
        except KeyboardInterrupt:
            raise
        except BaseException as exc:
            slot.fail(exc)
        slot.overhead = clock() - t0 - slot.env_time - slot.policy_time  # a fresh slot: all of it
        if slot.done:
            self.finished.append((index, slot))
            self.close_env(i)
            return None
        return slot

    def act(self, slots: list[tuple[int, _Slot]]) -> float:
        """One act_batch call for `slots` (their chunks are used up); returns its time."""
        self.passes()
        c, t = self.cpu(), clock()
        try:
            with self.nfe.counting():
                batch = self.policy.act_batch([s.context for _, s in slots], [s.obs for _, s in slots])
            actions = np.asarray(batch.actions)
            if actions.ndim != 3 or actions.shape[0] != len(slots):
                raise ValueError(
                    f"policy returned actions of shape {actions.shape}; expected ({len(slots)}, chunk>=1, "
                    "action_dim): one chunk per episode of the call"
                )
        except KeyboardInterrupt:
            raise
        except BaseException as exc:
            elapsed, cpu = clock() - t, self.cpu() - c
            passes, server, work, wait = self.passes()
            for (_, slot), share in zip(slots, work.split(len(slots)), strict=True):
                slot.policy_time += elapsed / len(slots)
                slot.cpu_time += cpu / len(slots)
                slot.charge(passes, server / len(slots), share, wait / len(slots))
                if len(slots) == 1:
                    slot.fail(exc)
            if len(slots) > 1:  # which episode raised? ask each alone (the failed call stays charged)
                elapsed += sum(self.act([served]) for served in slots)
            return elapsed
        elapsed, cpu = clock() - t, self.cpu() - c
        passes, server, work, wait = self.passes()
        tokens = _shares(int(batch.action_tokens), len(slots))
        works = work.split(len(slots))
        for row, (_, slot) in enumerate(slots):
            slot.policy_time += elapsed / len(slots)
            slot.cpu_time += cpu / len(slots)
            slot.charge(passes, server / len(slots), works[row], wait / len(slots))
            slot.tokens += tokens[row]
            slot.chunks += 1
            if slot.traces is not None and batch.trace:
                slot.traces.append({**batch.trace[row], "chunk": slot.chunks - 1, "step": slot.steps})
            try:
                check_chunk(actions[row : row + 1], int(np.prod(slot.context.action_space.shape)))
                returned = slot.space.apply(actions[row], slot.steps)  # type: ignore[union-attr]
            except ValueError as exc:
                slot.fail(exc)
                continue
            chunk = returned if self.replan_every == 0 else returned[: self.replan_every]
            slot.actions.extend(chunk)
        return elapsed

    def tick(self, slots: dict[int, _Slot]) -> float:
        """One lockstep step: one call for the slots whose chunk is used up, then one
        action for each running slot; returns the time charged to the slots."""
        charged = 0.0
        hungry = [(i, s) for i, s in sorted(slots.items()) if not s.actions]
        if hungry:
            charged += self.act(hungry)
        for i, slot in sorted(slots.items()):
            if not slot.done and slot.actions:
                charged += self.step(i, slot)
        return charged

    def step(self, i: int, slot: _Slot) -> float:
        """Execute slot i's next action; returns the time charged to it (the env's, and
        the policy's when a chain's instruction changed)."""
        t = clock()
        try:
            slot.obs, _, terminated, truncated, info = self.envs[i].step(slot.actions.popleft())
        except KeyboardInterrupt:
            raise
        except BaseException as exc:
            slot.fail(exc)
            elapsed = clock() - t
            slot.env_time += elapsed
            return elapsed
        elapsed = clock() - t
        slot.env_time += elapsed
        slot.steps += 1
        slot.info = info
        if info.get("success"):
            slot.success = slot.done = True
        elif terminated or truncated or slot.steps >= slot.context.max_steps:
            slot.done = True
        elif (switched := in_force(slot.context, info)) is not slot.context:
            elapsed += self.switch(slot, switched)
        return elapsed

    def switch(self, slot: _Slot, context: EpisodeContext) -> float:
        """A chain's next subtask: its instruction to the policy, the old chunk dropped;
        returns the policy's time."""
        slot.context = context
        slot.actions.clear()
        self.passes()
        c, t = self.cpu(), clock()
        try:
            with self.nfe.counting():
                self.policy.reset([context])
        except KeyboardInterrupt:
            raise
        except BaseException as exc:
            slot.fail(exc)
        elapsed = clock() - t
        slot.policy_time += elapsed
        slot.cpu_time += self.cpu() - c
        slot.charge(*self.passes())
        return elapsed


STARTED, STEPPED, DONE = "started", "stepped", "done"  # what batch_events yields


def run_batched(
    specs: Sequence[EpisodeSpec],
    make_env: Callable[[], gym.Env],
    policy: Any,
    nfe: NFECounter,
    context_for: Callable[[EpisodeSpec, gym.Env], EpisodeContext],
    batch_envs: int,
    replan_every: int = 0,
    record_traces: bool = False,
    envs: list[gym.Env | None] | None = None,
    out_of_space: str = DEFAULT_OUT_OF_SPACE,
    latency: LatencyPlan | None = None,
) -> Iterator[tuple[int, EpisodeOutcome]]:
    """Run every episode of `specs` (one task) with `batch_envs` slots; yields (position in
    `specs`, outcome) as each episode ends, each exactly once.

    envs: the slots' envs, reused and left open for the caller to close (a slot's env is
    closed and rebuilt after an episode that failed; None entries are built with
    make_env). Its length becomes `batch_envs`. latency: each slot's own chunks in flight
    (harness/batched_latency.py); None at `none`.
    """
    events = batch_events(
        specs, make_env, policy, nfe, context_for, batch_envs, replan_every, record_traces, envs, out_of_space,
        latency,
    )  # fmt: skip
    for kind, payload in events:
        if kind == DONE:
            yield payload


def batch_events(
    specs: Sequence[EpisodeSpec],
    make_env: Callable[[], gym.Env],
    policy: Any,
    nfe: NFECounter,
    context_for: Callable[[EpisodeSpec, gym.Env], EpisodeContext],
    batch_envs: int,
    replan_every: int = 0,
    record_traces: bool = False,
    envs: list[gym.Env | None] | None = None,
    out_of_space: str = DEFAULT_OUT_OF_SPACE,
    latency: LatencyPlan | None = None,
) -> Iterator[tuple[str, Any]]:
    """`run_batched` that also says when each episode starts and when each lockstep step
    ends: (STARTED, position) before an episode's env is built or reset, (STEPPED, None)
    after each step of the loop, (DONE, (position, outcome)) as an episode ends.

    A worker process forwards these to the scheduler (harness/backends/schedule.py),
    which must know which episodes a lost worker held (those it said had started) and
    whether a batch still moves (--episode-timeout). The consumer's time between events
    is charged to no episode, as a row's writing is not.
    """
    envs = [] if envs is None else envs
    envs.extend([None] * (batch_envs - len(envs)))
    args = (envs, make_env, policy, nfe, context_for, replan_every, record_traces, out_of_space)
    if latency is None:
        loop = _Loop(*args)
    else:  # each slot's chunks in flight under an inference latency
        from harness.batched_latency import DelayedLoop

        loop = DelayedLoop(latency, *args)
    queue = deque(enumerate(specs))
    slots: dict[int, _Slot] = {}

    def fill(i: int) -> Iterator[tuple[str, Any]]:
        while queue and i not in slots:
            index, spec = queue.popleft()
            yield STARTED, index
            slot = loop.start(i, index, spec)
            if slot is not None:
                slots[i] = slot

    def flush() -> Iterator[tuple[str, Any]]:
        remote = loop.remote is not None
        while loop.finished:
            index, done = loop.finished.pop(0)
            if isinstance(done, _Slot):
                done = done.outcome(batch_envs, remote, loop.cpu_measured)
            yield DONE, (index, done)

    for i in range(batch_envs):
        yield from fill(i)
    yield from flush()
    while slots:
        t0 = clock()
        running = len(slots)
        charged = loop.tick(slots)
        overhead = (clock() - t0 - charged) / running
        for slot in slots.values():
            slot.overhead += overhead
        yield STEPPED, None
        for i in [i for i, s in sorted(slots.items()) if s.done]:
            slot = slots.pop(i)
            loop.finished.append((slot.index, slot))
            if slot.failure is not None:
                loop.close_env(i)  # its state is suspect: rebuilt for the next episode
            yield from fill(i)
        yield from flush()
