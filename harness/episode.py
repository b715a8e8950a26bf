"""The episode loop: reset, ask for a chunk, execute it, stop on success or budget.

Every env and policy call is timed with one monotonic clock; the overhead column is
the episode's wall-clock minus both, so the three add up by construction and the
overhead is exactly the loop's own bookkeeping. Policy calls are also timed with a CPU
clock, which tells the policy's work from its wait for a core (harness/cpu_time.py).
NFE is counted by the harness's hooks, which are on only inside `policy.reset` and
`policy.act` (`nfe.counting()`).
A Python exception from the env or the policy ends the episode with a failure reason;
it never ends the run: a policy's SystemExit or other BaseException is that episode's
failure row too, and so is a non-finite or absurd action, and (under the default
`--out-of-space fail`) an action outside the action space (harness/action_space.py says
what the other rules do). Only KeyboardInterrupt (Ctrl-C, SIGTERM) stops the run. With `record_traces`, each chunk's decode trace (what the policy
returned in ChunkBatch.trace) is kept in memory and written by the runner after the
episode, so recording costs the loop one list append per chunk.
Instruction chains: when the env reports a new instruction in force, the rest of the
chunk is dropped and the policy is reset with it (policies/base.py, "Instruction chains").
"""

from __future__ import annotations

import dataclasses
import time
import traceback
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import gymnasium as gym
import numpy as np

from adapters.base import EpisodeSpec
from harness.action_space import DEFAULT_OUT_OF_SPACE, ActionCheck
from harness.cpu_time import cpu_clock
from harness.delayed import Tally, run_delayed
from harness.latency import LatencyPlan
from harness.nfe import NFECounter
from harness.work import Work
from policies.base import EpisodeContext, Policy


@dataclass
class EpisodeOutcome:
    success: bool
    steps: int
    chunks: int
    nfe_total: int | None  # None: a remote server that does not report its passes
    action_tokens_total: int
    policy_time_s: float
    env_time_s: float
    wall_clock_s: float
    started_at: datetime
    failure_reason: str | None = None
    traceback: str | None = None
    # With record_traces: per chunk, slot 0's trace plus "chunk" and "step" (env steps before it).
    traces: list[dict[str, Any]] | None = None
    # Where it ran (the `host` and `worker_id` columns), set by the backend that ran it.
    host: str = ""
    worker_id: str = ""
    # Environments stepped in lockstep with it, one policy call for them all (--batch-envs;
    # the `batch_envs` column). 1: unbatched (run_episode).
    batch_envs: int = 1
    # Instruction chains: the env's last `subtasks` records and `subtasks_completed`.
    subtasks: list[dict[str, Any]] | None = None
    subtasks_completed: int | None = None
    # Remote policies: the part of policy_time_s that was not the server's own policy time.
    transport_time_s: float | None = None
    # Action vectors outside the action space and the largest excess (harness/action_space.py);
    # None: not checked (not a Box, or the episode never reached its env).
    actions_out_of_space: int | None = None
    max_action_excess: float | None = None
    # Counted work of its passes (harness/work.py); a None field: not measured.
    work: Work = dataclasses.field(default_factory=Work)
    # Inference latency (harness/delayed.py): per chunk's delay in control steps, chunks that
    # came after the robot had run out of actions, steps spent holding still. At `none`:
    # every delay 0 (null without a chunk).
    delay_steps_mean: float | None = None
    delay_steps_max: int | None = None
    late_chunks: int = 0
    hold_steps: int = 0
    # CPU time over the same policy calls (harness/cpu_time.py); None: not measured
    # (remote policies, GPU policies).
    policy_cpu_time_s: float | None = None


def remote_policy(policy: Any) -> Any:
    """The policy if it is the built-in `remote` one (policies/remote.py), else None. By
    class identity, not duck typing: only that client may hand the runner a server's
    count of forward passes."""
    cls = type(policy)
    return policy if (cls.__module__, cls.__name__) == ("policies.remote", "RemotePolicy") else None


def in_force(context: EpisodeContext, info: dict[str, Any]) -> EpisodeContext:
    """The context with the instruction the env says is in force (chains); `context`
    itself when nothing changed, so `is` tells the caller whether to reset the policy."""
    instruction = info.get("instruction")
    if instruction is None:  # not a chain: one dict lookup a step
        return context
    k = int(info.get("subtask_index", context.subtask_index))
    if instruction == context.instruction and k == context.subtask_index:
        return context
    return dataclasses.replace(context, instruction=str(instruction), subtask_index=k)


def chain_fields(info: dict[str, Any]) -> dict[str, Any]:
    """What an outcome keeps of a chain env's last info (nothing for other envs)."""
    if "subtasks" not in info:
        return {}
    records = [dict(r) for r in info["subtasks"]]  # a copy: the env's records are live
    return {"subtasks": records, "subtasks_completed": int(info["subtasks_completed"])}


# Beyond any action space a simulator clips to: a policy's arithmetic went wrong, and the
# episode's outcome would say nothing about the policy (an env clips it to a corner).
ABSURD_ACTION = 1e6


