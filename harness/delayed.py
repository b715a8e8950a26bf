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


@dataclass
class _Chunk:
    actions: np.ndarray
    arrival: int
    anchor: int
    follows: bool  # a chunk was running when it was requested (not an awaited one)
    held: bool = False  # the robot held still for want of an action while it was on its way


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
            raise ValueError(
                f"--inference-latency {plan.mode.text} needs each call's forward passes, and this "
                "server reports none (an openpi server); use profile:NAME or measured"
            )
        return nfe.count + (served or 0)

    mark = passes()  # passes since the last request: a reset's belong to the next chunk
    since_request = reset_time  # wall clock since the last request (measured mode)
    current: _Chunk | None = None
    pending: _Chunk | None = None
    next_request = 0
    last_action: np.ndarray | None = None
    awaited = True

    def request() -> _Chunk:
        nonlocal mark, since_request
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
        now_passes = passes()
        d = plan.delay(now_passes - mark, since_request + took)
        mark, since_request = now_passes, 0.0
        tally.delays.append(d)  # before the checks: a refused chunk took its time too
        actions = np.asarray(batch.actions)
        check_chunk(actions, action_dim)
        returned = space.apply(actions[0], tally.steps)
        now = tally.steps
        anchor = now + d if awaited or plan.execution == "sync" else now
        return _Chunk(returned, now + d, anchor, follows=not awaited)

    while tally.steps < context.max_steps:
        t = tally.steps
        if pending is None and t >= next_request:
            pending = request()
            awaited = False
        if pending is not None and t >= pending.arrival:
            if pending.follows and pending.held:
                tally.late_chunks += 1  # the robot ran out of actions (or, sync, waited) for it
            tally.skipped_actions += min(t - pending.anchor, len(pending.actions))
            current, pending = pending, None
            s = len(current.actions) if replan_every == 0 else min(replan_every, len(current.actions))
            next_request = max(current.anchor + s, t)
            if t >= next_request:
                continue  # due again at once (d >= s): ask before acting
        i = -1 if current is None else t - current.anchor
        moving = current is not None and 0 <= i < len(current.actions)
        if moving and not (plan.execution == "sync" and pending is not None):
            action = current.actions[i]  # type: ignore[union-attr]
            last_action = action
        else:
            action = plan.hold(last_action, action_dim)
            tally.hold_steps += 1
            if pending is not None:
                pending.held = True
        t0 = clock()
        obs, _, terminated, truncated, info = env.step(action)
        tally.env_time += clock() - t0
        tally.info = info
        tally.steps += 1
        if info.get("success"):
            tally.success = True
            return
        if terminated or truncated:
            return
        if (switched := in_force(context, info)) is not context:
            context = switched  # a new subtask: what was decoded for the old one is dropped
            c, t0 = cpu(), clock()
            with nfe.counting():
                policy.reset([context])
            took = clock() - t0
            tally.policy_time += took
            tally.cpu_time += cpu() - c
            since_request += took
            current = pending = None
            next_request, awaited = tally.steps, True
