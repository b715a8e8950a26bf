"""A policy as the harness calls it: every call timed, its forward passes counted from outside.

`TimedPolicy` is the one place a policy is called from an episode. Each call is timed
with one monotonic clock and with a CPU clock (harness/episode/cpu_time.py: the CPU time
tells the policy's work from its wait for a core), and counted by the harness's hooks
(harness/episode/nfe.py), which are on only inside the call: NFE and counted work are
measured, never taken from the policy. What one call cost is a `Charge`, which the loop
shares among the episodes the call served (a batched call serves several).

A served policy (its model runs in another process, behind a policy server: the
`remote` policy of policies/remote.py) declares so with the capability `take_served()`:
what the server's own hooks counted for the calls since the last take, its own time,
and the time the client waited to connect again. Its passes and work are added to the
ones counted here, its own time tells transport from compute, and no CPU time is taken
(the client's CPU time is encoding and waiting, not the policy's work).

Calls the writing process makes outside episodes (`check_spaces` before anything is
written, `close` when the run ends) can be held to --episode-timeout: a policy that
never answers (a deadlocked GPU, a server that accepts and never replies) must not hang
the run there, and a thread is the only way to stop waiting for a call in this process;
the call goes on in a daemon thread, which the interpreter abandons at exit.
"""

from __future__ import annotations

import threading
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from harness.episode.cpu_time import cpu_clock
from harness.episode.nfe import NFECounter
from harness.episode.work import Work
from policies.base import ChunkBatch, EpisodeContext, Observation, Policy

clock = time.perf_counter


def _no_cpu() -> float:
    return 0.0


@dataclass
class ServedTotals:
    """What a served policy's server reported about the calls since the last take: its
    forward passes (None once a reply carried none), its own policy time, the client's
    wait to connect again (neither policy nor env time) and the passes' counted work."""

    nfe: int | None = 0
    server_time_s: float = 0.0
    connect_wait_s: float = 0.0
    work: Work = field(default_factory=Work)


def is_served(policy: object) -> bool:
    """Does `policy` declare that its model runs behind a server (`take_served`)?"""
    return callable(getattr(policy, "take_served", None))


@dataclass
class Charge:
    """What one policy call cost, to be charged to the episodes it served."""

    seconds: float = 0.0
    cpu_s: float = 0.0
    passes: int | None = 0  # None: a server that reports no passes
    work: Work = field(default_factory=Work)
    server_s: float = 0.0  # a served policy's own time within `seconds`
    connect_wait_s: float = 0.0

    def split(self, parts: int) -> list[Charge]:
        """Each of `parts` episodes' share: time, CPU time, server time and waits shared
        equally, the work in integers adding up to it, and every pass counted for each
        (NFE is per episode: a pass over K episodes is K episode-passes, never 1/K)."""
        if parts == 1:
            return [self]
        works = self.work.split(parts)
        return [
            Charge(
                self.seconds / parts,
                self.cpu_s / parts,
                self.passes,
                work,
                self.server_s / parts,
                self.connect_wait_s / parts,
            )
            for work in works
        ]


@dataclass
class Call:
    """What one policy call returned (or raised, with its traceback) and what it cost."""

    result: Any
    error: BaseException | None
    trace: str | None
    charge: Charge


class CallTimedOut(Exception):
    """The call did not return within its limit (it may still be running, abandoned)."""


def call_within(call: Callable[[], Any], seconds: float | None) -> Any:
    """`call()`, its result or its exception; CallTimedOut when `seconds` pass first.
    None: called here, unbounded (a run without --episode-timeout)."""
    if seconds is None:
        return call()
    outcome: dict[str, Any] = {}

    def target() -> None:
        try:
            outcome["value"] = call()
        except BaseException as exc:  # handed to the caller, raised there
            outcome["error"] = exc

    thread = threading.Thread(target=target, name="dvla-bounded-call", daemon=True)
    thread.start()
    thread.join(seconds)
    if thread.is_alive():
        raise CallTimedOut(f"no return within {seconds:g} s")
    if "error" in outcome:
        raise outcome["error"]
    return outcome.get("value")


