"""The action-token transformer every decoder runs on.

Sequence layout: [instruction words | state tokens | image tokens | action tokens]. All
but the last form the prefix (length P; image tokens only when the model was trained on
camera images: a small strided CNN per camera, pooled to a few tokens); action token a
sits at absolute position P + a. Which key a
query may attend to follows one rule, `group(key) <= group(query)`, with the prefix in
group -1 and action token a in group:

    bidirectional  0 for every action token (and, Dream-VLA style, the prefix sees the
                   actions too unless `prefix_sees_actions` is off)
    block_causal   a // block_size   (a block sees the prefix, earlier blocks, itself)
    causal         a                 (autoregressive)

The narrow interface the decoders use is one call, `model(...)`: run some positions
(the prefix, some action positions, or both) against an optional `KVCache` of earlier
positions and get logits for the action positions plus those positions' keys/values.
One call is one forward pass, which is what the harness's NFE hooks count. A larger
model (e.g. a transformers causal LM with a custom 4-D mask) can implement the same
call.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

PATTERNS = ("bidirectional", "block_causal", "causal")


@dataclass(frozen=True)
class ModelConfig:
    action_dim: int
    chunk_len: int
    state_dim: int
    bins: int = 256
    vocab_words: int = 256  # instruction word ids 1..vocab_words-1; 0 pads
    max_words: int = 12
    state_tokens: int = 3
    width: int = 128
    layers: int = 4
    heads: int = 4
    ffn: int = 512
    pattern: str = "bidirectional"
    block_size: int = 0  # action tokens per block; 0 = one action step (action_dim)
    prefix_sees_actions: bool = True  # only meaningful for "bidirectional"
    cameras: tuple[str, ...] = ()  # observation keys of the camera images, in token order
    image_size: int = 0  # square images of this many pixels (with cameras)
    image_tokens: int = 4  # tokens per camera (a square number: the pooled feature grid)

    def __post_init__(self) -> None:
        object.__setattr__(self, "cameras", tuple(self.cameras))  # JSON gives a list

    @property
    def action_tokens(self) -> int:
        return self.chunk_len * self.action_dim

    @property
    def prefix_len(self) -> int:
        return self.max_words + self.state_tokens + len(self.cameras) * self.image_tokens

    @property
    def mask_id(self) -> int:
        return self.bins

    @property
    def block(self) -> int:
        return self.block_size or self.action_dim

    def validate(self) -> None:
        if self.pattern not in PATTERNS:
            raise ValueError(f"pattern {self.pattern!r} is not one of {', '.join(PATTERNS)}")
        if self.width % self.heads:
            raise ValueError(f"width {self.width} is not divisible by heads {self.heads}")
        if self.action_tokens % self.block:
            raise ValueError(
                f"block size {self.block} does not divide the chunk's {self.action_tokens} action tokens"
            )
        for name in ("action_dim", "chunk_len", "state_dim", "layers", "heads", "width", "ffn"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.cameras:
            side = math.isqrt(self.image_tokens)
            if self.image_tokens < 1 or side * side != self.image_tokens:
                raise ValueError(
                    f"image_tokens must be a square number (1, 4, 9, ...), got {self.image_tokens}"
                )
            if self.image_size < 8 * side:
                raise ValueError(
                    f"image_size {self.image_size} is too small for {self.image_tokens} tokens per "
                    f"camera; use at least {8 * side} pixels"
                )

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class KVCache:
    """Keys/values of some absolute positions, one (B, heads, n, head_dim) pair per layer."""

    positions: Tensor  # (n,) long
    keys: list[Tensor]
    values: list[Tensor]

    def __len__(self) -> int:
        return int(self.positions.numel())

    def extend(self, other: KVCache) -> KVCache:
        return KVCache(
            torch.cat([self.positions, other.positions]),
            [torch.cat([a, b], dim=2) for a, b in zip(self.keys, other.keys, strict=True)],
            [torch.cat([a, b], dim=2) for a, b in zip(self.values, other.values, strict=True)],
        )

    def select(self, keep: Tensor) -> KVCache:
        """The entries whose positions are in `keep` (a bool mask over this cache)."""
        return KVCache(
            self.positions[keep], [k[:, :, keep] for k in self.keys], [v[:, :, keep] for v in self.values]
        )


@dataclass
class StepOutput:
    logits: Tensor  # (B, n_action_positions, bins)
    kv: KVCache  # keys/values of the positions this call computed (prefix first)


class Block(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.heads = cfg.heads
        self.norm1 = nn.LayerNorm(cfg.width)
        self.qkv = nn.Linear(cfg.width, 3 * cfg.width)
        self.proj = nn.Linear(cfg.width, cfg.width)
        self.norm2 = nn.LayerNorm(cfg.width)
        self.ffn = nn.Sequential(nn.Linear(cfg.width, cfg.ffn), nn.GELU(), nn.Linear(cfg.ffn, cfg.width))

    def forward(
        self, x: Tensor, allowed: Tensor, past_k: Tensor | None, past_v: Tensor | None
    ) -> tuple[Tensor, Tensor, Tensor]:
        b, n, d = x.shape
        q, k, v = self.qkv(self.norm1(x)).view(b, n, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        keys = k if past_k is None else torch.cat([past_k, k], dim=2)
        values = v if past_v is None else torch.cat([past_v, v], dim=2)
        attn = F.scaled_dot_product_attention(q, keys, values, attn_mask=allowed)
        x = x + self.proj(attn.transpose(1, 2).reshape(b, n, d))
        x = x + self.ffn(self.norm2(x))
        return x, k, v


class ImageEncoder(nn.Module):
    """Camera images to `image_tokens` tokens each: three stride-2 convolutions (1/8 of
    the resolution), average-pooled to a square grid, plus a learned camera embedding.
    Small on purpose: CPU training here, and the state vector carries the geometry."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        w = cfg.width
        self.convs = nn.Sequential(
            nn.Conv2d(3, 32, 5, stride=2, padding=2),
            nn.GELU(),
            nn.Conv2d(32, 64, 3, stride=2, padding=1),
            nn.GELU(),
            nn.Conv2d(64, w, 3, stride=2, padding=1),
            nn.AdaptiveAvgPool2d(math.isqrt(cfg.image_tokens)),
        )
        self.camera = nn.Embedding(len(cfg.cameras), w)

    def forward(self, images: Tensor) -> Tensor:
        """(B, cameras, H, W, 3) uint8 -> (B, cameras * image_tokens, width)."""
        b, c, h, w, _ = images.shape
        x = images.reshape(b * c, h, w, 3).permute(0, 3, 1, 2).float() / 255.0 - 0.5
        feats = self.convs(x).flatten(2).transpose(1, 2)  # (B*C, tokens, width)
        feats = feats.view(b, c, -1, feats.shape[-1]) + self.camera.weight[None, :, None, :]
        return feats.reshape(b, -1, feats.shape[-1])


