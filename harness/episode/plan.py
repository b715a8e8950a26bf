"""How a run's episodes execute: the plan made once per run, and each episode's timeline.

`ExecutionPlan` is everything the episode loop needs from a run's config, worked out
once (in the writing process, and again in each worker that rebuilds the run): actions
per chunk before re-planning, the out-of-space rule, the inference latency and execution
(docs/latency.md), how many environments step in lockstep, whether decode traces are
kept. It is plain data, so it crosses process boundaries as it is.

`EpisodeTimeline` is one episode's chunks in control steps t. A chunk requested at step t
from that step's observation arrives at t + d (d from harness/episode/latency.py). Its
action i belongs to step anchor + i, where the anchor is the request step under async
(so its first d actions lie in the past and are skipped) and the arrival step under sync
(the robot held still meanwhile) and for an awaited chunk: the episode's first, and the
first after an instruction switch, when nothing was moving. Requests follow
replan_every: the next one is due s steps after the anchor (s = replan_every, or the
whole chunk when it is 0, at most the chunk), and never before the previous request
arrived (one call in flight, as one policy object decodes). Any step with no action due
is a hold (LatencyPlan.hold), and every step counts against the budget.

With no latency (`none`, the world waits for every chunk, as every upstream benchmark
does) d is 0 for every chunk: each chunk arrives as it is requested, is executed up to
replan_every actions, and the next is requested from the observation after them, so
the same rules give the upstream loop exactly, and there is one loop for every mode.

Instruction switch (chains): the env's new instruction resets the policy at once; a
chunk in flight was decoded for the old instruction and is dropped, and so is the rest of
the current chunk; a new awaited request is made from the same step's observation.

Batched episodes (--batch-envs K) each keep their own timeline: batching only groups
the requests that fall due in the same lockstep step into one call; it never moves one.
The delay a slot's chunk is charged: `passes:` the passes charged to the slot since its
previous request (its NFE column's passes: a batched call's every pass counts for each
slot it served, so an adaptive decoder's row waits for its slowest row, as its NFE
says); `profile:` the profile's chunk latency for the policy; `measured` the wall clock
of the call that served it (the whole call, not a share: the slot got its chunk when the
call returned), plus its resets since its previous request.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from harness.episode.actions import DEFAULT_OUT_OF_SPACE
from harness.episode.latency import LatencyPlan, latency_plan, parse_latency
from harness.episode.video import VideoPlan


@dataclass(frozen=True)
class ExecutionPlan:
    """How every episode of a run is executed."""

    replan_every: int = 0  # actions executed per chunk before asking again; 0 = the whole chunk
    out_of_space: str = DEFAULT_OUT_OF_SPACE  # harness/episode/actions.py
    latency: LatencyPlan | None = None  # None: `none`, the world waits for every chunk
    batch_envs: int = 1  # environments stepped in lockstep, one policy call for their chunks
    traces: bool = False  # keep each chunk's decode trace (traces.jsonl)
    video: VideoPlan | None = None  # record rollout videos (harness/episode/video.py)

    @classmethod
    def for_run(
        cls, resolved: Any, batch_envs: int = 1, traces: bool = False, video: VideoPlan | None = None
    ) -> ExecutionPlan:
        """The plan of a resolved run (harness/config.py ResolvedRun, whose latency was
        checked when it was resolved), made once per process that runs its episodes."""
        config = resolved.config
        latency = latency_plan(parse_latency(config.inference_latency), config.execution, resolved.suite)
        return cls(config.replan_every, config.out_of_space, latency, batch_envs, traces, video)

    def timeline(self, policy: str, action_dim: int, reset_s: float) -> EpisodeTimeline:
        """A new episode's timeline. Its passes are counted from 0, before the policy's
        reset, and `reset_s` is the reset's time: both delay the first chunk."""
        return EpisodeTimeline(self, policy, action_dim, mark=0, since_request=reset_s)


@dataclass
class _Chunk:
    actions: np.ndarray
    arrival: int
    anchor: int
    follows: bool  # a chunk was running when it was requested (not an awaited one)
    held: bool = False  # the robot held still for want of an action while it was on its way