def check_chunk(actions: np.ndarray, action_dim: int) -> None:
    if actions.ndim != 3 or actions.shape[0] != 1 or actions.shape[1] < 1:
        raise ValueError(
            f"policy returned actions of shape {actions.shape}; expected (1, chunk>=1, {action_dim})"
        )
    if actions.shape[2] != action_dim:
        raise ValueError(f"policy returned {actions.shape[2]}-D actions; the action space is {action_dim}-D")
    if not np.isfinite(actions).all():
        raise ValueError("policy returned a non-finite action (NaN or infinity)")
    if np.abs(actions).max() > ABSURD_ACTION:
        raise ValueError(f"policy returned an absurd action ({np.abs(actions).max():.3g} in magnitude)")


def run_episode(
    env: gym.Env,
    policy: Policy,
    nfe: NFECounter,
    context: EpisodeContext,
    spec: EpisodeSpec,
    replan_every: int = 0,
    record_traces: bool = False,
    out_of_space: str = DEFAULT_OUT_OF_SPACE,
    latency: LatencyPlan | None = None,
) -> EpisodeOutcome:
    clock = time.perf_counter
    cpu_now = None if remote_policy(policy) is not None else cpu_clock(policy)
    cpu = cpu_now or (lambda: 0.0)  # unmeasured: read as 0 and recorded as None
    started_at = datetime.now(UTC)
    action_dim = int(np.prod(context.action_space.shape))
    success = False
    steps = chunks = tokens = 0
    policy_time = env_time = cpu_time = 0.0
    failure = trace = None
    traces: list[dict[str, Any]] | None = [] if record_traces else None
    info: dict[str, Any] = {}
    tally: Tally | None = None
    space = ActionCheck.for_space(context.action_space, out_of_space)
    nfe.take()
    nfe.take_work()
    remote = remote_policy(policy)
    if remote is not None:
        remote.take_remote()
    start = clock()
    try:
        obs, info = env.reset(seed=spec.seed, options={"episode": spec})
        t = clock()
        env_time += t - start
        context = in_force(context, info)
        c = cpu()
        with nfe.counting():
            policy.reset([context])
        t2 = clock()
        policy_time += t2 - t
        cpu_time += cpu() - c
        done = latency is not None
        if latency is not None:  # under an inference latency: harness/delayed.py
            tally = Tally(info=info)
            run_delayed(env, policy, nfe, context, obs, latency, replan_every, space, tally, traces, t2 - t)
        while not done and steps < context.max_steps:
            c, t = cpu(), clock()
            with nfe.counting():
                batch = policy.act([obs])
            t2 = clock()
            policy_time += t2 - t
            cpu_time += cpu() - c
            chunks += 1
            tokens += batch.action_tokens
            if traces is not None and batch.trace:
                traces.append({**batch.trace[0], "chunk": chunks - 1, "step": steps})
            actions = np.asarray(batch.actions)
            check_chunk(actions, action_dim)
            returned = space.apply(actions[0], steps)
            chunk = returned if replan_every == 0 else returned[:replan_every]
            for action in chunk:
                t = clock()
                obs, _, terminated, truncated, info = env.step(action)
                t2 = clock()
                env_time += t2 - t
                steps += 1
                if info.get("success"):
                    success = done = True
                elif terminated or truncated or steps >= context.max_steps:
                    done = True
                if done:
                    break
                if (switched := in_force(context, info)) is not context:
                    context = switched  # a new subtask: a fresh chunk for its instruction
                    c, t = cpu(), clock()
                    with nfe.counting():
                        policy.reset([context])
                    policy_time += clock() - t
                    cpu_time += cpu() - c
                    break
    except KeyboardInterrupt:
        raise  # an interrupt (Ctrl-C, SIGTERM) stops the run; it is not the episode's failure
    except BaseException as exc:  # SystemExit from a policy too: that episode's failure row
        failure = f"{type(exc).__name__}: {exc}"
        trace = traceback.format_exc()
        success = False
    wall = clock() - start
    delays = {"delay_steps_mean": 0.0 if chunks else None, "delay_steps_max": 0 if chunks else None}
    if tally is not None:
        steps, chunks, tokens, success = (
            tally.steps,
            tally.chunks,
            tally.tokens,
            tally.success and not failure,
        )
        policy_time, env_time, info = policy_time + tally.policy_time, env_time + tally.env_time, tally.info
        cpu_time += tally.cpu_time
        delays = {
            "delay_steps_mean": float(np.mean(tally.delays)) if tally.delays else None,
            "delay_steps_max": max(tally.delays) if tally.delays else None,
            "late_chunks": tally.late_chunks,
            "hold_steps": tally.hold_steps,
        }
    passes: int | None = nfe.take()
    work = nfe.take_work()
    transport = None
    if remote is not None:  # the server's hooks counted its passes; None if it reports none
        totals = remote.take_remote()
        passes = None if totals.nfe is None else passes + totals.nfe
        # connecting again to a server that went away (a restart) is nobody's compute:
        # it stays in wall_clock_s, so it lands in overhead_s
        policy_time = max(0.0, policy_time - totals.connect_wait_s)
        work += totals.work
        transport = max(0.0, policy_time - totals.server_time_s)
    return EpisodeOutcome(
        success=success,
        steps=steps,
        chunks=chunks,
        nfe_total=passes,
        work=work,
        transport_time_s=transport,
        action_tokens_total=tokens,
        policy_time_s=policy_time,
        policy_cpu_time_s=None if cpu_now is None else cpu_time,
        env_time_s=env_time,
        wall_clock_s=wall,
        started_at=started_at,
        failure_reason=failure,
        traceback=trace,
        traces=traces,
        **space.columns(),
        **chain_fields(info),
        **delays,
    )
