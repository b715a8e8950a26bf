"""What one episode measured: the per-episode half of a row (harness/run/rows.py adds the rest).

A field named like a column of results/schema.py's `EpisodeRow` becomes that column
as it is; the others (the work counts, the traceback, the decode traces) are turned
into columns or written elsewhere by the run. The loop (harness/episode/loop.py)
accumulates into one of these per running episode, so there is no second list of
per-episode fields to keep in step with it.
"""

from __future__ import annotations

import dataclasses
import traceback
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from harness.episode.work import Work


@dataclass
class EpisodeOutcome:
    success: bool = False
    steps: int = 0
    chunks: int = 0
    nfe_total: int | None = 0  # None: a served policy whose server does not report its passes
    action_tokens_total: int = 0
    policy_time_s: float = 0.0
    env_time_s: float = 0.0
    wall_clock_s: float = 0.0
    started_at: datetime = dataclasses.field(default_factory=lambda: datetime.now(UTC))
    failure_reason: str | None = None
    traceback: str | None = None
    # With traces: per chunk, the policy's trace of it plus "chunk" and "step" (env steps before it).
    traces: list[dict[str, Any]] | None = None
    # Where it ran (the `host` and `worker_id` columns), set by the backend that ran it.
    host: str = ""
    worker_id: str = ""
    # Environments stepped in lockstep with it, one policy call for them all (--batch-envs).
    batch_envs: int = 1
    # Instruction chains: the env's last `subtasks` records and `subtasks_completed`.
    subtasks: list[dict[str, Any]] | None = None
    subtasks_completed: int | None = None
    # Served policies: the part of policy_time_s that was not the server's own policy time.
    transport_time_s: float | None = None
    # Action vectors outside the action space and the largest excess (harness/episode/actions.py);
    # None: not checked (not a Box, or the episode never reached its env).
    actions_out_of_space: int | None = None
    max_action_excess: float | None = None
    # Counted work of its passes (harness/episode/work.py); a None field: not measured.
    work: Work = dataclasses.field(default_factory=Work)
    # Inference latency (harness/episode/plan.py): per chunk's delay in control steps, chunks
    # that came after the robot had run out of actions, steps spent holding still. At `none`
    # every delay is 0 (null without a chunk).
    delay_steps_mean: float | None = None
    delay_steps_max: int | None = None
    late_chunks: int = 0
    hold_steps: int = 0
    # CPU time over the same policy calls (harness/episode/cpu_time.py); None: not measured
    # (served policies, GPU policies).
    policy_cpu_time_s: float | None = None
    # With --video: the episode's rollout video, an MP4's bytes (harness/episode/video.py),
    # which the run's writer puts in its folder and names in the row's `video` column.
    video_mp4: bytes | None = None

    def progress(self) -> Progress:
        """How far it has got (a worker reports it while the episode runs)."""
        return Progress(
            self.steps,
            self.chunks,
            self.nfe_total,
            self.action_tokens_total,
            self.policy_time_s,
            self.env_time_s,
        )

    def fail(self, exc: BaseException, trace: str | None = None) -> None:
        """End the episode on `exc`: its failure row's reason (the traceback goes to the
        run's events.jsonl)."""
        self.failure_reason = f"{type(exc).__name__}: {exc}"
        self.traceback = trace if trace is not None else traceback.format_exc()
        self.success = False


@dataclass(frozen=True)
class Progress:
    """What a running episode has done so far: the counts and times its row would have."""

    steps: int = 0
    chunks: int = 0
    nfe_total: int | None = 0
    action_tokens_total: int = 0
    policy_time_s: float = 0.0
    env_time_s: float = 0.0


def failure_outcome(
    reason: str,
    started_at: datetime | None = None,
    host: str = "",
    worker_id: str = "",
    progress: Progress | None = None,
    wall_clock_s: float = 0.0,
) -> EpisodeOutcome:
    """The outcome of an episode that did not run to an end (its worker was lost, it ran
    past its time): a reason, and what it had done as its worker last reported it
    (`progress`; none: nothing counted) over the `wall_clock_s` it held the worker."""
    done = dataclasses.asdict(progress or Progress())
    return EpisodeOutcome(
        started_at=started_at or datetime.now(UTC),
        failure_reason=reason,
        host=host,
        worker_id=worker_id,
        wall_clock_s=wall_clock_s,
        **done,
    )


def chain_fields(info: dict[str, Any]) -> dict[str, Any]:
    """What an outcome keeps of a chain env's last info (nothing for other envs)."""
    if "subtasks" not in info:
        return {}
    records = [dict(r) for r in info["subtasks"]]  # a copy: the env's records are live
    return {"subtasks": records, "subtasks_completed": int(info["subtasks_completed"])}
