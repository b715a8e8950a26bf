"""Training the action-token model from demonstrations, by recipe.

    bidirectional    masked-diffusion loss: a random mask ratio per sample, cross-entropy
                     on the masked positions; every token sees every token (Dream-VLA).
    autoregressive   next-token loss under the causal pattern ([MASK] stands for 'begin').
    block_diffusion  block-causal pattern, cross-entropy on the masked positions. By
                     default BD3-LM's clean-context loss: every block is noised and
                     predicted with every earlier block clean in context, the condition
                     block-by-block decoding always meets. From scratch, or as the papers
                     build the baseline, with --init from a bidirectional checkpoint (its
                     weights, tokenizer, vocabulary and normalisation carry over; the
                     pattern becomes block-causal, blocks of --block-size or its own).
    distill          Fast-dVLA's asymmetric distillation: a block-causal student that
                     starts from the bidirectional teacher's weights matches the frozen
                     teacher's distribution (KL over masked positions); the teacher sees
                     every noisy block, the student blocks 1..i (a DART row's later
                     actions stay masked for both, as in the teacher's own training).
                     Full fine-tuning (the paper uses LoRA rank 32). Options not in the
                     paper: --demo-ce adds the demonstrations' cross-entropy; --ema (any
                     recipe) saves a moving average of the weights.

Noise schedules (`--noise-schedule`, for block_diffusion and distill; the checkpoint
records the one used). Under block-causal attention a block's loss depends only on the
prefix, itself and earlier blocks, and decoding starts every block fully masked.
    clean_context   block_diffusion's default (BD3-LM): each block's mask ratio ~ U(0, 1),
                    independently, and the model runs two streams in one pass of twice the
                    chunk: a clean copy, block-causal among itself, and a noisy copy whose
                    block i reads the prefix, clean blocks < i and noisy block i, never
                    clean block i (policies/dvla/losses.py). Every scored token sees clean
                    earlier blocks; in one noisy stream only ~10% do. Not for distill: its
                    teacher reads one noisy chunk whole, so there is no clean copy to match.
The diffusion-forcing schedules run one noisy stream with ratios t_1 <= ... <= t_N, so
earlier blocks are cleaner, as in decoding where they are clean or partly decoded:
    frontier        distill's default: a random frontier block f with ratio r ~ U(0, 1);
                    earlier blocks below r, later blocks above it: covers "this block fully
                    masked, the ones before clean or half done" (the project's own).
    d2f             Discrete Diffusion Forcing's (D2F, which Fast-dVLA builds on): a start
                    ratio in [0.2, 0.7] plus random non-negative increments per block,
                    staying within [0.2, 0.7].
    linear          t_i = t_0 + slope * i / (N - 1), t_0 and slope random.
    sorted_uniform  N uniform ratios, sorted: the naive recipe; the first block is rarely
                    near fully masked (kept for ablations).

Reading the demonstrations is policies/dvla/demos.py; the losses, policies/dvla/losses.py.
"""

from __future__ import annotations

import csv
import hashlib
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from policies.dvla.checkpoint import Checkpoint, load, save, words_of
from policies.dvla.demos import Demos, load_demos
from policies.dvla.losses import PROBE_SEED, probe_loss, recipe_loss
from policies.dvla.model import ActionTokenModel, ModelConfig
from policies.dvla.recipes import ACTION_RANGES, PATTERN, TrainConfig
from policies.dvla.tokenizer import ActionTokenizer
from policies.observations import relative_positions


def _lr(step: int, cfg: TrainConfig) -> float:
    warmup = cfg.warmup if cfg.warmup_steps is None else cfg.warmup_steps
    if step < warmup:
        return cfg.lr * (step + 1) / warmup
    progress = (step - warmup) / max(1, cfg.steps - warmup)
    return cfg.lr * 0.5 * (1 + math.cos(math.pi * progress))


def _student_weights(cfg: TrainConfig, teacher: Checkpoint, student_cfg: ModelConfig) -> dict:
    """The teacher's weights, or with --init those of a student of this very teacher:
    continued distillation, which must not mix in another teacher's tokenizer or targets."""
    if not cfg.init:
        return teacher.model.state_dict()
    student = load(cfg.init)
    if student.model.cfg != student_cfg:
        raise ValueError(
            f"{cfg.init}: not a block-causal student of this teacher's shape "
            f"(pattern {student.model.cfg.pattern!r}, block size {student.model.cfg.block})"
        )
    if student.meta.get("teacher_sha256") != _sha256(cfg.teacher):
        raise ValueError(
            f"{cfg.init}: was distilled from another teacher (its teacher_sha256 "
            f"{str(student.meta.get('teacher_sha256'))[:12]!r} is not {cfg.teacher}'s)"
        )
    return student.model.state_dict()


