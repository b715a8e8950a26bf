"""The replay benchmark behind `dvla-harness bench`: record observations, then time every
configuration of a run decoding them, round after round.

Recording: the reference decoder (bidirectional by default) plays the first episode of
each task of the run again, the same episode spec (seed, layout) the run played, and
every observation it is asked to decode is kept with the context in force; K of them per
task, evenly spaced over the episode, go to RUN_DIR/replay_observations.npz (arrays only,
no pickle). Recording from the reference's episodes, not each policy's own, gives every
configuration the same observations, and a candidate whose decoder changed still decodes
exactly what the baseline decoded (`--observations BASELINE_DIR` reuses the file itself).

Timing, as pyperf and asv time code: a warm-up pass per configuration (every observation
once, outside the figures, its forward passes and tokens counted), then R rounds; in each
round every configuration decodes every observation once (reset untimed, act timed),
interleaved as finely as it goes: observation by observation, every configuration in
turn, starting from a different one each time, so a load that comes and goes within a
round still hits all configurations alike (a round of whole configurations one after
another paired poorly on a shared machine: ratios 0.49-0.78 where interleaving per
observation keeps them close). A round's figure is its mean seconds per chunk. Garbage collection is held off inside a round (pyperf's advice for short timings).
"""

from __future__ import annotations

import gc
import hashlib
import io
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from harness.config import PolicyRun, ResolvedRun
from harness.episode.nfe import NFECounter
from harness.errors import UsageError
from policies.base import EpisodeContext

# What a recorded observation's context keeps (the spaces come from the task's env).
CONTEXT_FIELDS = (
    "task",
    "instruction",
    "max_steps",
    "episode_index",
    "seed",
    "init_state_id",
    "subtask_index",
)


@dataclass
class Recorded:
    """Observations to decode, each with the context (JSON-able fields) it was decoded in."""

    suite: str
    contexts: list[dict[str, Any]]
    observations: list[Any]  # np.ndarray or dict of np.ndarray, as the env gave them

    def digest(self) -> str:
        """SHA-256 of the observations and contexts: two runs decoded the same set iff equal."""
        h = hashlib.sha256(json.dumps([self.suite, self.contexts], sort_keys=True).encode())
        for obs in self.observations:
            parts = sorted(obs.items()) if isinstance(obs, dict) else [("", obs)]
            for key, value in parts:
                array = np.ascontiguousarray(value)
                h.update(f"{key}|{array.dtype}|{array.shape}".encode())
                h.update(array.tobytes())
        return h.hexdigest()


class _Recorder:
    """Stands in for a policy during one episode and keeps what it is asked to decode."""

    def __init__(self, policy: Any):
        self.policy = policy
        self.context: EpisodeContext | None = None
        self.seen: list[tuple[EpisodeContext, Any]] = []

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        self.context = episodes[0]
        self.policy.reset(episodes)

    def act(self, observations: Sequence[Any]) -> Any:
        self.seen.append((self.context, fresh(observations[0])))
        return self.policy.act(observations)


def fresh(obs: Any) -> Any:
    """A copy of an observation. Every decode gets its own: a policy may write into the
    arrays it is handed (the Meta-World scripted expert does), and the next configuration
    must decode what was recorded."""
    if isinstance(obs, dict):
        return {k: np.array(v, copy=True) for k, v in obs.items()}
    return np.array(obs, copy=True)


def _context_fields(context: EpisodeContext) -> dict[str, Any]:
    return {name: getattr(context, name) for name in CONTEXT_FIELDS}


def evenly_spaced(n: int, k: int) -> list[int]:
    """k indices of 0..n-1 spread over the whole range (all of them when n <= k)."""
    if n <= k:
        return list(range(n))
    return sorted(set(np.rint(np.linspace(0, n - 1, k)).astype(int).tolist()))


def record_observations(resolved: ResolvedRun, source: PolicyRun, per_task: int) -> Recorded:
    """Play each task's first episode with `source` and keep `per_task` of its observations."""
    from harness.episode.context import episode_context
    from harness.episode.loop import run_episode
    from harness.episode.plan import ExecutionPlan

    contexts: list[dict[str, Any]] = []
    observations: list[Any] = []
    for task in resolved.tasks:
        specs = resolved.episodes(task)
        if not specs:
            continue
        env = resolved.suite.make_env(task)
        try:
            recorder = _Recorder(source.policy)
            context = episode_context(resolved.suite.name, task, specs[0], env)
            plan = ExecutionPlan(resolved.config.replan_every)
            outcome = run_episode(env, recorder, context, specs[0], plan)
        finally:
            env.close()
        if outcome.failure_reason:
            raise UsageError(
                f"recording: {source.spec.name} raised on {task.name} episode {specs[0].index}: "
                f"{outcome.failure_reason}"
            )
        for i in evenly_spaced(len(recorder.seen), per_task):
            ctx, obs = recorder.seen[i]
            contexts.append(_context_fields(ctx))
            observations.append(obs)
    return Recorded(resolved.suite.name, contexts, observations)