def no_passes(latency: LatencyPlan) -> ValueError:
    """The failure of a `passes:` episode whose served policy's server reports no passes."""
    return ValueError(
        f"--inference-latency {latency.mode.text} needs each call's forward passes, and this "
        "server reports none (an openpi server); use profile:NAME or measured"
    )


@dataclass
class EpisodeTimeline:
    """One episode's chunks in control steps: the one running, the one on its way, when
    the next request is due; its own clock is the episode's step count.

    The loop, at each step t: asks `due(t)` and, while it says so, makes a request from
    t's observation, tells `delay` what the call cost and hands its admitted chunk to
    `send`; then executes `action(t)`; after an instruction switch it calls `switch`."""

    plan: ExecutionPlan
    policy: str  # a latency profile's key
    action_dim: int
    mark: int | None  # passes counted when the last request was made (resets' go to the next)
    since_request: float  # wall clock of policy calls since then (measured mode)
    current: _Chunk | None = None
    pending: _Chunk | None = None
    next_request: int = 0
    last_action: np.ndarray | None = None
    awaited: bool = True  # the next chunk is awaited: nothing is moving
    delays: list[int] = field(default_factory=list)  # per chunk, in control steps
    late_chunks: int = 0
    hold_steps: int = 0

    def due(self, t: int) -> bool:
        """Take in the chunk that has arrived by step t; is a request due at t?"""
        while self.pending is not None and t >= self.pending.arrival:
            pending, self.pending = self.pending, None
            if pending.follows and pending.held:
                self.late_chunks += 1  # the robot ran out of actions (or, sync, waited) for it
            self.current = pending
            n = len(pending.actions)
            s = n if self.plan.replan_every == 0 else min(self.plan.replan_every, n)
            self.next_request = max(pending.anchor + s, t)  # t: due again at once (d >= s)
        return self.pending is None and t >= self.next_request

    def delay(self, passes: int | None, took: float) -> int:
        """The delay of the chunk a request just returned, from the passes counted so far
        (the episode's running total) and the call's wall clock; recorded at once, before
        the chunk is admitted: a refused chunk took its time too."""
        latency = self.plan.latency
        if latency is None:
            d = 0
        else:
            if passes is None and latency.mode.kind == "passes":
                raise no_passes(latency)
            d = latency.delay((passes or 0) - (self.mark or 0), self.since_request + took, self.policy)
        self.mark, self.since_request = passes, 0.0
        self.delays.append(d)
        return d

    def send(self, t: int, actions: np.ndarray, d: int) -> None:
        """The admitted chunk requested at step t, arriving at t + d."""
        sync = self.plan.latency is None or self.plan.latency.execution == "sync"
        anchor = t + d if self.awaited or sync else t
        self.pending = _Chunk(actions, t + d, anchor, follows=not self.awaited)
        self.awaited = False

    def action(self, t: int) -> np.ndarray:
        """What the robot does at step t: the running chunk's action for t, or a hold
        (none due, or sync with a chunk on its way)."""
        current = self.current
        i = -1 if current is None else t - current.anchor
        if current is not None and 0 <= i < len(current.actions):
            latency = self.plan.latency
            if self.pending is None or latency is None or latency.execution != "sync":
                self.last_action = current.actions[i]
                return self.last_action
        self.hold_steps += 1
        if self.pending is not None:
            self.pending.held = True
        return self.plan.latency.hold(self.last_action, self.action_dim)  # type: ignore[union-attr]

    def switch(self, t: int, took: float) -> None:
        """A new instruction is in force after step t (the policy reset, taking `took`
        s): the chunk in flight and the rest of the current one are dropped, and the
        next is requested at once and awaited."""
        self.since_request += took
        self.current = self.pending = None
        self.next_request, self.awaited = t, True

    def columns(self) -> dict[str, Any]:
        """The row's latency columns."""
        return {
            "delay_steps_mean": float(np.mean(self.delays)) if self.delays else None,
            "delay_steps_max": max(self.delays) if self.delays else None,
            "late_chunks": self.late_chunks,
            "hold_steps": self.hold_steps,
        }
