"""`dvla-harness sweep`: a grid of policy parameters as one resumable run."""

from __future__ import annotations

import argparse

from harness.errors import EXIT_STATUS_HELP, UsageError

EXAMPLES = """\
examples:
  # decode block size x Fast-dVLA thresholds, 5 episodes per task, one resumable run
  dvla-harness sweep --suite metaworld/mt10 --policy fast_dvla \\
      --grid block_size=4,8,16 --grid tau_conf=0.3,0.5,0.7 --episodes-per-task 5 --out runs/sweep
  # block diffusion's inference-time unmasking schedule, with decode traces
  dvla-harness sweep --suite metaworld/mt10 --policy block_diffusion \\
      --grid block_size=4,8 --grid schedule=linear,cosine --traces --out runs/bd-sweep
  # the training-time noise schedule lives in the checkpoint: sweep checkpoints
  dvla-harness sweep --suite metaworld/mt10 --policy fast_dvla --grid block_size=4,8 \\
      --grid checkpoint=ckpt/frontier.safetensors,ckpt/linear.safetensors --out runs/noise
  dvla-harness sweep ...same flags... --resume        # finish an interrupted sweep
  dvla-harness plot ablation runs/sweep --x block_size --y success,tokens_per_s --hue tau_conf --out fig.png

"""


def register(sub: argparse._SubParsersAction) -> None:
    from harness.commands.run import add_run_arguments

    p = sub.add_parser(
        "sweep",
        help="evaluate the Cartesian product of policy-parameter values as one run",
        description=(
            "Run every combination of the --grid values for each --policy as one run: the "
            "run's policy list is the grid's points, interleaved episode by episode, with the "
            "same run folder, progress bar, summary and --resume as `run`. Grid keys are "
            "policy parameters (`dvla-harness list policies`), including checkpoint; every "
            "value is checked before anything runs. The training-time noise schedule is a "
            "property of a checkpoint, not a parameter: sweep checkpoints trained with each "
            "(see docs/sweeps-and-plots.md)."
        ),
        epilog=EXAMPLES + EXIT_STATUS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_run_arguments(p)
    p.add_argument(
        "--grid",
        action="append",
        metavar="KEY=V1,V2,...",
        help="a policy parameter and the values to sweep; repeat for more axes (the product is run)",
    )
    p.set_defaults(func=cmd_sweep)


def cmd_sweep(args: argparse.Namespace) -> int:
    from harness.commands.run import config_from_args, execute_run, prepare_compute
    from harness.config import load_config_file, resolve
    from harness.run.folder import OpenMode
    from harness.run.sweep import expand, parse_grid

    mode = OpenMode.from_flags(args.resume, args.overwrite, args.retry_failed)
    if not args.policy and not (args.config and load_config_file(args.config).get("policy")):
        raise UsageError("sweep needs the policy to vary: --policy NAME (e.g. --policy fast_dvla)")
    grid = parse_grid(args.grid or [])
    config = expand(config_from_args(args), grid)
    prepare_compute(args)  # threads and device, before the policies load torch
    resolved = resolve(config)
    return execute_run(resolved, args, mode, "the same `dvla-harness sweep` command with --resume")
