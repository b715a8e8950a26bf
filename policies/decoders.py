"""The five ways to turn an action-token model into an action chunk.

Every decoder talks to the model only through `model(...)` (see policies/model.py), so
each call is one forward pass and the harness's hooks count it. Confidence is the
probability of the arg-max token (`max_prob`) or its margin over the runner-up
(`margin`). Decoding is greedy (arg-max) unless a temperature is given, and never
depends on global random state, so the same inputs give the same tokens.

`images` (camera images, for models trained on them) travel with words and state: they
are part of the prefix. Every tensor a decoder makes lives on the device of its inputs, so a model moved to a
GPU decodes there (benchmarks/decoders.py uses CUDA when it is available).

NFE per chunk, by construction: bidirectional and fast_dllm T; block_diffusion
blocks x steps_per_block; autoregressive one per action token; fast_dvla data-dependent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from policies.model import ActionTokenModel, KVCache
from policies.schedules import still_masked


@dataclass
class Decoded:
    tokens: Tensor  # (B, A) in [0, bins)
    # One entry per forward pass: the action positions committed by it (batch slot 0).
    trace: list[list[int]] = field(default_factory=list)


def _scores(logits: Tensor, confidence: str, temperature: float, gen: torch.Generator | None):
    """(choice, confidence, probabilities) per position from logits (..., bins)."""
    probs = torch.softmax(logits.float(), dim=-1)
    if temperature > 0:
        sample = torch.softmax(logits.float() / temperature, dim=-1)
        flat = sample.reshape(-1, sample.shape[-1])
        choice = torch.multinomial(flat, 1, generator=gen).view(sample.shape[:-1])
    else:
        choice = probs.argmax(-1)
    if confidence == "margin":
        top2 = probs.topk(2, dim=-1).values
        conf = top2[..., 0] - top2[..., 1]
    else:
        conf = probs.gather(-1, choice.unsqueeze(-1)).squeeze(-1)
    return choice, conf, probs


def _commit_top(masked: Tensor, conf: Tensor, count: Tensor) -> Tensor:
    """Per row, the `count` most confident masked positions (bool, same shape)."""
    ranked = conf.masked_fill(~masked, -math.inf)
    order = ranked.argsort(dim=-1, descending=True)
    rank = order.argsort(dim=-1)
    return masked & (rank < count.unsqueeze(-1))


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
) -> Decoded:
    """MaskGIT-style parallel refinement over all action tokens, T forward passes.

    remask > 0 is DD-VLA's secondary remasking: after step t, committed tokens whose
    confidence is below remask * t / T return to [MASK] (never on the last step).
    reuse_prefix_cache computes the prefix once and reuses its keys/values: exact when
    the prefix does not see the actions, stale (the Fast-dLLM approximation) when it does.
    """
    cfg = model.cfg
    b, total, dev = words.shape[0], cfg.action_tokens, words.device
    tokens = torch.full((b, total), cfg.mask_id, dtype=torch.long, device=dev)
    positions = torch.arange(total, device=dev)
    out = Decoded(tokens)
    cache: KVCache | None = None
    for step in range(1, steps + 1):
        if cache is None:
            result = model(tokens, positions, words, state, images=images)
            if reuse_prefix_cache:
                cache = result.kv.select(result.kv.positions < cfg.prefix_len)
        else:
            result = model(tokens, positions, cache=cache)
        choice, conf, probs = _scores(result.logits, confidence, 0.0, None)
        masked = tokens == cfg.mask_id
        target = still_masked(schedule, step, steps, total)
        count = (masked.sum(-1) - target).clamp(min=1 if step < steps else total)
        commit = _commit_top(masked, conf, count)
        tokens = torch.where(commit, choice, tokens)
        out.trace.append(commit[0].nonzero().flatten().tolist())
        if remask > 0 and step < steps:
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
    tokens = torch.empty((b, total), dtype=torch.long, device=dev)
    previous = torch.full((b, 1), cfg.mask_id, dtype=torch.long, device=dev)
    out = Decoded(tokens)
    cache: KVCache | None = None
    for i in range(total):
        pos = torch.tensor([i], device=dev)
        result = (
            model(previous, pos, words, state, images=images)
            if cache is None
            else model(previous, pos, cache=cache)
        )
        cache = result.kv if cache is None else cache.extend(result.kv)
        choice, _, _ = _scores(result.logits[:, -1], "max_prob", temperature, generator)
        tokens[:, i] = choice
        previous = choice.unsqueeze(1)
        out.trace.append([i])
    return out


def decode_block_diffusion(
    model: ActionTokenModel,
    words: Tensor,
    state: Tensor,
    steps_per_block: int = 4,
    schedule: str = "linear",
    confidence: str = "max_prob",
    images: Tensor | None = None,
) -> Decoded:
    """Blocks strictly one after another, a fixed number of steps each. A finished
    block is re-run once with its final tokens as part of the next block's first pass,
    which gives its exact keys/values for the cache at no extra forward pass."""
    cfg = model.cfg
    b, total, k, dev = words.shape[0], cfg.action_tokens, cfg.block, words.device
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
            if finished is not None or cache is None:
                keep = result.kv.positions < cfg.prefix_len + start  # prefix and finished block
                done = result.kv.select(keep)
                cache = done if cache is None else cache.extend(done)
                finished = None
            logits = result.logits[:, -k:]
            choice, conf, _ = _scores(logits, confidence, 0.0, None)
            masked = tokens[:, block] == cfg.mask_id
            target = still_masked(schedule, step, steps_per_block, k)
            count = (masked.sum(-1) - target).clamp(min=1 if step < steps_per_block else k)
            commit = _commit_top(masked, conf, count)
            tokens[:, block] = torch.where(commit, choice, tokens[:, block])
            out.trace.append((block[commit[0]]).tolist())
        finished = block
    out.tokens = tokens
    return out


def decode_fast_dvla(
    model: ActionTokenModel,
    words: Tensor,
    state: Tensor,
    tau_conf: float = 0.5,
    tau_add: float = 2 / 7,
    tau_act: float = 4 / 7,
    n: int = 2,
    confidence: str = "max_prob",
    images: Tensor | None = None,
) -> Decoded:
    """Fast-dVLA's pipelined decoding over a block-causal model.

    Blocks are inactive, semi-activated or fully activated. Block i+1 is added (semi)
    once block i's decoded fraction exceeds tau_add, and fully activated once it exceeds
    tau_act (or when block i is complete, so tau_add = tau_act = 1 is block-by-block).
    A semi-activated block commits tokens with confidence >= tau_conf. A fully activated
    block with R masked tokens commits every token with confidence >=
    min(tau_conf, k-th highest confidence), k = floor(R / n).
    Progress rule (the sources are silent): when that commits nothing, including R = 1
    where k = 0, the block commits its single most confident token, so every forward
    pass finishes at least one token and decoding ends in at most A passes.
    A block's keys/values are cached once it and every block before it are complete,
    computed in the next pass that runs anyway. Batch rows are decoded one at a time
    (their block states diverge).
    """
    rows = [
        _fast_dvla_row(
            model,
            words[i : i + 1],
            state[i : i + 1],
            None if images is None else images[i : i + 1],
            tau_conf,
            tau_add,
            tau_act,
            n,
            confidence,
        )
        for i in range(words.shape[0])
    ]
    out = Decoded(torch.cat([r.tokens for r in rows]), rows[0].trace)
    return out


def _fast_dvla_row(model, words, state, images, tau_conf, tau_add, tau_act, n, confidence) -> Decoded:
    # Bookkeeping (which block is where, what to commit) runs in numpy on one copy of
    # each pass's choices and confidences: per-token tensor ops cost more than a small
    # model's forward pass, and this loop runs once per pass.
    cfg = model.cfg
    total, k, dev = cfg.action_tokens, cfg.block, words.device
    blocks = total // k
    tokens = np.full(total, cfg.mask_id, dtype=np.int64)
    done = np.zeros(blocks, dtype=np.int64)  # committed tokens per block
    status = ["full"] + ["inactive"] * (blocks - 1)
    trace: list[list[int]] = []
    cache: KVCache | None = None
    cached = 0  # leading blocks whose keys/values are in the cache
    while done.sum() < total:
        first_open = int(np.argmax(done < k))
        active = [i for i in range(blocks) if status[i] != "inactive" and done[i] < k]
        run_blocks = sorted(set(range(cached, first_open)) | set(active))
        run_np = np.concatenate([np.arange(i * k, (i + 1) * k) for i in run_blocks])
        run = torch.from_numpy(run_np).to(dev)
        inputs = torch.from_numpy(tokens[run_np]).to(dev)[None]
        if cache is None:
            result = model(inputs, run, words, state, images=images)
        else:
            result = model(inputs, run, cache=cache)
        if cache is None or first_open > cached:
            finished = result.kv.select(result.kv.positions < cfg.prefix_len + first_open * k)
            cache = finished if cache is None else cache.extend(finished)
            cached = first_open
        choice_t, conf_t, _ = _scores(result.logits[0], confidence, 0.0, None)
        choice, conf = choice_t.cpu().numpy(), conf_t.cpu().numpy()
        committed: list[int] = []
        for i in active:
            sel = (run_np >= i * k) & (run_np < (i + 1) * k)
            pos, c = run_np[sel], conf[sel]
            masked = tokens[pos] == cfg.mask_id
            if status[i] == "semi":
                commit = masked & (c >= tau_conf)
            else:
                kth = int(masked.sum()) // n
                threshold = tau_conf
                if kth >= 1:
                    threshold = min(tau_conf, float(np.sort(c[masked])[-kth]))
                commit = masked & (c >= threshold)
                if not commit.any():
                    commit = np.zeros_like(masked)
                    commit[int(np.argmax(np.where(masked, c, -np.inf)))] = True
            tokens[pos[commit]] = choice[sel][commit]
            done[i] += int(commit.sum())
            committed += pos[commit].tolist()
        trace.append(sorted(committed))
        for i in range(blocks - 1):
            if status[i] == "inactive":
                break
            fraction, complete = done[i] / k, done[i] == k
            if status[i + 1] == "inactive" and (fraction > tau_add or complete):
                status[i + 1] = "semi"
            if status[i + 1] == "semi" and (fraction > tau_act or complete):
                status[i + 1] = "full"
    return Decoded(torch.from_numpy(tokens).to(dev)[None], trace)
