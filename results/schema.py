"""The tidy episode table: one row per episode, every column named, typed and documented.

`EpisodeRow` is the single source of truth: its fields, in order, are the columns; each
field carries its Arrow type, unit and meaning, and is nullable exactly when its type
admits None. The Parquet schema, the episode key used for resume and pairing, and
docs/results-schema.md (checked by a test) all come from it, and a run's rows are built
as EpisodeRow values (harness/run/rows.py), so a column cannot be added, dropped or
misnamed in one place and not the others. Bump SCHEMA_VERSION whenever a column changes
meaning, type or name.
"""

from __future__ import annotations

import types
import typing
from dataclasses import dataclass, field, fields
from datetime import datetime
from typing import Any

import pyarrow as pa

SCHEMA_VERSION = "5"
# Versions this code reads: a version-1 table (before instruction chains) gets the chain
# columns as nulls, a version-2 table (before variants) a null `variant`, which is what
# they mean for its suites; a version-3 table (before the action-space check, counted
# work, CPU time, configuration labels and inference latency) gets null out-of-space,
# work, CPU-time and latency columns (its actions were not checked, its work and CPU
# time not measured, it ran at `none`) and `config_label` filled in on read
# (results.labels.with_config_labels); a version-4 table (before rollout videos) a null
# `video` (none was recorded).
READABLE_VERSIONS = ("1", "2", "3", "4", "5")
SCHEMA_VERSION_KEY = b"dvla_harness.schema_version"


@dataclass(frozen=True)
class Column:
    """One column as readers see it (derived from EpisodeRow's field of that name)."""

    name: str
    type: pa.DataType
    unit: str
    meaning: str
    nullable: bool = False


def column(kind: pa.DataType, unit: str, meaning: str) -> dict[str, Any]:
    """An EpisodeRow field's metadata: its Arrow type, unit and meaning (the field has no
    default: every row says every column)."""
    return {"arrow": kind, "unit": unit, "meaning": meaning}


_TS = pa.timestamp("us", tz="UTC")
SUBTASK = pa.struct(
    [
        pa.field("id", pa.string()),
        pa.field("instruction", pa.string()),
        pa.field("success", pa.bool_()),
        pa.field("steps", pa.int64()),
        # CALVIN's credit rule (adapters/chain_credit.py); null in rows written before it.
        pa.field("start_step", pa.int64()),
        pa.field("end_step", pa.int64()),
        pa.field("goal_held_at_start", pa.bool_()),
        pa.field("outcome", pa.string()),
    ]
)


