"""Steps to convergence: Fast-dVLA's distillation against block-diffusion fine-tuning,
both from the same bidirectional teacher.

The paper compares the two recipes from the same fine-tuned bidirectional model: its
asymmetric distillation converges in ~2k steps where the block-diffusion loss needs ~10k
from those weights (~20k from scratch). Here both start from --teacher's weights with
the block-causal pattern: `distill` (KL to the frozen teacher, `frontier` masks) and
`block_diffusion --init TEACHER` (BD3-LM's clean-context cross-entropy). Their training
losses differ, so both are measured on the same yardsticks, the probe losses of
policies/dvla/losses.py on a fixed sample of demonstration steps with masks from a fixed seed:

    frontier       cross-entropy of the true tokens at masked positions in one noisy
                   stream, earlier blocks partly masked (what pipelined decoding meets);
    clean_context  the same with every earlier block clean (what block-by-block decoding
                   meets).

Same data, batch, learning rate, seed and step budget for both.

    python benchmarks/convergence.py --demos demos/mt10-600 \\
        --teacher policies/checkpoints/metaworld-mt10-bidirectional.safetensors \\
        [--steps 300] [--probe-every 25] [--json benchmarks/results/convergence.json]

Reported per yardstick: each recipe's curve; the level both reach (the higher of the two
final values) and the step at which each first reaches it; and the step at which each
comes within 10% of its own final value above its start-to-final drop.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from policies.dvla.recipes import TrainConfig
from policies.dvla.training import train

YARDSTICKS = ("frontier", "clean_context")


def first_step_at_or_below(probes: list[tuple[int, float]], level: float) -> int | None:
    return next((step for step, value in probes if value <= level), None)


def summary(curves: dict[str, dict[str, list[tuple[int, float]]]]) -> list[dict]:
    """Per yardstick and recipe: start, final, steps to the level both reach, steps to
    within 10% of the own drop."""
    rows = []
    for stick in YARDSTICKS:
        level = max(curves[r][stick][-1][1] for r in curves)
        for recipe, sticks in curves.items():
            probes = sticks[stick]
            start, final = probes[0][1], probes[-1][1]
            rows.append(
                {
                    "yardstick": stick,
                    "recipe": recipe,
                    "start_probe_loss": start,
                    "final_probe_loss": final,
                    "common_level": level,
                    "steps_to_common_level": first_step_at_or_below(probes, level),
                    "steps_to_90pct_of_own_drop": first_step_at_or_below(
                        probes, final + 0.1 * max(0.0, start - final)
                    ),
                }
            )
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--demos", required=True, help="demonstrations folder (dvla-harness collect)")
    parser.add_argument("--teacher", required=True, help="bidirectional checkpoint both recipes start from")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--probe-every", type=int, default=25)
    parser.add_argument("--batch-size", type=int, default=256)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", default="benchmarks/results/convergence.json")
    parser.add_argument(
        "--keep", metavar="DIR", help="keep both checkpoints here (e.g. to evaluate them on a suite)"
    )
    args = parser.parse_args(argv)

    configs = {
        "distill": TrainConfig(recipe="distill", teacher=args.teacher),
        "block_diffusion": TrainConfig(recipe="block_diffusion", init=args.teacher),
    }
    curves: dict[str, dict[str, list[tuple[int, float]]]] = {}
    seconds: dict[str, float] = {}
    schedules: dict[str, str] = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.keep or tmp)
        folder.mkdir(parents=True, exist_ok=True)
        for recipe, base in configs.items():
            cfg = replace(
                base,
                steps=args.steps,
                batch_size=args.batch_size,
                seed=args.seed,
                probe_every=args.probe_every,
            )
            print(
                f"training {recipe} from the teacher for {args.steps} steps ...", file=sys.stderr, flush=True
            )
            report = train(cfg, args.demos, folder / f"{recipe}.safetensors")
            curves[recipe] = {"frontier": report.probes, "clean_context": report.clean_probes}
            seconds[recipe] = report.seconds
            schedules[recipe] = cfg.schedule

    rows = summary(curves)
    for stick in YARDSTICKS:
        print(f"\nprobe loss, {stick} masks (CE of the true tokens at masked positions)\n")
        print("| step | " + " | ".join(curves) + " |")
        print("|---|" + "---|" * len(curves))
        for i, (step, _) in enumerate(curves["distill"][stick]):
            print(f"| {step} | " + " | ".join(f"{curves[r][stick][i][1]:.3f}" for r in curves) + " |")
    print(
        "\n| yardstick | recipe | start | final | level both reach | steps to it | steps to 90% of own drop |"
    )
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['yardstick']} | {r['recipe']} | {r['start_probe_loss']:.3f} | {r['final_probe_loss']:.3f} | "
            f"{r['common_level']:.3f} | {r['steps_to_common_level']} | {r['steps_to_90pct_of_own_drop']} |"
        )
    print("\n" + ", ".join(f"{r}: {s:.0f} s" for r, s in seconds.items()))
    out = {
        "benchmark": "convergence",
        "args": vars(args),
        "start": "both recipes from --teacher's weights (block-causal pattern)",
        "noise_schedules": schedules,
        "machine": {"cpu": platform.processor() or platform.machine(), "python": platform.python_version()},
        "curves": curves,
        "train_seconds": seconds,
        "rows": rows,
    }
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    print(f"\nwrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
