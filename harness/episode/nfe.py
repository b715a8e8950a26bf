"""Counts model forward passes (NFE) from the outside, so a policy cannot under-report.

The harness counts only while it is inside a policy call:

    with counter.counting():
        batch = policy.act(observations)

(the same around `policy.reset(...)`). Inside, process-wide torch module hooks
(`torch.nn.modules.module.register_module_forward_pre_hook`, and
`register_module_forward_hook` where needed) see every `torch.nn.Module` call in the
process, so modules made lazily, built inside `act`, held only in a closure or nested
at any depth are counted like attributes of the policy. Outside the call no hook is
installed: nothing is counted there and other code runs at full speed.

What one forward pass is: an outermost entry (no pass already open) into a module that
(a) has parameters somewhere in its subtree, and
(b) is not a wrapper: a wrapper has no parameters of its own and all of its subtree's
    parameters sit under exactly one child (a module that loops over an inner model,
    `nn.Sequential(Linear, ReLU)`).
Entering a wrapper or a parameter-free module does not start a pass; the first
pass-starting module entered below it does, and every module entered until that one
returns belongs to its pass. So:
- a model (embeddings + blocks + head) counts 1 per call, however many sub-modules it
  calls;
- a wrapper whose `forward` calls its inner model N times counts N;
- a sub-module called directly (to sidestep the model's own `forward`) counts 1: it is
  outermost;
- a parameter-free module called on its own (`nn.Softmax()`) counts 0, and so does one
  whose weights are only buffers or plain tensors (e.g. a lone `PackedLinear`).
The decision (a)+(b) is cached per module in a `weakref.WeakKeyDictionary` (a module
built inside `act` is forgotten with it) once the module's subtree holds parameters;
children added to a module after its first counted entry do not change its decision.

Batches: a forward pass over a batch of K episodes' observations counts 1 for each of
those K episodes: NFE is per episode, never divided by the batch. With --batch-envs K
(harness/episode/loop.py) one `act_batch` call serves up to K episodes; the batched decoders
decode it in one pass per step, and each episode the call served is charged every pass.

Limitations. A model whose `forward` is called as `model.forward(...)` (not
`model(...)`) runs no hook of its own, so each pass-starting child it calls counts as a
pass: over-counting, never under-counting. `torch.compile`'s OptimizedModule starts a
pass itself (the modules inside run in the compiled graph, unseen), so a compiled model
counts 1 per call, as a TorchScript module does (it takes no hooks of its own, so its
passes are counted the way threaded ones are, below); with other Python threads alive,
torch.compile would trace the process-wide hooks into its graph. Torch is never
imported here (`sys.modules` is read when a call starts): the one call in which a policy
first imports torch is not counted; every later call is. The policies shipped here
load torch when they are built.

Cost: between passes one pre-hook sees each module entry. When a pass starts and this
is the only Python thread, the process-wide hook comes off until the pass's module
returns (hooks on that module alone see it return, and count it calling itself), so
the modules inside the pass run torch's hook-free path. Measured on the shipped
~0.9M-parameter MT10 model (46 module calls per pass, batch 1, one CPU thread): about
12 us of hook work per pass (its modules at width 8, where compute noise is small);
20-55 us (1.5-4%) of a ~1.4 ms pass timed directly on a loaded 2-core CPU, where
compute varies more than that. A hook call on every module (the previous counter, or
process-wide hooks left on) cost 75-135 us per pass. With other Python threads alive,
a pass keeps the process-wide hooks on and nests per thread, so no thread's module
calls go unseen.

Counted work (harness/episode/work.py says what is counted and why). The same hooks count how
big each pass was: FLOPs of the matrix products of the counted module kinds (nn.Linear,
PackedLinear, nn.Conv*, and attention through the parameter-free `Attention` module of
policies/dvla/model.py, the hook point that shows the hooks the query and key shapes),
and per pass the query, key/value and cached key/value positions of its attention. All
are read from the shapes of the tensors a module is called with, never from anything the
policy reports. Between passes, and during threaded passes, the process-wide pre-hook
sees every counted module and counts it. A single-thread pass takes that hook off, so
its module's counted modules (found once per policy call, so a layer swapped between
calls is counted as what it is now) get their `forward` wrapped for the rest of the
call: the wrapper counts while a single-thread pass is open and is removed with the
other hooks when the call ends, so nothing runs wrapped outside counting. A wrapper,
not a forward pre-hook: a pre-hook sends each call through torch's slow hook path
(~5 us a call; 23 counted calls per MT10 pass made the counter 4x dearer), a wrapper
costs one Python call. A pass module that holds parameters in a kind whose products
are not counted, or a compiled module (its modules run in a graph, unseen, and are
left untouched), leaves the call's FLOPs not measured (`take_work()` gives None), never
an under-count. Limitation: in a single-thread pass, a counted module outside the pass
module's subtree (held in a closure, called from its forward) is not wrapped, so its
work is not seen; the shipped models hold all their modules. Measured
(benchmarks/counter_overhead.py, thread CPU time, MT10's shape, 8 passes a call, on a
2-core EPYC at load 8-12, where every figure is ~4x an idle machine's): the counter
added 118-141 us per pass at width 8 (NFE alone, before counted work: 47-50 us) and
150-180 us per 1.3-1.4 ms pass at the shipped width 128 (NFE alone: 85-93 us).

Only one counter counts at a time (the runner interleaves policies one call at a time,
so each counter sees only its own policy's calls); entering `counting()` while another
counter is counting raises RuntimeError. The hooks are removed when the call ends,
by an exception too, and an exception inside a pass leaves no open pass behind, so the
counter stays correct for the next call.
"""