# ---- the .npz file ----------------------------------------------------------------------


def observations_bytes(recorded: Recorded) -> bytes:
    """The .npz file's contents: one array per observation (or per key of a dict
    observation), the suite and contexts as a JSON string; no object arrays."""
    arrays: dict[str, np.ndarray] = {
        "meta": np.array(json.dumps({"suite": recorded.suite, "contexts": recorded.contexts}))
    }
    for i, obs in enumerate(recorded.observations):
        if isinstance(obs, dict):
            for key, value in obs.items():
                arrays[f"o{i:05d}__{key}"] = np.asarray(value)
        else:
            arrays[f"o{i:05d}"] = np.asarray(obs)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def load_observations(path: Path) -> Recorded:
    """A replay_observations.npz, checked; UsageError naming what is wrong."""
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"]))
            arrays = {name: data[name] for name in data.files if name != "meta"}
    except (OSError, ValueError, KeyError, json.JSONDecodeError) as exc:
        raise UsageError(f"{path}: not a recorded-observations file ({type(exc).__name__}: {exc})") from None
    contexts = meta.get("contexts") if isinstance(meta, dict) else None
    if not isinstance(contexts, list) or not contexts or not isinstance(meta.get("suite"), str):
        raise UsageError(f"{path}: no recorded observations (its meta names no suite or contexts)")
    observations: list[Any] = []
    for i, ctx in enumerate(contexts):
        if not isinstance(ctx, dict) or set(CONTEXT_FIELDS) - set(ctx):
            raise UsageError(f"{path}: context {i} lacks {sorted(set(CONTEXT_FIELDS) - set(ctx or {}))}")
        bare = arrays.get(f"o{i:05d}")
        keyed = {n.split("__", 1)[1]: a for n, a in arrays.items() if n.startswith(f"o{i:05d}__")}
        if bare is None and not keyed:
            raise UsageError(f"{path}: observation {i} is missing")
        observations.append(bare if bare is not None else keyed)
    return Recorded(meta["suite"], contexts, observations)


def episode_contexts(resolved: ResolvedRun, recorded: Recorded) -> list[EpisodeContext]:
    """The recorded contexts with the spaces of their task's env (built once per task)."""
    if recorded.suite != resolved.suite.name:
        raise UsageError(
            f"the recorded observations are of suite {recorded.suite!r}; this run is {resolved.suite.name!r}"
        )
    spaces: dict[str, tuple[Any, Any]] = {}
    out = []
    for ctx in recorded.contexts:
        name = ctx["task"]
        if name not in spaces:
            try:
                task = resolved.suite.task(name)
            except KeyError:
                raise UsageError(
                    f"the recorded observations name task {name!r}, which the suite lacks"
                ) from None
            env = resolved.suite.make_env(task)
            spaces[name] = (env.action_space, env.observation_space)
            env.close()
        action_space, observation_space = spaces[name]
        out.append(
            EpisodeContext(
                suite=recorded.suite,
                action_space=action_space,
                observation_space=observation_space,
                **{k: ctx[k] for k in CONTEXT_FIELDS},
            )
        )
    return out


def portable_params(p: Any) -> dict[str, Any]:
    """The configuration's parameters with a shipped checkpoint by its set name: a bench of
    a committed baseline then records no folder of the machine it ran on (the figures pair
    by policy_config_id, so nothing reads this path back)."""
    from policies.registry import portable_checkpoint

    params = json.loads(p.params_json)
    if isinstance(params.get("checkpoint"), str):
        params["checkpoint"] = portable_checkpoint(p.spec, params["checkpoint"])
    return params


def stopping_rule(
    baseline: dict[str, Any] | None,
    timed: Sequence[PolicyRun],
    reference: str,
    limits: tuple[float, int, int],
) -> Any:
    """The sequential rule (results/replay_stop.py) against the baseline bench (its
    replay.json), with `limits` = (max_slowdown, min_rounds, cap), or None
    (all `cap` rounds) when there is nothing to judge against: no baseline bench, another
    torch thread count, no reference on both sides, no configuration paired."""
    from harness.threads import threads_record
    from results.replay_stop import JudgedPair, StoppingRule

    max_slowdown, min_rounds, cap = limits
    if baseline is None or baseline.get("torch_threads") != threads_record().get("torch_intra_op"):
        return None
    configs = baseline["configurations"]
    mine = [p for p in timed if reference in (p.spec.name, p.config_id)]
    theirs = [c for c in configs if reference in (c["policy"], c["policy_config_id"])]
    if len(mine) != 1 or len(theirs) != 1:
        return None
    pairs = []
    for p in timed:
        same = [c for c in configs if c["policy"] == p.spec.name and c is not theirs[0]]
        exact = [c for c in same if c.get("policy_params") == portable_params(p)]
        found = exact if len(exact) == 1 else same if len(same) == 1 else []
        if p is not mine[0] and found:
            pairs.append(JudgedPair(p.spec.name, p.config_id, found[0]["policy_config_id"]))
    if not pairs:
        return None
    return StoppingRule(
        {c["policy_config_id"]: c["round_chunk_s"] for c in configs},
        tuple(pairs),
        JudgedPair(mine[0].spec.name, mine[0].config_id, theirs[0]["policy_config_id"]),
        max_slowdown,
        min_rounds,
        cap,
    )


