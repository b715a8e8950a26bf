"""The action-token model: attention patterns and KV-cache exactness, per pattern."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from policies.dvla.model import ActionTokenModel
from policies.dvla.tokenizer import ActionTokenizer
from tests.fakes import tiny_model

TOL = 1e-4


_model = tiny_model


def _inputs(model: ActionTokenModel, batch: int = 2):
    g = torch.Generator().manual_seed(1)
    cfg = model.cfg
    words = torch.randint(1, cfg.vocab_words, (batch, cfg.max_words), generator=g)
    state = torch.randn(batch, cfg.state_dim, generator=g)
    tokens = torch.randint(0, cfg.bins + 1, (batch, cfg.action_tokens), generator=g)  # some [MASK]s
    return words, state, tokens


def _full(model, words, state, tokens):
    positions = torch.arange(model.cfg.action_tokens)
    with torch.no_grad():
        return model(tokens, positions, words, state).logits


@pytest.mark.parametrize(("pattern", "step"), [("block_causal", 4), ("block_causal", 8), ("causal", 1)])
def test_cached_decoding_matches_full_forward(pattern, step):
    model = _model(pattern, block_size=step if pattern == "block_causal" else 0)
    words, state, tokens = _inputs(model)
    full = _full(model, words, state, tokens)
    with torch.no_grad():
        cache = model(words=words, state=state).kv  # the prefix, once
        for start in range(0, model.cfg.action_tokens, step):
            pos = torch.arange(start, start + step)
            out = model(tokens[:, pos], pos, cache=cache)
            assert (out.logits - full[:, pos]).abs().max() < TOL
            cache = cache.extend(out.kv)
    assert len(cache) == model.cfg.prefix_len + model.cfg.action_tokens


def test_caches_extended_from_one_parent_stay_independent():
    """The cache grows in place in shared stores; a second extension of the same parent
    (or a pass run against the parent) must not change what the first one holds."""
    model = _model("block_causal", block_size=4)
    words, state, tokens = _inputs(model)
    full = _full(model, words, state, tokens)
    first, second = torch.arange(0, 4), torch.arange(4, 8)
    with torch.no_grad():
        parent = model(words=words, state=state).kv.select(torch.ones(model.cfg.prefix_len, dtype=torch.bool))
        a = parent.extend(model(tokens[:, first], first, cache=parent).kv)
        a_keys = [k.clone() for k in a.keys]
        other = tokens.roll(3, dims=1)
        b = parent.extend(model(other[:, first], first, cache=parent).kv)  # a branch
        model(other[:, second], second, cache=a)  # a pass against a, never committed
        b_full = _full(model, words, state, other)
        assert all(torch.equal(k, kept) for k, kept in zip(a.keys, a_keys, strict=True))
        assert (model(tokens[:, second], second, cache=a).logits - full[:, second]).abs().max() < TOL
        assert (model(other[:, second], second, cache=b).logits - b_full[:, second]).abs().max() < TOL
    assert a.key_stores[0].data_ptr() == parent.key_stores[0].data_ptr()  # grew in place
    assert b.key_stores[0].data_ptr() != parent.key_stores[0].data_ptr()  # copied


def test_bidirectional_with_isolated_prefix_caches_the_prefix_exactly():
    model = _model("bidirectional", prefix_sees_actions=False)
    words, state, tokens = _inputs(model)
    full = _full(model, words, state, tokens)
    positions = torch.arange(model.cfg.action_tokens)
    with torch.no_grad():
        cache = model(words=words, state=state).kv
        cached = model(tokens, positions, cache=cache).logits
    assert (cached - full).abs().max() < TOL


def test_dream_style_bidirectional_prefix_cache_goes_stale():
    """Every token sees every token: a prefix cached before the actions changed is stale
    (this is the approximation the fast_dllm decoder accepts)."""
    model = _model("bidirectional")
    words, state, tokens = _inputs(model)
    positions = torch.arange(model.cfg.action_tokens)
    with torch.no_grad():
        first = model(tokens, positions, words, state)
        prefix_kv = first.kv.select(first.kv.positions < model.cfg.prefix_len)
        changed = tokens.roll(1, dims=1)
        stale = model(changed, positions, cache=prefix_kv).logits
    assert (stale - _full(model, words, state, changed)).abs().max() > 1e-5  # exact caches stay < 1e-6


def test_block_causal_blocks_do_not_see_later_blocks():
    model = _model("block_causal", block_size=4)
    words, state, tokens = _inputs(model)
    changed = tokens.clone()
    changed[:, 8:] = (changed[:, 8:] + 1) % model.cfg.bins
    a, b = _full(model, words, state, tokens), _full(model, words, state, changed)
    assert (a[:, :8] - b[:, :8]).abs().max() < TOL  # blocks 0-1 unaffected by blocks 2-3
    assert (a[:, 8:] - b[:, 8:]).abs().max() > 1e-3


def test_invalid_config_names_the_problem():
    with pytest.raises(ValueError, match="block size 5 does not divide the chunk's 16 action tokens"):
        _model("block_causal", block_size=5)
    with pytest.raises(ValueError, match="pattern 'sideways' is not one of"):
        _model("sideways")


def test_tokenizer_round_trip_and_serialisation():
    rng = np.random.default_rng(0)
    actions = np.clip(rng.normal(0, 0.5, (2000, 4)), -1, 1)
    actions[:, 3] = np.where(rng.random(2000) > 0.5, 1.0, -1.0)  # a gripper
    tok = ActionTokenizer.fit(actions, bins=256, binary_dims=(3,))
    assert tok.round_trip_error(actions) < 0.01
    chunk = actions[:8][None]  # (1, H=8, D=4)
    tokens = tok.encode(chunk)
    assert tokens.shape == (1, 32) and tokens.min() >= 0 and tokens.max() < 256
    assert set(tokens[0, 3::4].tolist()) <= {0, 255}  # time-major: every 4th token is the gripper
    again = ActionTokenizer.from_dict(tok.to_dict())
    assert np.array_equal(again.decode(tokens), tok.decode(tokens))
    with pytest.raises(ValueError, match="tokens outside"):
        tok.decode(np.array([[256, 0, 0, 0]]))
    with pytest.raises(ValueError, match="invalid tokenizer description"):
        ActionTokenizer.from_dict({"low": [0.0], "high": [0.0], "bins": 256, "binary_dims": []})


def test_a_zero_action_round_trips_exactly_so_a_gripper_can_hold():
    # robosuite's gripper acts on the sign of its command: +0.004 closes, only 0 holds.
    actions = np.tile(np.array([[-1.0, 1.0, 0.3]]), (100, 1))
    actions[:, 0] = np.linspace(-1, 1, 100)
    actions[::2, 1] = -1.0
    tok = ActionTokenizer.fit(actions, bins=256, percentiles=(0.0, 100.0))
    hold = np.array([[[0.0, 0.0, 0.3]]])
    decoded = tok.decode(tok.encode(hold))[0, 0]
    assert decoded[0] == 0.0 and decoded[1] == 0.0  # not the bin centre 1/255
    assert decoded[2] != 0.0  # a range without 0 has no zero token
    assert tok.zero_token()[2] == -1
    near = tok.decode(tok.encode(np.array([[[0.02, -0.02, 0.3]]])))[0, 0]
    assert np.all(np.sign(near[:2]) == [1.0, -1.0])  # neighbouring bins keep their sign


def test_worst_error_shows_a_rare_action_the_percentile_bins_clip():
    # LIBERO spatial's drawer grasp turns the wrist at 1.0 in under 1% of the steps; the
    # 99th percentile is far below, so 1.0 decodes as that while the mean error stays tiny.
    actions = np.zeros((1000, 2))
    actions[:, 0] = np.linspace(-0.05, 0.05, 1000)
    actions[:5, 1] = 1.0  # 0.5% of the steps
    actions[5:, 1] = np.linspace(-0.05, 0.05, 995)
    clipped = ActionTokenizer.fit(actions)
    assert clipped.round_trip_error(actions) < 0.001
    worst = clipped.worst_error(actions)
    assert worst[0] < 0.01 and worst[1] > 0.9
    full = ActionTokenizer.fit(actions, percentiles=(0.0, 100.0))
    assert full.high[1] == 1.0 and full.worst_error(actions).max() < 0.01


@pytest.mark.parametrize(("pattern", "step"), [("block_causal", 4), ("causal", 1)])
def test_camera_images_join_the_prefix_and_the_cache_stays_exact(pattern, step):
    model = _model(
        pattern,
        block_size=step if pattern == "block_causal" else 0,
        cameras=["agentview", "wrist"],
        image_size=16,
    )
    cfg = model.cfg
    assert cfg.cameras == ("agentview", "wrist")  # JSON lists become tuples
    assert cfg.prefix_len == cfg.max_words + cfg.state_tokens + 2 * cfg.image_tokens
    words, state, tokens = _inputs(model)
    images = torch.randint(
        0, 256, (2, 2, 16, 16, 3), dtype=torch.uint8, generator=torch.Generator().manual_seed(2)
    )
    positions = torch.arange(cfg.action_tokens)
    with torch.no_grad():
        full = model(tokens, positions, words, state, images=images).logits
        other = model(tokens, positions, words, state, images=255 - images).logits
        cache = model(words=words, state=state, images=images).kv
        for start in range(0, cfg.action_tokens, step):
            pos = torch.arange(start, start + step)
            out = model(tokens[:, pos], pos, cache=cache)
            assert (out.logits - full[:, pos]).abs().max() < TOL
            cache = cache.extend(out.kv)
    assert (full - other).abs().max() > 1e-3  # the images change what the model predicts
    with pytest.raises(ValueError, match="reads camera images"):
        model(tokens, positions, words, state)


def test_image_config_is_validated():
    with pytest.raises(ValueError, match="square number"):
        _model("causal", cameras=["a"], image_size=32, image_tokens=3)
    with pytest.raises(ValueError, match="at least 16 pixels"):
        _model("causal", cameras=["a"], image_size=8)


def test_coordinate_inputs_let_the_image_encoder_tell_where_a_thing_is():
    """CoordConv: one globally pooled token is the same for a spot moved by the encoder's
    stride (8 px) without coordinates (convolution is shift-equivariant, pooling forgets
    where), and differs with them."""
    from policies.dvla.model import ImageEncoder

    torch.manual_seed(0)
    frames = torch.zeros(2, 1, 128, 128, 3, dtype=torch.uint8)
    frames[0, 0, 48:51, 48:51] = 255  # far from the borders the padding touches
    frames[1, 0, 56:59, 56:59] = 255
    for coords in (False, True):
        cfg = _model(
            "bidirectional", cameras=["cam"], image_size=128, image_tokens=1, image_coords=coords
        ).cfg
        encoder = ImageEncoder(cfg)
        with torch.no_grad():
            if coords:
                encoder.convs[0].weight[:, 3:] *= 100  # a filter that has learned to read them
            a, b = encoder(frames)[:, 0]
        # a 3x3 spot in a 128 px frame moves the pooled token a little, but only with coordinates
        assert (torch.max(torch.abs(a - b)).item() > 1e-6) == coords
