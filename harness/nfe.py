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
(harness/batched.py) one `act_batch` call serves up to K episodes; the batched decoders
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
            for handle in (self._pre, self._post, *(h for hs in self._local.values() for h in hs)):
                if handle is not None:
                    handle.remove()
            self._pre = self._post = self._hooks = None
            self._local.clear()
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
        elif starts_pass(module):
            self.count += 1
            if threading.active_count() == 1 and self._open_pass(module, args, sys._getframe(1)):
                return
            # other threads may call modules meanwhile (or `module` takes no hooks of its
            # own, a TorchScript module): keep the process-wide hooks on, nest per thread
            if self._post is None:
                self._post = self._hooks.register_module_forward_hook(self._exit, always_call=True)
            self._depths[tid] = 1

    def _exit(self, module: Any, args: Any, output: Any) -> None:
        tid = threading.get_ident()
        depth = self._depths.get(tid, 0)
        if depth:
            self._depths[tid] = depth - 1

    def _open_pass(self, module: Any, args: Any, frame: Any) -> bool:
        """One thread: the process-wide hooks come off until `module` returns (False,
        and nothing changed, when `module` cannot take hooks of its own)."""
        if module not in self._local:  # kept for the rest of the policy call
            try:
                pre = module.register_forward_pre_hook(self._reentered)
            except RuntimeError:  # "not supported on ScriptModules"
                return False
            post = module.register_forward_hook(self._returned, always_call=True)
            self._local[module] = [pre, post]
        for handle in (self._pre, self._post):
            if handle is not None:
                handle.remove()
        self._pre = self._post = None
        self._pass_module, self._pass_args, self._pass_frame = module, args, frame
        self._pass_depth = 1
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
