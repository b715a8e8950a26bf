"""Dynamic batching for `dvla-harness serve --max-batch B`: one policy, many clients.

The layout peers use on a machine with a GPU and many simulator processes: one policy
process owns the model and serves every env worker (`run --workers N --policy
remote:url=...`), and the calls that arrive together share one `act_batch` call, so the
GPU decodes N episodes in one forward pass per step instead of N passes.

The rule: the first waiting request opens a call; the policy thread then takes more
requests until the call holds `max_batch` observations, or `wait_s` has passed since the
call opened, or every active client has a request in it (a client sends one request at a
time, so none can come: with one client nothing ever waits). Active: it asked for a
chunk within the last `ACTIVE_S` seconds; a connection that only checked the server's
metadata (the parent process of `run --workers N`) or sits between runs is not waited
for. A request is never split: a client's own batch (`--batch-envs K`) goes into one
call whole, even past `max_batch`. Requests from different tasks and episodes share a call: `act_batch` takes
each row's own episode context (policies/base.py).

What each request is told (and its row charged): every forward pass of the call (a pass
over K episodes counts 1 for each, as `--batch-envs` defines it), the call's whole
policy time (each client waited through all of it), the time it waited in the queue
before its call started, its rows' share of the call's action tokens, and the call's
size. The remote client counts both times as the server's, so `transport_time_s` stays
the transport alone.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from harness.episode.work import NOT_MEASURED, Work
from policies.base import EpisodeContext

ACTIVE_S = 2.0  # a client that asked within this long is expected to ask again soon


def checked_actions(actions: Any, rows: int) -> np.ndarray:
    """A served policy's chunks as float32 (rows, chunk, action_dim), or why not."""
    out = np.asarray(actions, dtype=np.float32)
    if out.ndim != 3 or out.shape[0] != rows or not np.isfinite(out).all():
        raise RuntimeError(f"the served policy returned actions of shape {out.shape} (or not finite)")
    return out


@dataclass
class Request:
    """One client call waiting for its rows' chunks."""

    contexts: Sequence[EpisodeContext]
    observations: Sequence[Any]
    submitted: float = field(default_factory=time.perf_counter)
    done: threading.Event = field(default_factory=threading.Event)
    actions: np.ndarray | None = None  # (rows, chunk, action_dim)
    nfe: int = 0
    policy_time_s: float = 0.0
    queue_time_s: float = 0.0
    action_tokens: int = 0
    work: Work = field(default_factory=Work)  # its rows' share of the call's counted work
    call_rows: int = 0
    error: BaseException | None = None


class Coalescer:
    """The policy thread of a serving process and its queue. `call(fn)` runs one policy
    call under the NFE hooks and returns (result, passes, seconds): `Served.call`."""

    def __init__(self, call: Any, act_batch: Any, max_batch: int, wait_s: float):
        self.call, self.act_batch = call, act_batch
        self.max_batch, self.wait_s = max_batch, wait_s
        self.queue: queue.Queue[Request] = queue.Queue()
        self.seen: dict[int, float] = {}  # client id -> when it last asked for a chunk
        self.calls = self.rows = 0  # what it decoded: the mean batch is rows / calls
        self._lock = threading.Lock()
        threading.Thread(target=self._serve, name="dvla-policy", daemon=True).start()

    def gone(self, client: int) -> None:
        """A client disconnected: no request will come from it."""
        with self._lock:
            self.seen.pop(client, None)

    def active(self) -> int:
        """Clients that asked for a chunk within ACTIVE_S: how many requests could come."""
        now = time.perf_counter()
        with self._lock:
            return sum(now - t < ACTIVE_S for t in self.seen.values())

    def submit(
        self, contexts: Sequence[EpisodeContext], observations: Sequence[Any], client: int = 0
    ) -> Request:
        """Queue a client's rows and wait for their chunks (raises what the call raised)."""
        with self._lock:
            self.seen[client] = time.perf_counter()
        request = Request(contexts, observations)
        self.queue.put(request)
        request.done.wait()
        if request.error is not None:
            raise request.error
        return request

    def _gather(self, first: Request) -> list[Request]:
        taken, rows = [first], len(first.observations)
        opened, clients = time.perf_counter(), self.active()
        while rows < self.max_batch and len(taken) < clients:
            left = self.wait_s - (time.perf_counter() - opened)
            if left <= 0:
                break
            try:
                request = self.queue.get(timeout=left)
            except queue.Empty:
                break
            taken.append(request)
            rows += len(request.observations)
        return taken

    def _serve(self) -> None:
        while True:
            taken = self._gather(self.queue.get())
            contexts = [c for r in taken for c in r.contexts]
            observations = [o for r in taken for o in r.observations]
            started = time.perf_counter()
            try:
                batch, passes, seconds, *counted = self.call(
                    lambda c=contexts, o=observations: self.act_batch(c, o)
                )
                actions = checked_actions(batch.actions, len(observations))
            except Exception as exc:  # every request of the call gets the error
                for request in taken:
                    request.error = exc
                    request.done.set()
                continue
            self.calls, self.rows = self.calls + 1, self.rows + len(observations)
            total = int(batch.action_tokens)
            per_row = (counted[0] if counted else NOT_MEASURED).split(len(observations))
            row = 0
            for request in taken:
                k = len(request.observations)
                request.work = sum(per_row[row : row + k], Work())
                request.actions = actions[row : row + k]
                request.nfe, request.policy_time_s = passes, seconds
                request.queue_time_s = max(0.0, started - request.submitted)
                request.action_tokens = round(total * k / len(observations))
                request.call_rows = len(observations)
                row += k
                request.done.set()
