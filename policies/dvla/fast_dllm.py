"""Fast-dLLM (arXiv 2505.22618) over a bidirectional model, as its reference code does it.

The chunk is decoded block by block. Each block starts with a full forward pass over
the prefix and every action token (its logits are the block's first step, its keys and
values the refreshed cache); the following steps inside the block reuse that cache,
stale as tokens get committed:

    cache=none    every step is a full pass (no cache; parallel decoding only)
    cache=prefix  steps run the block and everything after it against the cached keys
                  of everything before the block (the observation prefix, earlier blocks)
    cache=dual    steps run only the block, against cached keys of everything else,
                  the still-masked suffix included (DualCache, Fast-dLLM's headline)

Confidence-aware parallel decoding: each step commits every masked token of the block
whose confidence reaches `threshold`, and at least the most confident one, so the
number of steps per block, and the NFE per chunk, vary with the model's certainty.
threshold = 0 commits a fixed number per step instead (steps_per_block, `schedule`).

This function's defaults are the paper's settings read literally: DualCache,
threshold 0.9, and a block that is 1/8 of the answer (its 32 of 256 tokens), which on
a chunk of 8 actions is one action step (action_dim tokens, the block Fast-dVLA uses).
That block forces a refresh every few tokens; the registered policy's defaults
(FastDLLMParams) are instead chosen by a sweep on held-out states
(benchmarks/fast_dllm_sweep.py). Any divisor of the chunk can be asked for. In a batch,
rows move to the next block together (a row that finished its block early waits), as
batched Fast-dLLM does; each row commits exactly what it would alone.
"""

from __future__ import annotations

import torch
from torch import Tensor

from policies.dvla.decoding import Decoded, Pass, commit_confident, commit_top, committed_lists, score
from policies.dvla.model import ActionTokenModel, KVCache
from policies.dvla.schedules import CACHE_MODES, still_masked


def decode_fast_dllm(
    model: ActionTokenModel,
    words: Tensor,
    state: Tensor,
    block_size: int = 0,
    threshold: float = 0.9,
    cache: str = "dual",
    steps_per_block: int = 4,
    schedule: str = "linear",
    confidence: str = "max_prob",
    images: Tensor | None = None,
    temperature: float = 0.0,
    generator: torch.Generator | None = None,
) -> Decoded:
    cfg = model.cfg
    b, total, dev = words.shape[0], cfg.action_tokens, words.device
    k = block_size or cfg.action_dim
    if total % k or cache not in CACHE_MODES:
        raise ValueError(f"block_size {k} must divide {total}; cache must be one of {CACHE_MODES}")
    gen = generator or torch.Generator().manual_seed(0)
    tokens = torch.full((b, total), cfg.mask_id, dtype=torch.long, device=dev)
    everything = torch.arange(total, device=dev)
    out = Decoded(tokens)
    for start in range(0, total, k):
        block = everything[start : start + k]
        kv: KVCache | None = None
        step = 0
        while (tokens[:, block] == cfg.mask_id).any():
            step += 1
            if kv is None or cache == "none":
                result = model(tokens, everything, words, state, images=images)
                logits = result.logits[:, start : start + k]
                out.passes.append(Pass(everything.tolist(), True, 0, []))
                if cache == "prefix":
                    kv = result.kv.select(result.kv.positions < cfg.prefix_len + start)
                elif cache == "dual":
                    in_block = (result.kv.positions >= cfg.prefix_len + start) & (
                        result.kv.positions < cfg.prefix_len + start + k
                    )
                    kv = result.kv.select(~in_block)
            else:
                run = block if cache == "dual" else everything[start:]
                logits = model(tokens[:, run], run, cache=kv).logits[:, :k]
                out.passes.append(Pass(run.tolist(), False, len(kv), []))
            choice, conf = score(logits, confidence, temperature, gen)
            masked = tokens[:, block] == cfg.mask_id
            if threshold > 0:
                commit = commit_confident(masked, conf, threshold)
            else:
                target = still_masked(schedule, step, steps_per_block, k)
                count = (masked.sum(-1) - target).clamp(min=1 if step < steps_per_block else k)
                commit = commit_top(masked, conf, count)
            tokens[:, block] = torch.where(commit, choice, tokens[:, block])
            out.passes[-1].committed = committed_lists(commit, block)
    out.tokens = tokens
    return out
