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
from dataclasses import asdict, dataclass, field

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
    # The first convolution also reads each pixel's x and y (CoordConv, Liu et al. 2018):
    # average pooling keeps what is in a cell, not where in it; with the coordinates a
    # filter can say where, which a policy without object poses needs to reach a cube.
    image_coords: bool = False

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
    """Keys/values of some absolute positions, one (B, heads, n, head_dim) pair per layer.

    They sit at the front of per-layer stores with room to grow: extending a cache, and
    running a pass against it, write only the new positions, where concatenating copied
    the whole cache in every layer of every pass (~4% of a Fast-dVLA pass at paper-like
    shapes). Caches extended from one another share stores; `filled` (shared with them)
    counts the stores' committed entries, and a cache writes past its end only when that
    is the stores' end, so extending never changes a cache another was extended from
    (it copies instead). A pass's own keys/values come back in stores without room;
    their `capacity` (all of the model's positions) is what a copy of them gets.
    """

    positions: Tensor  # (n,) long
    key_stores: list[Tensor]  # (B, heads, >= n, head_dim): entries [:n] are this cache's
    value_stores: list[Tensor]
    capacity: int = 0  # positions to allocate when this cache is copied into new stores
    filled: list[int] = field(default_factory=list)  # one int, shared by the stores' caches

    def __post_init__(self) -> None:
        if not self.filled:
            self.filled.append(len(self))

    def __len__(self) -> int:
        return int(self.positions.numel())

    @property
    def keys(self) -> list[Tensor]:
        return [s[:, :, : len(self)] for s in self.key_stores]

    @property
    def values(self) -> list[Tensor]:
        return [s[:, :, : len(self)] for s in self.value_stores]

    def _has_room(self, extra: int) -> bool:
        return self.filled[0] == len(self) and len(self) + extra <= self.key_stores[0].shape[2]

    def joined(self, layer: int, k: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
        """This cache's keys/values of `layer` followed by a pass's own (k, v), to attend
        to: written into the room after the cache when there is some (scratch, part of no
        cache until `extend` commits it), concatenated otherwise."""
        n, m = len(self), k.shape[2]
        ks, vs = self.key_stores[layer], self.value_stores[layer]
        if not self._has_room(m):
            return torch.cat([ks[:, :, :n], k], dim=2), torch.cat([vs[:, :, :n], v], dim=2)
        ks[:, :, n : n + m] = k
        vs[:, :, n : n + m] = v
        return ks[:, :, : n + m], vs[:, :, : n + m]

    def extend(self, other: KVCache) -> KVCache:
        n, m = len(self), len(other)
        positions = torch.cat([self.positions, other.positions])
        if not self._has_room(m):
            return _stored(positions, [self.keys, other.keys], [self.values, other.values], self.capacity)
        for store, new in zip(self.key_stores + self.value_stores, other.keys + other.values, strict=True):
            store[:, :, n : n + m] = new
        self.filled[0] = n + m
        return KVCache(positions, self.key_stores, self.value_stores, self.capacity, self.filled)

    def select(self, keep: Tensor) -> KVCache:
        """The entries whose positions are in `keep` (a bool mask over this cache), in
        stores of their own."""
        keys = [k[:, :, keep] for k in self.keys]
        values = [v[:, :, keep] for v in self.values]
        return _stored(self.positions[keep], [keys], [values], self.capacity)


def _stored(
    positions: Tensor, keys: list[list[Tensor]], values: list[list[Tensor]], capacity: int
) -> KVCache:
    """A cache in fresh stores of max(capacity, n) positions; keys/values are given as
    pieces (each a per-layer list) laid end to end."""
    size = max(capacity, int(positions.numel()))

    def store(pieces: tuple[Tensor, ...]) -> Tensor:
        first = pieces[0]
        out = first.new_empty(first.shape[0], first.shape[1], size, first.shape[3])
        at = 0
        for piece in pieces:
            out[:, :, at : at + piece.shape[2]] = piece
            at += piece.shape[2]
        return out

    return KVCache(
        positions,
        [store(p) for p in zip(*keys, strict=True)],
        [store(p) for p in zip(*values, strict=True)],
        capacity,
    )


@dataclass
class StepOutput:
    logits: Tensor  # (B, n_action_positions, bins)
    kv: KVCache  # keys/values of the positions this call computed (prefix first)


class Attention(nn.Module):
    """`F.scaled_dot_product_attention` as a module without parameters: the harness's
    hooks see each call's query, key and value shapes and count its work (harness/episode/work.py:
    FLOPs, and the positions attended, cached or not). Queries (B, heads, L, E) attend
    keys/values (B, heads, S, E) that end with the call's own L positions."""

    def forward(self, q: Tensor, keys: Tensor, values: Tensor, allowed: Tensor | None) -> Tensor:
        return F.scaled_dot_product_attention(q, keys, values, attn_mask=allowed)


class Block(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.heads = cfg.heads
        self.attention = Attention()
        self.norm1 = nn.LayerNorm(cfg.width)
        self.qkv = nn.Linear(cfg.width, 3 * cfg.width)
        self.proj = nn.Linear(cfg.width, cfg.width)
        self.norm2 = nn.LayerNorm(cfg.width)
        self.ffn = nn.Sequential(nn.Linear(cfg.width, cfg.ffn), nn.GELU(), nn.Linear(cfg.ffn, cfg.width))

    def forward(
        self, x: Tensor, allowed: Tensor, cache: KVCache | None, layer: int
    ) -> tuple[Tensor, Tensor, Tensor]:
        b, n, d = x.shape
        q, k, v = self.qkv(self.norm1(x)).view(b, n, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        keys, values = (k, v) if cache is None else cache.joined(layer, k, v)
        attn = self.attention(q, keys, values, allowed)
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
            nn.Conv2d(5 if cfg.image_coords else 3, 32, 5, stride=2, padding=2),
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
        if self.cfg.image_coords:
            ys = torch.linspace(-0.5, 0.5, h, device=x.device).view(1, 1, h, 1).expand(b * c, 1, h, w)
            xs = torch.linspace(-0.5, 0.5, w, device=x.device).view(1, 1, 1, w).expand(b * c, 1, h, w)
            x = torch.cat([x, xs, ys], dim=1)
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
        attn_mask: Tensor | None = None,  # (n_q, n_k) bool, replaces the pattern's (training)
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
        allowed = self.attention_mask(pos, key_pos) if attn_mask is None else attn_mask
        keys, values = [], []
        for i, block in enumerate(self.blocks):
            x, k, v = block(x, allowed, cache, i)
            keys.append(k)
            values.append(v)
        logits = self.head(self.norm(x[:, x.shape[1] - n_actions :]))
        return StepOutput(logits, KVCache(pos, keys, values, cfg.prefix_len + cfg.action_tokens))
