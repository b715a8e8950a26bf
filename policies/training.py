"""Training the action-token model from demonstrations, by recipe.

    bidirectional    masked-diffusion loss: a random mask ratio per sample, cross-entropy
                     on the masked positions; every token sees every token (Dream-VLA).
    autoregressive   next-token loss under the causal pattern ([MASK] stands for 'begin').
    block_diffusion  block-causal pattern from scratch with diffusion forcing: per-block
                     mask ratios, non-decreasing along the chunk, from `noise_schedule`.
    distill          Fast-dVLA's asymmetric distillation: a block-causal student that
                     starts from the bidirectional teacher's weights matches the frozen
                     teacher's distribution (KL over masked positions); the teacher sees
                     every noisy block, the student blocks 1..i. Full fine-tuning (the
                     paper uses LoRA rank 32).

Noise schedules (per-block mask ratios t_1 <= ... <= t_N) and why: decoding starts
every block fully masked while earlier blocks are clean or partly decoded, and under
block-causal attention a block's loss depends only on itself and earlier blocks.
    frontier        a random frontier block f with ratio r ~ U(0, 1); earlier blocks below
                    r, later blocks above it: covers "this block fully masked, the ones
                    before clean or half done", which is what decoding meets (default).
    linear          t_i = t_0 + slope * i / (N - 1), t_0 and slope random.
    sorted_uniform  N uniform ratios, sorted: the naive recipe; the first block is rarely
                    near fully masked (kept for ablations).
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import torch
import torch.nn.functional as F

from policies.checkpoint import Checkpoint, load, save, words_of
from policies.model import ActionTokenModel, ModelConfig
from policies.observations import relative_positions
from policies.recipes import ACTION_RANGES, PATTERN, TrainConfig
from policies.tokenizer import ActionTokenizer


@dataclass
class Demos:
    observations: np.ndarray  # (N, obs_dim) float32
    actions: np.ndarray  # (N, action_dim)
    chunk_index: np.ndarray  # (N, H) rows of `actions` forming each step's target chunk
    instructions: list[str]  # per row
    sha256: str
    cameras: tuple[str, ...] = ()
    image_size: int = 0
    images: list[np.ndarray] = field(default_factory=list)  # per camera: (N,) PNG bytes
    state_dims: tuple[int, ...] = ()  # observation sizes before padding (one unless mixed)
    noisy: np.ndarray | None = None  # (N,) bool: row from a `collect --action-noise` folder
    # Where world positions sit in the state (the envs' `state_positions`), one tuple per
    # task the manifests recorded them for; `positions()` says whether they are usable.
    state_positions: dict[str, tuple[int, ...]] = field(default_factory=dict)
    tasks: frozenset[str] = frozenset()

    def positions(self) -> tuple[int, ...]:
        """The one set of state positions every task shares; raises saying why not."""
        missing = sorted(self.tasks - set(self.state_positions))
        if missing:
            raise ValueError(
                f"--state-features relative: the demonstrations do not record where positions sit "
                f"in the state of task {missing[0]!r} (collected before `state_positions` was "
                "recorded, or the suite's env does not declare them); collect them again or use "
                "--state-features raw"
            )
        found = {self.state_positions[t] for t in self.tasks}
        if len(found) > 1:
            raise ValueError(
                "--state-features relative: the tasks keep positions at different places in their "
                f"states ({len(found)} layouts, e.g. LIBERO goal/10/90); train one suite of one "
                "layout, or use --state-features raw"
            )
        return found.pop()

    def image_batch(self, rows: torch.Tensor) -> torch.Tensor | None:
        """(B, cameras, H, W, 3) uint8 for some rows, decoded on demand: the PNGs of a
        LIBERO suite are ~1 GB as pixels, a tenth of that compressed."""
        if not self.cameras:
            return None
        from policies.observations import unpng

        idx = rows.tolist()
        frames = [[unpng(column[i]) for column in self.images] for i in idx]
        return torch.from_numpy(np.asarray(frames, dtype=np.uint8))


def load_demos(folders: str | Path | Sequence[str | Path], chunk_len: int) -> Demos:
    """One demonstrations folder, or several trained on as one (e.g. clean and DART-noisy
    collections of a suite): their episodes are concatenated, and the data hash is the
    folder's own, or for several the hash of their hashes in the order given."""
    paths = [Path(folders)] if isinstance(folders, str | Path) else [Path(f) for f in folders]
    manifests, frames = [], []
    for folder in paths:
        if not (folder / "manifest.json").is_file() or not (folder / "steps.parquet").is_file():
            raise ValueError(f"{folder}: not a demonstrations folder (needs manifest.json and steps.parquet)")
        manifests.append(json.loads((folder / "manifest.json").read_text()))
        frames.append(pq.read_table(folder / "steps.parquet").to_pandas())
    folder, manifest = paths[0], manifests[0]
    for other, m in zip(paths[1:], manifests[1:], strict=True):
        for key in ("cameras", "image_size", "action_dim"):
            if m.get(key) != manifest.get(key):
                raise ValueError(
                    f"{other}: {key} {m.get(key)!r} differs from {folder}'s {manifest.get(key)!r}; "
                    "demonstrations trained on together must match"
                )
    positions: dict[str, tuple[int, ...]] = {}
    for path, m in zip(paths, manifests, strict=True):
        for task, found in (m.get("state_positions") or {}).items():
            if positions.setdefault(task, tuple(found)) != tuple(found):
                raise ValueError(f"{path}: task {task!r} records other state positions than before")
    offset = 0
    for df, m in zip(frames, manifests, strict=True):
        df["episode_id"] += offset  # episode ids unique across folders: chunks never cross
        offset = int(df["episode_id"].max()) + 1
        df["_noisy"] = float(m.get("action_noise") or 0.0) > 0
    df = frames[0] if len(frames) == 1 else pd.concat(frames, ignore_index=True)
    sha256 = manifest.get("steps_sha256", "")
    if len(paths) > 1:
        joined = "+".join(m.get("steps_sha256", "") for m in manifests)
        sha256 = hashlib.sha256(joined.encode()).hexdigest()
    obs, state_dims = _padded(df["observation"].to_numpy())
    actions = np.stack(df["action"].to_numpy()).astype(np.float64)
    # Target chunk of step t: actions t..t+H-1 of the same episode, the last one repeated.
    episode = df["episode_id"].to_numpy()
    last = np.zeros(len(df), dtype=np.int64)
    for ep_end in np.flatnonzero(np.r_[episode[1:] != episode[:-1], True]):
        start = ep_end
        while start > 0 and episode[start - 1] == episode[ep_end]:
            start -= 1
        last[start : ep_end + 1] = ep_end
    idx = np.minimum(np.arange(len(df))[:, None] + np.arange(chunk_len)[None, :], last[:, None])
    cameras = tuple(manifest.get("cameras") or ())
    missing = [c for c in cameras if f"image_{c}" not in df.columns]
    if missing:
        raise ValueError(f"{folder}: the manifest lists cameras {missing} that steps.parquet lacks")
    return Demos(
        obs,
        actions,
        idx,
        df["instruction"].tolist(),
        sha256,
        cameras,
        int(manifest.get("image_size") or 0),
        [df[f"image_{c}"].to_numpy() for c in cameras],
        state_dims,
        df["_noisy"].to_numpy(dtype=bool),
        positions,
        frozenset(df["task"].unique()),
    )


