"""How Fast-dLLM's block size and threshold trade forward passes for agreement with its teacher.

Fast-dLLM (`fast_dllm`) decodes a bidirectional checkpoint block by block, refreshing its
approximate KV cache at every block start and committing every token whose confidence
reaches the threshold. Its block is the knob that transfers worst from text to actions:
the paper's 32-token block is 1/8 of a 256-token answer, and 1/8 of an action chunk is
one action step (4 or 7 tokens), which forces a refresh every few tokens. This script
chooses the policy's default block and threshold on held-out states (demonstrations of
the train split, never the evaluation episodes), not by taste.

`measure` decodes the same demonstration states with the teacher (`bidirectional` at
its defaults) and with `fast_dllm` at every block size x threshold on the same weights,
and records per setting:

    NFE/chunk      forward passes per chunk, as one state alone would need them (the
                   passes that committed a token for it: a row never waits on another);
    = teacher      share of tokens equal to the teacher's decode of the same state;
    = demo         share equal to the demonstrated chunk's tokens;
    L1 to demo     mean |action - demonstrated action| over the chunk.

`choose` reads one such file per checkpoint set, keeps the settings every set can use
(a block that is the same fraction of every chunk: 1, 2, 4 or 8 blocks per chunk), and
picks the default by `select`'s rule (below); it writes the choice, the table and a
Pareto plot. The policy's defaults (FastDLLMParams) are checked against the committed
choice by tests/test_fast_dllm_sweep.py.

    python benchmarks/fast_dllm_sweep.py measure --label metaworld-mt10 --demos DIR [DIR ...] \\
        --teacher policies/checkpoints/metaworld-mt10-bidirectional.safetensors \\
        [--thresholds 0.3,0.5,0.7,0.9] [--samples 256] [--json benchmarks/results/fast-dllm-sweep-mt10.json]
    python benchmarks/fast_dllm_sweep.py choose benchmarks/results/fast-dllm-sweep-*.json \\
        [--tolerance 0.02] [--json benchmarks/results/fast-dllm-sweep.json] [--plot docs/fast-dllm-sweep.png]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.commit_rule import build, row_of

THRESHOLDS = (0.3, 0.5, 0.7, 0.9)
TOLERANCE = 0.02  # agreement with the teacher a default may give up against a set's best


def block_sizes(action_tokens: int, action_dim: int) -> list[int]:
    """Every block size from one action step to the whole chunk that divides the chunk."""
    return [d for d in range(action_dim, action_tokens + 1) if action_tokens % d == 0]


def pareto_front(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the (passes, agreement) points no other point beats: none has as few
    passes and as much agreement with one of the two strictly better."""
    front = []
    for i, (n, a) in enumerate(points):
        beaten = any((m <= n and b >= a) and (m < n or b > a) for j, (m, b) in enumerate(points) if j != i)
        if not beaten:
            front.append(i)
    return front


def select(sets: dict[str, list[dict[str, Any]]], tolerance: float = TOLERANCE) -> tuple[int, float]:
    """(blocks per chunk, threshold) for the policy's default.

    A candidate is a (blocks, threshold) pair measured on every set. It qualifies when,
    on every set, its agreement with the teacher is within `tolerance` of that set's best
    fast_dllm agreement; of those, the one with the fewest passes relative to each set's
    teacher (mean over sets of NFE / teacher NFE) wins, ties to the higher agreement.
    A row is {"blocks", "threshold", "nfe_per_chunk", "same_as_teacher",
    "teacher_nfe"}. Raises ValueError when no candidate qualifies on every set."""
    if not sets:
        raise ValueError("no sweep results to choose from")
    keyed = {name: {(r["blocks"], r["threshold"]): r for r in rows} for name, rows in sets.items()}
    common = set.intersection(*(set(k) for k in keyed.values()))
    best = {name: max(r["same_as_teacher"] for r in rows.values()) for name, rows in keyed.items()}
    scored = []
    for key in common:
        rows = [keyed[name][key] for name in keyed]
        if all(keyed[name][key]["same_as_teacher"] >= best[name] - tolerance for name in keyed):
            cost = float(np.mean([r["nfe_per_chunk"] / r["teacher_nfe"] for r in rows]))
            agreement = float(np.mean([r["same_as_teacher"] for r in rows]))
            scored.append((cost, -agreement, key))
    if not scored:
        raise ValueError(f"no setting is within {tolerance} of the best agreement on every set")
    blocks, threshold = min(scored)[2]
    return int(blocks), float(threshold)


