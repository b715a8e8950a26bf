"""Steps to convergence: Fast-dVLA's distillation against block diffusion from scratch.

The paper reports that asymmetric distillation from the bidirectional teacher converges
in ~2k steps where the block-diffusion loss needs ~20k from scratch. The two recipes
optimise different losses (KL to the teacher vs cross-entropy), so both are measured
with one yardstick, the probe loss of policies/training.py: cross-entropy of the true
action tokens at masked positions under fixed diffusion-forcing masks, on a fixed
sample of demonstration steps. Both runs use the same data, batch, learning rate,
seed and step budget.

    python benchmarks/convergence.py --demos demos/mt10 \\
        --teacher policies/checkpoints/metaworld-mt10-bidirectional.safetensors \\
        [--steps 300] [--probe-every 25] [--json benchmarks/results/convergence.json]

Reported: each recipe's probe curve; the step at which each first reaches the level
block diffusion ends at (its final probe loss), and the step at which each comes within
10% of its own final value.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from policies.recipes import TrainConfig
from policies.training import train


def first_step_at_or_below(probes: list[tuple[int, float]], level: float) -> int | None:
    return next((step for step, value in probes if value <= level), None)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--demos", required=True, help="demonstrations folder (dvla-harness collect)")
    parser.add_argument("--teacher", required=True, help="bidirectional teacher checkpoint")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--probe-every", type=int, default=25)
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", default="benchmarks/results/convergence.json")
    args = parser.parse_args(argv)

    curves: dict[str, list[tuple[int, float]]] = {}
    seconds: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for recipe in ("block_diffusion", "distill"):
            cfg = TrainConfig(
                recipe=recipe,
                steps=args.steps,
                batch_size=args.batch_size,
                seed=args.seed,
                probe_every=args.probe_every,
                teacher=args.teacher if recipe == "distill" else "",
            )
            print(f"training {recipe} for {args.steps} steps ...", file=sys.stderr, flush=True)
            report = train(cfg, args.demos, Path(tmp) / f"{recipe}.safetensors")
            curves[recipe] = report.probes
            seconds[recipe] = report.seconds

    bd_final = curves["block_diffusion"][-1][1]
    rows = []
    for recipe, probes in curves.items():
        final = probes[-1][1]
        rows.append(
            {
                "recipe": recipe,
                "start_probe_loss": probes[0][1],
                "final_probe_loss": final,
                "steps_to_block_diffusion_final": first_step_at_or_below(probes, bd_final),
                "steps_to_within_10pct_of_own_final": first_step_at_or_below(probes, final * 1.1),
                "train_seconds": seconds[recipe],
            }
        )
    print(f"\nprobe loss (CE at masked positions, fixed frontier masks), {args.steps} steps each\n")
    print("| step | " + " | ".join(curves) + " |")
    print("|---|" + "---|" * len(curves))
    for i, (step, _) in enumerate(curves["block_diffusion"]):
        print(f"| {step} | " + " | ".join(f"{curves[r][i][1]:.3f}" for r in curves) + " |")
    print(
        "\n| recipe | start | final | steps to block_diffusion's final | steps to within 10% of own final |"
    )
    print("|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['recipe']} | {r['start_probe_loss']:.3f} | {r['final_probe_loss']:.3f} | "
            f"{r['steps_to_block_diffusion_final']} | {r['steps_to_within_10pct_of_own_final']} |"
        )
    out = {
        "benchmark": "convergence",
        "args": vars(args),
        "machine": {"cpu": platform.processor() or platform.machine(), "python": platform.python_version()},
        "curves": curves,
        "rows": rows,
    }
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
