"""Counted work at torch's dispatcher: the FLOPs of every matrix product a policy call
runs, wherever in the policy's code it is called from.

The NFE counter's module hooks (harness/episode/nfe.py, harness/episode/work.py) see the
products of the counted module kinds (nn.Linear, convolutions, the `Attention` module)
and nothing else: a `torch.matmul` in a decoder's own loop, outside any module, is
invisible to them, and so is a product done through `F.linear` on a bare weight. Torch
routes every op through its dispatcher, so a `TorchDispatchMode` sees them all. The
mode here does what `torch.utils.flop_counter.FlopCounterMode` does, without its
per-module bookkeeping (a third of its cost, and process-wide module hooks beside the
NFE counter's): it decomposes composite ops (`matmul`, `linear`, `einsum`,
`scaled_dot_product_attention`) into the aten products they run (mm, addmm, bmm,
baddbmm, convolution, the attention kernels) and counts those by shape with torch's own
formulas, 2 FLOPs per multiply-accumulate: the same convention as the module hooks, so
on a model that does all its products in counted modules the two counts agree exactly
(tests/test_op_work.py checks every shipped decoder).

Torch's own table leaves out products that a CPU decoder can reach; they are added
here: the CPU attention kernel (`_scaled_dot_product_flash_attention_for_cpu`, what
`F.scaled_dot_product_attention` runs on a CPU), oneDNN's prepacked linear
(`mkldnn._linear_pointwise`, policies/dvla/kernels.py), matrix-vector and vector
products (`mv`, `addmv`, `dot`, `vdot`: `torch.matmul` on a 1-D operand), `addbmm` and
integer `_int_mm`.

What it cannot see: work outside torch (numpy, a C extension called directly), ops of
other libraries registered without a FLOP formula (a quantized engine's packed linear),
and elementwise ops, norms and softmax, which are not counted by either counter. It costs
a Python call per op, so it counts only untimed decodes (the replay benchmark's warm-up
pass, harness/bench.py), never the timed ones or an episode's.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any


def _attention(query: Any, key: Any, value: Any, *args: Any, **kwargs: Any) -> int:
    """2 * batch * heads * L * S * (E + Ev): scores and the weighted sum, over every key."""
    *rows, length, width = query.shape
    return 2 * math.prod(rows) * length * key.shape[-2] * (width + value.shape[-1])


def _linear_pointwise(x: Any, *args: Any, out_val: Any = None, **kwargs: Any) -> int:
    """oneDNN's prepacked linear: 2 * rows * in_features * out_features (the packed
    weight's layout is oneDNN's, so the sizes come from the input and the output)."""
    return 2 * x.numel() * out_val.shape[-1]


def _mv(matrix: Any, vector: Any, *args: Any, **kwargs: Any) -> int:
    return 2 * matrix.numel()


def _addmv(bias: Any, matrix: Any, vector: Any, *args: Any, **kwargs: Any) -> int:
    return 2 * matrix.numel()


def _dot(a: Any, b: Any, *args: Any, **kwargs: Any) -> int:
    return 2 * a.numel()


def _addbmm(bias: Any, a: Any, b: Any, *args: Any, **kwargs: Any) -> int:
    return 2 * a.numel() * b.shape[-1]


def _int_mm(a: Any, b: Any, *args: Any, **kwargs: Any) -> int:
    return 2 * a.numel() * b.shape[-1]


_EXTRA = {
    ("aten", "_scaled_dot_product_flash_attention_for_cpu"): _attention,
    ("mkldnn", "_linear_pointwise"): _linear_pointwise,
    ("aten", "mv"): _mv,
    ("aten", "addmv"): _addmv,
    ("aten", "dot"): _dot,
    ("aten", "vdot"): _dot,
    ("aten", "addbmm"): _addbmm,
    ("aten", "_int_mm"): _int_mm,
}
_formulas: dict[Any, Callable[..., int]] = {}


def formulas() -> dict[Any, Callable[..., int]]:
    """FLOP formulas by op packet: torch.utils.flop_counter's table (its formulas take the
    op's tensors and `out_val`) and the ones it lacks (ops this torch build does not
    have are left out). Built once per process."""
    if not _formulas:
        import torch
        from torch.utils.flop_counter import flop_registry

        _formulas.update(flop_registry)
        for (namespace, name), formula in _EXTRA.items():
            try:
                _formulas[getattr(getattr(torch.ops, namespace), name)] = formula
            except (AttributeError, RuntimeError):
                continue
    return _formulas


@dataclass
class OpFlops:
    """What `op_flops()` counted: FLOPs of the products, and how many ops ran at all."""

    flops: int = 0
    ops: int = 0


def _mode(counted: OpFlops) -> Any:
    from torch.utils._python_dispatch import TorchDispatchMode

    table = formulas()

    class Counting(TorchDispatchMode):
        def __torch_dispatch__(self, func: Any, types: Any, args: Any = (), kwargs: Any = None) -> Any:
            kwargs = kwargs or {}
            counted.ops += 1
            formula = table.get(func._overloadpacket)
            if formula is None:  # a composite op (matmul, linear, einsum): count what it runs
                with self:
                    out = func.decompose(*args, **kwargs)
                if out is not NotImplemented:
                    return out
            out = func(*args, **kwargs)
            if formula is not None:
                counted.flops += int(formula(*args, **kwargs, out_val=out))
            return out

    return Counting()


@contextmanager
def op_flops() -> Iterator[OpFlops]:
    """Count the ops and the FLOPs of the torch products run inside the block, in this
    thread. Nothing is counted when torch is not loaded (no torch op can run)."""
    counted = OpFlops()
    if "torch" not in sys.modules:
        yield counted
        return
    with _mode(counted):
        yield counted
