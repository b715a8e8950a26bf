"""benchmarks/decoders.py's worker: what the README's speed table is made of."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest


def _decoders_benchmark():
    path = Path(__file__).resolve().parent.parent / "benchmarks" / "decoders.py"
    spec = importlib.util.spec_from_file_location("decoders_benchmark", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_paper_shape_worker_counts_nfe_and_says_which_kernels_ran():
    import torch

    from policies import kernels

    bench = _decoders_benchmark()
    grad = torch.is_grad_enabled()
    with torch.random.fork_rng(devices=[]):  # the worker seeds and disables grad: its own process
        try:
            row = bench.measure("fast_dvla", chunks=1, device="cpu")
        finally:
            torch.set_grad_enabled(grad)
    # Random weights: no token clears tau_conf, so every block advances by the forced
    # 1/n commits (4 passes a block, a new block every 2): 2 x 7 + 4 = 18.
    assert row["nfe_per_chunk"] == 18
    assert row["device"] == "cpu" and row["tokens_per_s"] > 0
    if not hasattr(torch.ops.mkldnn, "_reorder_linear_weight"):
        pytest.skip(f"torch {torch.__version__} has no prepacked linear ops")
    assert kernels.unavailable_reason() is None
    assert row["packed_linears"] == "33 of 35"  # all but the state input and the head
