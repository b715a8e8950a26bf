"""A process's open environments, by task, reused between episodes.

A LIBERO env takes seconds to build and holds ~0.5 GB, so a task's envs are kept for its
next episodes (of any policy) and closed when an episode of another task needs one:
ninety LIBERO tasks' envs would not fit. An env whose episode failed is closed, not
reused: its state is suspect. With --batch-envs K a task holds at most K envs, one per
slot of the loop. Every env is wrapped in the run's `ActionGuard` once, when it is taken
in, so the loop admits every chunk through the run's out-of-space rule.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium as gym

from harness.episode.actions import DEFAULT_OUT_OF_SPACE, ActionGuard


class TaskEnvs:
    """Idle envs of the current task (the most recently given back is taken first, so a
    batch slot keeps its env from episode to episode), built on demand."""

    def __init__(
        self, make_env: Callable[[Any], gym.Env], rule: str = DEFAULT_OUT_OF_SPACE, close_failed: bool = True
    ):
        self.make_env, self.rule, self.close_failed = make_env, rule, close_failed
        self.idle: dict[str, list[ActionGuard]] = {}

    def _close_other_tasks(self, task: str) -> None:
        for name in [n for n in self.idle if n != task]:
            for env in self.idle.pop(name):
                env.close()

    def take(self, task: Any) -> ActionGuard:
        """An env for an episode of `task` (a TaskSpec): an idle one, or a new one (its
        build's exception propagates); other tasks' idle envs are closed first."""
        self._close_other_tasks(task.name)
        idle = self.idle.get(task.name)
        if idle:
            return idle.pop()
        return ActionGuard(self.make_env(task), self.rule)

    def give_back(self, task: str, env: ActionGuard, suspect: bool = False) -> None:
        """An episode of `task` is over: its env is kept for the next one, or closed when
        the episode failed."""
        if suspect and self.close_failed:
            env.close()
        else:
            self.idle.setdefault(task, []).append(env)

    def adopt(self, task: str, env: gym.Env) -> None:
        """An env of `task` built elsewhere (the preflight's, the warm-up's), for the episodes."""
        guarded = env if isinstance(env, ActionGuard) else ActionGuard(env, self.rule)
        self.give_back(task, guarded)

    def peek(self, task: Any) -> ActionGuard:
        """An env of `task` to read spaces from (a warm-up's observation), left idle."""
        env = self.take(task)
        self.give_back(task.name, env)
        return env

    def close(self) -> None:
        while self.idle:
            for env in self.idle.popitem()[1]:
                env.close()