def _padded(rows: np.ndarray) -> tuple[np.ndarray, tuple[int, ...]]:
    """Observations as one (N, D) array, zero-padded at the end to the longest.

    LIBERO goal/10/90 tasks have different objects, so their state vectors differ in
    length; the instruction tells the model which layout it is reading. The sizes seen
    are recorded in the checkpoint so the policy pads (and accepts) exactly those."""
    sizes = tuple(sorted({len(r) for r in rows}))
    if len(sizes) == 1:
        return np.stack(rows).astype(np.float32), sizes
    out = np.zeros((len(rows), sizes[-1]), dtype=np.float32)
    for i, r in enumerate(rows):
        out[i, : len(r)] = r
    return out, sizes


def block_ratios(schedule: str, batch: int, blocks: int, g: torch.Generator) -> torch.Tensor:
    """(batch, blocks) non-decreasing mask ratios."""
    if schedule == "sorted_uniform":
        return torch.rand(batch, blocks, generator=g).sort(dim=1).values
    if schedule == "linear":
        t0 = torch.rand(batch, 1, generator=g)
        slope = torch.rand(batch, 1, generator=g) * (1 - t0)
        steps = torch.arange(blocks) / max(blocks - 1, 1)
        return t0 + slope * steps
    r = torch.rand(batch, 1, generator=g)
    f = torch.randint(0, blocks, (batch, 1), generator=g)
    u = torch.rand(batch, blocks, generator=g).sort(dim=1).values
    i = torch.arange(blocks)[None, :]
    return torch.where(i < f, r * u, torch.where(i == f, r, r + (1 - r) * u))


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
        student_cfg = ModelConfig(
            **{
                **teacher.model.cfg.to_dict(),
                "pattern": "block_causal",
                "block_size": cfg.block_size or teacher.model.cfg.block_size,
            }
        )
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
            state_positions=teacher.state_positions,
        )
        return ckpt, teacher.model.eval()
    if cfg.init:
        # Continued training: same tokenizer, vocabulary and normalisation, or the
        # weights would read inputs they were not trained on.
        ckpt = load(cfg.init)
        if ckpt.model.cfg.pattern != PATTERN[cfg.recipe]:
            raise ValueError(
                f"{cfg.init}: a {ckpt.model.cfg.pattern} model; recipe {cfg.recipe!r} trains a "
                f"{PATTERN[cfg.recipe]} model"
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
            raise ValueError(
                f"{cfg.init}: the demonstrations use words it has never seen: {sorted(unknown)[:5]}"
            )
        return ckpt, None
    tokenizer = ActionTokenizer.fit(demos.actions, bins=cfg.bins, percentiles=ACTION_RANGES[cfg.action_range])
    words = sorted({w for text in set(demos.instructions) for w in words_of(text)})
    vocab = {w: i + 2 for i, w in enumerate(words)}
    max_words = max(1, max(len(words_of(t)) for t in set(demos.instructions)))
    positions = demos.positions() if cfg.state_features == "relative" else ()
    states = relative_positions(demos.observations, positions)
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
    )
    return Checkpoint(
        ActionTokenModel(model_cfg), tokenizer, vocab, mean, std, state_positions=positions
    ), None