@dataclass(frozen=True, slots=True)
class EpisodeRow:
    """One row of episodes.parquet; the field order is the column order."""

    run_id: str = field(metadata=column(pa.string(), "", "Identifier of the run (kept across --resume)."))
    suite: str = field(
        metadata=column(
            pa.string(),
            "",
            "Suite name with its options, e.g. `metaworld/mt10`, `libero/spatial:obs=upstream,seeding=openvla` (the observation regime is read from it).",
        )
    )
    suite_version: str = field(
        metadata=column(pa.string(), "", "Version of the suite's task/episode definition.")
    )
    task: str = field(metadata=column(pa.string(), "", "Task name within the suite."))
    task_index: int = field(metadata=column(pa.int64(), "", "Position of the task in the suite."))
    instruction: str = field(
        metadata=column(
            pa.string(),
            "",
            "Language instruction given to the policy; for an instruction chain, its instructions in order joined by ` | `.",
        )
    )
    episode_index: int = field(
        metadata=column(pa.int64(), "", "Index of the episode spec within its task (0-based).")
    )
    seed: int | None = field(
        metadata=column(
            pa.int64(), "", "Seed of the episode's start (Meta-World: the seed that drew the task's layouts)."
        )
    )
    init_state_id: int | None = field(
        metadata=column(pa.int64(), "", "Fixed initial state / layout the episode starts from.")
    )
    policy: str = field(metadata=column(pa.string(), "", "Registered policy name."))
    policy_params: str = field(
        metadata=column(pa.string(), "JSON", "All policy parameters, defaults included.")
    )
    policy_config_id: str = field(
        metadata=column(pa.string(), "", "Short hash of policy, params and checkpoint.")
    )
    config_label: str | None = field(
        metadata=column(
            pa.string(),
            "",
            "The configuration's name as the tables print it: the policy, plus the parameters that set it apart from the run's other configurations of that policy or from its defaults, e.g. `fast_dvla`, `acme_pd (gain=0.5)`. Unique per configuration within a run: group by it instead of parsing policy_params. Null in rows written before it was recorded (the harness's readers fill it in).",
        )
    )
    checkpoint: str = field(
        metadata=column(pa.string(), "path", "Checkpoint file the policy loaded; empty if none.")
    )
    checkpoint_sha256: str = field(
        metadata=column(pa.string(), "", "SHA-256 of the checkpoint; empty if none.")
    )
    replan_every: int = field(
        metadata=column(
            pa.int64(), "actions", "Actions executed per chunk before re-planning (0 = whole chunk)."
        )
    )
    max_steps: int = field(metadata=column(pa.int64(), "steps", "Step budget of the task."))
    success: bool = field(
        metadata=column(
            pa.bool_(),
            "",
            "The environment reported success before the budget ran out (a chain: all its subtasks).",
        )
    )
    steps: int = field(
        metadata=column(pa.int64(), "steps", "Environment steps executed (settle steps excluded).")
    )
    chunks: int = field(metadata=column(pa.int64(), "", "Policy calls (action chunks requested)."))
    nfe_total: int | None = field(
        metadata=column(
            pa.int64(),
            "passes",
            "Model forward passes, counted by the harness's hooks (for a remote policy, by the serving dvla-harness's hooks, returned with each reply). Null when a remote server reports none (openpi's): not measured, never 0.",
        )
    )
    nfe_per_chunk: float | None = field(metadata=column(pa.float64(), "passes", "nfe_total / chunks."))
    flops_total: int | None = field(
        metadata=column(
            pa.int64(),
            "FLOP",
            "Counted work: floating-point operations of the matrix products (linear layers, convolutions, attention; 2 per multiply-accumulate) of every forward pass, counted by the NFE hooks from the tensors' shapes (harness/episode/work.py; for a remote policy, by the serving dvla-harness's hooks). Identical on every machine and load. A batched call's work is split equally among the episodes it served (each one's row). Null when not measured: a remote server that reports none, a model holding a layer of a kind whose products are not counted, rows written before it was recorded.",
        )
    )
    flops_per_chunk: float | None = field(metadata=column(pa.float64(), "FLOP", "flops_total / chunks."))
    query_tokens_total: int | None = field(
        metadata=column(
            pa.int64(),
            "positions",
            "Counted work: positions the forward passes computed (queries of their attention), summed over passes. Null when not measured (no attention call was seen, a remote server that reports none).",
        )
    )
    kv_tokens_total: int | None = field(
        metadata=column(
            pa.int64(),
            "positions",
            "Counted work: key/value positions the passes' queries attended, cached or not, summed over passes. Null when not measured.",
        )
    )
    kv_cached_tokens_total: int | None = field(
        metadata=column(
            pa.int64(),
            "positions",
            "Of kv_tokens_total, the positions read from a KV cache (attended but not computed by the pass): what a cache saves shows here. Null when not measured.",
        )
    )
    action_tokens_total: int = field(
        metadata=column(pa.int64(), "tokens", "Discrete action tokens decoded (0 for non-token policies).")
    )
    tokens_per_s: float | None = field(
        metadata=column(
            pa.float64(), "tokens/s", "action_tokens_total / policy_time_s; null when no tokens were decoded."
        )
    )
    policy_time_s: float = field(
        metadata=column(pa.float64(), "s", "Time inside the policy (reset and act calls).")
    )
    transport_time_s: float | None = field(
        metadata=column(
            pa.float64(),
            "s",
            "Remote policies (docs/remote-policies.md): the part of policy_time_s that was not the server's own policy time (encoding, the network, waiting). Null for policies in this process.",
        )
    )
    policy_cpu_time_s: float | None = field(
        metadata=column(
            pa.float64(),
            "s",
            "CPU time over the same policy calls as policy_time_s: the calling thread's (time.thread_time) when torch runs on one intra-op thread, else the process's (time.process_time); batched calls shared equally as policy_time_s is. Null when not the policy's work: remote policies (the server works), GPU policies (the thread waits for kernels), and rows written before it was recorded.",
        )
    )
    starved: bool | None = field(
        metadata=column(
            pa.bool_(),
            "",
            "The policy waited for a core: policy_time_s above 1.25 x policy_cpu_time_s (the machine was busy with other work during this episode's calls), so its timings are not comparable and the run's speed_reliable is false. Null when not judged: no CPU time, or policy_time_s under 0.05 s (too short to judge).",
        )
    )
    env_time_s: float = field(
        metadata=column(pa.float64(), "s", "Time inside the environment (reset and step calls).")
    )
    overhead_s: float = field(
        metadata=column(
            pa.float64(), "s", "wall_clock_s - policy_time_s - env_time_s: the harness's own time."
        )
    )
    wall_clock_s: float = field(
        metadata=column(pa.float64(), "s", "Monotonic time from episode start to end.")
    )
    control_hz: float | None = field(
        metadata=column(
            pa.float64(),
            "Hz",
            "Actions executed / policy_time_s: the control rate the policy alone could sustain.",
        )
    )
    loop_hz: float | None = field(
        metadata=column(pa.float64(), "Hz", "steps / wall_clock_s: the rate of the whole loop.")
    )
    failure_reason: str | None = field(
        metadata=column(
            pa.string(),
            "",
            "Null for a clean episode; otherwise the exception (type: message) that ended it.",
        )
    )
    out_of_space_rule: str | None = field(
        metadata=column(
            pa.string(),
            "",
            "What the run did with actions outside the env's action space (--out-of-space): `fail` (the episode ends, failure_reason `ActionOutOfSpace: ...`), `clip` (clipped to the bounds before the env saw them) or `record` (passed to the env unclipped). Null in rows written before it was recorded.",
        )
    )
    actions_out_of_space: int | None = field(
        metadata=column(
            pa.int64(),
            "actions",
            "Action vectors the policy returned outside the action space (one per env step, however many of its elements are outside), counted over every returned chunk, including actions past --replan-every that were never executed. 0: all inside. Null when not checked (an action space that is not a Box; an episode whose env could not be built or whose worker was lost) and in rows written before it was recorded.",
        )
    )
    max_action_excess: float | None = field(
        metadata=column(
            pa.float64(),
            "action units",
            "The largest distance of any returned action element beyond its bound (0.0 when all were inside); null when actions_out_of_space is.",
        )
    )
    inference_latency: str | None = field(
        metadata=column(
            pa.string(),
            "",
            "The run's --inference-latency mode (docs/latency.md): `none` (the world waits for the policy, the upstream protocols), `passes:MS[+FIXED_MS]`, `profile:NAME` or `measured`. Null in rows written before it was recorded (they ran at `none`).",
        )
    )
    execution: str | None = field(
        metadata=column(
            pa.string(),
            "",
            "--execution under a latency: `sync` (the robot holds still while a chunk decodes) or `async` (it keeps executing the current chunk; the new one's first d actions are skipped). Null in rows written before it was recorded.",
        )
    )
    delay_steps_mean: float | None = field(
        metadata=column(
            pa.float64(),
            "control steps",
            "Mean over the episode's chunks of d = ceil(latency / control period); 0.0 at `none`. Null for an episode without a chunk and in rows written before it was recorded.",
        )
    )
    delay_steps_max: int | None = field(
        metadata=column(
            pa.int64(), "control steps", "The largest d of the episode's chunks; null as delay_steps_mean."
        )
    )
    late_chunks: int | None = field(
        metadata=column(
            pa.int64(),
            "chunks",
            "Chunks that arrived after the robot had held still waiting for them (async: the previous chunk ran out; sync: every chunk with d > 0), the episode's first and the first after an instruction switch not counted. 0 at `none`; null in rows written before it was recorded.",
        )
    )
    hold_steps: int | None = field(
        metadata=column(
            pa.int64(),
            "steps",
            "Env steps spent on the suite's hold action waiting for a chunk (counted in `steps`). 0 at `none`; null in rows written before it was recorded.",
        )
    )
    started_at: datetime = field(metadata=column(_TS, "UTC", "Wall-clock time the episode started."))
    host: str | None = field(
        metadata=column(
            pa.string(),
            "",
            "Host name of the machine the episode ran on (a Ray cluster's rows name their node); speedups pair rows of one host. Null in rows written before it was recorded.",
        )
    )
    worker_id: str | None = field(
        metadata=column(
            pa.string(),
            "",
            "Which worker ran it: `main` (the writing process, --workers 1), `local-K` (the K-th worker process started, replacements included), `ray-K` (the K-th Ray actor). Null in rows written before it was recorded.",
        )
    )
    batch_envs: int | None = field(
        metadata=column(
            pa.int64(),
            "",
            "Environments stepped in lockstep with this episode, one policy call for all of them (--batch-envs K); 1 = unbatched. NFE then counts each batched forward pass once for every episode it served, and policy time is the call's time shared equally among them (see 'Batched inference'); speed figures compare only between rows of one batch size. Null in rows written before it was recorded.",
        )
    )
    speed_reliable: bool | None = field(
        metadata=column(
            pa.bool_(),
            "",
            "False when the run's calibration moved beyond the tolerance between its start and end (the machine's load changed), or when any of the run's episodes was `starved`; the manifest's speed_warning says which and how much: this row's timings (policy_time_s, tokens_per_s, control_hz, ...) are not comparable. Set on every row when the run finishes; null while it runs, after an interrupt, for runs without torch policies (unless starved), and in rows written before it was recorded.",
        )
    )
    video: str | None = field(
        metadata=column(
            pa.string(),
            "path",
            "The episode's rollout video, relative to the run folder (`videos/<policy_config_id>/<task>/episode-NNN.mp4`: by configuration, task and episode), recorded with `--video N` or `--video failures` from the suite's camera (docs/runs.md, 'Rollout videos'). Null when none was recorded or kept. Recording changes no other column but the timings.",
        )
    )
    variant: str | None = field(
        metadata=column(
            pa.string(),
            "",
            "SimplerEnv-like suites: the scene setting the episode ran under, `canonical` (ManiSkill3's canonical scene) or `<axis>=<level>` (one level of one variant axis, e.g. `lighting=dim`; docs/simpler.md). Part of the episode key. Null for suites without variants.",
        )
    )
    chain_id: str | None = field(
        metadata=column(
            pa.string(),
            "",
            "Instruction chains (CALVIN-like suites): `<scene>/<j>`, the j-th stored chain of the scene (docs/chains.md). Null for other suites.",
        )
    )
    subtasks_completed: int | None = field(
        metadata=column(
            pa.int64(),
            "subtasks",
            "Instruction chains: subtasks completed in order before the first failure (0-5), CALVIN's chain length. Null for other suites.",
        )
    )
    subtasks: list[dict[str, Any]] | None = field(
        metadata=column(
            pa.list_(SUBTASK),
            "",
            "Instruction chains: one record per planned subtask, in order: id, instruction, success, steps, start_step and end_step (the chain's steps when it took over and when it ended, settle steps excluded; steps = end_step - start_step), goal_held_at_start (its goal held when it took over, so it was never credited: CALVIN's rule) and outcome (`completed`, `out_of_steps`, `goal_held_at_start`, `in_progress` when the episode ended otherwise, `not_reached`). A subtask never reached: false, 0 and null steps. Rows written before the credit rule have the last four null. A nested column rather than a second table, so one episode stays one appended row. Null for other suites.",
        )
    )


