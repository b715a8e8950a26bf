"""An episode's row: what the episode measured, what it was, and what follows from both.

A row is an `EpisodeRow` (results/schema.py) made of three parts, each written once:
the outcome's fields that are columns, taken by name (harness/episode/outcome.py); the
episode's identity and the run's settings (`identity`); and the columns computed from
the outcome (`derived`). The row's constructor refuses a missing or unknown column.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import pandas as pd

from adapters.simpler_variants import label as variant_label
from harness.episode.cpu_time import is_starved
from harness.episode.outcome import EpisodeOutcome
from harness.episode.video import video_path
from results.labels import config_labels
from results.schema import COLUMN_NAMES, EpisodeRow, row_dict

if TYPE_CHECKING:
    from harness.backends.jobs import EpisodeJob
    from harness.config import ResolvedRun

# The outcome's fields that are columns as they are.
OUTCOME_COLUMNS = tuple(f.name for f in dataclasses.fields(EpisodeOutcome) if f.name in COLUMN_NAMES)


def run_config_labels(resolved: ResolvedRun) -> dict[str, str]:
    """The run's configuration labels (results.labels), from every configuration it lists,
    so a row's config_label is the same whichever episodes have run so far."""
    configs = pd.DataFrame(
        [(p.config_id, p.spec.name, p.params_json) for p in resolved.policies],
        columns=["policy_config_id", "policy", "policy_params"],
    )
    return config_labels(configs)


def identity(run_id: str, resolved: ResolvedRun, job: EpisodeJob, label: str) -> dict[str, Any]:
    """What the episode was: run, suite, task, spec, policy configuration and the run's
    settings that decide what happened in it."""
    p, task, spec, config = job.policy, job.task, job.spec, resolved.config
    return {
        "run_id": run_id,
        "suite": resolved.suite.name,
        "suite_version": resolved.suite.version,
        "task": task.name,
        "task_index": task.index,
        "episode_index": spec.index,
        "seed": spec.seed,
        "init_state_id": spec.init_state_id,
        "variant": variant_label(spec.variant),
        "policy": p.spec.name,
        "policy_params": p.params_json,
        "policy_config_id": p.config_id,
        "config_label": label,
        "checkpoint": p.checkpoint,
        "checkpoint_sha256": p.checkpoint_sha256,
        "replan_every": config.replan_every,
        "max_steps": task.max_steps,
        "out_of_space_rule": config.out_of_space,
        "inference_latency": config.inference_latency,
        "execution": config.execution,
        "speed_reliable": None,  # the run's calibration verdict, set when it finishes
        "chain_id": f"{task.name}/{spec.index}" if spec.chain else None,
    }


def _per_chunk(total: int | None, chunks: int) -> float | None:
    return total / chunks if chunks and total is not None else None


def derived(out: EpisodeOutcome, task_instruction: str, chain: bool) -> dict[str, Any]:
    """The columns that follow from what the episode measured."""
    work, policy_s = out.work, out.policy_time_s
    return {
        "instruction": " | ".join(r["instruction"] for r in out.subtasks)
        if out.subtasks
        else task_instruction,
        "nfe_per_chunk": _per_chunk(out.nfe_total, out.chunks),
        "flops_total": work.flops,
        "flops_per_chunk": _per_chunk(work.flops, out.chunks),
        "query_tokens_total": work.query_tokens,
        "kv_tokens_total": work.kv_tokens,
        "kv_cached_tokens_total": work.kv_cached_tokens,
        "tokens_per_s": out.action_tokens_total / policy_s
        if out.action_tokens_total and policy_s > 0
        else None,
        "starved": is_starved(policy_s, out.policy_cpu_time_s),
        "overhead_s": out.wall_clock_s - policy_s - out.env_time_s,
        "control_hz": out.steps / policy_s if policy_s > 0 else None,
        "loop_hz": out.steps / out.wall_clock_s if out.wall_clock_s > 0 else None,
        # chain columns: null for other suites, whatever the env said
        "subtasks_completed": (out.subtasks_completed or 0) if chain else None,
        "subtasks": out.subtasks if chain else None,
    }


def make_row(
    run_id: str,
    resolved: ResolvedRun,
    job: EpisodeJob,
    out: EpisodeOutcome,
    labels: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """One episode's row, in column order; `labels`: run_config_labels(resolved), worked
    out once per run."""
    labels = run_config_labels(resolved) if labels is None else labels
    measured = {name: getattr(out, name) for name in OUTCOME_COLUMNS}
    chain = bool(job.spec.chain)
    video = video_path(job.policy.config_id, job.task.name, job.spec.index) if out.video_mp4 else None
    row = EpisodeRow(
        **identity(run_id, resolved, job, labels[job.policy.config_id]),
        **(measured | derived(out, job.task.instruction, chain) | {"video": video}),
    )
    return row_dict(row)


def trace_lines(run_id: str, resolved: ResolvedRun, job: EpisodeJob, out: EpisodeOutcome) -> list[dict]:
    """traces.jsonl lines of one episode: its key fields, then each chunk's trace."""
    key = {
        "run_id": run_id,
        "suite": resolved.suite.name,
        "task": job.task.name,
        "episode_index": job.spec.index,
        "policy": job.policy.spec.name,
        "policy_config_id": job.policy.config_id,
        "started_at": out.started_at,
    }
    return [key | chunk for chunk in out.traces or ()]