def _check_features(cfg: TrainConfig, path: str, ckpt: Checkpoint, demos: Demos) -> None:
    """A continued model or a student reads states exactly as the checkpoint it grows
    from: asking for other features is an error, not a silent switch."""
    has = "relative" if ckpt.state_positions else "raw"
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


@dataclass
class TrainReport:
    checkpoint: Path
    losses: list[float] = field(default_factory=list)
    probes: list[tuple[int, float]] = field(default_factory=list)  # (step, probe loss)
    seconds: float = 0.0


PROBE_SAMPLES = 512
PROBE_SEED = 20260


def probe_loss(model: ActionTokenModel, clean, words, state, positions, images=None) -> float:
    """One yardstick for recipes whose training losses differ (KL for distill, CE else).

    Cross-entropy of the true tokens at masked positions, with masks drawn once from a
    fixed seed (block-causal models: per-block `frontier` ratios, the conditions
    decoding meets; bidirectional: one ratio per sample; causal: next-token). Comparing
    it across recipes is how steps-to-convergence is measured (benchmarks/convergence.py).
    """
    recipe = {"block_causal": "block_diffusion", "causal": "autoregressive"}.get(
        model.cfg.pattern, "bidirectional"
    )
    g = torch.Generator().manual_seed(PROBE_SEED)
    was_training = model.training
    model.eval()
    with torch.no_grad():
        value = _loss(recipe, "frontier", model, None, clean, words, state, positions, g, images).item()
    model.train(was_training)
    return value


def train(
    cfg: TrainConfig,
    demos_dir: str | Path | Sequence[str | Path],
    out: str | Path,
    on_step: Callable[[int, float], None] | None = None,
) -> TrainReport:
    cfg.validate()
    torch.manual_seed(cfg.seed)
    g = torch.Generator().manual_seed(cfg.seed)
    demos = load_demos(demos_dir, cfg.chunk_len)
    ckpt, teacher = _prepare(cfg, demos)
    model, mcfg = ckpt.model.train(), ckpt.model.cfg
    tokens_all = torch.from_numpy(ckpt.tokenizer.encode(demos.actions[demos.chunk_index]))
    words_all = torch.tensor([ckpt.encode_instruction(t) for t in demos.instructions], dtype=torch.long)
    states_all = torch.from_numpy(
        (ckpt.features(demos.observations) - ckpt.state_mean) / ckpt.state_std
    ).float()
    positions = torch.arange(mcfg.action_tokens)
    opt = torch.optim.AdamW(
        [p for p in model.parameters() if p.requires_grad], lr=cfg.lr, weight_decay=cfg.weight_decay
    )
    task_weights = _task_weights(demos.instructions) if cfg.sampling == "task" else None
    first_only_all = None
    if cfg.noisy_targets == "first_action" and demos.noisy is not None and demos.noisy.any():
        first_only_all = torch.from_numpy(demos.noisy.copy())
    report = TrainReport(Path(out))
    probe_rows = torch.randint(
        0, len(tokens_all), (PROBE_SAMPLES,), generator=torch.Generator().manual_seed(PROBE_SEED)
    )
    probe_inputs = (
        tokens_all[probe_rows],
        words_all[probe_rows],
        states_all[probe_rows],
        positions,
        demos.image_batch(probe_rows),
    )
    start = time.perf_counter()
    for step in range(cfg.steps):
        if cfg.probe_every and step % cfg.probe_every == 0:
            report.probes.append((step, probe_loss(model, *probe_inputs)))
        size = min(cfg.batch_size, len(tokens_all))
        if task_weights is None:
            batch = torch.randint(0, len(tokens_all), (size,), generator=g)
        else:
            batch = torch.multinomial(task_weights, size, replacement=True, generator=g)
        clean, words = tokens_all[batch], words_all[batch]
        state = states_all[batch] + cfg.obs_noise * torch.randn(len(batch), mcfg.state_dim, generator=g)
        images = demos.image_batch(batch)
        first_only = None if first_only_all is None else first_only_all[batch]
        loss = _loss(
            cfg.recipe,
            cfg.noise_schedule,
            model,
            teacher,
            clean,
            words,
            state,
            positions,
            g,
            images,
            first_only,
        )
        for group in opt.param_groups:
            group["lr"] = _lr(step, cfg)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        value = loss.item()
        report.losses.append(value)
        if on_step:
            on_step(step, value)
    report.seconds = time.perf_counter() - start
    if cfg.probe_every:
        report.probes.append((cfg.steps, probe_loss(model, *probe_inputs)))
    ckpt.model = model.eval()
    ckpt.meta = {
        "recipe": cfg.recipe,
        "train_config": asdict(cfg),
        "data_sha256": demos.sha256,
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
    }
    save(ckpt, out)
    _write_curve(report, Path(out))
    return report


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


