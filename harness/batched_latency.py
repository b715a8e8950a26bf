"""Batched inference under an inference latency: `--batch-envs K` with `--inference-latency`.

Each slot of the batch is an episode with its own clock (its step count) and its own
chunks in flight, following the same rules as the unbatched loop (harness/delayed.py's
`Schedule`, docs/latency.md): in `sync` it holds for its own d steps before each new
chunk, in `async` its next chunk is requested from its own observation at its own
replanning point and arrives d steps later with its first d actions skipped. Batching
only groups the requests that fall due in the same lockstep step into one `act_batch`
call; it never moves a request. The latency model gives each slot the decoder to itself
(no queueing behind another slot's call), so a slot's row is the row it would have
alone whenever its charged passes are the ones it would run alone.

What a slot's delay is made of:
- `passes:MS[+FIXED_MS]`: the passes charged to the slot since its previous request
  (the call that served it, plus any instruction-switch reset since), which are the
  passes of its NFE column: a batched call's every pass counts for each slot it served
  (harness/batched.py). A decoder with a fixed number of passes per chunk (the teacher,
  block_diffusion) gives each slot the delays it would have unbatched, whatever the
  batch size; an adaptive one (fast_dvla, fast_dllm's threshold) decodes until its
  slowest row is done, and its delay says so, as its NFE does.
- `profile:NAME`: the profile's chunk latency for the policy, as unbatched.
- `measured`: the wall clock of the `act_batch` call that served the slot (the whole
  call, not a share: the slot got its chunk when the call returned), plus its resets
  since its previous request. It depends on the machine, its load and the batch size.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from harness.batched import _Loop, _Slot
from harness.delayed import Schedule, Tally
from harness.latency import LatencyPlan
from policies.base import EpisodeContext

clock = time.perf_counter


class DelayedLoop(_Loop):
    """The batched loop with a `Schedule` per slot: each lockstep step, the slots whose
    request is due are served by one call (again, while a chunk that arrives at once
    makes another due at once), then every running slot takes its action or holds."""

    def __init__(self, plan: LatencyPlan, *args: Any):
        super().__init__(*args)
        self.plan = plan
        # the base keeps a whole chunk in slot.actions; the schedule applies replan_every
        self.every, self.replan_every = self.replan_every, 0
        self.called: float | None = None  # when the outermost act_batch call began

    def start(self, i: int, index: int, spec: Any) -> _Slot | None:
        slot = super().start(i, index, spec)
        if slot is not None:
            action_dim = int(np.prod(slot.context.action_space.shape))
            # from 0: the reset's passes and time delay the first chunk, as unbatched
            slot.schedule = Schedule(self.plan, self.every, action_dim, Tally(), 0, slot.policy_time)
        return slot

    def tick(self, slots: dict[int, _Slot]) -> float:
        charged = 0.0
        while due := [(i, s) for i, s in sorted(slots.items()) if not s.done and s.schedule.due(s.steps)]:
            charged += self.act(due)
        for i, slot in sorted(slots.items()):
            if not slot.done:
                slot.actions.append(slot.schedule.action(slot.steps))
                charged += self.step(i, slot)
        return charged

    def act(self, slots: list[tuple[int, _Slot]]) -> float:
        """The base call (its charges, checks, and retries alone when it raises), then
        each served slot's chunk handed to its schedule. A retry alone comes back through
        here and hands its slot's chunk over itself; its latency runs from the start of
        the batch call that raised."""
        outer = self.called is None
        if outer:
            self.called = clock()
        try:
            elapsed = super().act(slots)
            wall = clock() - self.called  # type: ignore[operator]
            for _, slot in slots:
                if len(slot.schedule.tally.delays) < slot.chunks:  # not yet handed over
                    self.receive(slot, wall)
        finally:
            if outer:
                self.called = None
        return elapsed

    def receive(self, slot: _Slot, wall: float) -> None:
        """Record the delay of the slot's new chunk (even one refused by the checks: it
        took its time too) and send it on its way."""
        chunk = np.array(slot.actions)
        slot.actions.clear()
        try:
            d = slot.schedule.delay(slot.nfe, wall)
        except ValueError as exc:  # passes: a server that reports none
            slot.fail(exc)
            return
        if not slot.done:
            slot.schedule.send(slot.steps, chunk, d)

    def switch(self, slot: _Slot, context: EpisodeContext) -> float:
        elapsed = super().switch(slot, context)
        slot.schedule.switch(slot.steps, elapsed)
        return elapsed