class ActionTokenModel(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        cfg.validate()
        self.cfg = cfg
        self.words = nn.Embedding(cfg.vocab_words, cfg.width)
        self.state = nn.Sequential(
            nn.Linear(cfg.state_dim, cfg.width), nn.GELU(), nn.Linear(cfg.width, cfg.state_tokens * cfg.width)
        )
        self.images = ImageEncoder(cfg) if cfg.cameras else None
        self.tokens = nn.Embedding(cfg.bins + 1, cfg.width)  # + [MASK]
        self.positions = nn.Embedding(cfg.prefix_len + cfg.action_tokens, cfg.width)
        self.blocks = nn.ModuleList(Block(cfg) for _ in range(cfg.layers))
        self.norm = nn.LayerNorm(cfg.width)
        self.head = nn.Linear(cfg.width, cfg.bins)
        groups = torch.full((cfg.prefix_len + cfg.action_tokens,), -1, dtype=torch.long)
        action = torch.arange(cfg.action_tokens)
        groups[cfg.prefix_len :] = {"bidirectional": action * 0, "block_causal": action // cfg.block}.get(
            cfg.pattern, action
        )
        self.register_buffer("groups", groups, persistent=False)

    def attention_mask(self, query_pos: Tensor, key_pos: Tensor) -> Tensor:
        """(n_q, n_k) bool: may the query at each position attend to each key."""
        cfg = self.cfg
        if cfg.pattern == "bidirectional" and cfg.prefix_sees_actions:
            return torch.ones(len(query_pos), len(key_pos), dtype=torch.bool, device=query_pos.device)
        return self.groups[key_pos][None, :] <= self.groups[query_pos][:, None]

    def forward(
        self,
        action_tokens: Tensor | None = None,  # (B, n) token ids, [MASK] = cfg.mask_id
        action_positions: Tensor | None = None,  # (n,) indices into the chunk, 0..A-1
        words: Tensor | None = None,  # (B, max_words): with state, computes the prefix
        state: Tensor | None = None,  # (B, state_dim)
        cache: KVCache | None = None,  # keys/values of earlier positions to attend to
        images: Tensor | None = None,  # (B, cameras, H, W, 3) uint8, with the prefix
    ) -> StepOutput:
        cfg = self.cfg
        parts, positions = [], []
        if words is not None:
            b = words.shape[0]
            parts += [self.words(words), self.state(state).view(b, cfg.state_tokens, cfg.width)]
            if self.images is not None:
                if images is None:
                    raise ValueError(
                        f"this model reads camera images ({', '.join(cfg.cameras)}); pass images"
                    )
                parts.append(self.images(images))
            positions.append(torch.arange(cfg.prefix_len, device=words.device))
        n_actions = 0
        if action_tokens is not None:
            parts.append(self.tokens(action_tokens))
            positions.append(action_positions + cfg.prefix_len)
            n_actions = action_tokens.shape[1]
        if not parts:
            raise ValueError("nothing to run: pass the prefix (words, state) and/or action tokens")
        x = torch.cat(parts, dim=1)
        pos = torch.cat(positions)
        x = x + self.positions(pos)
        key_pos = pos if cache is None else torch.cat([cache.positions, pos])
        allowed = self.attention_mask(pos, key_pos)
        keys, values = [], []
        for i, block in enumerate(self.blocks):
            past_k = None if cache is None else cache.keys[i]
            past_v = None if cache is None else cache.values[i]
            x, k, v = block(x, allowed, past_k, past_v)
            keys.append(k)
            values.append(v)
        logits = self.head(self.norm(x[:, x.shape[1] - n_actions :]))
        return StepOutput(logits=logits, kv=KVCache(pos, keys, values))
