"""Prepacked CPU linears (policies/dvla/kernels.py): same logits and tokens, and a way out."""

from __future__ import annotations

import copy
import dataclasses

import pytest
import torch

from policies.dvla import kernels
from policies.dvla.decoders import decode_autoregressive, decode_bidirectional, decode_block_diffusion
from policies.dvla.fast_dvla import decode_fast_dvla
from tests.fakes import tiny_model

PATTERN = {
    decode_bidirectional: "bidirectional",
    decode_block_diffusion: "block_causal",
    decode_fast_dvla: "block_causal",
    decode_autoregressive: "causal",
}


@pytest.fixture
def packing():
    """Skips only where torch lacks the ops; where it has them, packing must be on (a
    packed layer that disagrees with F.linear turns it off, and that is a failure here)."""
    ops = torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_reorder_linear_weight")
    if not ops:
        pytest.skip(f"torch {torch.__version__} has no prepacked linear ops")
    assert kernels.unavailable_reason() is None


def _linears(model):
    return sum(isinstance(m, torch.nn.Linear) for m in model.modules())


@pytest.mark.parametrize("decode", list(PATTERN), ids=lambda f: f.__name__)
def test_packed_model_gives_the_same_logits_and_tokens(packing, decode):
    model = tiny_model(PATTERN[decode]).eval()
    packed = copy.deepcopy(model)
    linears = _linears(model)
    assert kernels.pack_linears(packed, min_elements=0) == linears > 0
    assert _linears(packed) == 0
    assert sum(isinstance(m, kernels.PackedLinear) for m in packed.modules()) == linears
    g = torch.Generator().manual_seed(5)
    words, state = torch.randint(1, 20, (2, 5), generator=g), torch.randn(2, 6, generator=g)
    tokens = torch.randint(0, 32, (2, model.cfg.action_tokens), generator=g)
    positions = torch.arange(model.cfg.action_tokens)
    with torch.inference_mode():
        want = model(tokens, positions, words, state).logits
        got = packed(tokens, positions, words, state).logits
        assert (got - want).abs().max().item() < 1e-4
        assert torch.equal(decode(packed, words, state).tokens, decode(model, words, state).tokens)


def test_packing_can_be_turned_off_and_says_so(monkeypatch):
    monkeypatch.setenv(kernels.ENV, "0")
    kernels.unavailable_reason.cache_clear()
    try:
        model = tiny_model("block_causal")
        assert kernels.pack_linears(model, min_elements=0) == 0
        assert _linears(model) > 0
        assert kernels.describe() == f"default ({kernels.ENV}=0)"
    finally:
        kernels.unavailable_reason.cache_clear()


def test_only_float32_cpu_models_are_packed(packing):
    model = tiny_model("bidirectional").to(torch.bfloat16)
    assert kernels.pack_linears(model, min_elements=0) == 0
    assert _linears(model) > 0


def test_only_weights_big_enough_to_gain_are_packed(packing):
    model = torch.nn.Sequential(
        torch.nn.Linear(512, 512), torch.nn.Linear(512, 511), torch.nn.Linear(128, 512)
    )
    assert kernels.pack_linears(model) == 1
    assert [type(m).__name__ for m in model] == ["PackedLinear", "Linear", "Linear"]


def test_decoder_policies_pack_what_gains(packing, tmp_path):
    """The shipped MT10 models are too small to gain (they keep the default kernels); a
    wider one built through the same policy is packed."""
    from policies.dvla.checkpoint import load, save
    from policies.dvla.model import ActionTokenModel
    from policies.registry import get_policy, parse_params

    spec = get_policy("fast_dvla")
    small = spec.build(parse_params(spec, {}))
    assert not any(isinstance(m, kernels.PackedLinear) for m in small.model.modules())
    ckpt = load(small.params.checkpoint)
    wide = dataclasses.replace(ckpt.model.cfg, width=512, ffn=1024, heads=4)
    ckpt.model = ActionTokenModel(wide).eval()
    save(ckpt, tmp_path / "wide.safetensors")
    policy = spec.build(parse_params(spec, {"checkpoint": str(tmp_path / "wide.safetensors")}))
    # per layer qkv, proj and both FFN linears, and the state MLP's 512 -> 3 x 512 (the
    # 39 -> 512 state input and the 512 -> 256 head are too small)
    assert sum(isinstance(m, kernels.PackedLinear) for m in policy.model.modules()) == 4 * wide.layers + 1
    assert kernels.describe().startswith("onednn-prepacked for weights of >= 262144")
