"""The shared policy server's dynamic batching (harness/serving/coalesce.py): which concurrent
calls share one act_batch call, and what each is told about it."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from harness.serving.coalesce import Coalescer
from policies.base import ChunkBatch

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes


class Recorder:
    """A batch policy that answers row i with its observation's value, records each
    call's size, and counts one forward pass per call."""

    def __init__(self, delay_s: float = 0.0):
        self.sizes: list[int] = []
        self.delay_s = delay_s

    def act_batch(self, contexts, observations) -> ChunkBatch:
        time.sleep(self.delay_s)
        self.sizes.append(len(observations))
        actions = np.array([[[float(o)] * 2] for o in observations])  # (rows, 1, 2)
        return ChunkBatch(actions=actions, action_tokens=4 * len(observations))

    def call(self, fn):
        start = time.perf_counter()
        return fn(), 3, time.perf_counter() - start  # 3 passes a call


def _submit_together(coalescer: Coalescer, groups: list[list[int]]) -> list:
    results: list = [None] * len(groups)

    def one(i: int) -> None:
        results[i] = coalescer.submit([None] * len(groups[i]), groups[i], client=i)

    threads = [threading.Thread(target=one, args=(i,)) for i in range(len(groups))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=10)
    return results


def test_concurrent_clients_share_one_call_and_each_gets_its_rows_and_the_calls_passes():
    policy = Recorder()
    coalescer = Coalescer(policy.call, policy.act_batch, max_batch=8, wait_s=2.0)
    coalescer.seen = {0: time.perf_counter(), 1: time.perf_counter(), 2: time.perf_counter()}
    results = _submit_together(coalescer, [[1], [2], [3, 4]])
    assert policy.sizes == [4]  # three active clients, three requests: one call, no 2 s wait
    for request, rows in zip(results, [[1], [2], [3, 4]], strict=True):
        assert request.actions[:, 0, 0].tolist() == rows  # each its own rows, in order
        assert request.nfe == 3 and request.call_rows == 4  # every pass of the call counts for each
        assert request.action_tokens == 4 * len(rows)  # its rows' share of the tokens
        assert request.queue_time_s >= 0 and request.policy_time_s >= 0
    assert (coalescer.calls, coalescer.rows) == (1, 4)


def test_one_client_never_waits_and_a_call_stops_at_max_batch_or_the_wait():
    policy = Recorder()
    coalescer = Coalescer(policy.call, policy.act_batch, max_batch=2, wait_s=5.0)
    start = time.perf_counter()
    coalescer.submit([None], [7], client=0)
    assert time.perf_counter() - start < 1.0 and policy.sizes == [1]  # nobody else could send
    now = time.perf_counter()
    coalescer.seen |= {1: now, 2: now}  # three active clients, max_batch 2: a call of 2, then 1
    _submit_together(coalescer, [[1], [2], [3]])
    assert sorted(policy.sizes[1:]) == [1, 2]
    # a wait long enough that not waiting stays far below it on a busy CPU (tests run in parallel)
    waits = Coalescer(policy.call, policy.act_batch, max_batch=8, wait_s=0.5)
    waits.seen = {1: time.perf_counter()}  # another client asked lately: wait 500 ms for it
    start = time.perf_counter()
    waits.submit([None], [5], client=0)
    assert 0.4 < time.perf_counter() - start < 5.0 and policy.sizes[-1] == 1
    waits.seen = {1: time.perf_counter() - 10}  # ... but not one that went quiet (or only connected)
    start = time.perf_counter()
    waits.submit([None], [6], client=0)
    assert time.perf_counter() - start < 0.4


def test_a_clients_own_batch_is_never_split_and_an_error_reaches_every_request_of_the_call():
    policy = Recorder()
    coalescer = Coalescer(policy.call, policy.act_batch, max_batch=2, wait_s=0.5)
    request = coalescer.submit([None] * 5, [1, 2, 3, 4, 5])
    assert policy.sizes == [5] and request.actions.shape == (5, 1, 2)

    def broken(contexts, observations):
        raise RuntimeError("model on fire")

    failing = Coalescer(policy.call, broken, max_batch=4, wait_s=1.0)
    errors: list[str] = []

    def one(value: int) -> None:
        try:
            failing.submit([None], [value], client=value)
        except RuntimeError as exc:
            errors.append(str(exc))

    threads = [threading.Thread(target=one, args=(v,)) for v in (1, 2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=10)
    assert errors == ["model on fire", "model on fire"]
    failing.act_batch = policy.act_batch  # the model mended: the same policy thread serves on
    failing.gone(2)
    assert failing.submit([None], [9]).actions[0, 0, 0] == 9.0


def test_serve_refuses_batching_a_policy_that_cannot(cli):
    pytest.importorskip("websockets")
    pytest.importorskip("metaworld")
    code, _, err = cli(
        "serve", "--policy", "scripted", "--suite", "metaworld/mt1/reach-v3", "--max-batch", "4"
    )
    assert code == 2 and "cannot decode a batch" in err and "--max-batch 1" in err
    code, _, err = cli("serve", "--policy", "random", "--suite", "metaworld/mt1/reach-v3", "--max-batch", "0")
    assert code == 2 and "--max-batch must be at least 1" in err