def _prepare(cfg: TrainConfig, demos: Demos) -> tuple[Checkpoint, ActionTokenModel | None]:
    """The checkpoint to train (model, tokenizer, vocab, normalisation) and the teacher."""
    if cfg.recipe == "distill":
        teacher = load(cfg.teacher)
        if teacher.model.cfg.pattern != "bidirectional":
            raise ValueError(f"{cfg.teacher}: the teacher must be a bidirectional model")
        if teacher.model.cfg.cameras != demos.cameras:
            raise ValueError(
                f"{cfg.teacher}: reads cameras {list(teacher.model.cfg.cameras)}, the demonstrations "
                f"have {list(demos.cameras)}"
            )
        student_cfg = _block_causal(teacher.model.cfg, cfg.block_size)
        _check_features(cfg, cfg.teacher, teacher, demos)
        student = ActionTokenModel(student_cfg)
        student.load_state_dict(_student_weights(cfg, teacher, student_cfg))
        for p in teacher.model.parameters():
            p.requires_grad_(False)
        ckpt = Checkpoint(
            student,
            teacher.tokenizer,
            teacher.vocab,
            teacher.state_mean,
            teacher.state_std,
            meta={"state_dims": list(demos.state_dims)},
            state_positions=teacher.state_positions,
            state_prefix=teacher.state_prefix,
        )
        return ckpt, teacher.model.eval()
    if cfg.init:
        return _initial(cfg, demos), None
    defaults = TrainConfig(recipe=cfg.recipe)
    if not demos.cameras and (cfg.image_tokens, cfg.image_coords) != (
        defaults.image_tokens,
        defaults.image_coords,
    ):
        raise ValueError(
            "--image-tokens/--image-coords shape an image encoder; these demonstrations have no camera "
            "images (collect with the suite's images, e.g. simpler/all:obs=images)"
        )
    tokenizer = ActionTokenizer.fit(demos.actions, bins=cfg.bins, percentiles=ACTION_RANGES[cfg.action_range])
    words = sorted({w for text in set(demos.instructions) for w in words_of(text)})
    vocab = {w: i + 2 for i, w in enumerate(words)}
    max_words = max(1, max(len(words_of(t)) for t in set(demos.instructions)))
    positions = demos.positions() if cfg.state_features == "relative" else ()
    prefix = demos.proprio() if cfg.state_features == "proprio" else 0
    states = demos.observations[:, :prefix] if prefix else relative_positions(demos.observations, positions)
    mean = states.mean(0)
    std = np.maximum(states.std(0), 1e-2)
    model_cfg = ModelConfig(
        action_dim=demos.actions.shape[1],
        chunk_len=cfg.chunk_len,
        state_dim=states.shape[1],
        bins=cfg.bins,
        vocab_words=len(vocab) + 2,
        max_words=max_words,
        width=cfg.width,
        layers=cfg.layers,
        heads=cfg.heads,
        ffn=cfg.ffn,
        pattern=PATTERN[cfg.recipe],
        block_size=cfg.block_size,
        cameras=demos.cameras,
        image_size=demos.image_size,
        image_tokens=cfg.image_tokens,
        image_coords=cfg.image_coords,
    )
    return Checkpoint(
        ActionTokenModel(model_cfg),
        tokenizer,
        vocab,
        mean,
        std,
        meta={"state_dims": list(demos.state_dims)},
        state_positions=positions,
        state_prefix=prefix,
    ), None


def _initial(cfg: TrainConfig, demos: Demos) -> Checkpoint:
    """The --init checkpoint to continue, checked against the demonstrations: same
    tokenizer, vocabulary and normalisation, or the weights would read inputs they were
    not trained on. block_diffusion may start from a bidirectional model (a teacher)."""
    ckpt = load(cfg.init)
    pattern = ckpt.model.cfg.pattern
    # block_diffusion also starts from a bidirectional model, as the papers fine-tune it.
    starts = ("bidirectional", "block_causal") if cfg.recipe == "block_diffusion" else (PATTERN[cfg.recipe],)
    if pattern not in starts:
        also = (
            "; only block_diffusion starts from a bidirectional model (distill takes one as --teacher)"
            if pattern == "bidirectional"
            else ""
        )
        raise ValueError(
            f"{cfg.init}: a {pattern} model; recipe {cfg.recipe!r} trains a {PATTERN[cfg.recipe]} model{also}"
        )
    if (
        ckpt.raw_state_dim != demos.observations.shape[1]
        or ckpt.model.cfg.action_dim != demos.actions.shape[1]
    ):
        raise ValueError(f"{cfg.init}: its state/action sizes do not match the demonstrations")
    _check_features(cfg, cfg.init, ckpt, demos)
    if (ckpt.model.cfg.cameras, ckpt.model.cfg.image_size) != (demos.cameras, demos.image_size):
        raise ValueError(
            f"{cfg.init}: reads cameras {list(ckpt.model.cfg.cameras)} at "
            f"{ckpt.model.cfg.image_size} px, the demonstrations have {list(demos.cameras)} at "
            f"{demos.image_size} px"
        )
    unknown = {w for t in set(demos.instructions) for w in words_of(t)} - set(ckpt.vocab)
    if unknown:
        raise ValueError(f"{cfg.init}: the demonstrations use words it has never seen: {sorted(unknown)[:5]}")
    if PATTERN[cfg.recipe] == "block_causal":
        # The weights carry over; the attention pattern (and the block size, if asked) change.
        block_cfg = _block_causal(ckpt.model.cfg, cfg.block_size)
        if block_cfg != ckpt.model.cfg:
            model = ActionTokenModel(block_cfg)
            model.load_state_dict(ckpt.model.state_dict())
            ckpt.model = model
    return ckpt


