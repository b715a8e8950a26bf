"""Every pass of an exactly cached decoder equals an uncached full forward pass over the
tokens visible at that moment; a batch decodes in one pass per step and each row comes
out as it would alone.

Confidences are scripted: the model's logits at each action position are multiplied by
a fixed factor (tiny = flat, low confidence; huge = peaked, confidence ~1), the same in
the decoder's passes and in the reference. Random weights alone never clear tau_conf,
so without the script the paths where blocks finish out of order are never reached.
"""

from __future__ import annotations

import pytest
import torch

from policies.dvla.decoders import decode_autoregressive, decode_bidirectional, decode_block_diffusion
from policies.dvla.fast_dllm import decode_fast_dllm
from policies.dvla.fast_dvla import decode_fast_dvla
from policies.dvla.model import StepOutput
from tests.fakes import tiny_model

TOL = 1e-4
FLAT, PEAKED = 1e-3, 1e3


class ScriptedModel:
    """Runs the model, scales its logits per (row, action position) for the decoder, and
    records each pass's positions and unscaled logits."""

    def __init__(self, model, scale: torch.Tensor):
        self.model, self.cfg, self.scale = model, model.cfg, scale
        self.calls: list[tuple[torch.Tensor, torch.Tensor]] = []

    def __call__(
        self, action_tokens=None, action_positions=None, words=None, state=None, cache=None, images=None, **kw
    ):
        out = self.model(action_tokens, action_positions, words, state, cache, images, **kw)
        self.calls.append((action_positions.clone(), out.logits.clone()))  # compared unscaled
        return StepOutput(out.logits * self.scale[:, action_positions, None], out.kv)

    def full(self, tokens, words, state) -> torch.Tensor:
        positions = torch.arange(self.cfg.action_tokens)
        return self.model(tokens, positions, words, state).logits


def _inputs(batch=1, seed=3):
    g = torch.Generator().manual_seed(seed)
    return torch.randint(1, 20, (batch, 5), generator=g), torch.randn(batch, 6, generator=g)


def _visible(final: torch.Tensor, trace: list[list[int]], before: int, mask_id: int) -> torch.Tensor:
    """Row 0's tokens before pass `before`: what earlier passes committed, [MASK] elsewhere."""
    tokens = torch.full_like(final, mask_id)
    for step in trace[:before]:
        tokens[:, step] = final[:, step]
    return tokens


def _out_of_order_scale() -> torch.Tensor:
    """Block 0 flat (decodes a token or two a pass), blocks 1-3 peaked (a semi-activated
    block clears tau_conf at once): block 1 finishes while block 0 is still open."""
    scale = torch.full((1, 16), PEAKED)
    scale[:, :4] = FLAT
    return scale


def _check_every_pass(spy: ScriptedModel, out, words, state, passes=None) -> None:
    mask_id = spy.cfg.mask_id
    with torch.no_grad():
        for p, (positions, logits) in enumerate(spy.calls):
            if passes is not None and p not in passes:
                continue
            visible = _visible(out.tokens, out.trace, p, mask_id)
            reference = spy.full(visible, words, state)[:, positions]
            gap = (logits - reference).abs().max().item()
            assert gap < TOL, f"pass {p} (positions {positions.tolist()}) differs from a full pass by {gap}"


FAST_DVLA_PIPELINED = {"tau_conf": 0.5, "tau_add": 0.0, "tau_act": 0.9, "n": 2}


