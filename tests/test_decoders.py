"""The decoders: NFE identities counted by the harness's hooks, vocabulary, determinism."""

from __future__ import annotations

import pytest
import torch

from harness.episode.nfe import NFECounter
from policies.dvla.decoders import decode_autoregressive, decode_bidirectional, decode_block_diffusion
from policies.dvla.fast_dvla import decode_fast_dvla
from policies.dvla.schedules import still_masked
from tests.fakes import tiny_model

_model = tiny_model


def _inputs(batch=1):
    g = torch.Generator().manual_seed(3)
    return torch.randint(1, 20, (batch, 5), generator=g), torch.randn(batch, 6, generator=g)


class Holder:
    """A policy-like object holding the model, as a registered policy will."""

    def __init__(self, model):
        self.model = model


def _count(model, fn, **kw):
    counter = NFECounter(Holder(model))
    with torch.inference_mode(), counter.counting():
        out = fn(model, *_inputs(), **kw)
    nfe = counter.take()
    counter.close()
    return out, nfe


@pytest.mark.parametrize("steps", [1, 5, 12])
def test_bidirectional_nfe_is_t(steps):
    out, nfe = _count(_model("bidirectional"), decode_bidirectional, steps=steps)
    assert nfe == steps and len(out.trace) == steps
    assert sorted(p for step in out.trace for p in step) == list(range(16))  # each committed once


def test_a_never_refreshed_prefix_cache_keeps_t():
    out, nfe = _count(_model("bidirectional"), decode_bidirectional, steps=6, reuse_prefix_cache=True)
    assert nfe == 6 and (out.tokens < 32).all()


def test_autoregressive_nfe_is_the_number_of_action_tokens():
    out, nfe = _count(_model("causal"), decode_autoregressive)
    assert nfe == 16 and out.trace == [[i] for i in range(16)]


@pytest.mark.parametrize(("block", "steps"), [(4, 2), (8, 3), (4, 4)])
def test_block_diffusion_nfe_is_blocks_times_steps(block, steps):
    out, nfe = _count(_model("block_causal", block_size=block), decode_block_diffusion, steps_per_block=steps)
    assert nfe == (16 // block) * steps
    assert (out.tokens >= 0).all() and (out.tokens < 32).all()


def test_fast_dvla_decodes_everything_in_at_most_a_passes():
    out, nfe = _count(_model("block_causal", block_size=4), decode_fast_dvla)
    assert 1 <= nfe <= 16 and len(out.trace) == nfe
    assert sorted(p for step in out.trace for p in step) == list(range(16))


def test_fast_dvla_with_tau_one_degenerates_to_block_by_block():
    out, _ = _count(_model("block_causal", block_size=4), decode_fast_dvla, tau_add=1.0, tau_act=1.0)
    blocks_per_pass = [{p // 4 for p in step} for step in out.trace]
    assert all(len(b) == 1 for b in blocks_per_pass)
    order = [min(b) for b in blocks_per_pass]
    assert order == sorted(order)  # never returns to an earlier block


def test_fast_dvla_pipelines_blocks_with_low_thresholds():
    out, _ = _count(
        _model("block_causal", block_size=4), decode_fast_dvla, tau_add=0.0, tau_act=0.0, tau_conf=1.0
    )
    assert any(len({p // 4 for p in step}) > 1 for step in out.trace)


def test_decoders_are_deterministic_and_in_vocabulary():
    model = _model("bidirectional")
    a = decode_bidirectional(model, *_inputs(batch=2), steps=4, confidence="margin", remask=0.3)
    b = decode_bidirectional(model, *_inputs(batch=2), steps=4, confidence="margin", remask=0.3)
    assert torch.equal(a.tokens, b.tokens)
    assert (a.tokens >= 0).all() and (a.tokens < 32).all()


@pytest.mark.parametrize("schedule", ["cosine", "linear", "concave"])
def test_schedules_start_full_and_end_empty(schedule):
    counts = [still_masked(schedule, s, 8, 56) for s in range(9)]
    assert counts[0] == 56 and counts[-1] == 0
    assert counts == sorted(counts, reverse=True)
