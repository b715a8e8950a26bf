"""The work a backend is given: a run's episodes as jobs, their ids, their batches.

A job pairs one policy configuration of the run with one episode spec of one task.
Jobs run in the order task -> episode -> policy, so the policies of one comparison are
interleaved in time and share whatever the machine was doing: their timing ratios are
measured side by side. Workers are sent job ids, not jobs: each rebuilds the run and
finds its jobs by id (`index_jobs`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeVar

from adapters.base import EpisodeSpec, TaskSpec
from adapters.simpler_variants import label as variant_label
from results.schema import EPISODE_KEY

if TYPE_CHECKING:
    from harness.config import PolicyRun, ResolvedRun

T = TypeVar("T")
JobId = tuple[str, int, str]  # task name, episode index, policy_config_id


@dataclass(frozen=True)
class EpisodeJob:
    policy: PolicyRun
    task: TaskSpec
    spec: EpisodeSpec


def plan_jobs(resolved: ResolvedRun) -> list[EpisodeJob]:
    """Every episode of the run, in the order they run (task -> episode -> policy)."""
    return [
        EpisodeJob(policy, task, spec)
        for task in resolved.tasks
        for spec in resolved.episodes(task)
        for policy in resolved.policies
    ]


def job_id(job: EpisodeJob) -> JobId:
    """What a worker is sent: its own ResolvedRun holds the task, spec and policy."""
    return (job.task.name, job.spec.index, job.policy.config_id)


def index_jobs(resolved: ResolvedRun) -> dict[JobId, EpisodeJob]:
    """Every episode of a (re)built ResolvedRun by its JobId (in a worker)."""
    return {job_id(job): job for job in plan_jobs(resolved)}


def normalised_key(values: dict[str, Any]) -> tuple:
    """An episode key (results/schema.py EPISODE_KEY) from a row or a job, normalised
    (pandas gives numpy ints and NaN for nulls)."""
    out = []
    for name in EPISODE_KEY:
        v = values[name]
        if v is None or (isinstance(v, float) and v != v):
            out.append(None)
        elif hasattr(v, "item"):
            out.append(v.item())
        else:
            out.append(v)
    return tuple(out)


def job_key(suite: str, job: EpisodeJob) -> tuple:
    """The episode key a job's row will have: --resume skips a job whose key is recorded."""
    return normalised_key(
        {
            "suite": suite,
            "task": job.task.name,
            "episode_index": job.spec.index,
            "seed": job.spec.seed,
            "init_state_id": job.spec.init_state_id,
            "variant": variant_label(job.spec.variant),
            "policy": job.policy.spec.name,
            "policy_params": job.policy.params_json,
            "checkpoint_sha256": job.policy.checkpoint_sha256,
        }
    )


def batch_groups(items: Sequence[T], task: Callable[[T], str], policy: Callable[[T], str]) -> list[list[T]]:
    """`items` (episodes in plan order) as batches: task by task in order of first
    appearance, and within a task one group per policy (a batch serves one policy)."""
    groups: dict[str, dict[str, list[T]]] = {}
    for item in items:
        groups.setdefault(task(item), {}).setdefault(policy(item), []).append(item)
    return [group for by_policy in groups.values() for group in by_policy.values()]
