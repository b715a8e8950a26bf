"""Calls into a policy made by the process that writes the run, held to --episode-timeout.

With a timeout the episodes and each worker's warm-up run in worker processes, which
the scheduler kills when they overrun (harness/backends/schedule.py). The writing process
still calls its own copy of each policy twice: `check_spaces` before anything is written,
and `close` when the run ends. A policy that never answers (a deadlocked GPU, a server
that accepts and never replies) must not hang the run there either, and a thread is the
only way to stop waiting for a call in this process: the call goes on in a daemon thread,
which the interpreter abandons at exit.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any


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
