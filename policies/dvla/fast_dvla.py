"""Fast-dVLA's pipelined parallel decoding over a block-causal model.

Blocks are inactive, semi-activated or fully activated. Block i+1 is added (semi) once
block i's decoded fraction exceeds tau_add, and fully activated once it exceeds tau_act
(or when block i is complete, so tau_add = tau_act = 1 is block-by-block). A
semi-activated block commits tokens with confidence >= tau_conf. A fully activated block
with R masked tokens commits every token with confidence >= min(tau_conf, k-th highest
confidence), k = floor(R / n).

Progress rule (the sources are silent): when that commits nothing, including R = 1 where
k = 0, the block commits its single most confident token, so every forward pass
finishes at least one token and a chunk takes at most A passes.

What each pass runs: every block from the first one not yet in the KV cache up to the
last block still decoding. That includes blocks that finished out of order (a
semi-activated block whose tokens all cleared tau_conf before its predecessor finished):
their keys depend on the unfinished predecessor, so they cannot be cached yet, and the
blocks after them must still see them. A block's keys/values are cached once it and
every block before it are complete, computed in the next pass that runs anyway.

A batch decodes in one forward pass per step: each row keeps its own block states, the
pass runs the union of the rows' ranges (the extra positions are exact too: later
blocks never change earlier ones), and a row that has finished waits for the others.
Each row commits exactly what it would commit decoded alone.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from policies.dvla.decoding import Decoded, Pass, score
from policies.dvla.model import ActionTokenModel, KVCache

INACTIVE, SEMI, FULL = 0, 1, 2


def commit_semi(masked: np.ndarray, conf: np.ndarray, tau_conf: float) -> np.ndarray:
    """A semi-activated block: only tokens that clear tau_conf (possibly none)."""
    return masked & (conf >= tau_conf)


def commit_full(masked: np.ndarray, conf: np.ndarray, tau_conf: float, n: int) -> np.ndarray:
    """A fully activated block: confidence >= min(tau_conf, k-th highest of the masked
    ones), k = floor(R / n); at least its most confident masked token."""
    kth = int(masked.sum()) // n
    threshold = tau_conf
    if kth >= 1:
        threshold = min(tau_conf, float(np.sort(conf[masked])[-kth]))
    commit = masked & (conf >= threshold)
    if masked.any() and not commit.any():
        commit[int(np.argmax(np.where(masked, conf, -np.inf)))] = True
    return commit


def advance(
    status: np.ndarray, done: np.ndarray, sizes: np.ndarray | int, tau_add: float, tau_act: float
) -> None:
    """Promote blocks after a pass (in place): block i+1 becomes semi-activated once
    block i's decoded fraction exceeds tau_add, fully activated once it exceeds tau_act,
    and both once block i is complete. `sizes`: tokens per block (or one size for all)."""
    sizes = np.broadcast_to(sizes, done.shape)
    for i in range(len(status) - 1):
        if status[i] == INACTIVE:
            break
        fraction, complete = done[i] / sizes[i], done[i] == sizes[i]
        if status[i + 1] == INACTIVE and (fraction > tau_add or complete):
            status[i + 1] = SEMI
        if status[i + 1] == SEMI and (fraction > tau_act or complete):
            status[i + 1] = FULL


def random_block_sizes(total: int, mean: int, generator: torch.Generator) -> list[int]:
    """Block sizes for the paper's random-block-size ablation: each drawn uniformly from
    1..2*mean-1 (so `mean` on average), the last cut to fit the chunk."""
    sizes: list[int] = []
    while sum(sizes) < total:
        draw = int(torch.randint(1, 2 * mean, (1,), generator=generator))
        sizes.append(min(draw, total - sum(sizes)))
    return sizes


def block_mask(prefix_len: int, starts: np.ndarray, total: int, query: Tensor, keys: Tensor) -> Tensor:
    """The block-causal rule `group(key) <= group(query)` for blocks that start at
    `starts`, over absolute positions (prefix in group -1): what the model's own mask
    does for equal blocks, for a partition of the decoder's choosing."""
    groups = torch.full((prefix_len + total,), -1, dtype=torch.long)
    groups[prefix_len:] = torch.from_numpy(np.searchsorted(starts, np.arange(total), side="right") - 1)
    groups = groups.to(query.device)
    return groups[keys][None, :] <= groups[query][:, None]


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
    temperature: float = 0.0,
    generator: torch.Generator | None = None,
    block_sizes: list[int] | None = None,
) -> Decoded:
    """`block_sizes` replaces the model's equal blocks by another partition of the chunk
    (the random-block-size ablation); the attention mask follows it."""
    # Bookkeeping (which block is where, what to commit) runs in numpy on one copy of
    # each pass's choices and confidences: per-token tensor ops cost more than a small
    # model's forward pass, and this loop runs once per pass.
    cfg = model.cfg
    rows, total, dev = words.shape[0], cfg.action_tokens, words.device
    gen = generator or torch.Generator().manual_seed(0)
    sizes = np.asarray(block_sizes or [cfg.block] * (total // cfg.block))
    if sizes.sum() != total or (sizes < 1).any():
        raise ValueError(f"block sizes {sizes.tolist()} do not partition the chunk's {total} tokens")
    starts = np.concatenate([[0], np.cumsum(sizes)])  # block i is starts[i]:starts[i + 1]
    uniform = not block_sizes or (sizes == cfg.block).all()
    blocks = len(sizes)
    tokens = np.full((rows, total), cfg.mask_id, dtype=np.int64)
    done = np.zeros((rows, blocks), dtype=np.int64)  # committed tokens per block
    status = np.full((rows, blocks), INACTIVE, dtype=np.int8)
    status[:, 0] = FULL
    out = Decoded(torch.empty(0))
    cache: KVCache | None = None
    cached = 0  # leading blocks whose keys/values are in the cache (complete in every row)
    while (done < sizes).any():
        open_ = (done < sizes) & (status != INACTIVE)  # blocks decoding, per row
        first_open = int(np.argmax(done < sizes, axis=1)[(done < sizes).any(axis=1)].min())
        last = int(np.nonzero(open_.any(axis=0))[0].max())
        first_run = cached
        run_np = np.arange(starts[first_run], starts[last + 1])
        run = torch.from_numpy(run_np).to(dev)
        inputs = torch.from_numpy(tokens[:, run_np]).to(dev)
        extra = {}  # equal blocks: the model's own mask; other partitions bring theirs
        if not uniform:
            query = run + cfg.prefix_len
            if cache is None:
                query = torch.cat([torch.arange(cfg.prefix_len, device=dev), query])
            keys = query if cache is None else torch.cat([cache.positions, query])
            extra["attn_mask"] = block_mask(cfg.prefix_len, starts, total, query, keys)
        if cache is None:
            result = model(inputs, run, words, state, images=images, **extra)
        else:
            result = model(inputs, run, cache=cache, **extra)
        out.passes.append(Pass(run_np.tolist(), cache is None, 0 if cache is None else len(cache), []))
        if cache is None or first_open > cached:
            finished = result.kv.select(result.kv.positions < cfg.prefix_len + starts[first_open])
            cache = finished if cache is None else cache.extend(finished)
            cached = first_open
        choice_t, conf_t = score(result.logits, confidence, temperature, gen)
        choice, conf = choice_t.cpu().numpy(), conf_t.cpu().numpy()
        for r in range(rows):
            committed: list[int] = []
            for i in np.nonzero(open_[r])[0]:
                at = slice(starts[i] - starts[first_run], starts[i + 1] - starts[first_run])
                pos, c = run_np[at], conf[r, at]
                masked = tokens[r, pos] == cfg.mask_id
                if status[r, i] == SEMI:
                    commit = commit_semi(masked, c, tau_conf)
                else:
                    commit = commit_full(masked, c, tau_conf, n)
                tokens[r, pos[commit]] = choice[r, at][commit]
                done[r, i] += int(commit.sum())
                committed += pos[commit].tolist()
            out.passes[-1].committed.append(sorted(committed))
            advance(status[r], done[r], sizes, tau_add, tau_act)
    out.tokens = torch.from_numpy(tokens).to(dev)
    return out
