"""Counted work at torch's dispatcher (harness/episode/op_work.py): it agrees exactly with
the module hooks on every shipped decoder, and it sees the products the hooks cannot
(a matmul in a decoder's own code, F.linear on a bare weight, einsum, a 1-D matmul,
oneDNN's prepacked linear)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from harness.episode.nfe import NFECounter
from harness.episode.op_work import op_flops
from policies.dvla.policy import shipped, shipped_sets
from policies.registry import get_policy, parse_params

RECIPE = {  # decoder -> the recipe of the checkpoint it reads
    "bidirectional": "bidirectional",
    "fast_dllm": "bidirectional",
    "block_diffusion": "block_diffusion",
    "fast_dvla": "fast_dvla",
    "autoregressive": "autoregressive",
}


def counted_both_ways(policy, observation) -> tuple[int, int | None, int]:
    """One chunk decoded: FLOPs at the dispatcher, FLOPs by the module hooks, passes."""
    counter = NFECounter()
    with counter.counting(), op_flops() as ops:
        policy.act([observation])
    passes, work = counter.take(), counter.take_work()
    counter.close()
    return ops.flops, work.flops, passes


@pytest.mark.parametrize("checkpoint_set", shipped_sets())
def test_every_shipped_decoder_counts_the_same_at_the_dispatcher_as_by_its_modules(
    checkpoint_set, one_torch_thread
):
    decoders = [d for d, recipe in RECIPE.items() if Path(shipped(recipe, checkpoint_set)).is_file()]
    assert decoders, f"no decoder reads {checkpoint_set}"
    rng = np.random.default_rng(0)
    for name in decoders:
        spec = get_policy(name)
        policy = spec.build(parse_params(spec, {"checkpoint": checkpoint_set}))
        cfg = policy.model.cfg
        state = rng.uniform(-1, 1, policy.ckpt.raw_state_dim).astype(np.float32)
        images = {c: rng.integers(0, 256, (cfg.image_size, cfg.image_size, 3), np.uint8) for c in cfg.cameras}
        policy._instructions = ["put the cube in the drawer"]
        ops, hooks, passes = counted_both_ways(policy, {"state": state, **images} if images else state)
        assert passes > 0 and hooks is not None and hooks > 0, name
        assert ops == hooks, f"{checkpoint_set} {name}: dispatcher {ops} vs module hooks {hooks}"


def test_products_outside_any_module_are_counted_exactly():
    a, b = torch.ones(5, 7), torch.ones(7, 3)
    weight = torch.ones(3, 7)
    cases = [
        (lambda: torch.matmul(a, b), 2 * 5 * 7 * 3),  # mm
        (lambda: a @ b, 2 * 5 * 7 * 3),
        (lambda: F.linear(a, weight), 2 * 5 * 7 * 3),  # a bare weight: no nn.Linear to hook
        (lambda: torch.einsum("ij,jk->ik", a, b), 2 * 5 * 7 * 3),
        (lambda: torch.matmul(torch.ones(4, 5, 7), torch.ones(4, 7, 3)), 4 * 2 * 5 * 7 * 3),  # bmm
        (lambda: torch.matmul(a, torch.ones(7)), 2 * 5 * 7),  # mv
        (lambda: torch.matmul(torch.ones(7), torch.ones(7)), 2 * 7),  # dot
        (
            lambda: F.scaled_dot_product_attention(
                torch.ones(1, 2, 3, 4), torch.ones(1, 2, 5, 4), torch.ones(1, 2, 5, 6)
            ),
            2 * 2 * 3 * 5 * (4 + 6),  # scores and the weighted sum over every key
        ),
        (lambda: a + 1.0, 0),  # elementwise: not counted by either counter
    ]
    for run, expected in cases:
        for mode in (torch.no_grad, torch.inference_mode):
            with mode(), op_flops() as counted:
                run()
            assert counted.flops == expected and counted.ops >= 1


def test_the_prepacked_linear_is_counted_like_the_linear_it_replaces():
    from policies.dvla.kernels import PackedLinear, unavailable_reason

    if unavailable_reason() is not None:
        pytest.skip(f"oneDNN prepacking unavailable: {unavailable_reason()}")
    linear = torch.nn.Linear(64, 48)
    x = torch.ones(3, 5, 64)
    with torch.inference_mode(), op_flops() as packed:
        PackedLinear(linear)(x)
    with torch.inference_mode(), op_flops() as plain:
        linear(x)
    assert packed.flops == plain.flops == 2 * 15 * 64 * 48


def test_nothing_runs_nothing_is_counted():
    with op_flops() as counted:
        np.ones(3) @ np.ones(3)  # numpy: outside torch, and outside what this counter can see
    assert (counted.flops, counted.ops) == (0, 0)
