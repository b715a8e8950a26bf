"""Linear layers with prepacked weights, for decoding on a CPU.

Decoding runs many forward passes over a handful of tokens: a Fast-dVLA pass reads 7-21
action tokens against its cache, an autoregressive pass one. At that size the default
float32 GEMM (MKL, behind torch.nn.functional.linear) spends most of a call laying the
weight matrix out for its kernel, every call: on this project's 2-core EPYC, 7-row
linears at paper-like shapes read their weights at ~7 GB/s where a plain sum reads
30 GB/s. oneDNN weights prepacked once (the layout torch.compile's CPU freezing uses)
make those passes ~2x faster and full-size ones ~14% faster (benchmarks/decoders.py).

Only large weights are packed: oneDNN's call costs ~15 us more, which small layers never
win back. Measured per layer, one thread: 512x2048 with 8 rows 1.67x faster, 512x512
1.23x, 256x768 1.14x, but 128x512 (the shipped checkpoints' widest) 0.79x, and one row
(autoregressive) loses below ~384x1536. Packing the shipped MT10 models made their
decoders 1.3-1.6x slower, so they keep the default kernels.

The two ops are torch-internal (`torch.ops.mkldnn._reorder_linear_weight`,
`_linear_pointwise`), so packing is probed once, checked against F.linear, and skipped,
leaving the model as it is, wherever they are missing or disagree. Packed layers hold no
Parameters and have no backward: for inference copies only, never for training.
`DVLA_HARNESS_PACKED_LINEARS=0` turns packing off (e.g. to time the default kernels).
"""

from __future__ import annotations

import functools
import os

import torch
import torch.nn.functional as F
from torch import Tensor, nn

ENV = "DVLA_HARNESS_PACKED_LINEARS"
TOLERANCE = 1e-4  # max |packed - F.linear| on the probe, float32
MIN_ELEMENTS = 1 << 18  # weights at least this big are packed (512x512, 256x1024, ...)


class PackedLinear(nn.Module):
    def __init__(self, linear: nn.Linear):
        super().__init__()
        self.in_features, self.out_features = linear.in_features, linear.out_features
        weight = linear.weight.detach()
        self.register_buffer("packed", torch.ops.mkldnn._reorder_linear_weight(weight, None))
        bias = None if linear.bias is None else linear.bias.detach().clone()
        self.register_buffer("bias", bias)

    def forward(self, x: Tensor) -> Tensor:
        return torch.ops.mkldnn._linear_pointwise(x, self.packed, self.bias, "none", [], "")

    def extra_repr(self) -> str:
        return f"in_features={self.in_features}, out_features={self.out_features}, oneDNN-prepacked"


@functools.cache
def unavailable_reason() -> str | None:
    """Why packing is off here, or None when it is on (probed once per process)."""
    if os.environ.get(ENV, "1") == "0":
        return f"{ENV}=0"
    if not torch.backends.mkldnn.is_available():
        return "this torch has no oneDNN (mkldnn)"
    try:
        g = torch.Generator().manual_seed(0)
        probe = nn.Linear(64, 48)
        x = torch.randn(3, 5, 64, generator=g)
        with torch.no_grad():
            diff = (PackedLinear(probe)(x) - F.linear(x, probe.weight, probe.bias)).abs().max().item()
    except (AttributeError, RuntimeError, TypeError) as exc:  # op missing or signature changed
        return f"prepacked linear ops unusable in torch {torch.__version__}: {type(exc).__name__}"
    if not diff < TOLERANCE:
        return f"prepacked linears disagree with F.linear by {diff:.2g} in torch {torch.__version__}"
    return None


def describe() -> str:
    """For a run's manifest: which linear kernels CPU decoding uses."""
    reason = unavailable_reason()
    if reason is None:
        return f"onednn-prepacked for weights of >= {MIN_ELEMENTS} entries, default below"
    return f"default ({reason})"


def pack_linears(model: nn.Module, min_elements: int = MIN_ELEMENTS) -> int:
    """Swap the nn.Linear layers of a float32 CPU model whose weights have at least
    `min_elements` entries for PackedLinear ones, in place; returns how many were swapped
    (0 when packing is off here or the model is elsewhere)."""
    params = list(model.parameters())
    on_cpu_fp32 = all(p.device.type == "cpu" and p.dtype == torch.float32 for p in params)
    if not params or not on_cpu_fp32 or unavailable_reason() is not None:
        return 0
    swapped = 0
    for parent in list(model.modules()):
        for name, child in list(parent.named_children()):
            if isinstance(child, nn.Linear) and child.weight.numel() >= min_elements:
                setattr(parent, name, PackedLinear(child))
                swapped += 1
    return swapped
