"""What every decoder shares: the record of a decode, scoring, and commit rules.

A decode is a sequence of forward passes. Each `Pass` records what the pass processed
(the action positions run as queries, whether the observation prefix was computed, how
many positions were read from the KV cache) and what it committed, per batch row. That
record is what `--traces` writes and what benchmarks/decoders.py replays at paper-like
shapes, so a speedup can be explained by passes, tokens processed and tokens read from
cache rather than by time alone.

Confidence measures (how positions are ranked for committing):
    max_prob  probability of the chosen token (LLaDA's "low_confidence" remasking)
    margin    its margin over the runner-up
    entropy   negative entropy of the position's distribution
    random    a seeded uniform draw (LLaDA's "random" remasking)
Temperature > 0 samples the chosen token from softmax(logits / temperature) (the
Gumbel-max trick of LLaDA and Fast-dLLM); its confidence is still read from the
untempered distribution, as theirs is. Nothing reads global random state: a decoder
given the same inputs and the same generator seed returns the same tokens.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor


@dataclass
class Pass:
    """One forward pass over a batch: what it processed and what it committed."""

    query: list[int]  # action positions run as queries, in the order run
    prefix: bool  # whether the observation prefix was computed (not read from cache)
    cached: int  # positions read from the KV cache (prefix positions included)
    committed: list[list[int]]  # per batch row, the action positions this pass committed


@dataclass
class Decoded:
    tokens: Tensor  # (B, A) in [0, bins)
    passes: list[Pass] = field(default_factory=list)

    @property
    def trace(self) -> list[list[int]]:
        """Batch row 0's committed positions, one list per forward pass."""
        return [p.committed[0] for p in self.passes]

    def row_trace(self, row: int) -> dict[str, Any]:
        """One batch row's decode trace, as `ChunkBatch.trace` carries it per slot: per
        pass the positions it committed, the action positions it ran, whether it ran
        the prefix, and how many cached positions it read."""
        return {
            "committed": [p.committed[row] for p in self.passes],
            "query": [p.query for p in self.passes],
            "prefix": [p.prefix for p in self.passes],
            "cached": [p.cached for p in self.passes],
        }


def score(
    logits: Tensor, confidence: str, temperature: float = 0.0, generator: torch.Generator | None = None
) -> tuple[Tensor, Tensor]:
    """(choice, confidence) per position from logits (..., bins). Decoders pass their
    own seeded generator; None (a direct call) draws from a fixed seed, never from
    global random state."""
    if generator is None and (temperature > 0 or confidence == "random"):
        generator = torch.Generator().manual_seed(0)
    probs = torch.softmax(logits.float(), dim=-1)
    if temperature > 0:
        tempered = torch.softmax(logits.float() / temperature, dim=-1)
        flat = tempered.reshape(-1, tempered.shape[-1])
        drawn = torch.multinomial(flat.cpu(), 1, generator=generator)  # a CPU generator
        choice = drawn.view(tempered.shape[:-1]).to(logits.device)
    else:
        choice = probs.argmax(-1)
    if confidence == "margin":
        top2 = probs.topk(2, dim=-1).values
        conf = top2[..., 0] - top2[..., 1]
    elif confidence == "entropy":
        conf = (probs * probs.clamp_min(1e-12).log()).sum(-1)
    elif confidence == "random":
        conf = torch.rand(choice.shape, generator=generator).to(choice.device)
    else:
        conf = probs.gather(-1, choice.unsqueeze(-1)).squeeze(-1)
    return choice, conf


def commit_top(masked: Tensor, conf: Tensor, count: Tensor) -> Tensor:
    """Per row, the `count` most confident masked positions (bool, same shape)."""
    ranked = conf.masked_fill(~masked, -math.inf)
    rank = ranked.argsort(dim=-1, descending=True).argsort(dim=-1)
    return masked & (rank < count.unsqueeze(-1))


def commit_confident(masked: Tensor, conf: Tensor, threshold: float) -> Tensor:
    """Fast-dLLM's parallel rule: every masked position whose confidence reaches
    `threshold`, and at least the most confident one in every row that has any left."""
    top = commit_top(masked, conf, torch.ones(masked.shape[0], dtype=torch.long, device=masked.device))
    return top | (masked & (conf >= threshold))


def committed_lists(commit: Tensor, positions: Tensor) -> list[list[int]]:
    """Per row, the action positions a (B, n) commit mask over `positions` selects."""
    rows, cols = commit.nonzero(as_tuple=True)
    out: list[list[int]] = [[] for _ in range(commit.shape[0])]
    for r, p in zip(rows.tolist(), positions[cols].tolist(), strict=True):
        out[r].append(p)
    return [sorted(row) for row in out]
