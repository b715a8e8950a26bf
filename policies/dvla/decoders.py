"""The fixed-step decoders: bidirectional (dVLA baseline), block diffusion, autoregressive.

The adaptive ones live beside them: policies/dvla/fast_dllm.py and policies/dvla/fast_dvla.py.
Every decoder talks to the model only through `model(...)` (see policies/dvla/model.py), so
each call is one forward pass and the harness's hooks count it; each decodes a whole
batch of observations with one pass per step. Shared pieces (the `Decoded` record,
confidence measures, commit rules) are in policies/dvla/decoding.py.

`images` (camera images, for models trained on them) travel with words and state: they
are part of the prefix. Every tensor a decoder makes lives on the device of its inputs,
so a model moved to a GPU decodes there.

NFE per chunk, by construction: bidirectional T; block_diffusion blocks x steps_per_block;
autoregressive one per action token.
"""

from __future__ import annotations

import torch
from torch import Tensor

from policies.dvla.decoding import Decoded, Pass, commit_top, committed_lists, score
from policies.dvla.model import ActionTokenModel, KVCache
from policies.dvla.schedules import still_masked


def decode_bidirectional(
    model: ActionTokenModel,
    words: Tensor,
    state: Tensor,
    steps: int = 12,
    schedule: str = "cosine",
    confidence: str = "max_prob",
    remask: float = 0.0,
    reuse_prefix_cache: bool = False,
    images: Tensor | None = None,
    temperature: float = 0.0,
    generator: torch.Generator | None = None,
) -> Decoded:
    """MaskGIT-style parallel refinement over all action tokens, T forward passes.

    remask > 0 is DD-VLA's secondary remasking: after step t, committed tokens whose
    confidence is below remask * t / T return to [MASK] (never on the last step). Their
    confidence is read from the logits at their own, now visible, positions, which the
    masked-diffusion loss never scores (it scores masked positions only): what the model
    predicts there is untrained, so treat remasking with these weights as an ablation.
    reuse_prefix_cache computes the prefix once and reuses its keys/values: exact when
    the prefix does not see the actions, stale when it does (a prefix cache that is never
    refreshed; policies/dvla/fast_dllm.py is Fast-dLLM proper, refreshed at block boundaries).
    """
    cfg = model.cfg
    b, total, dev = words.shape[0], cfg.action_tokens, words.device
    gen = generator or torch.Generator().manual_seed(0)
    tokens = torch.full((b, total), cfg.mask_id, dtype=torch.long, device=dev)
    positions = torch.arange(total, device=dev)
    out = Decoded(tokens)
    cache: KVCache | None = None
    for step in range(1, steps + 1):
        if cache is None:
            result = model(tokens, positions, words, state, images=images)
            if reuse_prefix_cache:
                cache = result.kv.select(result.kv.positions < cfg.prefix_len)
            out.passes.append(Pass(list(range(total)), True, 0, []))
        else:
            result = model(tokens, positions, cache=cache)
            out.passes.append(Pass(list(range(total)), False, len(cache), []))
        choice, conf = score(result.logits, confidence, temperature, gen)
        masked = tokens == cfg.mask_id
        target = still_masked(schedule, step, steps, total)
        count = (masked.sum(-1) - target).clamp(min=1 if step < steps else total)
        commit = commit_top(masked, conf, count)
        tokens = torch.where(commit, choice, tokens)
        out.passes[-1].committed = committed_lists(commit, positions)
        if remask > 0 and step < steps:
            probs = torch.softmax(result.logits.float(), dim=-1)
            committed_conf = probs.gather(-1, tokens.clamp(max=cfg.bins - 1).unsqueeze(-1)).squeeze(-1)
            weak = (~masked) & (committed_conf < remask * step / steps)
            tokens = torch.where(weak, torch.full_like(tokens, cfg.mask_id), tokens)
    out.tokens = tokens
    return out


def decode_autoregressive(
    model: ActionTokenModel,
    words: Tensor,
    state: Tensor,
    temperature: float = 0.0,
    generator: torch.Generator | None = None,
    images: Tensor | None = None,
) -> Decoded:
    """One token per forward pass with a KV cache. Input at action position i is token
    i-1 ([MASK] stands for 'begin' at position 0); its logits predict token i."""
    cfg = model.cfg
    b, total, dev = words.shape[0], cfg.action_tokens, words.device
    gen = generator or torch.Generator().manual_seed(0)
    tokens = torch.empty((b, total), dtype=torch.long, device=dev)
    previous = torch.full((b, 1), cfg.mask_id, dtype=torch.long, device=dev)
    out = Decoded(tokens)
    cache: KVCache | None = None
    for i in range(total):
        pos = torch.tensor([i], device=dev)
        if cache is None:
            result = model(previous, pos, words, state, images=images)
            out.passes.append(Pass([i], True, 0, [[i]] * b))
        else:
            result = model(previous, pos, cache=cache)
            out.passes.append(Pass([i], False, len(cache), [[i]] * b))
        cache = result.kv if cache is None else cache.extend(result.kv)
        choice, _ = score(result.logits[:, -1], "max_prob", temperature, gen)
        tokens[:, i] = choice
        previous = choice.unsqueeze(1)
    return out


def decode_block_diffusion(
    model: ActionTokenModel,
    words: Tensor,
    state: Tensor,
    steps_per_block: int = 4,
    schedule: str = "linear",
    confidence: str = "max_prob",
    images: Tensor | None = None,
    temperature: float = 0.0,
    generator: torch.Generator | None = None,
) -> Decoded:
    """Blocks strictly one after another, a fixed number of steps each. A finished
    block is re-run once with its final tokens as part of the next block's first pass,
    which gives its exact keys/values for the cache at no extra forward pass."""
    cfg = model.cfg
    b, total, k, dev = words.shape[0], cfg.action_tokens, cfg.block, words.device
    gen = generator or torch.Generator().manual_seed(0)
    tokens = torch.full((b, total), cfg.mask_id, dtype=torch.long, device=dev)
    out = Decoded(tokens)
    cache: KVCache | None = None
    finished: Tensor | None = None  # positions of the block whose keys are not cached yet
    for start in range(0, total, k):
        block = torch.arange(start, start + k, device=dev)
        for step in range(1, steps_per_block + 1):
            run = block if finished is None else torch.cat([finished, block])
            if cache is None:
                result = model(tokens[:, run], run, words, state, images=images)
            else:
                result = model(tokens[:, run], run, cache=cache)
            out.passes.append(Pass(run.tolist(), cache is None, 0 if cache is None else len(cache), []))
            if finished is not None or cache is None:
                keep = result.kv.positions < cfg.prefix_len + start  # prefix and finished block
                done = result.kv.select(keep)
                cache = done if cache is None else cache.extend(done)
                finished = None
            choice, conf = score(result.logits[:, -k:], confidence, temperature, gen)
            masked = tokens[:, block] == cfg.mask_id
            target = still_masked(schedule, step, steps_per_block, k)
            count = (masked.sum(-1) - target).clamp(min=1 if step < steps_per_block else k)
            commit = commit_top(masked, conf, count)
            tokens[:, block] = torch.where(commit, choice, tokens[:, block])
            out.passes[-1].committed = committed_lists(commit, block)
        finished = block
    out.tokens = tokens
    return out
