"""The block_diffusion recipe as BD3-LM trains it: clean earlier blocks in context, a
D2F noise schedule beside the project's own, and fine-tuning from a bidirectional teacher."""

from __future__ import annotations

import hashlib

import pytest
import torch

from policies.dvla.checkpoint import load
from policies.dvla.losses import block_ratios, clean_context_logits, recipe_loss
from policies.dvla.policy import checkpoint_fields
from policies.dvla.recipes import TrainConfig
from policies.dvla.training import train
from tests.fakes import TINY_TRAIN, tiny_model

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

TINY = TINY_TRAIN


def _inputs(model, batch=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    n = model.cfg.action_tokens
    clean = torch.randint(0, model.cfg.bins, (batch, n), generator=g)
    noisy = torch.where(torch.rand(batch, n, generator=g) < 0.5, model.cfg.mask_id, clean)
    words, state = torch.randint(1, 20, (batch, 5), generator=g), torch.randn(batch, 6, generator=g)
    return clean, noisy, words, state, torch.arange(n)


def test_a_noisy_block_reads_the_clean_copy_of_earlier_blocks_only():
    """Noisy block i's logits do not move when clean block i or a later one changes, and
    do when an earlier one does; and they equal what block-by-block decoding computes
    (clean blocks < i, then block i as it is) under the model's block-causal pattern."""
    model = tiny_model("block_causal")
    k, blocks = model.cfg.block, model.cfg.action_tokens // model.cfg.block
    clean, noisy, words, state, positions = _inputs(model)
    base = clean_context_logits(model, clean, noisy, positions, words, state)
    for j in range(blocks):
        changed = clean.clone()
        changed[:, j * k : (j + 1) * k] = (changed[:, j * k : (j + 1) * k] + 1) % model.cfg.bins
        moved = clean_context_logits(model, changed, noisy, positions, words, state) - base
        per_block = moved.abs().amax(dim=(0, 2)).view(blocks, k).amax(dim=1)
        assert (per_block[: j + 1] == 0).all(), (j, per_block)  # block j itself and earlier ones
        assert (per_block[j + 1 :] > 1e-4).all(), (j, per_block)  # every later block reads it
    for i in range(blocks):
        seen = torch.cat([clean[:, : i * k], noisy[:, i * k : (i + 1) * k]], dim=1)
        decoded = model(seen, positions[: (i + 1) * k], words, state).logits[:, i * k :]
        torch.testing.assert_close(base[:, i * k : (i + 1) * k], decoded, atol=1e-5, rtol=1e-5)


def test_the_clean_context_loss_trains_through_the_clean_copy_too():
    model = tiny_model("block_causal").train()
    clean, _, words, state, positions = _inputs(model, batch=8)
    all_masked = torch.full_like(clean, model.cfg.mask_id)  # clean tokens appear in the clean copy only
    clean_context_logits(model, clean, all_masked, positions, words, state).logsumexp(-1).sum().backward()
    read = clean[:, : -model.cfg.block].unique()  # the last clean block is no block's context
    assert model.tokens.weight.grad[read].abs().sum(-1).min() > 0

    g = torch.Generator().manual_seed(0)
    loss = recipe_loss("block_diffusion", "clean_context", model, None, clean, words, state, positions, g)
    g = torch.Generator().manual_seed(0)
    frontier = recipe_loss("block_diffusion", "frontier", model, None, clean, words, state, positions, g)
    assert torch.isfinite(loss) and not torch.isclose(loss, frontier)


def test_d2f_ratios_start_in_range_and_only_grow_within_it():
    ratios = block_ratios("d2f", 4096, 8, torch.Generator().manual_seed(0))
    assert ratios.shape == (4096, 8)
    assert (ratios >= 0.2).all() and (ratios <= 0.7 + 1e-6).all()
    assert (ratios.diff(dim=1) >= 0).all()
    assert ratios[:, 0].min() < 0.25 and ratios[:, 0].max() > 0.65  # the start covers the range
    assert (ratios.diff(dim=1) > 0).float().mean() > 0.99  # random increments, not a constant
    clean = block_ratios("clean_context", 4096, 8, torch.Generator().manual_seed(0))
    assert (clean.diff(dim=1) < 0).any() and clean.min() < 0.01 and clean.max() > 0.99  # independent U(0, 1)


def test_block_diffusion_starts_from_a_bidirectional_teacher(demos, tmp_path):
    teacher = tmp_path / "teacher.safetensors"
    train(TrainConfig(recipe="bidirectional", **{**TINY, "steps": 10}), demos, teacher)
    bd, student = tmp_path / "bd.safetensors", tmp_path / "student.safetensors"
    few = {**TINY, "steps": 5}
    report = train(TrainConfig(recipe="block_diffusion", init=str(teacher), probe_every=5, **few), demos, bd)
    distilled = train(
        TrainConfig(recipe="distill", teacher=str(teacher), probe_every=5, **few), demos, student
    )
    # Both recipes start from the teacher's very weights (one yardstick, same first value).
    assert report.probes[0][1] == pytest.approx(distilled.probes[0][1], rel=1e-6)
    assert report.clean_probes[0][1] == pytest.approx(distilled.clean_probes[0][1], rel=1e-6)
    ckpt, source = load(bd), load(teacher)
    assert ckpt.model.cfg.pattern == "block_causal" and ckpt.model.cfg.block == source.model.cfg.action_dim
    assert ckpt.vocab == source.vocab and ckpt.tokenizer.to_dict() == source.tokenizer.to_dict()
    assert (ckpt.state_mean == source.state_mean).all() and (ckpt.state_std == source.state_std).all()
    assert ckpt.meta["init_sha256"] == hashlib.sha256(teacher.read_bytes()).hexdigest()
    assert ckpt.meta["train_config"]["noise_schedule"] == "clean_context"

    wider = train(
        TrainConfig(recipe="block_diffusion", init=str(teacher), block_size=8, **{**TINY, "steps": 1}),
        demos,
        tmp_path / "wider.safetensors",
    )
    assert load(wider.checkpoint).model.cfg.block == 8

    with pytest.raises(ValueError, match="only block_diffusion starts from a bidirectional model"):
        train(
            TrainConfig(recipe="autoregressive", init=str(teacher), **TINY),
            demos,
            tmp_path / "ar.safetensors",
        )
    assert not (tmp_path / "ar.safetensors").exists()


def test_each_recipe_records_the_noise_schedule_it_used(demos, tmp_path, cli):
    one = {**TINY, "steps": 1}
    teacher = tmp_path / "t.safetensors"
    train(TrainConfig(recipe="bidirectional", **one), demos, teacher)
    runs = {
        "bd": TrainConfig(recipe="block_diffusion", **one),
        "bd-d2f": TrainConfig(recipe="block_diffusion", noise_schedule="d2f", **one),
        "distill": TrainConfig(recipe="distill", teacher=str(teacher), **one),
    }
    for name, cfg in runs.items():
        train(cfg, demos, tmp_path / f"{name}.safetensors")
    recorded = {
        name: checkpoint_fields(str(tmp_path / f"{name}.safetensors"))["noise_schedule"] for name in runs
    }
    assert recorded == {"bd": "clean_context", "bd-d2f": "d2f", "distill": "frontier"}
    assert load(teacher).meta["train_config"]["noise_schedule"] == ""  # it draws no block ratios

    base = ["train", "--demos", str(demos), "--steps", "1", "--out", str(tmp_path / "x.safetensors")]
    code, _, err = cli(
        *base, "--recipe", "distill", "--teacher", str(teacher), "--noise-schedule", "clean_context"
    )
    assert code == 2 and "distill matches the teacher" in err and "frontier (its default)" in err
    code, _, err = cli(*base, "--recipe", "bidirectional", "--noise-schedule", "frontier")
    assert code == 2 and "only block_diffusion and distill take a noise schedule" in err
    assert not (tmp_path / "x.safetensors").exists()


def test_distill_adds_the_demonstrations_cross_entropy_only_when_asked(demos, tmp_path, cli):
    """--demo-ce W: KL to the teacher plus W x the cross-entropy against the demonstrated
    tokens on the masked positions, a noisy row's first action only."""
    student = tiny_model("block_causal")
    teacher = tiny_model("bidirectional")
    clean, _, words, state, positions = _inputs(student, batch=6)
    first_only = torch.tensor([True, False, True, False, False, True])
    seen = []
    student.register_forward_hook(lambda _m, args, out: seen.append((args[0], out.logits)))

    def loss(w: float) -> torch.Tensor:
        g = torch.Generator().manual_seed(3)
        args = (student, teacher, clean, words, state, positions, g)
        return recipe_loss("distill", "frontier", *args, first_only=first_only, demo_ce=w)

    kl = loss(0.0)
    mixed = loss(0.5)
    noisy, logits = seen[-1]
    masked = noisy == student.cfg.mask_id
    later = first_only[:, None] & (positions >= student.cfg.action_dim)[None, :]
    assert (masked & later).any() and (masked & ~later).any()  # both kinds are in the batch
    ce = torch.nn.functional.cross_entropy(logits[masked & ~later], clean[masked & ~later])
    torch.testing.assert_close(mixed, kl + 0.5 * ce)
    assert torch.equal(seen[0][0], noisy)  # the weight draws nothing: the same masks

    base = ["train", "--demos", str(demos), "--steps", "1", "--out", str(tmp_path / "x.safetensors")]
    code, _, err = cli(*base, "--recipe", "bidirectional", "--demo-ce", "0.5")
    assert code == 2 and "only distill mixes a cross-entropy term" in err
    code, _, err = cli(*base, "--recipe", "bidirectional", "--demo-ce", "-1")
    assert code == 2 and "demo_ce must be >= 0" in err
    assert not (tmp_path / "x.safetensors").exists()
    one = {**TINY, "steps": 1}
    t = tmp_path / "t.safetensors"
    train(TrainConfig(recipe="bidirectional", **one), demos, t)
    train(
        TrainConfig(recipe="distill", teacher=str(t), demo_ce=0.5, **one), demos, tmp_path / "s.safetensors"
    )
    assert load(tmp_path / "s.safetensors").meta["train_config"]["demo_ce"] == 0.5
