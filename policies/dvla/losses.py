"""The training recipes' losses and the noise schedules they draw masks from.

What each recipe and schedule is, and why, is explained in policies/dvla/training.py; this
module is the arithmetic. `recipe_loss` is one batch's loss for a recipe; `probe_loss`
is the one yardstick recipes whose losses differ are compared on.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from policies.dvla.model import ActionTokenModel

D2F_RANGE = (0.2, 0.7)  # Discrete Diffusion Forcing's per-block mask ratios stay in here
PROBE_SEED = 20260


def block_ratios(schedule: str, batch: int, blocks: int, g: torch.Generator) -> torch.Tensor:
    """(batch, blocks) per-block mask ratios: non-decreasing along the chunk for the
    diffusion-forcing schedules, independent per block for `clean_context` (its earlier
    blocks are seen clean, so there is nothing to order)."""
    if schedule == "clean_context":
        return torch.rand(batch, blocks, generator=g)
    if schedule == "sorted_uniform":
        return torch.rand(batch, blocks, generator=g).sort(dim=1).values
    if schedule == "linear":
        t0 = torch.rand(batch, 1, generator=g)
        slope = torch.rand(batch, 1, generator=g) * (1 - t0)
        steps = torch.arange(blocks) / max(blocks - 1, 1)
        return t0 + slope * steps
    if schedule == "d2f":
        # A start ratio in [lo, hi], then N - 1 increments of at most (hi - start) / (N - 1)
        # each, so the last block is at most hi.
        lo, hi = D2F_RANGE
        t0 = lo + (hi - lo) * torch.rand(batch, 1, generator=g)
        steps = torch.rand(batch, blocks - 1, generator=g) * (hi - t0) / max(blocks - 1, 1)
        return torch.cat([t0, t0 + steps.cumsum(dim=1)], dim=1).clamp(max=hi)
    if schedule != "frontier":
        raise ValueError(f"unknown noise schedule {schedule!r}")
    r = torch.rand(batch, 1, generator=g)
    f = torch.randint(0, blocks, (batch, 1), generator=g)
    u = torch.rand(batch, blocks, generator=g).sort(dim=1).values
    i = torch.arange(blocks)[None, :]
    return torch.where(i < f, r * u, torch.where(i == f, r, r + (1 - r) * u))


def clean_context_mask(model: ActionTokenModel, positions: torch.Tensor) -> torch.Tensor:
    """(P + 2n, P + 2n) bool attention mask of the two-stream layout [prefix | clean copy
    of the action positions | noisy copy of them]: the prefix and the clean copy attend
    as the model's own pattern says (block-causal: the prefix sees itself, clean block i
    the prefix and clean blocks <= i); noisy block i sees the prefix, clean blocks < i and
    noisy block i, never clean block i or anything later. This is what block-by-block
    decoding meets: earlier blocks finished (clean, cached), this block being denoised."""
    p = model.cfg.prefix_len
    prefix = torch.arange(p, device=positions.device)
    own = model.attention_mask(
        torch.cat([prefix, positions + p]), torch.cat([prefix, positions + p])
    )  # prefix and clean copy, as the pattern says
    group = model.groups[positions + p]
    n = len(positions)
    mask = torch.zeros(p + 2 * n, p + 2 * n, dtype=torch.bool, device=positions.device)
    mask[: p + n, : p + n] = own
    mask[p + n :, :p] = True
    mask[p + n :, p : p + n] = group[None, :] < group[:, None]
    mask[p + n :, p + n :] = group[None, :] == group[:, None]
    return mask


def clean_context_logits(
    model: ActionTokenModel, clean, noisy, positions, words, state, images=None
) -> torch.Tensor:
    """(B, n, bins) logits of the noisy copy, each block predicted with every earlier
    block clean in context (BD3-LM's training condition), in one forward pass over the
    prefix and both copies; gradients flow through the clean copy's keys/values too."""
    tokens = torch.cat([clean, noisy], dim=1)
    out = model(
        tokens,
        torch.cat([positions, positions]),
        words,
        state,
        images=images,
        attn_mask=clean_context_mask(model, positions),
    )
    return out.logits[:, clean.shape[1] :]


def recipe_loss(
    recipe,
    schedule,
    model,
    teacher,
    clean,
    words,
    state,
    positions,
    g,
    images=None,
    first_only=None,
    demo_ce: float = 0.0,
) -> torch.Tensor:
    """The recipe's loss on one batch. `first_only` (B,) marks rows whose chunk target is
    only its first action (see `first_action_only`); None leaves every row whole.
    `demo_ce` (distill only) adds that weight times the cross-entropy against the
    demonstrated tokens on the masked positions (a noisy row's first action only)."""
    cfg = model.cfg
    b, n = clean.shape
    later = None if first_only is None else first_only[:, None] & (positions >= cfg.action_dim)[None, :]
    if recipe == "autoregressive":
        inputs = torch.cat([torch.full((b, 1), cfg.mask_id, device=clean.device), clean[:, :-1]], dim=1)
        logits = model(inputs, positions, words, state, images=images).logits
        if later is not None:
            return F.cross_entropy(logits[~later], clean[~later])
        return F.cross_entropy(logits.reshape(-1, cfg.bins), clean.reshape(-1))
    if recipe == "bidirectional":
        ratio = torch.rand(b, 1, generator=g).expand(b, n)
    else:
        ratio = block_ratios(schedule, b, n // cfg.block, g).repeat_interleave(cfg.block, dim=1)
    # Drawn on the CPU from g whatever the model's device, so a seed means one set of masks.
    mask = torch.rand(b, n, generator=g) < ratio
    none = ~mask.any(dim=1)
    mask[none, torch.randint(0, n, (int(none.sum()),), generator=g)] = True  # at least one per sample
    mask = mask.to(clean.device)
    scored = mask
    if later is not None and recipe == "distill":
        # The teacher never read a noisy row's later actions (first_action_only hid them in
        # its training): shown them, it predicts from the blur (first-action cross-entropy
        # 7.2 instead of 3.2 on the tray teacher) and the student learns that. Hidden from
        # both, the teacher's answer is a function of the state again.
        mask = scored = mask | later
    elif later is not None:
        mask, scored = first_action_only(mask, later, cfg.action_dim, g)
    noisy = torch.where(mask, torch.full_like(clean, cfg.mask_id), clean)
    if schedule == "clean_context" and recipe != "bidirectional":
        if recipe == "distill":  # TrainConfig.validate refuses it first; this is the guard
            raise ValueError("distill has no clean-context loss")
        # The clean copy of a noisy row's later actions is what it must never read: masked.
        context = clean if later is None else torch.where(later, cfg.mask_id, clean)
        logits = clean_context_logits(model, context, noisy, positions, words, state, images)
        return F.cross_entropy(logits[scored], clean[scored])
    logits = model(noisy, positions, words, state, images=images).logits
    if recipe == "distill":
        with torch.no_grad():
            target = torch.log_softmax(teacher(noisy, positions, words, state, images=images).logits, dim=-1)
        kl = F.kl_div(torch.log_softmax(logits, dim=-1), target, log_target=True, reduction="none").sum(-1)
        loss = kl[mask].mean()
        demo = mask if later is None else mask & ~later
        if demo_ce and demo.any():
            loss = loss + demo_ce * F.cross_entropy(logits[demo], clean[demo])
        return loss
    return F.cross_entropy(logits[scored], clean[scored])


def first_action_only(
    mask: torch.Tensor, later: torch.Tensor, action_dim: int, g: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """(input mask, loss mask) for rows of DART-noisy demonstrations.

    Such a row's chunk is the demonstrator's next H actions, but actions 2..H answer noise
    executed after the row's state, which that state cannot predict: trained on whole, the
    model learns their blur (a spatial teacher fell from 64 to 22 of 100 that way). Only
    the first action is the demonstrator's answer to this state, so only it is scored, and
    the later positions are always [MASK] so the model never reads the blur either.
    Distillation hides them too (in `recipe_loss`), but scores every masked position: its
    target is the teacher's answer, not the demonstration.
    """
    mask = mask | later
    scored = mask & ~later
    rows = ~scored.any(dim=1)
    if rows.any():  # a row whose first action drew no mask: mask one of its tokens
        pick = torch.randint(0, action_dim, (int(rows.sum()),), generator=g).to(mask.device)
        mask[rows.nonzero().squeeze(1), pick] = True
        scored[rows.nonzero().squeeze(1), pick] = True
    return mask, scored


def probe_loss(
    model: ActionTokenModel, clean, words, state, positions, images=None, schedule: str = "frontier"
) -> float:
    """One yardstick for recipes whose training losses differ (KL for distill, CE else).

    Cross-entropy of the true tokens at masked positions, with masks drawn once from a
    fixed seed (block-causal models: per-block ratios of `schedule`, by default
    `frontier`, the conditions pipelined decoding meets, in one stream; `clean_context`
    scores each block with the earlier ones clean, the condition block-by-block decoding
    meets; bidirectional: one ratio per sample; causal: next-token). Comparing it across
    recipes is how steps-to-convergence is measured (benchmarks/convergence.py).
    """
    recipe = {"block_causal": "block_diffusion", "causal": "autoregressive"}.get(
        model.cfg.pattern, "bidirectional"
    )
    g = torch.Generator().manual_seed(PROBE_SEED)
    was_training = model.training
    model.eval()
    with torch.no_grad():
        value = recipe_loss(recipe, schedule, model, None, clean, words, state, positions, g, images).item()
    model.train(was_training)
    return value