def _nullable(annotation: Any) -> bool:
    return isinstance(annotation, types.UnionType) and type(None) in typing.get_args(annotation)


_HINTS = typing.get_type_hints(EpisodeRow)
COLUMNS: tuple[Column, ...] = tuple(
    Column(f.name, f.metadata["arrow"], f.metadata["unit"], f.metadata["meaning"], _nullable(_HINTS[f.name]))
    for f in fields(EpisodeRow)
)

COLUMN_NAMES = tuple(c.name for c in COLUMNS)

# Columns that say how fast an episode ran, measured on a machine under its load: they differ
# between two runs of the same config, so comparisons of what happened leave them out.
TIMING_COLUMNS = frozenset(
    {
        "policy_time_s",
        "transport_time_s",
        "policy_cpu_time_s",
        "starved",
        "env_time_s",
        "overhead_s",
        "wall_clock_s",
        "control_hz",
        "loop_hz",
        "tokens_per_s",
        "speed_reliable",
    }
)
# Columns that say when and where an episode ran, not what happened in it.
PROVENANCE_COLUMNS = frozenset({"run_id", "started_at", "host", "worker_id"})

# What identifies an episode across runs: resume skips rows with a known key, and
# comparisons pair rows by it.
EPISODE_KEY = (
    "suite",
    "task",
    "episode_index",
    "seed",
    "init_state_id",
    "variant",
    "policy",
    "policy_params",
    "checkpoint_sha256",
)


def row_dict(row: EpisodeRow) -> dict[str, Any]:
    """A row as a mapping in column order (what pending.jsonl holds, one line each)."""
    return {name: getattr(row, name) for name in COLUMN_NAMES}


def arrow_schema() -> pa.Schema:
    fields = [pa.field(c.name, c.type, nullable=c.nullable) for c in COLUMNS]
    return pa.schema(fields, metadata={SCHEMA_VERSION_KEY: SCHEMA_VERSION.encode()})


def markdown_table() -> str:
    """The column reference in docs/results-schema.md."""
    lines = ["| column | type | unit | meaning |", "|---|---|---|---|"]
    for c in COLUMNS:
        kind = str(c.type) + (" (nullable)" if c.nullable else "")
        lines.append(f"| `{c.name}` | {kind} | {c.unit} | {c.meaning} |")
    return "\n".join(lines)
