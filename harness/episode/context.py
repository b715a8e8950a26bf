"""What a policy is told about its episode, and which instruction is in force.

Instruction chains (CALVIN-like suites, docs/chains.md): the env reports the
instruction in force in its info; when it changes, the loop drops the rest of the
chunk and resets the policy with the new instruction (policies/base.py).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import gymnasium as gym

from adapters.base import EpisodeSpec, TaskSpec
from policies.base import EpisodeContext


def episode_context(suite: str, task: TaskSpec, spec: EpisodeSpec, env: gym.Env) -> EpisodeContext:
    return EpisodeContext(
        suite=suite,
        task=task.name,
        instruction=task.instruction,
        action_space=env.action_space,
        observation_space=env.observation_space,
        max_steps=task.max_steps,
        episode_index=spec.index,
        seed=spec.seed,
        init_state_id=spec.init_state_id,
    )


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
