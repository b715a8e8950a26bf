"""`dvla-harness train`: an action-token model from demonstrations, by recipe."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from harness.console import console, err_console
from harness.device import DEFAULT_DEVICE, DEVICES, resolve_device
from harness.errors import UsageError

if TYPE_CHECKING:
    from policies.dvla.recipes import TrainConfig

CLIPPED = 0.1  # warn above this tokenizer error on a training action (a tenth of a half-range)


def register(sub: argparse._SubParsersAction) -> None:
    from policies.dvla.recipes import TrainConfig

    d = TrainConfig(recipe="bidirectional")
    p = sub.add_parser(
        "train",
        help="train an action-token model from demonstrations",
        description=(
            "Train the action-token transformer on a demonstrations folder (from `dvla-harness "
            "collect`) with one recipe, deterministically for a given --seed (on a CPU; see --device). Writes OUT "
            "(safetensors; its header holds the model shape, attention pattern, tokenizer, "
            "instruction vocabulary, normalisation, recipe and data hash), OUT.json (the same "
            "header, readable) and the loss curve as OUT.loss.csv and OUT.loss.png."
        ),
        epilog=(
            "examples:\n"
            "  dvla-harness train --demos demos/mt10 --recipe bidirectional --out ckpt/teacher.safetensors\n"
            "  dvla-harness train --demos demos/mt10 --recipe distill --teacher ckpt/teacher.safetensors "
            "--out ckpt/fast_dvla.safetensors\n"
            "  # the block-diffusion baseline, fine-tuned from the same teacher (clean-context loss)\n"
            "  dvla-harness train --demos demos/mt10 --recipe block_diffusion --init ckpt/teacher.safetensors "
            "--out ckpt/bd.safetensors\n"
            "\n"
            "recipes: bidirectional (masked diffusion, full attention), autoregressive (next token),\n"
            "block_diffusion (block-causal; by default BD3-LM's clean-context loss: each block noised\n"
            "and predicted with every earlier block clean), distill (Fast-dVLA: a block-causal student\n"
            "matches the bidirectional --teacher's distribution). Noise schedules (block_diffusion,\n"
            "distill): clean_context (block_diffusion's default), and the diffusion-forcing ones,\n"
            "one noisy stream with mask ratios non-decreasing along the chunk: frontier (distill's\n"
            "default), d2f (D2F: start in [0.2, 0.7], increments staying within it), linear,\n"
            "sorted_uniform. policies/dvla/training.py explains each."
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _data_arguments(p.add_argument_group("data and recipe"), d)
    _representation_arguments(p.add_argument_group("what the model reads and predicts"))
    _model_arguments(p.add_argument_group("model and optimisation"), d)
    _output_arguments(p.add_argument_group("output and device"))
    p.set_defaults(func=cmd_train)


def _data_arguments(p: Any, d: Any) -> None:
    from policies.dvla.recipes import NOISY_TARGETS, RECIPES, SAMPLING

    p.add_argument(
        "--demos",
        required=True,
        nargs="+",
        metavar="DIR",
        help="demonstrations folder(s); several are trained on as one (e.g. clean and "
        "`collect --action-noise` ones)",
    )
    p.add_argument("--recipe", required=True, choices=RECIPES)
    p.add_argument("--out", required=True, metavar="FILE.safetensors", help="checkpoint to write")
    p.add_argument("--teacher", metavar="FILE", help="distill: the bidirectional teacher checkpoint")
    p.add_argument(
        "--init",
        metavar="FILE",
        help="start from this checkpoint (its tokenizer, vocabulary and normalisation are kept): one "
        "of the recipe's pattern to continue; with block_diffusion also a bidirectional one (a "
        "teacher: the weights carry over, the pattern becomes block-causal with blocks of "
        "--block-size or its own); with distill, a student of --teacher to distil further",
    )
    p.add_argument(
        "--sampling",
        choices=SAMPLING,
        default=d.sampling,
        help="task: each instruction equally often in a batch (default); step: each demonstration step",
    )
    p.add_argument(
        "--warmup-steps", type=int, metavar="N", help=f"learning-rate warm-up (default {d.warmup})"
    )
    p.add_argument(
        "--noisy-targets",
        choices=NOISY_TARGETS,
        default=d.noisy_targets,
        help="rows of `collect --action-noise` folders: first_action scores only the first "
        "action of their chunk and hides the later ones, which answer noise (default; distill "
        "hides them from the teacher too); chunk treats them as clean rows",
    )
    p.add_argument(
        "--demo-ce",
        type=float,
        default=d.demo_ce,
        metavar="W",
        help="distill only: add W x the cross-entropy against the demonstrated tokens to the KL "
        "to the teacher (default 0: Fast-dVLA's loss alone; not in the paper)",
    )
    p.add_argument(
        "--ema",
        type=float,
        default=d.ema,
        metavar="DECAY",
        help="save an exponential moving average of the weights with this decay per step, e.g. "
        "0.995 (default 0: the last step's weights)",
    )


def _representation_arguments(p: Any) -> None:
    from policies.dvla.recipes import ACTION_RANGES, DEFAULT_NOISE_SCHEDULE, NOISE_SCHEDULES, STATE_FEATURES

    p.add_argument(
        "--state-features",
        choices=STATE_FEATURES,
        help="what the model reads of the state: raw; relative (also each object's and goal "
        "region's offset from the end effector, where the demonstrations record where positions "
        "sit: LIBERO, Meta-World, ManiSkill); or proprio (only the robot's own entries: hand, "
        "gripper, joints; needs camera demonstrations, where the model must find the objects, "
        "as upstream VLAs do). Default: what --init/--teacher reads, else raw",
    )
    p.add_argument(
        "--action-range",
        choices=ACTION_RANGES,
        help="what the action tokenizer's bins span per dimension: percentile (the 1st-99th "
        "percentile of the training actions, outliers clipped, as DD-VLA; default) or full "
        "(every training action: no rare action is clipped). --init and --teacher bring theirs",
    )
    p.add_argument(
        "--noise-schedule",
        choices=NOISE_SCHEDULES,
        help="per-block mask ratios, block_diffusion and distill only (default: "
        + ", ".join(f"{s} for {r}" for r, s in DEFAULT_NOISE_SCHEDULE.items())
        + "; clean_context is block_diffusion's only); recorded in the checkpoint",
    )


def _model_arguments(p: Any, d: Any) -> None:
    for name, kind in (
        ("steps", int),
        ("batch_size", int),
        ("lr", float),
        ("seed", int),
        ("chunk_len", int),
        ("width", int),
        ("layers", int),
        ("heads", int),
        ("ffn", int),
        ("block_size", int),
    ):
        p.add_argument(
            "--" + name.replace("_", "-"),
            type=kind,
            default=getattr(d, name),
            help=f"default {getattr(d, name)}"
            if name != "block_size"
            else "action tokens per block, block-causal recipes (default 0: one action step, or "
            "with --init / --teacher that checkpoint's)",
        )
    p.add_argument(
        "--image-tokens",
        type=int,
        default=d.image_tokens,
        metavar="N",
        help=f"camera demonstrations: tokens per camera, a square number (the pooled feature grid; "
        f"default {d.image_tokens})",
    )
    p.add_argument(
        "--image-coords",
        action="store_true",
        help="camera demonstrations: the image encoder also reads each pixel's x and y (CoordConv), "
        "so a policy without object poses (--state-features proprio) can tell where things are",
    )


def _output_arguments(p: Any) -> None:
    p.add_argument(
        "--device",
        choices=DEVICES,
        default=DEFAULT_DEVICE,
        help="where the model trains (default cpu): cuda needs a GPU torch sees (exit 2 without one), "
        "auto takes one when there is one. Batches and masks are drawn on the CPU from --seed either "
        "way, so every device sees the same data; CPU runs repeat bit for bit, GPU runs are not "
        "promised to (PyTorch's CUDA kernels need not be deterministic). The checkpoint records the device",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing checkpoint")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def cmd_train(args: argparse.Namespace) -> int:
    from policies.dvla.checkpoint import CheckpointError
    from policies.dvla.training import train

    out = Path(args.out)
    if out.suffix != ".safetensors":
        raise UsageError(f"--out {args.out!r}: a checkpoint file name must end in .safetensors")
    if out.exists() and not args.overwrite:
        raise UsageError(f"checkpoint {args.out!r} exists; pass --overwrite to replace it")
    for folder in args.demos:
        if not Path(folder).is_dir():
            raise UsageError(f"--demos {folder!r} is not a folder (make one with `dvla-harness collect`)")
    cfg = train_config(args)
    progress, on_step = _progress(cfg, args.quiet)
    try:
        with progress:
            report = train(cfg, args.demos, out, on_step)
    except (ValueError, CheckpointError) as exc:
        raise UsageError(str(exc)) from None
    _report(out, cfg, report)
    return 0


def train_config(args: argparse.Namespace) -> TrainConfig:
    """The flags as a TrainConfig, validated (UsageError, exit 2)."""
    from policies.dvla.recipes import TrainConfig

    cfg = TrainConfig(
        recipe=args.recipe,
        steps=args.steps,
        batch_size=args.batch_size,
        lr=args.lr,
        seed=args.seed,
        chunk_len=args.chunk_len,
        width=args.width,
        layers=args.layers,
        heads=args.heads,
        ffn=args.ffn,
        block_size=args.block_size,
        noise_schedule=args.noise_schedule or "",
        teacher=args.teacher or "",
        init=args.init or "",
        warmup_steps=args.warmup_steps,
        sampling=args.sampling,
        noisy_targets=args.noisy_targets,
        demo_ce=args.demo_ce,
        ema=args.ema,
        state_features=args.state_features or "",
        action_range=args.action_range or "percentile",
        image_tokens=args.image_tokens,
        image_coords=args.image_coords,
        device=resolve_device(args.device),
    )
    if args.action_range and (cfg.init or cfg.recipe == "distill"):
        raise UsageError(
            "--action-range: the tokenizer comes from the --init or --teacher checkpoint; leave it out"
        )
    try:
        cfg.validate()
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return cfg


def _progress(cfg: TrainConfig, quiet: bool) -> tuple[Progress, Any]:
    """A progress bar over the steps, and its per-step callback (a line every 5% where no
    live bar shows: a log file, CI)."""
    progress = Progress(
        TextColumn("[bold]training"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("loss {task.fields[loss]}"),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        console=err_console,
        disable=quiet,
    )
    task = progress.add_task("train", total=cfg.steps, loss="-")

    every = max(1, cfg.steps // 20)
    started = time.monotonic()

    def on_step(step: int, loss: float) -> None:
        progress.update(task, advance=1, loss=f"{loss:.4f}")
        # A log file or CI has no live bar: a line every 5% instead.
        if not err_console.is_terminal and not quiet and (step + 1) % every == 0:
            elapsed = time.monotonic() - started
            eta = elapsed / (step + 1) * (cfg.steps - step - 1)
            err_console.print(
                f"step {step + 1}/{cfg.steps}  loss {loss:.4f}  {elapsed:.0f} s, ETA {eta:.0f} s"
            )

    return progress, on_step


def _report(out: Path, cfg: TrainConfig, report: Any) -> None:
    """What was written, what it was trained on, and how well its tokenizer fits."""
    console.print(
        f"wrote {out} ({cfg.recipe}, {cfg.steps} steps, {report.seconds:.0f} s, "
        f"final loss {sum(report.losses[-50:]) / len(report.losses[-50:]):.4f}); curve: {out.with_suffix('.loss.png')}"
    )
    from policies.dvla.checkpoint import load

    meta = load(out).meta
    console.print(trained_on(meta))
    error = meta.get("tokenizer_round_trip_error")
    console.print(f"action tokenizer round-trip error on the training actions: {error:.5f} (mean |a - a'|)")
    worst = meta.get("tokenizer_worst_error") or []
    lost = [f"dimension {d}: up to {w:.2f}" for d, w in enumerate(worst) if w > CLIPPED]
    if lost:
        err_console.print(
            "[yellow]warning:[/] the action tokenizer clips some training actions by more than "
            f"{CLIPPED} ({'; '.join(lost)}): rare large actions decode smaller than demonstrated. "
            + _widen_hint(cfg)
        )


def _widen_hint(cfg: TrainConfig) -> str:
    """A continued or distilled model keeps the tokenizer it started from (its bins were
    fit on that model's demonstrations), so --action-range cannot widen it here."""
    source = cfg.teacher or cfg.init
    if source:
        flag = "--teacher" if cfg.teacher else "--init"
        return (
            f"The tokenizer is {flag} {source}'s, fit on its own demonstrations: to widen it, "
            "train a model from scratch on these with --action-range full."
        )
    return "If they matter, train with --action-range full."


def trained_on(meta: dict) -> str:
    """One line naming the starts each demonstrations folder came from, printed where the
    checkpoint is written: a LIBERO model trained on the evaluation's own initial states
    scores on its training starts, and the user should not find that out later."""
    parts = []
    for source in meta.get("data_sources") or []:
        held_out = source.get("fresh_initial_states") or (
            not str(source.get("suite", "")).startswith("libero/") and source.get("split") == "train"
        )
        starts = "held-out starts" if held_out else "the evaluation's own starts"
        parts.append(f"{source.get('suite')} {source.get('split')} split ({starts})")
    return "trained on: " + (
        "; ".join(parts) if parts else "unrecorded data (checkpoint predates data_sources)"
    )
