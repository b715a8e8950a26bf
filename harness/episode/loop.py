"""The episode loop: K environment slots in lockstep, one policy call for the chunks due.

Every episode of every run goes through this loop, whatever its execution: one slot
(K = 1, the default) runs a queue of episodes one after another; `--batch-envs K` runs a
task's episodes of one policy K at a time, and an episode that ends frees its slot at once
for the next of the queue, so the batch stays full until the queue runs dry. Each control
step, every running slot asks its timeline (harness/episode/plan.py) whether a chunk is
due; the slots whose request is due are served by one call (`act` for one slot,
`act_batch` for a batch), each chunk is admitted through the env's action guard
(harness/episode/actions.py) and handed to its timeline, then every running slot executes
its action for this step (or holds, under an inference latency). A slot stops on the env's
success, termination, truncation or its step budget. A chain's new instruction resets the
policy and drops what was decoded for the old one.

What each episode is charged, so that a batched row means what an unbatched row means:
- NFE: every forward pass of a call counts 1 for each episode the call served (a pass
  over K episodes is K episode-passes, never 1/K). An adaptive decoder (fast_dvla,
  fast_dllm's threshold) runs until its slowest row is decoded, so a row may be charged
  more passes than it needed alone: the passes it waited for.
- Policy time and CPU time: a call's shared equally among the slots it served.
- Env time: the slot's own env.reset and env.step calls, timed one by one.
- Wall clock: policy share + env time + an equal share of the loop's own bookkeeping in
  each step among the slots running in it, so the rows' wall clocks add up to the time
  the loop ran and episodes/s = rows / sum(wall_clock_s) whatever K was. Building an env
  is no episode's time.
- Tokens and counted work: a call's split among its slots, in integers adding up to it
  (a batched pass's rows have one shape, so each episode is charged its own row's work).

Failures stay with their episode: an exception from the env or the policy, a chunk that
is not finite, absurd or (under `--out-of-space fail`) outside the action space ends that
slot's episode with a failure reason; its env is closed and rebuilt for the next one. When
a batched call raises, each episode it served is asked for again alone, so only the one
whose observation makes the policy raise fails; the failed call stays charged to all of
them (they waited for it). Only KeyboardInterrupt (Ctrl-C, SIGTERM) stops the loop.

`events` says when each episode starts and when each lockstep step ends, besides when
each episode ends: a worker forwards these to the scheduler (harness/backends/scheduler.py),
which must know which episodes a lost worker held and whether a batch still moves.
"""

from __future__ import annotations

import time
import traceback
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import gymnasium as gym
import numpy as np

from adapters.base import EpisodeSpec, TaskSpec
from harness.episode.actions import ActionGuard
from harness.episode.context import episode_context, in_force
from harness.episode.envs import TaskEnvs
from harness.episode.outcome import EpisodeOutcome, chain_fields
from harness.episode.plan import EpisodeTimeline, ExecutionPlan, no_passes
from harness.episode.timed import Call, Charge, TimedPolicy
from harness.episode.video import Recording, frame_of
from harness.episode.work import NO_WORK
from policies.base import EpisodeContext, Policy

clock = time.perf_counter


class EpisodeEvent(Enum):
    """What `EpisodeLoop.events` yields, with its payload (the values cross process pipes)."""

    STARTED = "started"  # the position of an episode about to start
    STEPPED = "stepped"  # ((position, EpisodeOutcome), ...) of the running episodes: a lockstep step ended
    DONE = "done"  # (position, EpisodeOutcome): an episode ended


@dataclass(frozen=True)
class Episode:
    """One episode to run: its task, its spec, the policy that acts in it, and (tests,
    demonstrations) a context given instead of the one built from the task and the env."""

    task: TaskSpec
    spec: EpisodeSpec
    policy: TimedPolicy
    context: EpisodeContext | None = None


