"""The episode loop under an inference latency (harness/latency.py; docs/latency.md).

Time is counted in control steps t. A chunk requested at step t from that step's
observation arrives at t + d. Its action i belongs to step anchor + i, where the anchor
is the request step under async (so its first d actions lie in the past and are
skipped) and the arrival step under sync (the robot held still meanwhile) and for an
awaited chunk: the episode's first, and the first after an instruction switch, when
nothing was moving. Requests follow replan_every: the next one is due s steps after the
anchor (s = replan_every, or the whole chunk when it is 0, at most the chunk), and never
before the previous request arrived (one call in flight, as one policy object decodes).
Any step with no action due is a hold (LatencyPlan.hold), and every step counts against
the budget. With d = 0 this is the upstream loop exactly (tests/test_latency.py).

Instruction switch (chains): the env's new instruction resets the policy at once; a
chunk in flight was decoded for the old instruction and is dropped, and so is the rest
of the current chunk; a new awaited request is made from the same step's observation.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np

from harness.action_space import ActionCheck
from harness.cpu_time import cpu_clock
from harness.latency import LatencyPlan
from harness.nfe import NFECounter
from policies.base import EpisodeContext, Policy


@dataclass
class Tally:
    """What the loop accumulates; kept in the caller so an exception loses nothing."""

    steps: int = 0
    chunks: int = 0
    tokens: int = 0
    policy_time: float = 0.0
    cpu_time: float = 0.0  # CPU time of the same policy calls (harness/cpu_time.py)
    env_time: float = 0.0
    success: bool = False
    info: dict[str, Any] = field(default_factory=dict)
    delays: list[int] = field(default_factory=list)
    late_chunks: int = 0
    hold_steps: int = 0
    skipped_actions: int = 0

    def latency_columns(self) -> dict[str, Any]:
        """The row's latency columns (harness/episode.py's EpisodeOutcome fields)."""
        return {
            "delay_steps_mean": float(np.mean(self.delays)) if self.delays else None,
            "delay_steps_max": max(self.delays) if self.delays else None,
            "late_chunks": self.late_chunks,
            "hold_steps": self.hold_steps,
        }


@dataclass
class _Chunk:
    actions: np.ndarray
    arrival: int
    anchor: int
    follows: bool  # a chunk was running when it was requested (not an awaited one)
    held: bool = False  # the robot held still for want of an action while it was on its way


def no_passes(plan: LatencyPlan) -> ValueError:
    """The failure of a `passes:` episode whose remote server reports no passes."""
    return ValueError(
        f"--inference-latency {plan.mode.text} needs each call's forward passes, and this "
        "server reports none (an openpi server); use profile:NAME or measured"
    )


@dataclass
class Schedule:
    """One episode's chunks in control steps: the one running, the one on its way, when
    the next request is due. Its own clock is the episode's step count, so the unbatched
    loop (run_delayed) and each slot of a batch (harness/batched_latency.py) follow the
    same rules whatever else shares the process.

    The caller, at each step t: asks `due(t)` and, while it says so, makes a request from
    t's observation and hands its chunk to `send` (its delay from `delay`); then executes
    `action(t)`; after an instruction switch it calls `switch`."""

    plan: LatencyPlan
    replan_every: int
    action_dim: int
    tally: Tally  # where the delays, late chunks and holds are counted
    mark: int | None  # passes counted when the last request was made (a reset's go to the next)
    since_request: float  # wall clock of policy calls since then (measured mode)
    current: _Chunk | None = None
    pending: _Chunk | None = None
    next_request: int = 0
    last_action: np.ndarray | None = None
    awaited: bool = True  # the next chunk is awaited: nothing is moving

    def due(self, t: int) -> bool:
        """Take in the chunk that has arrived by step t; is a request due at t?"""
        while self.pending is not None and t >= self.pending.arrival:
            pending, self.pending = self.pending, None
            if pending.follows and pending.held:
                self.tally.late_chunks += 1  # the robot ran out of actions (or, sync, waited) for it
            self.tally.skipped_actions += min(t - pending.anchor, len(pending.actions))
            self.current = pending
            n = len(pending.actions)
            s = n if self.replan_every == 0 else min(self.replan_every, n)
            self.next_request = max(pending.anchor + s, t)  # t: due again at once (d >= s)
        return self.pending is None and t >= self.next_request

    def delay(self, passes: int | None, took: float) -> int:
        """The delay of the chunk a request just returned, from the passes counted so far
        (the episode's running total) and the call's wall clock; recorded at once, before
        the chunk is checked: a refused chunk took its time too."""
        if passes is None and self.plan.mode.kind == "passes":
            raise no_passes(self.plan)
        d = self.plan.delay((passes or 0) - (self.mark or 0), self.since_request + took)
        self.mark, self.since_request = passes, 0.0
        self.tally.delays.append(d)
        return d

    def send(self, t: int, actions: np.ndarray, d: int) -> None:
        """The checked chunk requested at step t, arriving at t + d."""
        anchor = t + d if self.awaited or self.plan.execution == "sync" else t
        self.pending = _Chunk(actions, t + d, anchor, follows=not self.awaited)
        self.awaited = False

    def action(self, t: int) -> np.ndarray:
        """What the robot does at step t: the running chunk's action for t, or a hold
        (none due, or sync with a chunk on its way)."""
        current = self.current
        i = -1 if current is None else t - current.anchor
        moving = current is not None and 0 <= i < len(current.actions)
        if moving and not (self.plan.execution == "sync" and self.pending is not None):
            self.last_action = current.actions[i]  # type: ignore[union-attr]
            return self.last_action  # type: ignore[return-value]
        self.tally.hold_steps += 1
        if self.pending is not None:
            self.pending.held = True
        return self.plan.hold(self.last_action, self.action_dim)

    def switch(self, t: int, took: float) -> None:
        """A new instruction is in force after step t (the policy reset, taking `took`
        s): the chunk in flight and the rest of the current one are dropped, and the
        next is requested at once and awaited."""
        self.since_request += took
        self.current = self.pending = None
        self.next_request, self.awaited = t, True


def run_delayed(
    env: gym.Env,
    policy: Policy,
    nfe: NFECounter,
    context: EpisodeContext,
    obs: Any,
    plan: LatencyPlan,
    replan_every: int,
    space: ActionCheck,
    tally: Tally,
    traces: list[dict[str, Any]] | None,
    reset_time: float,
) -> None:
    from harness.episode import check_chunk, in_force, remote_policy

    clock = time.perf_counter
    action_dim = int(np.prod(context.action_space.shape))
    remote = remote_policy(policy)
    cpu = (None if remote is not None else cpu_clock(policy)) or (lambda: 0.0)

    def passes() -> int:
        """Passes counted so far this episode: the harness's hooks, plus a remote server's."""
        if remote is None:
            return nfe.count
        served = remote.passes_so_far()
        if served is None and plan.mode.kind == "passes":
            raise no_passes(plan)
        return nfe.count + (served or 0)

    passes()  # a server that reports none fails the episode here, before its first step
    # the counter was cleared before the episode's reset: its passes delay the first chunk
    schedule = Schedule(plan, replan_every, action_dim, tally, mark=0, since_request=reset_time)

    def request() -> None:
        c, t = cpu(), clock()
        with nfe.counting():
            batch = policy.act([obs])
        took = clock() - t
        tally.policy_time += took
        tally.cpu_time += cpu() - c
        tally.chunks += 1
        tally.tokens += batch.action_tokens
        if traces is not None and batch.trace:
            traces.append({**batch.trace[0], "chunk": tally.chunks - 1, "step": tally.steps})
        d = schedule.delay(passes(), took)
        actions = np.asarray(batch.actions)
        check_chunk(actions, action_dim)
        schedule.send(tally.steps, space.apply(actions[0], tally.steps), d)

    while tally.steps < context.max_steps:
        while schedule.due(tally.steps):
            request()  # from this step's observation, before acting
        action = schedule.action(tally.steps)
        t0 = clock()
        obs, _, terminated, truncated, info = env.step(action)
        tally.env_time += clock() - t0
        tally.info = info
        tally.steps += 1
        if info.get("success"):
            tally.success = True
            return
        if terminated or truncated or tally.steps >= context.max_steps:
            return  # the budget is spent: no reset for an instruction that comes now
        if (switched := in_force(context, info)) is not context:
            context = switched  # a new subtask: what was decoded for the old one is dropped
            c, t0 = cpu(), clock()
            with nfe.counting():
                policy.reset([context])
            took = clock() - t0
            tally.policy_time += took
            tally.cpu_time += cpu() - c
            schedule.switch(tally.steps, took)