class TimedPolicy:
    """One policy of a run in one process, with the NFE counter that counts its calls.

    `name`: the policy's registered name (a latency profile's key). Only one counter
    counts at a time (harness/episode/nfe.py), which the loop guarantees by calling one
    policy at a time."""

    def __init__(self, policy: Policy, name: str, counter: NFECounter | None = None):
        self.policy, self.name = policy, name
        self.counter = counter if counter is not None else NFECounter(policy)
        self.served = is_served(policy)
        self._cpu: Callable[[], float] = _no_cpu
        self.cpu_measured = False
        self.clock_cpu()

    def clock_cpu(self) -> None:
        """Choose the CPU clock for the coming episode: none for a served policy or one on
        a GPU; the thread's or the process's by torch's thread count (harness/episode/cpu_time.py)."""
        chosen = None if self.served else cpu_clock(self.policy)
        self._cpu, self.cpu_measured = chosen or _no_cpu, chosen is not None

    def reset(self, contexts: Sequence[EpisodeContext]) -> Call:
        return self._call(lambda: self.policy.reset(contexts))

    def act(self, observations: Sequence[Observation]) -> Call:
        return self._call(lambda: self.policy.act(observations))

    def act_batch(self, contexts: Sequence[EpisodeContext], observations: Sequence[Observation]) -> Call:
        return self._call(lambda: self.policy.act_batch(contexts, observations))  # type: ignore[attr-defined]

    def _call(self, fn: Callable[[], ChunkBatch | None]) -> Call:
        if self.served:  # what its server reported for calls outside an episode (a warm-up's)
            self.policy.take_served()  # type: ignore[attr-defined]
        cpu = self._cpu
        c, t = cpu(), clock()
        result = error = trace = None
        try:
            with self.counter.counting():
                result = fn()
        except KeyboardInterrupt:
            raise  # an interrupt (Ctrl-C, SIGTERM) stops the run; it is not the episode's failure
        except BaseException as exc:  # a policy's SystemExit too: that episode's failure row
            error, trace = exc, traceback.format_exc()
        seconds, cpu_s = clock() - t, cpu() - c
        return Call(result, error, trace, self._take(seconds, cpu_s))

    def _take(self, seconds: float = 0.0, cpu_s: float = 0.0) -> Charge:
        passes, work = self.counter.take(), self.counter.take_work()
        if not self.served:
            return Charge(seconds, cpu_s, passes, work)
        totals = self.policy.take_served()  # type: ignore[attr-defined]
        passes_served = None if totals.nfe is None else passes + totals.nfe
        return Charge(
            seconds, cpu_s, passes_served, work + totals.work, totals.server_time_s, totals.connect_wait_s
        )

    def close_counter(self) -> None:
        self.counter.close()


@dataclass(frozen=True)
class BoundedCalls:
    """The writing process's own calls into its policies, outside every episode, each held
    to `limit` seconds (--episode-timeout; None: unbounded)."""

    limit: float | None = None

    def check_spaces(self, policy: Policy, observation_space: Any, action_space: Any) -> None:
        """The policy's own check that it can act in these spaces (ValueError if not), if it
        has one; CallTimedOut past the limit."""
        check = getattr(policy, "check_spaces", None)
        if callable(check):
            call_within(lambda: check(observation_space, action_space), self.limit)

    def close(self, policy: Policy) -> None:
        """Let a policy that holds something open (a served policy's connection) let go; a
        close that does not return within the limit is abandoned, and one that fails must
        not hide the run's outcome."""
        close = getattr(policy, "close", None)
        if callable(close):
            try:
                call_within(close, self.limit)
            except Exception:
                pass