@dataclass(slots=True)
class Slot:
    """One running episode: its env, the instruction in force, its chunks in time, and
    what it has been charged so far."""

    index: int  # its episode's position in the queue
    episode: Episode
    out: EpisodeOutcome
    env: ActionGuard | None = None
    context: EpisodeContext | None = None
    timeline: EpisodeTimeline | None = None
    obs: Any = None
    info: dict[str, Any] = field(default_factory=dict)  # the env's last info (chains read it)
    done: bool = False
    cpu_measured: bool = False
    cpu_s: float = 0.0
    server_s: float = 0.0  # served policies: the server's own share of policy_time_s
    overhead_s: float = 0.0  # its share of the loop's own time (wall = policy + env + this)
    recording: Recording | None = None  # --video: its frames so far (harness/episode/video.py)

    def fail(self, exc: BaseException, trace: str | None = None) -> None:
        self.out.fail(exc, trace)
        self.done = True

    def charge(self, charge: Charge) -> None:
        """Count a call's share: time, CPU time, passes (None-sticky: a server that reported
        none once), server time, work; a served policy's wait to connect again (a server
        restart) is nobody's compute, so it moves from policy time to overhead."""
        out = self.out
        out.policy_time_s += charge.seconds
        self.cpu_s += charge.cpu_s
        passes = charge.passes
        out.nfe_total = None if passes is None or out.nfe_total is None else out.nfe_total + passes
        self.server_s += charge.server_s
        if charge.work is not NO_WORK:
            out.work += charge.work
        if charge.connect_wait_s:
            moved = min(charge.connect_wait_s, out.policy_time_s)
            out.policy_time_s -= moved
            self.overhead_s += moved

    def outcome(self) -> EpisodeOutcome:
        """The finished episode's outcome, its totals and columns filled in."""
        out = self.out
        out.wall_clock_s = out.policy_time_s + out.env_time_s + self.overhead_s
        out.policy_cpu_time_s = self.cpu_s if self.cpu_measured else None
        if self.episode.policy.served:
            out.transport_time_s = max(0.0, out.policy_time_s - self.server_s)
        if self.env is not None:
            out.actions_out_of_space, out.max_action_excess = self.env.columns().values()
        if self.timeline is not None:
            for name, value in self.timeline.columns().items():
                setattr(out, name, value)
        for name, value in chain_fields(self.info).items():
            setattr(out, name, value)
        return out


def shares(total: int, parts: int) -> list[int]:
    """`total` split into `parts` integers that differ by at most 1 and add up to it."""
    if parts == 1:
        return [total]
    base, extra = divmod(total, parts)
    return [base + (i < extra) for i in range(parts)]


