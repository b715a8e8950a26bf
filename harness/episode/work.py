"""Counted work: what the forward passes counted by harness/episode/nfe.py computed, by shape.

NFE says how many passes a decoder ran; counted work says how big they were, so a
speedup (or a slowdown) can be explained and gated without a clock. Every figure is a
function of tensor shapes read by the NFE counter's hooks, identical on every machine,
under any load, at any torch thread count.

FLOPs are floating-point operations of matrix products, 2 per multiply-accumulate, the
convention of `torch.utils.flop_counter` (which counts the same products the same way):
- nn.Linear, and the oneDNN-prepacked PackedLinear (policies/dvla/kernels.py): 2 * rows *
  in_features * out_features (the bias add is not counted);
- nn.Conv1d/2d/3d: 2 * output elements * in_channels / groups * kernel elements;
- attention (the `Attention` module of policies/dvla/model.py, a parameter-free module
  around `F.scaled_dot_product_attention` that exists so these hooks see its shapes):
  2 * batch * heads * L * S * (E + Ev) for queries (B, heads, L, E) against keys (.., S, E)
  and values (.., S, Ev): the scores and the weighted sum, over every key position,
  masked or not (a masked kernel computes them too);
- nn.MultiheadAttention (LeRobot's ACT, among others): its four projections (2 * rows *
  in_features * embed_dim each for queries, keys and values, 2 * query rows * embed_dim^2
  for the output) and its attention as above, with E + Ev = 2 * embed_dim over all heads.
A counted module's tensors are read whether passed by position or by keyword (LeRobot's
ACT calls its decoder's cross-attention as `multihead_attn(query=..., key=..., value=...)`):
a single-thread pass wraps the module's `forward`, which sees both; beside other threads
(a server's connection threads) the process-wide pre-hook sees only positional arguments
(torch offers no keyword arguments to a process-wide pre-hook), so nn.MultiheadAttention is
counted there by the process-wide post-hook, which does see them (`with_kwargs`).
nn.MultiheadAttention gives FLOPs only: its query and key positions are not token figures
(those come from this project's `Attention` above), so a policy built on it has FLOPs
and null tokens.
Norms, embeddings (a lookup), activations, softmax and elementwise ops are not counted:
they are a small share of a pass and change with it. A module of another kind that
holds parameters of its own (a custom layer calling F.linear, nn.ConvTranspose1d)
could do any amount of work unseen: a pass of a model that contains one leaves the
policy call's FLOPs not measured (null), never an under-count presented as a count.

Tokens, per pass, from its attention calls (every layer of a transformer attends the
same positions, so a pass's figure is the largest of its calls, not their sum):
- query tokens: B * L, the positions the pass computes;
- KV tokens: B * S, the key/value positions they attend, cached or not;
- cached KV tokens: B * (S - L), the key positions the pass did not compute itself, read
  from a KV cache (in this project's self-attention a pass computes keys for exactly its
  query positions and attends them after the cached ones).
A pass in which no attention call was seen has no token figures; when a policy call ran
passes and none of them showed an attention call, its tokens are not measured (null).

What the count can miss: work done by functional calls on bare tensors (F.linear on a
weight held outside any module, a matmul in a policy's own code) is not seen, as such
calls are not passes either. The replay benchmark counts those too, at torch's
dispatcher (harness/episode/op_work.py), and the gate compares that count; on the
shipped models, which do all their products in the modules above, the two agree.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any

WIRE_KEY = "dvla/work"  # the reply key a dvla-harness server reports a call's work under


def _plus(a: int | None, b: int | None) -> int | None:
    """A sum that is not measured when either part is not."""
    return None if a is None or b is None else a + b


@dataclass(frozen=True)
class Work:
    """Counted work of some policy calls; None in a field: not measured."""

    flops: int | None = 0
    query_tokens: int | None = 0
    kv_tokens: int | None = 0
    kv_cached_tokens: int | None = 0

    def __add__(self, other: Work) -> Work:
        # field by field (not through dataclasses.fields): the loop adds a call's work per call
        return Work(
            _plus(self.flops, other.flops),
            _plus(self.query_tokens, other.query_tokens),
            _plus(self.kv_tokens, other.kv_tokens),
            _plus(self.kv_cached_tokens, other.kv_cached_tokens),
        )

    def _values(self) -> tuple[int | None, ...]:
        return tuple(getattr(self, f.name) for f in fields(self))

    def split(self, parts: int) -> list[Work]:
        """The work of one call split among the `parts` episodes it served: integers that
        differ by at most 1 and add up to each total (a batched pass's rows are the same
        shape, so each episode's share is its row's work)."""
        columns = [[None] * parts if v is None else shares(v, parts) for v in self._values()]
        return [Work(*row) for row in zip(*columns, strict=True)]

    def to_wire(self) -> dict[str, int | None]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_wire(cls, value: Any) -> Work:
        """A server's report; a reply without one (an openpi server) is not measured,
        and so is any field that is not a non-negative integer."""
        if not isinstance(value, dict):
            return NOT_MEASURED

        def number(name: str) -> int | None:
            v = value.get(name)
            ok = isinstance(v, int) and not isinstance(v, bool) and v >= 0
            return int(v) if ok else None

        return cls(*(number(f.name) for f in fields(cls)))


NOT_MEASURED = Work(None, None, None, None)
NO_WORK = Work()  # counted, and nothing: no pass ran


def shares(total: int, parts: int) -> list[int]:
    """`total` split into `parts` integers that differ by at most 1 and add up to it."""
    base, extra = divmod(total, parts)
    return [base + (i < extra) for i in range(parts)]


# ---- per module kind ----------------------------------------------------------------


def _linear(module: Any, args: tuple) -> int | None:
    if not args:  # called with keyword arguments only: the shape is not in reach
        return None
    return 2 * args[0].numel() * module.out_features


def _conv(module: Any, args: tuple) -> int | None:
    if not args:
        return None
    x = args[0]
    dims = len(module.kernel_size)
    spatial = x.shape[-dims:]
    padding = module.padding
    if isinstance(padding, str):  # "same" keeps the size, "valid" pads nothing
        out = list(spatial) if padding == "same" else None
        padding = (0,) * dims
    else:
        out = None
    if out is None:
        out = [
            (n + 2 * p - d * (k - 1) - 1) // s + 1
            for n, p, d, k, s in zip(
                spatial, padding, module.dilation, module.kernel_size, module.stride, strict=True
            )
        ]
    batch = x.shape[0] if x.dim() == dims + 2 else 1
    per_output = module.in_channels // module.groups * math.prod(module.kernel_size)
    return 2 * batch * module.out_channels * math.prod(out) * per_output


def _attention(module: Any, args: tuple) -> int | None:
    work = attention_work(args)
    return None if work is None else work[0]


def _multihead_attention(module: Any, args: tuple) -> int | None:
    """nn.MultiheadAttention called with query and key positionally (the value has the
    key's length and `vdim` features, so it need not be in reach)."""
    if len(args) < 2:
        return None
    query, key = args[0].shape, args[1].shape
    if len(query) == 2:  # unbatched (L, E)
        batch, length, keys = 1, query[0], key[0]
    elif module.batch_first:
        batch, length, keys = query[0], query[1], key[1]
    else:
        batch, length, keys = query[1], query[0], key[0]
    embed = module.embed_dim
    projections = batch * (length * embed * embed * 2 + keys * (module.kdim + module.vdim) * embed)
    return 2 * projections + 2 * batch * length * keys * 2 * embed


def attention_work(args: tuple) -> tuple[int, int, int, int] | None:
    """FLOPs, and query, KV and cached KV positions (summed over the batch rows) of one
    attention call; None when its tensors are not in reach (keyword arguments)."""
    if len(args) < 3:
        return None
    shape, keys, width_v = args[0].shape, args[1].shape[-2], args[2].shape[-1]
    length, width = shape[-2], shape[-1]
    dims = len(shape)
    rows = shape[0] if dims == 4 else math.prod(shape[:-3]) if dims > 4 else 1
    heads_rows = math.prod(shape[:-2])
    flops = 2 * heads_rows * length * keys * (width + width_v)
    return flops, rows * length, rows * keys, rows * max(keys - length, 0)


COUNTED: dict[tuple[str, str], Callable[[Any, tuple], int | None]] = {
    ("torch.nn.modules.linear", "Linear"): _linear,
    ("policies.dvla.kernels", "PackedLinear"): _linear,
    ("torch.nn.modules.conv", "Conv1d"): _conv,
    ("torch.nn.modules.conv", "Conv2d"): _conv,
    ("torch.nn.modules.conv", "Conv3d"): _conv,
    ("policies.dvla.model", "Attention"): _attention,
    ("torch.nn.modules.activation", "MultiheadAttention"): _multihead_attention,
}
ATTENTION, LINEAR, MULTIHEAD = _attention, _linear, _multihead_attention
# The names of each counted kind's leading parameters, for a call that passes them by keyword
KEYWORDS: dict[Callable[[Any, tuple], int | None], tuple[str, ...]] = {
    _linear: ("input",),
    _conv: ("input",),
    _multihead_attention: ("query", "key", "value"),
}


def in_reach(cost: Callable[[Any, tuple], int | None], args: tuple, kwargs: dict[str, Any]) -> tuple:
    """A call's leading arguments as one tuple, those it passed by keyword appended in
    their positional order, so a kind's count sees them either way."""
    if not kwargs:
        return args
    names, extra = KEYWORDS.get(cost, ()), []
    for name in names[len(args) :]:
        if name not in kwargs:
            break
        extra.append(kwargs[name])
    return (*args, *extra)


# Kinds that hold parameters but compute no matrix product: they do not make a pass's
# FLOPs unmeasurable.
NO_PRODUCTS = frozenset(
    {
        ("torch.nn.modules.normalization", "LayerNorm"),
        ("torch.nn.modules.normalization", "GroupNorm"),
        ("torch.nn.modules.normalization", "RMSNorm"),
        ("torch.nn.modules.batchnorm", "BatchNorm1d"),
        ("torch.nn.modules.batchnorm", "BatchNorm2d"),
        ("torch.nn.modules.batchnorm", "BatchNorm3d"),
        ("torch.nn.modules.sparse", "Embedding"),
        # nn.MultiheadAttention's out_proj: the attention module multiplies by its weight
        # itself (F.multi_head_attention_forward) and counts that product above
        ("torch.nn.modules.linear", "NonDynamicallyQuantizableLinear"),
    }
)
_costs: dict[type, Callable[[Any, tuple], int | None] | None] = {}


def cost_of(module: Any) -> Callable[[Any, tuple], int | None] | None:
    """The FLOP count of `module`'s kind, or None when it is not counted. By exact class
    (module and name), so a subclass that changes `forward` is not taken for its parent."""
    cls = type(module)
    try:
        return _costs[cls]
    except KeyError:
        cost = _costs[cls] = COUNTED.get((cls.__module__, cls.__qualname__))
        return cost


def unseen_kind(module: Any) -> bool:
    """Does `module` hold parameters of its own in a kind whose products are not counted?"""
    cls = type(module)
    plain = _plain.get(cls)
    if plain is None:
        plain = _plain[cls] = (
            cost_of(module) is None and (cls.__module__, cls.__qualname__) not in NO_PRODUCTS
        )
    return plain and any(p is not None for p in module._parameters.values())


_plain: dict[type, bool] = {}  # per class: neither counted nor free of products