def measure(args: argparse.Namespace) -> dict[str, Any]:
    import torch

    from policies.dvla.checkpoint import load, to_tensors
    from policies.dvla.demos import load_demos

    torch.set_num_threads(args.threads)
    ckpt = load(args.teacher)
    cfg = ckpt.model.cfg
    demos = load_demos(args.demos, cfg.chunk_len)
    if args.samples > len(demos.actions):
        raise ValueError(f"--samples {args.samples}: the demonstrations hold {len(demos.actions)} steps")
    rows = np.random.default_rng(args.seed).choice(len(demos.actions), args.samples, replace=False)
    target = demos.actions[demos.chunk_index[rows]]
    demo_tokens = ckpt.tokenizer.encode(target).reshape(len(rows), -1)
    words, state = to_tensors(
        ckpt, [demos.instructions[r] for r in rows], demos.observations[rows][:, : ckpt.raw_state_dim]
    )

    def run(text: str) -> tuple[np.ndarray, np.ndarray]:
        policy, params, _ = build(text, args.teacher)
        tokens, nfe = [], []
        with torch.inference_mode():
            for b in range(0, len(rows), args.batch):
                decoded = policy._decode(
                    policy.model, words[b : b + args.batch], state[b : b + args.batch], params
                )
                tokens.append(decoded.tokens.cpu().numpy())
                per_row = [[bool(p.committed[r]) for p in decoded.passes] for r in range(len(tokens[-1]))]
                nfe.append(np.array([sum(c) for c in per_row]))
        return np.concatenate(tokens), np.concatenate(nfe)

    teacher_tokens, teacher_nfe = run("bidirectional")
    teacher_row = row_of(
        "bidirectional (teacher)",
        teacher_tokens,
        teacher_nfe,
        None,
        None,
        teacher_tokens,
        demo_tokens,
        target,
        ckpt,
    )
    table = []
    for size in block_sizes(cfg.action_tokens, cfg.action_dim):
        for threshold in args.thresholds:
            text = f"fast_dllm:block_size={size},threshold={threshold}"
            tokens, nfe = run(text)
            row = row_of(text, tokens, nfe, None, None, teacher_tokens, demo_tokens, target, ckpt)
            row.update(block_size=size, threshold=threshold, teacher_nfe=teacher_row["nfe_per_chunk"])
            if cfg.action_tokens % size == 0 and (cfg.action_tokens // size) in (1, 2, 4, 8):
                row["blocks"] = cfg.action_tokens // size
            table.append(_trim(row))
    return {
        "label": args.label,
        "demos": args.demos,
        "teacher": args.teacher,
        "action_tokens": cfg.action_tokens,
        "action_dim": cfg.action_dim,
        "samples": args.samples,
        "batch": args.batch,
        "seed": args.seed,
        "threads": args.threads,
        "machine": platform.platform(),
        "teacher_row": _trim(teacher_row),
        "rows": table,
    }


def _trim(row: dict[str, Any]) -> dict[str, Any]:
    """Drop commit_rule's pipelined-only columns, which fast_dllm never fills."""
    return {
        k: v
        for k, v in row.items()
        if not k.startswith("below") and "_below" not in k and "at_or_above" not in k
    }


def choose(paths: Sequence[str], tolerance: float) -> dict[str, Any]:
    results = [json.loads(Path(p).read_text()) for p in paths]
    sets = {r["label"]: [row for row in r["rows"] if "blocks" in row] for r in results}
    blocks, threshold = select(sets, tolerance)
    return {
        "rule": f"fewest passes (mean NFE / teacher NFE over sets) among the settings within "
        f"{tolerance} agreement with the teacher of each set's best",
        "tolerance": tolerance,
        "chosen": {"blocks": blocks, "threshold": threshold},
        "sets": {r["label"]: r for r in results},
    }


def render(choice: dict[str, Any]) -> str:
    lines = [
        "| set | block (tokens) | blocks/chunk | threshold | NFE/chunk | = teacher % | = demo % | L1 to demo | Pareto |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for label, result in choice["sets"].items():
        t = result["teacher_row"]
        lines.append(
            f"| {label} | teacher (bidirectional, 12 steps) | - | - | {t['nfe_per_chunk']:.1f} | 100.0 "
            f"| {100 * t['same_as_demo']:.1f} | {t['l1_to_demo']:.4f} | |"
        )
        rows = result["rows"]
        front = set(pareto_front([(r["nfe_per_chunk"], r["same_as_teacher"]) for r in rows]))
        for i, r in enumerate(rows):
            mark = (
                "**chosen**" if (r.get("blocks"), r["threshold"]) == tuple(choice["chosen"].values()) else ""
            )
            lines.append(
                f"| {label} | {r['block_size']} | {r.get('blocks', '-')} | {r['threshold']} | {r['nfe_per_chunk']:.1f} "
                f"| {100 * r['same_as_teacher']:.1f} | {100 * r['same_as_demo']:.1f} | {r['l1_to_demo']:.4f} "
                f"| {'yes' if i in front else ''} {mark} |"
            )
    return "\n".join(lines)


def plot(choice: dict[str, Any], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sets = choice["sets"]
    fig, axes = plt.subplots(1, len(sets), figsize=(5.2 * len(sets), 4.2), squeeze=False)
    chosen = tuple(choice["chosen"].values())
    for ax, (label, result) in zip(axes[0], sets.items(), strict=True):
        rows = result["rows"]
        sizes = sorted({r["block_size"] for r in rows})
        marks = dict(zip(sizes, "os^Dv<>", strict=False))
        cmap = plt.get_cmap("viridis")
        for r in rows:
            colour = cmap((r["threshold"] - 0.25) / 0.7)
            ax.scatter(
                r["nfe_per_chunk"],
                100 * r["same_as_teacher"],
                marker=marks[r["block_size"]],
                color=colour,
                s=45,
                zorder=3,
            )
            if (r.get("blocks"), r["threshold"]) == chosen:
                ax.scatter(
                    r["nfe_per_chunk"],
                    100 * r["same_as_teacher"],
                    s=220,
                    facecolors="none",
                    edgecolors="red",
                    linewidths=2,
                    zorder=4,
                )
            if r["block_size"] == result["action_dim"] and r["threshold"] == 0.9:
                ax.annotate(
                    "paper's literal\n(previous default)",
                    (r["nfe_per_chunk"], 100 * r["same_as_teacher"]),
                    fontsize=8,
                    xytext=(-95, 34),
                    textcoords="offset points",
                    arrowprops={"arrowstyle": "->", "lw": 0.8},
                )
        front = sorted(
            (rows[i]["nfe_per_chunk"], 100 * rows[i]["same_as_teacher"])
            for i in pareto_front([(r["nfe_per_chunk"], r["same_as_teacher"]) for r in rows])
        )
        ax.plot(*zip(*front, strict=True), color="grey", lw=1, zorder=2, label="Pareto front")
        ax.axvline(result["teacher_row"]["nfe_per_chunk"], color="black", ls=":", lw=1, label="teacher's NFE")
        for size in sizes:
            ax.scatter([], [], marker=marks[size], color="grey", label=f"block {size}")
        ax.set_title(
            f"{label} ({result['action_tokens']}-token chunk, {result['samples']} states)", fontsize=10
        )
        ax.set_xlabel("forward passes per chunk")
        ax.set_ylabel("tokens equal to the teacher's decode (%)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=4)
    sm = plt.cm.ScalarMappable(cmap=plt.get_cmap("viridis"), norm=plt.Normalize(0.25, 0.95))
    fig.colorbar(sm, ax=axes[0].tolist(), label="threshold", fraction=0.02)
    blocks = "the whole chunk as one block" if chosen[0] == 1 else f"{chosen[0]} blocks per chunk"
    fig.suptitle(
        f"fast_dllm block x threshold on held-out states (red ring: chosen default, {blocks}, threshold {chosen[1]})",
        fontsize=10,
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110, bbox_inches="tight")
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    sub = parser.add_subparsers(dest="command", required=True)
    m = sub.add_parser("measure", help="sweep one checkpoint set on demonstration states")
    m.add_argument("--label", required=True, help="the set's name in tables and the plot")
    m.add_argument(
        "--demos", nargs="+", required=True, help="held-out demonstrations folder(s) (train split)"
    )
    m.add_argument(
        "--teacher", required=True, help="bidirectional checkpoint (teacher and fast_dllm's weights)"
    )
    m.add_argument(
        "--thresholds", default=",".join(map(str, THRESHOLDS)), help="comma-separated (default: %(default)s)"
    )
    m.add_argument(
        "--samples", type=int, default=256, help="demonstration steps drawn (default: %(default)s)"
    )
    m.add_argument("--batch", type=int, default=64, help="states decoded per batch (default: %(default)s)")
    m.add_argument("--seed", type=int, default=0, help="which steps are drawn (default: %(default)s)")
    m.add_argument("--threads", type=int, default=1, help="torch threads (default: %(default)s)")
    m.add_argument("--json", required=True, help="where to write")
    c = sub.add_parser("choose", help="pick the default from one measure file per set")
    c.add_argument("results", nargs="+", help="measure outputs")
    c.add_argument("--tolerance", type=float, default=TOLERANCE, help="(default: %(default)s)")
    c.add_argument("--json", default="benchmarks/results/fast-dllm-sweep.json", help="(default: %(default)s)")
    c.add_argument("--plot", default="docs/fast-dllm-sweep.png", help="(default: %(default)s)")
    args = parser.parse_args(argv)
    try:
        if args.command == "measure":
            try:
                args.thresholds = [float(t) for t in args.thresholds.split(",")]
            except ValueError:
                parser.error(f"--thresholds: comma-separated numbers in (0, 1], got {args.thresholds!r}")
            if not all(0 < t <= 1 for t in args.thresholds):
                parser.error(f"--thresholds: each must be in (0, 1], got {args.thresholds}")
            for flag, value in (
                ("--samples", args.samples),
                ("--batch", args.batch),
                ("--threads", args.threads),
            ):
                if value < 1:
                    parser.error(f"{flag} must be at least 1, got {value}")
            result = measure(args)
            print(
                "\n".join(
                    render(
                        {"chosen": {"blocks": None, "threshold": None}, "sets": {args.label: result}}
                    ).splitlines()
                )
            )
        else:
            result = choose(args.results, args.tolerance)
            print(render(result))
            print(f"chosen: {result['chosen']}")
            plot(result, Path(args.plot))
            print(f"wrote {args.plot}")
    except (OSError, ValueError, KeyError) as exc:  # a missing folder or file, a foreign result file
        print(f"error: {exc}", file=sys.stderr)
        return 2
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
