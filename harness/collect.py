"""Demonstrations: run a policy through the ordinary episode loop, keep the successes.

On an instruction-chain suite the unit of success is the subtask: every chain keeps the
steps of the subtasks it completed, up to its first failure, each under its own
instruction. CALVIN trains on instruction-labelled segments too, and keeping only 5/5
chains would throw away most of what an expert that completes half its chains shows.

Recording is a Gymnasium wrapper around the suite's env, so collection uses exactly
the loop, seeds and success test that evaluation uses. The output folder is written
once, at the end, atomically (docs/demonstrations.md describes the format):

    DEMOS/steps.parquet   one row per executed step of a successful episode
    DEMOS/manifest.json   suite, split, policy, counts per task, shapes, data hash

`action_noise` > 0 collects DART-style: the env executes the demonstrator's action plus
Gaussian noise (every dimension but the last, the gripper), while the recorded action
stays the demonstrator's own. A closed-loop expert then shows how it gets back from the
states a learned policy drifts into; clean demonstrations only cover the path it takes.

Camera images (suites asked for them, e.g. `libero/spatial:obs=images`) are kept as one
PNG per camera and step in `image_<camera>` columns: lossless, and ~10x smaller than
raw pixels, which decides whether 50 demonstrations per task fit in memory.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from adapters.base import EpisodeSpec, TaskSpec
from adapters.libero_states import InitialStateOverlap
from harness.collect_pool import Job, collect_in_processes
from harness.config import ResolvedRun
from harness.episode.context import episode_context
from harness.episode.loop import run_episode
from harness.episode.outcome import EpisodeOutcome
from harness.episode.plan import ExecutionPlan
from harness.episode.timed import TimedPolicy
from harness.errors import UsageError
from harness.run.manifest import environment, now
from policies.observations import cameras_of, png, unpng

STEPS = "steps.parquet"
MANIFEST = "manifest.json"
DEMO_COLUMNS = pa.schema(
    [
        ("episode_id", pa.int64()),
        ("task", pa.string()),
        ("instruction", pa.string()),
        ("episode_index", pa.int64()),
        ("seed", pa.int64()),
        ("init_state_id", pa.int64()),
        ("step", pa.int64()),
        ("observation", pa.list_(pa.float32())),
        ("action", pa.list_(pa.float32())),
    ]
)


# Per episode, for suites that draw fresh initial states (LIBERO's train split): the
# sha256 of the flattened initial simulator state and its distance (m) to the nearest
# evaluation state (adapters/libero_states.py). Columns only where the env reports them,
# so other suites' folders stay byte for byte what they were.
START_COLUMNS = {"initial_state_sha256": pa.string(), "initial_state_distance": pa.float64()}


class RecordingEnv(gym.Wrapper):
    """Keeps (observation, action) pairs of the current episode; camera images as PNG."""

    def __init__(self, env: gym.Env):
        super().__init__(env)
        self.cameras = cameras_of(env.observation_space)
        self.observations: list[np.ndarray] = []
        self.images: list[list[bytes]] = []  # per step, one PNG per camera
        self.actions: list[np.ndarray] = []
        # Per step, the instruction in force when its observation was taken: an
        # instruction chain's env says which (info["instruction"]); None for other envs.
        self.instructions: list[str | None] = []
        self._instruction: str | None = None
        self._last: Any = None
        self.start: dict[str, Any] = {}  # the fresh initial state's hash and distance, if any
        self.refused: InitialStateOverlap | None = None

    def reset(self, **kwargs):
        self.start, self.refused = {}, None
        try:
            obs, info = self.env.reset(**kwargs)
        except InitialStateOverlap as exc:  # run_episode would make it one failed episode
            self.refused = exc
            raise
        self.start = {k: info[k] for k in START_COLUMNS if k in info}
        self.observations, self.images, self.actions, self._last = [], [], [], obs
        self.instructions, self._instruction = [], info.get("instruction")
        return obs, info

    def step(self, action):
        last = self._last
        if isinstance(last, Mapping):
            self.images.append([png(last[cam]) for cam in self.cameras])
            last = last["state"]
        self.observations.append(np.asarray(last, dtype=np.float32))
        executed = np.asarray(action, dtype=np.float32)
        space = self.env.action_space
        if isinstance(space, gym.spaces.Box):
            # What the env executes: Meta-World's experts emit up to ~10 where the env
            # clips to [-1, 1], and tokenizer bins fitted on unclipped values would
            # spend most of their range on actions that never happen.
            executed = np.clip(executed, space.low, space.high)
        self.actions.append(executed)
        self.instructions.append(self._instruction)
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._last = obs
        self._instruction = info.get("instruction", self._instruction)
        return obs, reward, terminated, truncated, info


class NoisyActions(gym.Wrapper):
    """Adds Gaussian noise (std `sigma` times the action range's half-width) to every
    action dimension but the last before the env executes it, clipped to the action
    space. Seeded per episode from the task and the episode's index, so a collection is
    reproducible; the gripper is left alone because noise on it flips grasps."""

    def __init__(self, env: gym.Env, sigma: float, task: str):
        super().__init__(env)
        space = env.action_space
        if not isinstance(space, gym.spaces.Box):
            raise UsageError("--action-noise needs continuous (Box) actions")
        self.task = zlib.crc32(task.encode())
        self.scale = sigma * (space.high - space.low) / 2
        self.scale[-1] = 0.0
        self.rng = np.random.default_rng()

    def reset(self, **kwargs):
        spec = (kwargs.get("options") or {}).get("episode")
        index = getattr(spec, "index", 0)
        self.rng = np.random.default_rng([self.task, index, kwargs.get("seed") or 0])
        return self.env.reset(**kwargs)

    def step(self, action):
        space = self.env.action_space
        noisy = np.asarray(action, dtype=np.float64) + self.rng.normal(size=space.shape) * self.scale
        return self.env.step(np.clip(noisy, space.low, space.high).astype(space.dtype))


@dataclass
class CollectReport:
    attempted: dict[str, int] = field(default_factory=dict)
    kept: dict[str, int] = field(default_factory=dict)  # chains: those with a completed subtask
    steps: int = 0
    # Instruction chains only, per task: subtasks completed over all chains (what was kept).
    subtasks_kept: dict[str, int] = field(default_factory=dict)
    # Per task, fresh initial states only: how many were drawn, and the smallest distance
    # (m, largest object displacement) of any of them to an evaluation state.
    fresh_states: dict[str, int] = field(default_factory=dict)
    closest_to_evaluation: dict[str, float] = field(default_factory=dict)
    # Per task, where the env's state vector holds world positions (adapters/base.py);
    # training reads them for --state-features relative.
    state_positions: dict[str, list[int]] = field(default_factory=dict)
    proprio_dims: dict[str, int] = field(default_factory=dict)


def check_demos_out(out: Path, overwrite: bool) -> None:
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise UsageError(
                f"output folder {str(out)!r} exists and is not empty; pass --overwrite to replace it"
            )
        if not (out / MANIFEST).is_file():
            raise UsageError(
                f"--overwrite: {str(out)!r} is not a demonstrations folder; refusing to delete it"
            )


def collect(
    resolved: ResolvedRun,
    out: Path,
    overwrite: bool = False,
    tick: Callable[[bool], None] | None = None,
    action_noise: float = 0.0,
    workers: int = 1,
) -> CollectReport:
    """Collect, on `workers` processes: the folder is byte for byte the one a single
    process writes (episodes are merged in the suite's order; noise is seeded per episode)."""
    check_demos_out(out, overwrite)
    if not 0.0 <= action_noise <= 1.0:
        raise UsageError(
            f"--action-noise must be in [0, 1] (a fraction of the action range), got {action_noise}"
        )
    if workers < 1:
        raise UsageError(f"--workers must be at least 1, got {workers}")
    jobs = _jobs(resolved, workers)
    if workers == 1:
        done = [_collect_job(resolved, job, action_noise, tick) for job in jobs]
    else:
        done = collect_in_processes(_collect_job, resolved, jobs, action_noise, tick, workers)
    return _merge_and_write(resolved, out, done, action_noise)


@dataclass
class EpisodeDemo:
    """One attempted episode, as the process that ran it hands it back."""

    task: str
    success: bool
    subtasks_completed: int | None
    start: dict[str, Any]
    rows: dict[str, list[Any]]  # the kept steps' columns, episode_id left to the merge


@dataclass
class JobResult:
    task: str
    cameras: list[str]
    state_positions: list[int]
    proprio_dim: int
    episodes: list[EpisodeDemo]


def _jobs(resolved: ResolvedRun, workers: int) -> list[Job]:
    """Episode ranges in the suite's order: each task whole on one process, or cut into
    about 4 ranges per worker (a chain scene is one task of 100 chains), so progress
    moves and a slow range does not hold the others back. Every range builds its env once."""
    jobs: list[Job] = []
    for i, task in enumerate(resolved.tasks):
        n = len(resolved.episodes(task))
        size = n if workers == 1 else max(1, -(-n // (4 * workers)))
        jobs += [(i, a, min(n, a + size)) for a in range(0, n, size)]
    return jobs


def _collect_job(
    resolved: ResolvedRun, job: Job, action_noise: float, tick: Callable[[bool], None] | None
) -> JobResult:
    """Run one range of a task's episodes on one env, keeping what each episode shows."""
    task_index, first, end = job
    task = resolved.tasks[task_index]
    policy_run = resolved.policies[0]
    policy = TimedPolicy(policy_run.policy, policy_run.spec.name)
    plan = ExecutionPlan(resolved.config.replan_every, resolved.config.out_of_space)
    env = resolved.suite.make_env(task)
    try:  # closed whatever happens, a refused --action-noise included
        if action_noise > 0:
            env = NoisyActions(env, action_noise, task.name)
        env = RecordingEnv(env)
        result = JobResult(task.name, env.cameras, _state_positions(env), _proprio_dim(env), [])
        for spec in resolved.episodes(task)[first:end]:
            context = episode_context(resolved.suite.name, task, spec, env)
            outcome = run_episode(env, policy, context, spec, plan)
            if env.refused is not None:
                raise UsageError(f"{task.name}: {env.refused}; nothing was written")
            rows: dict[str, list[Any]] = {}
            keep = _kept_steps(outcome, env)
            if keep:
                _episode_rows(rows, env, task, spec, result.cameras, keep)
            demo = EpisodeDemo(task.name, outcome.success, outcome.subtasks_completed, dict(env.start), rows)
            result.episodes.append(demo)
            if tick:
                tick(outcome.success)
        return result
    finally:
        env.close()
        policy.close_counter()


def _merge_and_write(
    resolved: ResolvedRun, out: Path, done: list[JobResult], action_noise: float
) -> CollectReport:
    """Every job's episodes in the suite's order, numbered and written once."""
    report = CollectReport()
    rows: dict[str, list[Any]] = {name: [] for name in DEMO_COLUMNS.names}
    cameras: list[str] | None = None
    episode_id = 0
    for result in done:
        if cameras is None:
            cameras = result.cameras
            rows.update({f"image_{cam}": [] for cam in cameras})
        task = result.task
        report.attempted.setdefault(task, 0)
        report.kept.setdefault(task, 0)
        if result.state_positions:
            report.state_positions[task] = result.state_positions
        if result.proprio_dim:
            report.proprio_dims[task] = result.proprio_dim
        for demo in result.episodes:
            _note_start(report, task, demo.start)
            report.attempted[task] += 1
            if demo.rows:
                keep = len(demo.rows["step"])
                report.kept[task] += 1
                report.steps += keep
                rows["episode_id"] += [episode_id] * keep
                for name, values in demo.rows.items():
                    rows.setdefault(name, []).extend(values)
                episode_id += 1
            if demo.subtasks_completed is not None:
                report.subtasks_kept[task] = report.subtasks_kept.get(task, 0) + demo.subtasks_completed
    if episode_id == 0:
        raise UsageError("no episode succeeded, so there is nothing to save; nothing was written")
    schema = DEMO_COLUMNS
    if report.fresh_states:
        for name, kind in START_COLUMNS.items():
            schema = schema.append(pa.field(name, kind))
    for cam in cameras or []:
        schema = schema.append(pa.field(f"image_{cam}", pa.binary()))
    _write(resolved, out, pa.table(rows, schema=schema), report, cameras or [], action_noise)
    return report


def _kept_steps(outcome: EpisodeOutcome, env: RecordingEnv) -> int:
    """How many of the episode's recorded steps to keep: all of a success; of a chain,
    those of the subtasks it completed (their records count each one's steps); else 0."""
    if outcome.subtasks_completed is None or not outcome.subtasks:
        return len(env.actions) if outcome.success else 0
    done = outcome.subtasks[: outcome.subtasks_completed]
    keep = sum(int(r["steps"]) for r in done)
    # The records and the recording must agree, or steps would go under the wrong instruction.
    labels = env.instructions[:keep]
    expected = [r["instruction"] for r in done for _ in range(int(r["steps"]))]
    if keep > len(env.actions) or labels != expected:
        raise RuntimeError(
            f"chain {outcome.subtasks_completed} subtasks: the recorded steps do not line up "
            "with the env's subtask records; nothing was written"
        )
    return keep


def _note_start(report: CollectReport, task: str, start: Mapping[str, Any]) -> None:
    if "initial_state_distance" not in start:
        return
    report.fresh_states[task] = report.fresh_states.get(task, 0) + 1
    distance = float(start["initial_state_distance"])
    report.closest_to_evaluation[task] = min(report.closest_to_evaluation.get(task, distance), distance)


def _state_positions(env: gym.Env) -> list[int]:
    try:
        return [int(p) for p in env.get_wrapper_attr("state_positions")]
    except AttributeError:
        return []


def _proprio_dim(env: gym.Env) -> int:
    try:
        return int(env.get_wrapper_attr("proprio_dim"))
    except AttributeError:
        return 0


def _episode_rows(
    rows: dict[str, list[Any]],
    env: RecordingEnv,
    task: TaskSpec,
    spec: EpisodeSpec,
    cameras: list[str],
    keep: int,
) -> None:
    """The first `keep` steps of an episode as columns (all but episode_id, which the
    merge numbers in the suite's order)."""
    steps = zip(env.observations[:keep], env.actions[:keep], env.instructions[:keep], strict=True)
    for step, (obs, action, instruction) in enumerate(steps):
        for name, value in (
            ("task", task.name),
            ("instruction", instruction or task.instruction),
            ("episode_index", spec.index),
            ("seed", spec.seed),
            ("init_state_id", spec.init_state_id),
            ("step", step),
            ("observation", obs.tolist()),
            ("action", action.tolist()),
        ):
            rows.setdefault(name, []).append(value)
    for name in START_COLUMNS:
        if name in env.start:
            rows.setdefault(name, []).extend([env.start[name]] * keep)
    for frames in env.images[:keep]:
        for cam, data in zip(cameras, frames, strict=True):
            rows.setdefault(f"image_{cam}", []).append(data)


def _write(
    resolved: ResolvedRun,
    out: Path,
    table: pa.Table,
    report: CollectReport,
    cameras: list[str],
    action_noise: float,
) -> None:
    staging = out.with_name(out.name + ".tmp")
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    try:
        _write_staged(resolved, staging, table, report, cameras, action_noise)
    except BaseException:  # a full disk, Ctrl-C: no half folder left beside the output
        shutil.rmtree(staging, ignore_errors=True)
        raise
    if out.exists():
        shutil.rmtree(out)
    staging.rename(out)


def _write_staged(
    resolved: ResolvedRun,
    staging: Path,
    table: pa.Table,
    report: CollectReport,
    cameras: list[str],
    action_noise: float,
) -> None:
    pq.write_table(table, staging / STEPS)
    digest = hashlib.sha256((staging / STEPS).read_bytes()).hexdigest()
    p = resolved.policies[0]
    manifest = {
        "format": "dvla-harness-demos/2",
        "suite": resolved.suite.name,
        "suite_version": resolved.suite.version,
        "split": resolved.config.split,
        "policy": p.spec.name,
        "policy_params": json.loads(p.params_json),
        "action_noise": action_noise,
        "episodes_attempted": report.attempted,
        "episodes_kept": report.kept,
        "steps": report.steps,
        # Instruction chains: episodes_kept counts chains with a completed subtask, and
        # only completed subtasks' steps were kept (module docstring).
        **({"subtasks_kept": report.subtasks_kept} if report.subtasks_kept else {}),
        "observation_dim": len(table["observation"][0]),
        "action_dim": len(table["action"][0]),
        "state_positions": report.state_positions,
        "proprio_dims": report.proprio_dims,
        # Fresh initial states (LIBERO's train split): per task, how many were drawn and
        # the closest any came to an evaluation state; none equals one (checked by hash).
        "initial_states": {
            task: {
                "fresh": n,
                "evaluation_overlap": 0,
                "closest_to_evaluation_m": report.closest_to_evaluation[task],
            }
            for task, n in report.fresh_states.items()
        },
        "cameras": cameras,
        "image_size": unpng(table[f"image_{cameras[0]}"][0].as_py()).shape[0] if cameras else 0,
        "steps_sha256": digest,
        "created_at": now(),
        "environment": environment(),
    }
    from results.store import strict_json

    (staging / MANIFEST).write_text(json.dumps(strict_json(manifest), indent=2, allow_nan=False) + "\n")