from __future__ import annotations

import sys
import threading
import weakref
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from harness.episode.work import (
    ATTENTION,
    LINEAR,
    MULTIHEAD,
    NO_WORK,
    Work,
    attention_work,
    cost_of,
    in_reach,
    unseen_kind,
)

_starts_pass_cache: weakref.WeakKeyDictionary[Any, bool] = weakref.WeakKeyDictionary()
_counting: NFECounter | None = None  # the counter inside counting(), if any
_lock = threading.Lock()


def _has_parameters(module: Any, recurse: bool = True) -> bool:
    return next(module.parameters(recurse=recurse), None) is not None


def _is_compiled(module: Any) -> bool:
    """`torch.compile(model)`'s OptimizedModule: the modules inside run in a compiled
    graph, unseen, so its own call is the pass."""
    cls = type(module)
    return cls.__name__ == "OptimizedModule" and cls.__module__.startswith("torch._dynamo")


def starts_pass(module: Any) -> bool:
    """Does an outermost entry into `module` start a forward pass (see the module doc)?"""
    cached = _starts_pass_cache.get(module)
    if cached is not None:
        return cached
    if not _has_parameters(module):
        return False  # not cached: parameters may still be added (a lazily built model)
    if _has_parameters(module, recurse=False) or _is_compiled(module):
        decision = True
    else:
        holders = sum(_has_parameters(child) for child in module.children())
        decision = holders != 1  # exactly one child holds them all: a wrapper
    _starts_pass_cache[module] = decision
    return decision


def work_plan(module: Any) -> tuple[bool, list[Any]]:
    """For a pass-starting module: can its passes' FLOPs be measured (no module in its
    subtree holds parameters in a kind whose products are not counted), and its counted
    modules below itself, which a single-thread pass wraps. Made afresh in each policy
    call (NFECounter keeps it for the call), so a layer swapped since the last call (a
    linear prepacked after a first pass) is counted as what it is now."""
    below = list(module.modules())[1:]
    if any(_is_compiled(m) for m in (module, *below)):
        return False, []  # its modules run in a compiled graph, unseen (and left untouched)
    return not any(map(unseen_kind, (module, *below))), [m for m in below if cost_of(m) is not None]


class _Counted:
    """A counted module's `forward`, wrapped for one policy call: counts the call's work
    while a single-thread pass is open (and the module is not that pass's own module,
    which the process-wide hook counted), then runs the forward it replaced. A wrapper
    costs a Python call; a forward pre-hook would send every call through torch's slow
    hook path, ~5 us a call (4x the NFE counter's own cost on the shipped models)."""

    def __init__(self, counter: NFECounter, module: Any):
        self.module = weakref.ref(module)
        self.own = module.__dict__.get("forward")  # an instance's own forward, kept as it was
        inner, cost = module.forward, cost_of(module)
        if cost is LINEAR:  # most counted calls: the count inlined, no call of its own
            per_element = 2 * module.out_features

            def forward(*args: Any, **kwargs: Any) -> Any:
                opened = counter._pass_module
                if opened is not None and opened is not module:
                    if args:
                        counter._flops += per_element * args[0].numel()
                    elif "input" in kwargs:
                        counter._flops += per_element * kwargs["input"].numel()
                    else:  # no input in reach
                        counter._flops_measured = False
                return inner(*args, **kwargs)
        else:

            def forward(*args: Any, **kwargs: Any) -> Any:
                opened = counter._pass_module
                if opened is not None and opened is not module:
                    counter._count(module, in_reach(cost, args, kwargs), cost, counter._pass_tid)
                return inner(*args, **kwargs)

        module.__dict__["forward"] = forward

    def remove(self) -> None:
        module = self.module()
        if module is None:
            return
        if self.own is None:
            module.__dict__.pop("forward", None)
        else:
            module.__dict__["forward"] = self.own


