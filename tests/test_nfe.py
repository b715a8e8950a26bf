"""NFE is counted by the harness's hooks inside each policy call, never reported."""

from __future__ import annotations

import subprocess
import sys
import threading
import warnings
from concurrent.futures import ThreadPoolExecutor
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from adapters.base import EpisodeSpec
from harness.episode.nfe import NFECounter
from policies.base import ChunkBatch
from tests.fakes import CountdownEnv, context, run_one


class TinyModel(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.embed = torch.nn.Linear(2, 8)
        self.block = torch.nn.Sequential(torch.nn.Linear(8, 8), torch.nn.ReLU())
        self.head = torch.nn.Linear(8, 2)

    def forward(self, x):
        return self.head(self.block(self.embed(x)))


class Refine(torch.nn.Module):
    """A wrapper: no parameters of its own, one inner model called `times` times."""

    def __init__(self, model, times):
        super().__init__()
        self.model, self.times = model, times

    def forward(self, x):
        for _ in range(self.times):
            x = self.model(x)
        return x


def _chunk():
    return ChunkBatch(actions=np.zeros((1, 4, 2)), action_tokens=8)


class RefiningPolicy:
    """Runs `passes` forward passes per chunk; may also call a sub-module directly."""

    def __init__(self, passes: int, sneaky: bool = False, hide_in_list: bool = False):
        model = TinyModel()
        self.models = [model] if hide_in_list else None
        self.model = None if hide_in_list else model
        self.passes, self.sneaky = passes, sneaky
        self.claimed_nfe = 0  # a policy's own report is never read

    def _model(self) -> TinyModel:
        return self.models[0] if self.models else self.model

    def reset(self, episodes):
        pass

    def act(self, observations):
        x = torch.zeros(1, 2)
        with torch.inference_mode():
            for _ in range(self.passes):
                x = self._model()(x)
            if self.sneaky:  # skips the model's forward, still a forward pass
                self._model().block(torch.zeros(1, 8))
        return _chunk()


class CallPolicy:
    """Each chunk calls `call()` (whatever it hides), `calls` times."""

    def __init__(self, call, calls=1):
        self.call, self.calls = call, calls

    def reset(self, episodes):
        pass

    def act(self, observations):
        with torch.inference_mode():
            for _ in range(self.calls):
                self.call()
        return _chunk()


def _episode(policy, succeed_at=8, env=None, counter=None):
    counter = counter or NFECounter(policy)
    env = env or CountdownEnv(succeed_at)
    out = run_one(env, policy, context(), EpisodeSpec(0), counter=counter)
    counter.close()
    return out


def test_counts_forward_passes_per_chunk():
    out = _episode(RefiningPolicy(passes=3))
    assert out.chunks == 2
    assert out.nfe_total == 6  # nested sub-module calls inside one forward count once


def test_direct_submodule_calls_are_counted():
    out = _episode(RefiningPolicy(passes=2, sneaky=True))
    assert out.nfe_total == 2 * (2 + 1)


def test_modules_in_containers_are_counted():
    assert _episode(RefiningPolicy(passes=1, hide_in_list=True)).nfe_total == 2


def test_policies_without_modules_count_zero_and_never_import_torch():
    class NoModel(RefiningPolicy):
        def act(self, observations):
            return ChunkBatch(actions=np.zeros((1, 4, 2)))

    policy = NoModel(passes=0)
    policy.model = None
    assert _episode(policy).nfe_total == 0
    script = (
        "import sys, numpy as np\n"
        "from adapters.base import EpisodeSpec\n"
        "from harness.episode.loop import run_episode\n"
        "from policies.base import ChunkBatch\n"
        "from tests.fakes import CountdownEnv, context\n"
        "class P:\n"
        "    def reset(self, episodes): pass\n"
        "    def act(self, obs): return ChunkBatch(actions=np.zeros((1, 4, 2)))\n"
        "out = run_episode(CountdownEnv(8), P(), context(), EpisodeSpec(0))\n"
        "assert out.chunks == 2 and out.nfe_total == 0, out\n"
        "assert 'torch' not in sys.modules\n"
    )
    subprocess.run([sys.executable, "-c", script], check=True)


def test_counter_counts_only_inside_counting_and_is_removable():
    policy = RefiningPolicy(passes=1)
    counter = NFECounter(policy)
    x = torch.zeros(1, 2)
    policy.model(x)  # outside a policy call: not counted
    assert counter.take() == 0
    with counter.counting():
        assert counter.active
        policy.model(x)
        policy.model(x)
    assert not counter.active and counter.take() == 2 and counter.take() == 0
    counter.close()
    with pytest.raises(RuntimeError, match="closed"), counter.counting():
        pass


def test_a_model_built_inside_act_is_counted():
    out = _episode(CallPolicy(lambda: TinyModel()(torch.zeros(1, 2)), calls=2))
    assert out.chunks == 2 and out.nfe_total == 4


def test_a_model_held_only_in_a_closure_is_counted():
    def make_call():
        model = TinyModel()  # reachable only through the closure's cell
        return lambda: model(torch.zeros(1, 2))

    policy = CallPolicy(make_call(), calls=3)
    assert _episode(policy).nfe_total == 6


def test_a_model_nested_deeper_than_the_old_scan_is_counted():
    policy = RefiningPolicy(passes=0)
    deep = SimpleNamespace(a=SimpleNamespace(b=SimpleNamespace(c=SimpleNamespace(d=TinyModel()))))
    policy.holder = SimpleNamespace(deep=deep)  # 6 attributes below the policy
    policy.act = lambda observations: (deep.a.b.c.d(torch.zeros(1, 2)), _chunk())[1]
    assert _episode(policy).nfe_total == 2


def test_a_wrapper_counts_each_pass_of_the_model_it_wraps():
    model = TinyModel()
    policy = CallPolicy(None)
    policy.wrapper = Refine(model, times=3)
    policy.call = lambda: policy.wrapper(torch.zeros(1, 2))
    out = _episode(policy)
    assert out.chunks == 2 and out.nfe_total == 2 * 3
    # a wrapper of a wrapper is still a wrapper; the model itself still counts once
    twice = Refine(Refine(model, times=3), times=2)
    assert _episode(CallPolicy(lambda: twice(torch.zeros(1, 2)))).nfe_total == 2 * 6
    assert _episode(CallPolicy(lambda: model(torch.zeros(1, 2)))).nfe_total == 2


def test_a_parameter_free_module_counts_zero():
    policy = CallPolicy(None, calls=2)
    policy.softmax = torch.nn.Softmax(dim=-1)
    policy.call = lambda: policy.softmax(torch.zeros(1, 4))
    assert _episode(policy).nfe_total == 0


class ModelInStep(CountdownEnv):
    """An env whose step runs a model (another policy's, or a learned reward)."""

    def __init__(self, succeed_at, step):
        super().__init__(succeed_at)
        self.on_step = step

    def step(self, action):
        self.on_step()
        return super().step(action)


def test_passes_outside_the_policy_call_are_not_counted():
    policy = RefiningPolicy(passes=1)
    x = torch.zeros(1, 2)
    # the policy's own model, run by the env between calls: not the policy's passes
    out = _episode(policy, env=ModelInStep(8, lambda: policy.model(x)))
    assert out.steps == 8 and out.nfe_total == 2
    # another policy sharing the model, counted by its own counter inside env.step
    other = RefiningPolicy(passes=5)
    other.model = policy.model
    other_counter = NFECounter(other)

    def other_call():
        with other_counter.counting():
            other.act([None])

    out = _episode(policy, env=ModelInStep(8, other_call))
    assert out.nfe_total == 2 and other_counter.take() == 8 * 5
    # and only one counter counts at a time
    mine = NFECounter(policy)
    with mine.counting(), pytest.raises(RuntimeError, match="only one"), other_counter.counting():
        pass


class Flaky(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.inner = TinyModel()
        self.extra = torch.nn.Linear(2, 2)
        self.fail = True

    def forward(self, x):
        x = self.extra(self.inner(x))
        if self.fail:
            raise RuntimeError("numerical trouble")
        return x


def test_an_exception_inside_a_pass_leaves_the_counter_correct():
    x = torch.zeros(1, 2)

    class Policy(CallPolicy):
        def act(self, observations):
            self.chunk = getattr(self, "chunk", 0) + 1
            self.model(x)
            try:
                self.flaky(x)  # raises mid-pass, the policy carries on
            except RuntimeError:
                pass
            self.model(x)
            if self.chunk == 2 and self.crash:
                self.flaky(x)  # the episode ends here
            return _chunk()

    policy = Policy(None)
    policy.model, policy.flaky = TinyModel(), Flaky()
    policy.crash = True
    counter = NFECounter(policy)
    out = _episode(policy, counter=counter)
    assert out.failure_reason == "RuntimeError: numerical trouble"
    assert out.chunks == 1 and out.nfe_total == 3 + 3 + 1
    assert not torch.nn.modules.module._global_forward_pre_hooks  # nothing left installed
    assert not torch.nn.modules.module._global_forward_hooks
    policy.chunk, policy.crash = 0, False
    counter = NFECounter(policy)
    out = _episode(policy, counter=counter)
    assert out.failure_reason is None and out.nfe_total == 2 * 3


def test_passes_in_several_threads_each_count():
    barrier = threading.Barrier(2)

    class Waits(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.a, self.b = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)

        def forward(self, x):
            x = self.a(x)
            barrier.wait(timeout=10)  # both threads inside a pass at once
            return self.b(x)

    policy = CallPolicy(None)
    policy.model = Waits()
    pool = ThreadPoolExecutor(2)
    try:
        policy.call = lambda: list(pool.map(lambda _: policy.model(torch.zeros(1, 2)), range(2)))
        assert _episode(policy).nfe_total == 2 * 2
    finally:
        pool.shutdown()


def test_a_module_calling_itself_is_one_pass_run_without_process_wide_hooks():
    class Recursive(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.lin, self.out = torch.nn.Linear(2, 2), torch.nn.Linear(2, 2)

        def forward(self, x, depth=2):
            seen.append(len(torch.nn.modules.module._global_forward_pre_hooks))
            x = self.lin(x)
            return self.out(x) if depth == 0 else self(x, depth - 1)

    seen: list[int] = []
    model = Recursive()
    counter = NFECounter()
    with counter.counting():
        model(torch.zeros(1, 2))
        model.lin(torch.zeros(1, 2))  # a pass closes when its outermost call returns
    assert counter.take() == 2
    # a pre-hook of the model's own that replaces its arguments changes nothing
    model.register_forward_pre_hook(lambda module, args: (args[0] + 1, *args[1:]))
    with counter.counting():
        for _ in range(3):
            model(torch.zeros(1, 2))
    assert counter.take() == 3
    if threading.active_count() == 1:  # one thread: no process-wide hook inside the pass
        assert seen == [0] * 12


def test_scripted_and_compiled_models_count_once_per_call():
    x = torch.zeros(1, 2)
    policy = CallPolicy(None, calls=2)
    policy.call = lambda: (policy.scripted(x), policy.compiled(x))
    with warnings.catch_warnings():  # jit.script is deprecated; compile warns about global hooks
        warnings.simplefilter("ignore")
        policy.scripted = torch.jit.script(TinyModel())  # takes no hooks of its own
        policy.compiled = torch.compile(TinyModel(), backend="eager")  # its modules run unseen
        out = _episode(policy)
    assert out.failure_reason is None and out.nfe_total == 2 * 2 * 2
    assert out.work.flops is None  # what runs unseen has no counted work: not measured, not 0