@pytest.mark.parametrize(
    ("name", "pattern", "kw", "decode", "params"),
    [
        ("bidirectional", "bidirectional", {}, decode_bidirectional, {"steps": 5}),
        (
            "bidirectional, exact prefix cache",
            "bidirectional",
            {"prefix_sees_actions": False},
            decode_bidirectional,
            {"steps": 5, "reuse_prefix_cache": True},
        ),
        (
            "bidirectional, exact prefix cache, as benchmarks/decoders.py's reference row",
            "bidirectional",
            {"prefix_sees_actions": False},
            decode_bidirectional,
            {"steps": 12, "schedule": "cosine", "confidence": "max_prob", "reuse_prefix_cache": True},
        ),
        (
            "block_diffusion",
            "block_causal",
            {"block_size": 4},
            decode_block_diffusion,
            {"steps_per_block": 2},
        ),
        ("fast_dvla", "block_causal", {"block_size": 4}, decode_fast_dvla, FAST_DVLA_PIPELINED),
        ("fast_dvla defaults", "block_causal", {"block_size": 4}, decode_fast_dvla, {}),
        ("fast_dllm without cache", "bidirectional", {}, decode_fast_dllm, {"cache": "none"}),
    ],
)
def test_every_pass_equals_a_full_uncached_pass(name, pattern, kw, decode, params):
    spy = ScriptedModel(tiny_model(pattern, **kw), _out_of_order_scale())
    words, state = _inputs()
    with torch.no_grad():
        out = decode(spy, words, state, **params)
    assert sorted(p for step in out.trace for p in step) == list(range(16))
    _check_every_pass(spy, out, words, state)


def test_fast_dvla_keeps_a_block_that_finished_out_of_order_in_context():
    spy = ScriptedModel(tiny_model("block_causal", block_size=4), _out_of_order_scale())
    words, state = _inputs()
    with torch.no_grad():
        out = decode_fast_dvla(spy, words, state, **FAST_DVLA_PIPELINED)
    finished_at = {
        b: next(
            p
            for p in range(len(out.trace))
            if {*range(4 * b, 4 * b + 4)} <= {q for step in out.trace[: p + 1] for q in step}
        )
        for b in range(2)
    }
    assert finished_at[1] < finished_at[0]  # the scenario really happens
    later = spy.calls[finished_at[1] + 1][0].tolist()
    assert set(range(4, 8)) <= set(later)  # block 1 is run (not yet cacheable) ...
    assert any(p >= 8 for p in later)  # ... beside the block after it


def test_autoregressive_pass_i_equals_the_full_causal_pass_at_i():
    spy = ScriptedModel(tiny_model("causal"), torch.ones(1, 16))
    words, state = _inputs()
    with torch.no_grad():
        out = decode_autoregressive(spy, words, state)
        shifted = torch.cat([torch.full((1, 1), spy.cfg.mask_id), out.tokens[:, :-1]], dim=1)
        full = spy.full(shifted, words, state)
    for i, (positions, logits) in enumerate(spy.calls):
        assert positions.tolist() == [i]
        assert (logits[:, -1] - full[:, i]).abs().max() < TOL


@pytest.mark.parametrize("cache", ["prefix", "dual"])
def test_fast_dllm_refreshes_its_cache_at_every_block_start(cache):
    """A block's first pass is a full pass over the current tokens (the refresh); the
    steps after it reuse that cache, stale by design."""
    spy = ScriptedModel(tiny_model("bidirectional"), torch.full((1, 16), FLAT))
    words, state = _inputs()
    with torch.no_grad():
        out = decode_fast_dllm(spy, words, state, cache=cache)
    starts = [p for p, record in enumerate(out.passes) if record.prefix]
    assert starts == [0, 4, 8, 12]  # one refresh per block of 4 (4 tokens, one a step)
    assert all(len(spy.calls[p][0]) == 16 for p in starts)
    _check_every_pass(spy, out, words, state, passes=set(starts))
    sizes = [len(spy.calls[p][0]) for p in range(16) if p not in starts]
    # dual: only the block runs; prefix: the block and everything after it
    assert sizes == ([4] * 12 if cache == "dual" else [16] * 3 + [12] * 3 + [8] * 3 + [4] * 3)
    # flat confidences never reach 0.9: one token a step, so one pass per token
    assert len(spy.calls) == 16 and all(len(s) == 1 for s in out.trace)


def test_fast_dllm_nfe_follows_confidence():
    words, state = _inputs()
    model = tiny_model("bidirectional")
    with torch.no_grad():
        peaked = decode_fast_dllm(ScriptedModel(model, torch.full((1, 16), PEAKED)), words, state)
        flat = decode_fast_dllm(ScriptedModel(model, torch.full((1, 16), FLAT)), words, state)
        fixed = decode_fast_dllm(model, words, state, threshold=0.0, steps_per_block=3)
    assert 4 <= len(peaked.passes) <= 6  # nearly every token clears 0.9 at its block's first step
    assert len(flat.passes) == 16
    assert len(fixed.passes) == 12  # threshold 0: 4 blocks x 3 steps


