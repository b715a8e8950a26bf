"""The command-line flags that choose how a run executes (shared by `run` and `sweep`).

Every refusal here (a worker count below 1, Ray asked for but not installed or not
reachable) is a UsageError raised before the run folder is touched: exit 2, one line
naming the fix, nothing written.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from typing import Any

from harness.backends import BACKENDS, DEFAULT_MAX_RETRIES, Execution
from harness.errors import UsageError


def add_backend_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--backend",
        choices=BACKENDS,
        default="local",
        help="where episodes run: local (this machine; default) or ray (Ray actors, local or a cluster; "
        "needs the ray extra)",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=1,
        metavar="N",
        help="worker processes (local) or actors (ray), each taking a task's episodes at a time; "
        "1 (default, local) runs in this process",
    )
    p.add_argument(
        "--max-retries",
        type=int,
        default=DEFAULT_MAX_RETRIES,
        metavar="K",
        help=f"an episode whose worker died (signal, segfault, out of memory) is run again on a fresh "
        f"worker up to K times, then recorded as a failure row (default {DEFAULT_MAX_RETRIES})",
    )
    p.add_argument(
        "--episode-timeout",
        type=float,
        metavar="SECONDS",
        help="an episode running longer is recorded as a failure row (reason 'timeout') and its worker "
        "replaced (runs episodes in a worker process even with --workers 1); with --batch-envs K, a "
        "batch with no step for that long is stopped and its episodes run again alone, where the "
        "limit is per episode",
    )
    p.add_argument(
        "--batch-envs",
        type=int,
        metavar="K",
        help="step K environments of a task in lockstep and decode their observations in one policy "
        "call (batched inference, in this process or in each worker; policies that declare "
        "act_batch); default 1, or the config's batch_envs",
    )
    p.add_argument(
        "--ray-address",
        metavar="auto|HOST:PORT",
        help="join a running Ray cluster (default: start a local Ray with this machine's cores)",
    )
    p.add_argument(
        "--ray-num-gpus",
        type=float,
        default=0.0,
        metavar="G",
        help="GPUs Ray reserves for each worker (e.g. 1, or 0.25 to share one GPU among 4); default 0; "
        "--device cuda needs it, and --device auto uses a worker's reserved GPU (none: the CPU)",
    )


def execution_from_args(args: argparse.Namespace) -> Execution:
    """The Execution the flags ask for, refused (UsageError) before anything is written."""
    backend = getattr(args, "backend", "local")
    workers = getattr(args, "workers", 1)
    if workers < 1:
        raise UsageError(f"--workers must be at least 1, got {workers}; 1 runs in this process")
    if args.max_retries < 0:
        raise UsageError(f"--max-retries must be 0 or more, got {args.max_retries}")
    timeout = args.episode_timeout
    if timeout is not None and not (math.isfinite(timeout) and timeout > 0):
        raise UsageError(
            f"--episode-timeout must be a positive, finite number of seconds, got {timeout:g}; "
            "leave it out for no limit"
        )
    if backend != "ray" and (args.ray_address is not None or args.ray_num_gpus):
        raise UsageError("--ray-address and --ray-num-gpus apply to --backend ray; add it or drop them")
    if args.ray_num_gpus < 0:
        raise UsageError(f"--ray-num-gpus must be 0 or more, got {args.ray_num_gpus:g}")
    batch_envs = getattr(args, "batch_envs", None)
    batch_envs = 1 if batch_envs is None else batch_envs
    if isinstance(batch_envs, bool) or not isinstance(batch_envs, int) or batch_envs < 1:
        raise UsageError(f"--batch-envs must be an integer of at least 1, got {batch_envs!r}; 1 = unbatched")
    execution = Execution(
        backend=backend,
        workers=workers,
        max_retries=args.max_retries,
        episode_timeout=timeout,
        ray_address=args.ray_address,
        ray_num_gpus=args.ray_num_gpus,
        threads=getattr(args, "threads", None),
        device=getattr(args, "device", None),
        batch_envs=batch_envs,
    )
    if backend == "ray":
        from harness.backends.ray import connect

        connect(execution)  # not installed, unreachable: exit 2 here
    return execution


def check_batching(policies: Sequence[Any], batch_envs: int) -> None:
    """Refuse (exit 2) a policy that cannot batch when --batch-envs K > 1. `policies`: the
    run's PolicyRun entries (spec name and built policy)."""
    from harness.episode.timed import is_served
    from policies.base import can_batch

    if batch_envs < 1:
        raise UsageError(f"--batch-envs must be at least 1, got {batch_envs}; 1 steps one env at a time")
    if batch_envs == 1:
        return
    for p in policies:
        try:
            batchable = can_batch(p.policy)  # a served policy asks its server
        except ConnectionError as exc:
            raise UsageError(f"policy {p.spec.name}: {exc}") from None
        if not batchable and is_served(p.policy):
            where = getattr(p.policy, "served_by", "its server")
            raise UsageError(
                f"policy {p.spec.name}: {where} cannot decode batches (its metadata has no act_batch: "
                "true; openpi servers and experts cannot); serve a decoder with dvla-harness serve, or "
                f"run with --batch-envs 1 (not {batch_envs})"
            )
        if not batchable:
            raise UsageError(
                f"policy {p.spec.name} cannot batch across environments (--batch-envs {batch_envs}): "
                "it must declare act_batch(episodes, observations) and keep no per-episode state "
                "between chunks (policies/base.py BatchPolicy); run it with --batch-envs 1"
            )
