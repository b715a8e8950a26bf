"""CPU time of the policy calls: what tells a policy's work from its wait for a core.

Wall-clock time inside a policy call is the policy's work plus whatever time the OS
gave its core to someone else. The CPU time over the same interval is the work alone,
so an episode whose policy wall time is well above its policy CPU time spent part of it
waiting: it was starved, and its speed figures say more about the machine's load than
about the policy. The episode loop (harness/episode/loop.py) sums both
over every policy call of an episode (`policy_time_s`, `policy_cpu_time_s`); the row's
`starved` column and the manifest's `starvation` count come from `is_starved`.

Which CPU clock: with torch at one intra-op thread (OMP_NUM_THREADS=1, `--threads 1`,
what CI and every baseline use) the whole forward pass runs in the calling thread, so
the thread's CPU time (`time.thread_time`) is the policy's work and nothing else's.
Otherwise the work may run on other threads (torch's intra-op pool, a BLAS pool), so
the process's CPU time (`time.process_time`) is taken: it also counts the process's
other threads during the call, which can only make an episode look less starved, never
more (a missed flag, not a false alarm).

Not judged (null CPU time, null `starved`): a remote policy (its work runs on the
server; the client's CPU time is encoding and waiting), and a policy decoding on a GPU
(its thread waits for kernels without using a core; that wait is the GPU's work).

The verdict is per episode, never per call: one call of a few milliseconds is at the
mercy of the clocks' resolution (thread CPU time is counted in scheduler ticks on some
systems) and of one context switch, while an episode's sum of calls is not. Episodes
whose policy wall time is under MIN_JUDGED_POLICY_TIME_S are not judged at all.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from typing import Any

# Policy wall time / policy CPU time above which an episode was starved. Measured on a
# 2-core machine (docs/ci-gate.md, "Starved episodes"; benchmarks/starvation.py): the
# smoke config's fast_dvla and bidirectional episodes at one torch thread read 1.00-1.03
# on a quiet machine and 1.24-4.18 (median 1.93) beside two busy loops.
STARVED_FACTOR = 1.25
# An episode whose policy calls took less wall time than this is not judged: too few
# scheduler time slices for the ratio to mean anything (a scripted expert's 2 ms).
MIN_JUDGED_POLICY_TIME_S = 0.05


def cpu_clock(policy: Any) -> Callable[[], float] | None:
    """The CPU clock that measures `policy`'s calls from this thread, or None when its
    CPU time here is not its work (a GPU policy; the caller rules out remote ones)."""
    device = getattr(policy, "device", None)
    if device is not None and str(device) != "cpu":
        return None
    torch = sys.modules.get("torch")
    if torch is not None and torch.get_num_threads() == 1:
        return time.thread_time
    return time.process_time


def is_starved(policy_time_s: float, policy_cpu_time_s: float | None) -> bool | None:
    """Whether an episode's policy waited for a core beyond STARVED_FACTOR; None when it
    cannot be judged (no CPU time measured, or too little policy time)."""
    if policy_cpu_time_s is None or policy_time_s < MIN_JUDGED_POLICY_TIME_S:
        return None
    return policy_time_s > STARVED_FACTOR * policy_cpu_time_s