def _block_causal(model: ModelConfig, block_size: int) -> ModelConfig:
    """A model's shape under the block-causal pattern, blocks of `block_size` or its own."""
    return ModelConfig(
        **{**model.to_dict(), "pattern": "block_causal", "block_size": block_size or model.block_size}
    )


def _check_features(cfg: TrainConfig, path: str, ckpt: Checkpoint, demos: Demos) -> None:
    """A continued model or a student reads states exactly as the checkpoint it grows
    from: asking for other features is an error, not a silent switch."""
    has = ckpt.state_features
    if cfg.state_features and cfg.state_features != has:
        raise ValueError(
            f"--state-features {cfg.state_features}: {path} reads {has} states, and a continued "
            "model or a distilled student reads what it grows from; leave --state-features out"
        )
    if ckpt.state_positions and demos.state_positions and demos.positions() != ckpt.state_positions:
        raise ValueError(
            f"{path}: reads positions at {list(ckpt.state_positions)} of the state, the demonstrations "
            f"keep them at {list(demos.positions())}"
        )
    if ckpt.state_prefix and demos.proprio_dims and demos.proprio() != ckpt.state_prefix:
        raise ValueError(
            f"{path}: reads the first {ckpt.state_prefix} state entries as the robot's, the "
            f"demonstrations' robot state has {demos.proprio()}"
        )


@dataclass
class TrainReport:
    checkpoint: Path
    losses: list[float] = field(default_factory=list)
    probes: list[tuple[int, float]] = field(default_factory=list)  # (step, probe loss)
    # Block-causal models: (step, probe loss with clean earlier blocks), the condition
    # block-by-block decoding meets (losses.probe_loss with schedule clean_context).
    clean_probes: list[tuple[int, float]] = field(default_factory=list)
    seconds: float = 0.0


PROBE_SAMPLES = 512