class NFECounter:
    """Counts forward passes made inside `counting()`; `take()` reads and clears them.

    `policy` is accepted for callers that name what is counted; the hooks do not need
    it (they see every module call in the process while counting).
    """

    def __init__(self, policy: Any = None):
        self.policy = policy
        self.count = 0
        self._nesting = 0  # counting() entered (re-entry by the same counter nests)
        self._closed = False
        self._hooks: Any = None  # torch.nn.modules.module while counting with torch loaded
        self._pre: Any = None  # handle of the process-wide pre-hook, installed between passes
        self._post: Any = None  # ... and of the post-hook, once a pass ran beside other threads
        self._depths: dict[int, int] = {}  # threaded passes: per thread, modules entered
        self._pass_module: Any = None  # the open single-thread pass's module
        self._pass_args: Any = None  # the arguments of the call that opened it
        self._pass_frame: Any = None  # and the frame of torch's _call_impl that runs its hooks
        self._pass_depth = 0  # entries of that module (a module may call itself)
        self._local: weakref.WeakKeyDictionary[Any, list[Any]] = weakref.WeakKeyDictionary()
        # Counted work (harness/episode/work.py), cleared by take_work():
        self._leaf_hooks: weakref.WeakKeyDictionary[Any, Any] = weakref.WeakKeyDictionary()
        self._plans: weakref.WeakKeyDictionary[Any, tuple[bool, list[Any]]] = weakref.WeakKeyDictionary()
        self._flops = 0
        self._flops_measured = True
        self._work_passes = 0  # passes since take_work()
        self._attended_passes = 0  # ... of which showed an attention call
        self._tokens = [0, 0, 0]  # query, KV, cached KV positions of the closed passes
        self._open_tokens: dict[int, list[int]] = {}  # per thread: its open pass's largest call
        self._pass_tid = 0  # the thread of the open single-thread pass

    @property
    def active(self) -> bool:
        """Is the harness inside a policy call counted by this counter?"""
        return self._nesting > 0

    @contextmanager
    def counting(self) -> Iterator[NFECounter]:
        """Count the forward passes made inside this block (one policy call)."""
        self._start()
        try:
            yield self
        finally:
            self._stop()

    def _start(self) -> None:
        global _counting
        if self._closed:
            raise RuntimeError("this NFECounter is closed")
        if self._nesting:
            self._nesting += 1
            return
        with _lock:
            if _counting is not None:
                raise RuntimeError("another NFECounter is counting; only one can count at a time")
            _counting, self._nesting = self, 1
            torch = sys.modules.get("torch")  # no module can run before torch is loaded
            if torch is not None:
                self._hooks = torch.nn.modules.module
                self._pre = self._hooks.register_module_forward_pre_hook(self._enter)

    def _stop(self) -> None:
        global _counting
        self._nesting -= 1
        if self._nesting:
            return
        with _lock:
            hooks = (*(h for hs in self._local.values() for h in hs), *self._leaf_hooks.values())
            for handle in (self._pre, self._post, *hooks):
                if handle is not None:
                    handle.remove()
            self._pre = self._post = self._hooks = None
            self._local.clear()
            self._leaf_hooks.clear()
            self._plans.clear()
            for tid in list(self._open_tokens):  # no pass outlives the policy call
                self._close_tokens(tid)
            self._pass_module = self._pass_args = self._pass_frame = None  # an exception leaves
            self._pass_depth = 0  # no open pass and no depth behind
            self._depths.clear()
            if _counting is self:
                _counting = None

    def _enter(self, module: Any, args: Any) -> None:
        """Process-wide pre-hook: installed between passes and during threaded passes."""
        tid = threading.get_ident()
        depth = self._depths.get(tid, 0)
        if depth:
            self._depths[tid] = depth + 1
            cost = cost_of(module)
            if cost is not None and cost is not MULTIHEAD:  # which _exit counts, keywords and all
                self._count(module, args, cost, tid)
        elif starts_pass(module):
            self.count += 1
            self._pass_started(module, tid)
            cost = cost_of(module)
            if cost is not None:  # a lone nn.Linear is a pass of its own
                self._count(module, args, cost, tid)
            if threading.active_count() == 1 and self._open_pass(module, args, sys._getframe(1), tid):
                return
            # other threads may call modules meanwhile (or `module` takes no hooks of its
            # own, a TorchScript module): keep the process-wide hooks on, nest per thread
            if self._post is None:
                self._post = self._hooks.register_module_forward_hook(
                    self._exit, with_kwargs=True, always_call=True
                )
            self._depths[tid] = 1
        else:
            cost = cost_of(module)
            if cost is not None:  # outside any pass (an attention or PackedLinear on its own)
                self._count(module, args, cost, tid)

    def _exit(self, module: Any, args: Any, kwargs: dict[str, Any], output: Any) -> None:
        tid = threading.get_ident()
        depth = self._depths.get(tid, 0)
        if depth:
            self._depths[tid] = depth - 1
            if depth > 1 and cost_of(module) is MULTIHEAD:  # inside a pass, not the pass's own module
                self._count(module, in_reach(MULTIHEAD, args, kwargs), MULTIHEAD, tid)

    def _open_pass(self, module: Any, args: Any, frame: Any, tid: int) -> bool:
        """One thread: the process-wide hooks come off until `module` returns (False,
        and nothing changed, when `module` cannot take hooks of its own)."""
        if module not in self._local:  # kept for the rest of the policy call
            try:
                pre = module.register_forward_pre_hook(self._reentered)
            except RuntimeError:  # "not supported on ScriptModules"
                return False
            post = module.register_forward_hook(self._returned, always_call=True)
            self._local[module] = [pre, post]
            for leaf in self._plan(module)[1]:  # the pass's counted modules count their work
                if leaf not in self._leaf_hooks:
                    self._leaf_hooks[leaf] = _Counted(self, leaf)
        for handle in (self._pre, self._post):
            if handle is not None:
                handle.remove()
        self._pre = self._post = None
        self._pass_module, self._pass_args, self._pass_frame = module, args, frame
        self._pass_depth = 1
        self._pass_tid = tid
        return True

    def _reentered(self, module: Any, args: Any) -> None:
        # The call that opened the pass may reach this hook too (from the same frame, with
        # the same args unless another pre-hook replaced them): not a re-entry. Taking it
        # for one would leave the pass open and the call's later passes uncounted, so a
        # re-entry must differ in both; missing one closes the pass early (over-counting).
        if (
            module is self._pass_module
            and args is not self._pass_args
            and sys._getframe(1) is not self._pass_frame
        ):
            self._pass_depth += 1

    def _returned(self, module: Any, args: Any, output: Any) -> None:
        if module is not self._pass_module:
            return
        self._pass_depth -= 1
        if not self._pass_depth:
            self._pass_module = self._pass_args = self._pass_frame = None
            if self._nesting and self._pre is None:
                self._pre = self._hooks.register_module_forward_pre_hook(self._enter)

    # ---- counted work ------------------------------------------------------------------

    def _count(self, module: Any, args: Any, cost: Any, tid: int) -> None:
        if cost is not ATTENTION:
            flops = cost(module, args)
            if flops is None:
                self._flops_measured = False
            else:
                self._flops += flops
            return
        work = attention_work(args)
        if work is None:
            self._flops_measured = False
            return
        self._flops += work[0]
        largest = self._open_tokens.get(tid)
        if largest is None:
            self._open_tokens[tid] = list(work[1:])
        elif work[2] > largest[1] or work[1] > largest[0]:
            largest[:] = map(max, largest, work[1:])

    def _pass_started(self, module: Any, tid: int) -> None:
        self._close_tokens(tid)  # this thread's previous pass has ended
        self._work_passes += 1
        if not self._plan(module)[0]:
            self._flops_measured = False

    def _plan(self, module: Any) -> tuple[bool, list[Any]]:
        plan = self._plans.get(module)
        if plan is None:
            plan = self._plans[module] = work_plan(module)
        return plan

    def _close_tokens(self, tid: int) -> None:
        largest = self._open_tokens.pop(tid, None)
        if largest is not None:
            self._attended_passes += 1
            self._tokens = [a + b for a, b in zip(self._tokens, largest, strict=True)]

    def take_work(self) -> Work:
        """Counted work since the last call, cleared (harness/episode/work.py says what is counted;
        a None field is not measured)."""
        for tid in list(self._open_tokens):
            self._close_tokens(tid)
        if not (self._work_passes or self._attended_passes or self._flops) and self._flops_measured:
            return NO_WORK  # nothing ran (a scripted policy's call): one shared zero
        if self._work_passes and not self._attended_passes:
            tokens: tuple[int | None, ...] = (None, None, None)
        else:
            tokens = tuple(self._tokens)
        work = Work(self._flops if self._flops_measured else None, *tokens)
        self._flops, self._flops_measured, self._tokens = 0, True, [0, 0, 0]
        self._work_passes = self._attended_passes = 0
        return work

    def take(self) -> int:
        """Forward passes since the last call, cleared."""
        count, self.count = self.count, 0
        return count

    def close(self) -> None:
        """Remove the hooks if they are installed; the counter counts nothing after this."""
        if self._nesting:
            self._nesting = 1
            self._stop()
        self._closed = True