# ---- timing -----------------------------------------------------------------------------


@dataclass
class Decodes:
    """What a configuration's warm-up pass over the observations found."""

    action_tokens: int
    nfe: int | None
    error: str | None = None
    # FLOPs of every torch product, counted at the dispatcher (harness/episode/op_work.py),
    # and of the counted modules' products, by the NFE counter's hooks (None: not measured)
    flops: int | None = None
    module_flops: int | None = None


def warm_up_pass(policy: Any, contexts: Sequence[EpisodeContext], observations: Sequence[Any]) -> Decodes:
    """Every observation decoded once, untimed; tokens, forward passes and work counted.

    The work is counted twice: at the dispatcher, which sees every torch product wherever
    the policy's code calls it (the figure the gate compares), and by the module hooks
    that count the episodes' work, so the bench shows when the two part."""
    from harness.episode.op_work import op_flops

    counter = NFECounter()
    tokens, flops, ops = 0, 0, 0
    try:
        for context, obs in zip(contexts, observations, strict=True):
            policy.reset([context])
            mine = fresh(obs)
            with counter.counting(), op_flops() as counted:
                tokens += int(policy.act([mine]).action_tokens)
            flops, ops = flops + counted.flops, ops + counted.ops
    except Exception as exc:  # this configuration is left out of the timing, with the reason
        return Decodes(0, None, f"{type(exc).__name__}: {exc}")
    finally:
        passes = counter.take()
        module_flops = counter.take_work().flops
        counter.close()
    # no torch op at all: the decoder's work is not torch's (a remote server's), not measured
    return Decodes(tokens, passes, flops=flops if ops else None, module_flops=module_flops if ops else None)


@dataclass
class Rounds:
    """Each configuration's mean seconds per chunk in each round (by policy_config_id):
    wall-clock, and the CPU time of the same calls (harness/episode/cpu_time.py's clock;
    None for a configuration whose CPU time is not its work, a GPU policy)."""

    wall: dict[str, list[float]]
    cpu: dict[str, list[float] | None]


def time_rounds(
    policies: Sequence[PolicyRun],
    contexts: Sequence[EpisodeContext],
    observations: Sequence[Any],
    rounds: int,
    tick: Callable[[], None] | None = None,
    stop: Callable[[dict[str, list[float]]], bool] | None = None,
) -> Rounds:
    """`rounds` rounds, or fewer when `stop`, asked after each round with the wall-clock
    figures so far, says the verdict is settled (results/replay_stop.py)."""
    from harness.episode.cpu_time import cpu_clock

    clock = time.perf_counter
    cpu = {p.config_id: cpu_clock(p.policy) for p in policies}
    out = Rounds({p.config_id: [] for p in policies}, {p.config_id: [] for p in policies})
    pairs = list(zip(contexts, observations, strict=True))
    n = len(policies)
    for r in range(rounds):
        spent = dict.fromkeys(out.wall, 0.0)
        used = dict.fromkeys(out.wall, 0.0)
        gc.collect()
        gc.disable()
        try:
            for j, (context, obs) in enumerate(pairs):
                shift = (r + j) % n
                for p in [*policies[shift:], *policies[:shift]]:
                    p.policy.reset([context])
                    mine = fresh(obs)
                    cpu_clock_of = cpu[p.config_id] or clock
                    start, start_cpu = clock(), cpu_clock_of()
                    p.policy.act([mine])
                    spent[p.config_id] += clock() - start
                    used[p.config_id] += cpu_clock_of() - start_cpu
        finally:
            gc.enable()
        for config_id, seconds in spent.items():
            out.wall[config_id].append(seconds / len(pairs))
            out.cpu[config_id].append(used[config_id] / len(pairs))
        if tick:
            tick()
        if stop is not None and stop(out.wall):
            break
    for config_id, clock_of in cpu.items():
        if clock_of is None:
            out.cpu[config_id] = None
    return out