DECODERS = [
    ("bidirectional", {}, decode_bidirectional, {"steps": 5}),
    ("block_causal", {"block_size": 4}, decode_block_diffusion, {"steps_per_block": 2}),
    ("block_causal", {"block_size": 4}, decode_fast_dvla, FAST_DVLA_PIPELINED),
    ("bidirectional", {}, decode_fast_dllm, {}),
    ("bidirectional", {}, decode_fast_dllm, {"cache": "prefix"}),
    ("causal", {}, decode_autoregressive, {}),
]


@pytest.mark.parametrize(("pattern", "kw", "decode", "params"), DECODERS)
def test_a_batch_decodes_in_one_pass_per_step_and_each_row_as_alone(pattern, kw, decode, params):
    model = tiny_model(pattern, **kw)
    words, state = _inputs(batch=3, seed=5)
    scale = torch.stack([_out_of_order_scale()[0], torch.full((16,), PEAKED), torch.full((16,), FLAT)])
    with torch.no_grad():
        spy = ScriptedModel(model, scale)
        batch = decode(spy, words, state, **params)
        alone = [
            decode(ScriptedModel(model, scale[r : r + 1]), words[r : r + 1], state[r : r + 1], **params)
            for r in range(3)
        ]
    assert len(spy.calls) == len(batch.passes) == max(len(a.passes) for a in alone)
    for r, single in enumerate(alone):
        assert torch.equal(batch.tokens[r], single.tokens[0]), f"row {r}"
        committed = [step for step in batch.row_trace(r)["committed"] if step]
        assert committed == [step for step in single.trace if step], f"row {r}"


def test_fast_dvla_with_random_block_sizes_attends_by_its_own_partition():
    """The random-block-size ablation: blocks of other sizes than the model's, with the
    attention mask following them; every pass still equals a full pass under that mask."""
    from policies.dvla.fast_dvla import block_mask, random_block_sizes

    model = tiny_model("block_causal", block_size=4)
    sizes = random_block_sizes(16, 4, torch.Generator().manual_seed(5))
    assert sum(sizes) == 16 and sizes != [4] * 4 and all(1 <= s <= 7 for s in sizes)
    starts = torch.tensor([0, *torch.tensor(sizes).cumsum(0).tolist()]).numpy()
    spy = ScriptedModel(model, torch.ones(1, 16))
    words, state = _inputs()
    with torch.no_grad():
        out = decode_fast_dvla(spy, words, state, block_sizes=sizes, **FAST_DVLA_PIPELINED)
        everything = torch.arange(model.cfg.prefix_len + 16)
        mask = block_mask(model.cfg.prefix_len, starts, 16, everything, everything)
        for p, (positions, logits) in enumerate(spy.calls):
            visible = _visible(out.tokens, out.trace, p, model.cfg.mask_id)
            full = model(visible, torch.arange(16), words, state, attn_mask=mask).logits
            assert (logits - full[:, positions]).abs().max() < TOL, f"pass {p}"
    assert sorted(p for step in out.trace for p in step) == list(range(16))
    with pytest.raises(ValueError, match="do not partition"):
        decode_fast_dvla(model, words, state, block_sizes=[4, 4, 4])


@pytest.mark.parametrize("steps", [5, 12])
def test_an_exact_prefix_cache_decodes_the_plain_decodes_tokens(steps):
    """The prefix-cached bidirectional decode (the speed benchmark's reference row) is the
    plain one computed with less work: same tokens, same commits per step, prefix once."""
    model = tiny_model("bidirectional", prefix_sees_actions=False)
    words, state = _inputs(batch=3)
    with torch.no_grad():
        plain = decode_bidirectional(model, words, state, steps=steps)
        cached = decode_bidirectional(model, words, state, steps=steps, reuse_prefix_cache=True)
    assert torch.equal(plain.tokens, cached.tokens)
    assert [p.committed for p in plain.passes] == [p.committed for p in cached.passes]
    assert [p.prefix for p in plain.passes] == [True] * steps
    assert [p.prefix for p in cached.passes] == [True] + [False] * (steps - 1)