def _loss(
    recipe, schedule, model, teacher, clean, words, state, positions, g, images=None, first_only=None
) -> torch.Tensor:
    """The recipe's loss on one batch. `first_only` (B,) marks rows whose chunk target is
    only its first action (see `_first_action_only`); None leaves every row whole."""
    cfg = model.cfg
    b, n = clean.shape
    later = None if first_only is None else first_only[:, None] & (positions >= cfg.action_dim)[None, :]
    if recipe == "autoregressive":
        inputs = torch.cat([torch.full((b, 1), cfg.mask_id), clean[:, :-1]], dim=1)
        logits = model(inputs, positions, words, state, images=images).logits
        if later is not None:
            return F.cross_entropy(logits[~later], clean[~later])
        return F.cross_entropy(logits.reshape(-1, cfg.bins), clean.reshape(-1))
    if recipe == "bidirectional":
        ratio = torch.rand(b, 1, generator=g).expand(b, n)
    else:
        ratio = block_ratios(schedule, b, n // cfg.block, g).repeat_interleave(cfg.block, dim=1)
    mask = torch.rand(b, n, generator=g) < ratio
    none = ~mask.any(dim=1)
    mask[none, torch.randint(0, n, (int(none.sum()),), generator=g)] = True  # at least one per sample
    scored = mask
    if later is not None and recipe != "distill":
        mask, scored = _first_action_only(mask, later, cfg.action_dim, g)
    noisy = torch.where(mask, torch.full_like(clean, cfg.mask_id), clean)
    logits = model(noisy, positions, words, state, images=images).logits
    if recipe == "distill":
        with torch.no_grad():
            target = torch.log_softmax(teacher(noisy, positions, words, state, images=images).logits, dim=-1)
        kl = F.kl_div(torch.log_softmax(logits, dim=-1), target, log_target=True, reduction="none").sum(-1)
        return kl[mask].mean()
    return F.cross_entropy(logits[scored], clean[scored])


def _first_action_only(
    mask: torch.Tensor, later: torch.Tensor, action_dim: int, g: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """(input mask, loss mask) for rows of DART-noisy demonstrations.

    Such a row's chunk is the demonstrator's next H actions, but actions 2..H answer noise
    executed after the row's state, which that state cannot predict: trained on whole, the
    model learns their blur (a spatial teacher fell from 64 to 22 of 100 that way). Only
    the first action is the demonstrator's answer to this state, so only it is scored, and
    the later positions are always [MASK] so the model never reads the blur either.
    Distillation needs none of this: its target is the teacher, a function of the state.
    """
    mask = mask | later
    scored = mask & ~later
    rows = ~scored.any(dim=1)
    if rows.any():  # a row whose first action drew no mask: mask one of its tokens
        pick = torch.randint(0, action_dim, (int(rows.sum()),), generator=g)
        mask[rows.nonzero().squeeze(1), pick] = True
        scored[rows.nonzero().squeeze(1), pick] = True
    return mask, scored


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