class EpisodeLoop:
    """Runs queued episodes through K slots with one process's envs.

    `suite`: the suite's name (what a policy is told); `envs`: the process's open envs,
    kept between calls of `events` (a worker's next group of the same task reuses them);
    `worker_id` and `host`: where the outcomes say they ran."""

    def __init__(self, suite: str, plan: ExecutionPlan, envs: TaskEnvs, worker_id: str = "", host: str = ""):
        self.suite, self.plan, self.envs = suite, plan, envs
        self.worker_id, self.host = worker_id, host

    def events(
        self, episodes: Sequence[Episode], alone: bool = False, steps: bool = False
    ) -> Iterator[tuple[EpisodeEvent, Any]]:
        """Run every episode of `episodes` (in order; batched, all of one task and one
        policy) through plan.batch_envs slots, or one slot when `alone`. Yields
        (STARTED, position) before an episode's env is taken, (DONE, (position, outcome))
        as each episode ends, exactly once, and with `steps` (STEPPED, running) after each
        lockstep step, running being each running episode's (position, outcome so far),
        whose `progress()` the consumer takes only when it reports: a worker's sign of life,
        and what a lost or timed-out episode had done. The
        consumer's time between events is charged to no episode."""
        k = 1 if alone else self.plan.batch_envs
        queue = deque(enumerate(episodes))
        running: dict[int, Slot] = {}
        kept: dict[int, tuple[str, ActionGuard]] = {}  # slot -> its last episode's env, for the next

        def fill(i: int) -> Iterator[tuple[EpisodeEvent, Any]]:
            while queue and i not in running:
                index, episode = queue.popleft()
                yield EpisodeEvent.STARTED, index
                slot = self._start(index, episode, k, self._kept_env(kept, i, episode.task.name))
                if slot.done:
                    yield EpisodeEvent.DONE, self._end(slot, kept, i)
                else:
                    running[i] = slot

        try:
            for i in range(k):
                yield from fill(i)
            while running:
                order = [running[i] for i in sorted(running)]  # slot order: each step's call order
                ending = False
                while not ending:
                    t0 = clock()
                    charged, ending = self._tick(order, k > 1)
                    overhead = (clock() - t0 - charged) / len(order)
                    for slot in order:
                        slot.overhead_s += overhead
                    if steps:
                        yield EpisodeEvent.STEPPED, tuple((slot.index, slot.out) for slot in order)
                ended = [i for i in sorted(running) if running[i].done]
                for i in ended:  # every ended episode's row before any slot starts another
                    yield EpisodeEvent.DONE, self._end(running.pop(i), kept, i)
                for i in ended:
                    yield from fill(i)
        finally:
            for task, env in kept.values():
                self.envs.give_back(task, env)
            for slot in running.values():  # stopped mid-episode (an interrupt): its state is suspect
                if slot.recording is not None:
                    slot.recording.abandon()
                if slot.env is not None:
                    slot.env.close()

    def run(self, episodes: Sequence[Episode], alone: bool = False) -> Iterator[tuple[int, EpisodeOutcome]]:
        """`events`, only the ended episodes: (position, outcome)."""
        for kind, payload in self.events(episodes, alone):
            if kind is EpisodeEvent.DONE:
                yield payload

    # ---- one episode's start and end --------------------------------------------------

    def _kept_env(self, kept: dict[int, tuple[str, ActionGuard]], i: int, task: str) -> ActionGuard | None:
        """Slot i's env from its last episode, if that was of `task` (else it goes back)."""
        held = kept.pop(i, None)
        if held is None:
            return None
        name, env = held
        if name == task:
            return env
        self.envs.give_back(name, env)
        return None

    def _start(self, index: int, episode: Episode, k: int, env: ActionGuard | None) -> Slot:
        out = EpisodeOutcome(batch_envs=k, host=self.host, worker_id=self.worker_id)
        out.traces = [] if self.plan.traces else None
        slot = Slot(index, episode, out)
        try:
            slot.env = env if env is not None else self.envs.take(episode.task)
        except Exception as exc:
            slot.fail(exc)
            return slot
        env, spec, policy = slot.env, episode.spec, episode.policy
        context = episode.context or episode_context(self.suite, episode.task, spec, env)
        policy.clock_cpu()
        slot.cpu_measured = policy.cpu_measured
        t0 = clock()
        try:
            slot.obs, slot.info = env.reset(seed=spec.seed, options={"episode": spec})
        except KeyboardInterrupt:
            raise
        except BaseException as exc:
            out.env_time_s += clock() - t0
            slot.fail(exc)
            return slot
        out.env_time_s += clock() - t0
        filming = self._film(slot, env) if self.plan.video and self.plan.video.records(spec.index) else 0.0
        slot.context = context = in_force(context, slot.info)
        call = policy.reset([context])
        slot.charge(call.charge)
        if call.error is not None:
            slot.fail(call.error, call.trace)
        else:
            self._begin(slot, env, context)
        slot.overhead_s += clock() - t0 - out.env_time_s - out.policy_time_s - filming
        return slot

    def _film(self, slot: Slot, env: ActionGuard, held: bool = False) -> float:
        """Add the env's frame to the slot's video (its first frame starts one); returns the
        time it took, which no episode is charged. A suite that cannot render leaves the
        episode unrecorded, and its row as it would be."""
        t = clock()
        try:
            frame = frame_of(env)
            if slot.recording is None:
                slot.recording = Recording(frame)
            else:
                slot.recording.add(frame, held)
        except Exception:
            if slot.recording is not None:
                slot.recording.abandon()
            slot.recording = None
        return clock() - t

    def _begin(self, slot: Slot, env: ActionGuard, context: EpisodeContext) -> None:
        """The reset episode's timeline (its reset's passes and time delay its first chunk)."""
        policy = slot.episode.policy
        slot.timeline = self.plan.timeline(policy.name, env.action_dim, slot.out.policy_time_s)
        latency = self.plan.latency
        if slot.out.nfe_total is None and latency is not None and latency.mode.kind == "passes":
            slot.fail(no_passes(latency))  # before its first step
        elif context.max_steps <= 0:
            slot.done = True

    def _end(
        self, slot: Slot, kept: dict[int, tuple[str, ActionGuard]], i: int
    ) -> tuple[int, EpisodeOutcome]:
        """The ended episode's outcome (read before its env's next reset starts the env's
        counts again); its env is kept for slot i's next episode, or closed if it failed.
        A recorded episode's video is finished here, after its times were summed."""
        outcome = slot.outcome()
        if slot.recording is not None and self.plan.video is not None:
            keep = self.plan.video.keeps(slot.episode.spec.index, outcome.success)
            outcome.video_mp4 = slot.recording.finish(keep)
            slot.recording = None
        if slot.env is not None:
            task = slot.episode.task.name
            if outcome.failure_reason is not None:
                self.envs.give_back(task, slot.env, suspect=True)
            else:
                kept[i] = (task, slot.env)
        return slot.index, outcome

    # ---- one lockstep step ------------------------------------------------------------

    def _tick(self, order: list[Slot], batched: bool) -> tuple[float, bool]:
        """One step of the running slots (in slot order): a call for the slots whose chunk
        is due (again, while a chunk that arrives at once makes another due at once), then
        an action for each slot still running; returns the time charged to the slots and
        whether an episode ended."""
        charged = 0.0
        while due := [s for s in order if not s.done and s.timeline.due(s.out.steps)]:  # type: ignore[union-attr]
            charged += self._request(due, batched)
        ended = False
        for slot in order:
            if not slot.done:
                charged += self._step(slot)
            ended = ended or slot.done
        return charged, ended

    def _request(self, slots: list[Slot], batched: bool, called: float | None = None) -> float:
        """One call for `slots` (their requests are due); returns its time. A batched call
        that raises is made again for each slot alone (the failed call stays charged); a
        request's delay (measured mode) runs from `called`, the start of the outermost call."""
        called = clock() if called is None else called
        call = self._call(slots, batched)
        elapsed = call.charge.seconds
        charges = call.charge.split(len(slots))
        if call.error is not None:
            for slot, share in zip(slots, charges, strict=True):
                slot.charge(share)
                if len(slots) == 1:
                    slot.fail(call.error, call.trace)
            if len(slots) > 1:  # which episode raised? ask each alone
                elapsed += sum(self._request([slot], batched, called) for slot in slots)
            return elapsed
        batch = call.result
        actions = np.asarray(batch.actions)
        tokens = shares(int(batch.action_tokens), len(slots))
        wall = clock() - called
        for row, slot in enumerate(slots):
            slot.charge(charges[row])
            out = slot.out
            out.action_tokens_total += tokens[row]
            out.chunks += 1
            if out.traces is not None and batch.trace:
                out.traces.append({**batch.trace[row], "chunk": out.chunks - 1, "step": out.steps})
            self._receive(slot, actions[row : row + 1] if batched else actions, wall)
        return elapsed

    def _call(self, slots: list[Slot], batched: bool) -> Call:
        policy = slots[0].episode.policy
        if not batched:
            return policy.act([slots[0].obs])
        call = policy.act_batch([s.context for s in slots], [s.obs for s in slots])  # type: ignore[misc]
        if call.error is None:
            actions = np.asarray(call.result.actions)
            if actions.ndim != 3 or actions.shape[0] != len(slots):
                call.error = ValueError(
                    f"policy returned actions of shape {actions.shape}; expected ({len(slots)}, chunk>=1, "
                    "action_dim): one chunk per episode of the call"
                )
                call.trace = "".join(traceback.format_exception(call.error))
        return call

    def _receive(self, slot: Slot, actions: np.ndarray, wall: float) -> None:
        """The slot's new chunk: its delay recorded (a refused chunk took its time too),
        admitted through the env's guard, and sent on its way."""
        out, timeline = slot.out, slot.timeline
        try:
            d = timeline.delay(out.nfe_total, wall)  # type: ignore[union-attr]
            chunk = slot.env.admit(actions, out.steps)  # type: ignore[union-attr]
        except Exception as exc:
            slot.fail(exc)
            return
        timeline.send(out.steps, chunk, d)  # type: ignore[union-attr]

    def _step(self, slot: Slot) -> float:
        """Execute the slot's action for this step; returns the time charged to it (the
        env's, and the policy's when a chain's instruction changed)."""
        out = slot.out
        holds = slot.timeline.hold_steps  # type: ignore[union-attr]
        action = slot.timeline.action(out.steps)  # type: ignore[union-attr]
        t = clock()
        try:
            slot.obs, _, terminated, truncated, info = slot.env.step(action)  # type: ignore[union-attr]
        except KeyboardInterrupt:
            raise
        except BaseException as exc:
            elapsed = clock() - t
            out.env_time_s += elapsed
            slot.fail(exc)
            return elapsed
        elapsed = clock() - t
        out.env_time_s += elapsed
        out.steps += 1
        slot.info = info
        if slot.recording is not None:  # its time is returned as spent, charged to no episode
            elapsed += self._film(slot, slot.env, held=slot.timeline.hold_steps > holds)  # type: ignore[arg-type,union-attr]
        if info.get("success"):
            out.success = slot.done = True
        elif terminated or truncated or out.steps >= slot.context.max_steps:  # type: ignore[union-attr]
            slot.done = True
        elif "instruction" in info and (switched := in_force(slot.context, info)) is not slot.context:  # type: ignore[arg-type]
            elapsed += self._switch(slot, switched)
        return elapsed

    def _switch(self, slot: Slot, context: EpisodeContext) -> float:
        """A chain's next subtask: its instruction to the policy, what was decoded for the
        old one dropped; returns the policy's time."""
        slot.context = context
        call = slot.episode.policy.reset([context])
        slot.charge(call.charge)
        if call.error is not None:
            slot.fail(call.error, call.trace)
        slot.timeline.switch(slot.out.steps, call.charge.seconds)  # type: ignore[union-attr]
        return call.charge.seconds


def run_episode(
    env: gym.Env,
    policy: Policy | TimedPolicy,
    context: EpisodeContext,
    spec: EpisodeSpec,
    plan: ExecutionPlan | None = None,
) -> EpisodeOutcome:
    """One episode on a given env with a given context, through the loop (demonstrations,
    the replay benchmark's recording, tests). `policy` bare gets its own NFE counter."""
    timed = policy if isinstance(policy, TimedPolicy) else TimedPolicy(policy, type(policy).__name__)
    plan = plan or ExecutionPlan()
    envs = TaskEnvs(_no_env, plan.out_of_space, close_failed=False)  # the env is the caller's
    envs.adopt(context.task, env)
    task = TaskSpec(context.task, context.instruction, context.max_steps, (spec,))
    loop = EpisodeLoop(context.suite, plan, envs)
    try:
        ((_, outcome),) = loop.run([Episode(task, spec, timed, context)], alone=True)
    finally:
        if timed is not policy:
            timed.close_counter()
    return outcome


def _no_env(task: TaskSpec) -> gym.Env:
    raise RuntimeError(f"run_episode was given no env for task {task.name}")