def train(
    cfg: TrainConfig,
    demos_dir: str | Path | Sequence[str | Path],
    out: str | Path,
    on_step: Callable[[int, float], None] | None = None,
) -> TrainReport:
    cfg.validate()
    cfg = replace(cfg, noise_schedule=cfg.schedule)  # the checkpoint records the one used
    torch.manual_seed(cfg.seed)
    g = torch.Generator().manual_seed(cfg.seed)
    demos = load_demos(demos_dir, cfg.chunk_len)
    ckpt, teacher = _prepare(cfg, demos)
    dev = torch.device(cfg.device)
    model, mcfg = ckpt.model.to(dev).train(), ckpt.model.cfg
    if teacher is not None:
        teacher = teacher.to(dev)
    tokens_all = torch.from_numpy(ckpt.tokenizer.encode(demos.actions[demos.chunk_index]))
    words_all = torch.tensor([ckpt.encode_instruction(t) for t in demos.instructions], dtype=torch.long)
    states_all = torch.from_numpy(
        (ckpt.features(demos.observations) - ckpt.state_mean) / ckpt.state_std
    ).float()
    positions = torch.arange(mcfg.action_tokens, device=dev)
    opt = torch.optim.AdamW(
        [p for p in model.parameters() if p.requires_grad], lr=cfg.lr, weight_decay=cfg.weight_decay
    )
    average = [p.detach().clone() for p in model.parameters()] if cfg.ema else None
    task_weights = _task_weights(demos.instructions) if cfg.sampling == "task" else None
    first_only_all = None
    if cfg.noisy_targets == "first_action" and demos.noisy is not None and demos.noisy.any():
        first_only_all = torch.from_numpy(demos.noisy.copy())
    report = TrainReport(Path(out))
    probe_rows = torch.randint(
        0, len(tokens_all), (PROBE_SAMPLES,), generator=torch.Generator().manual_seed(PROBE_SEED)
    )
    probe_inputs = (
        tokens_all[probe_rows].to(dev),
        words_all[probe_rows].to(dev),
        states_all[probe_rows].to(dev),
        positions,
        _to(demos.image_batch(probe_rows), dev),
    )

    def probe(step: int) -> None:
        report.probes.append((step, probe_loss(model, *probe_inputs)))
        if mcfg.pattern == "block_causal":
            report.clean_probes.append((step, probe_loss(model, *probe_inputs, schedule="clean_context")))

    start = time.perf_counter()
    for step in range(cfg.steps):
        if cfg.probe_every and step % cfg.probe_every == 0:
            probe(step)
        size = min(cfg.batch_size, len(tokens_all))
        if task_weights is None:
            batch = torch.randint(0, len(tokens_all), (size,), generator=g)
        else:
            batch = torch.multinomial(task_weights, size, replacement=True, generator=g)
        # Rows and state noise are drawn on the CPU (one seed, one run on any device), then moved.
        clean, words = tokens_all[batch].to(dev), words_all[batch].to(dev)
        noise = cfg.obs_noise * torch.randn(len(batch), mcfg.state_dim, generator=g)
        state = (states_all[batch] + noise).to(dev)
        images = _to(demos.image_batch(batch), dev)
        first_only = None if first_only_all is None else first_only_all[batch].to(dev)
        batch_inputs = (clean, words, state, positions, g, images, first_only)
        loss = recipe_loss(cfg.recipe, cfg.noise_schedule, model, teacher, *batch_inputs, demo_ce=cfg.demo_ce)
        for group in opt.param_groups:
            group["lr"] = _lr(step, cfg)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        if average is not None:
            with torch.no_grad():
                for a, p in zip(average, model.parameters(), strict=True):
                    a.lerp_(p, 1 - cfg.ema)
        value = loss.item()
        report.losses.append(value)
        if on_step:
            on_step(step, value)
    report.seconds = time.perf_counter() - start
    if average is not None:
        with torch.no_grad():
            for p, a in zip(model.parameters(), average, strict=True):
                p.copy_(a)
    if cfg.probe_every:
        probe(cfg.steps)
    ckpt.model = model.cpu().eval()  # checkpoints are device-free; policies place them (run --device)
    ckpt.meta = {
        "recipe": cfg.recipe,
        "train_config": asdict(cfg),
        "data_sha256": demos.sha256,
        "data_sources": demos.sources,
        # Observation sizes the model was trained on; shorter ones were zero-padded.
        "state_dims": list(demos.state_dims),
        # Mean |action - detokenize(tokenize(action))| over the training actions (clipped to
        # the bins' range): the precision floor no amount of training can beat.
        "tokenizer_round_trip_error": ckpt.tokenizer.round_trip_error(demos.actions),
        # Per dimension, the largest error on the actions as demonstrated, clipping included.
        "tokenizer_worst_error": ckpt.tokenizer.worst_error(demos.actions).tolist(),
        # Which weights it grew from, by content: a path alone says nothing once the file changes.
        "teacher_sha256": _sha256(cfg.teacher) if cfg.teacher else "",
        "init_sha256": _sha256(cfg.init) if cfg.init else "",
        "final_loss": float(np.mean(report.losses[-50:])),
        "train_seconds": report.seconds,
        "probe": report.probes,
        "probe_clean_context": report.clean_probes,
    }
    save(ckpt, out)
    _write_curve(report, Path(out))
    return report


def _to(images: torch.Tensor | None, dev: torch.device) -> torch.Tensor | None:
    return None if images is None else images.to(dev)


def _task_weights(instructions: list[str]) -> torch.Tensor:
    """Row weights giving every instruction the same share of each batch.

    Demonstrations of quick tasks are short (Meta-World reach: ~48 steps an episode,
    peg-insert: ~105), so sampling steps uniformly starves exactly the tasks whose
    precision matters at the end of a short episode.
    """
    _, inverse, counts = np.unique(np.asarray(instructions), return_inverse=True, return_counts=True)
    return torch.from_numpy(1.0 / counts[inverse]).double()


def _sha256(path: str) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _write_curve(report: TrainReport, ckpt_path: Path) -> None:
    csv_path = ckpt_path.with_suffix(".loss.csv")
    with open(csv_path, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["step", "loss", "probe_loss"])
        probes = dict(report.probes)
        for step, loss in enumerate(report.losses):
            writer.writerow([step, loss, probes.get(step, "")])
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    losses = np.asarray(report.losses)
    window = max(1, len(losses) // 50)
    smooth = np.convolve(losses, np.ones(window) / window, mode="valid")
    ax.plot(losses, alpha=0.3, label="loss")
    ax.plot(np.arange(len(smooth)) + window - 1, smooth, label=f"mean of {window}")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.set_title(ckpt_path.stem)
    ax.legend()
    fig.tight_layout()
    fig.savefig(ckpt_path.with_suffix(".loss.png"), dpi=120)
    plt.close(fig)
