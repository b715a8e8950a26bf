"""What the harness does with actions outside the env's action space (`--out-of-space`).

A policy's contract (policies/base.py) is to return actions inside the env's Box. Many
simulators clip what they are given, so an action of 5 in a [-1, 1] space runs without
complaint and the episode's row would describe a policy that did not keep the contract.
Every chunk is therefore checked as it is returned, over every action in it (those the
harness will not execute, past --replan-every, included: the policy returned them), and
one rule decides what happens:

- `fail` (the default): the episode ends there, its failure_reason naming the env step,
  the value and the bounds; the env never receives the action.
- `clip`: the chunk is clipped to the bounds (np.clip) before the env sees it; the
  episode runs on, its row counting what was clipped.
- `record`: the actions go to the env unclipped (what the env does with them is the
  env's business, as it was before the check), and the row counts them.

Each row says how many action vectors (one per env step, not per element) were outside
and the largest distance of any element beyond its bound, whatever the rule. Non-finite
actions and actions above 1e6 in magnitude fail the episode under every rule: they are
broken arithmetic, not a policy's choice. Action spaces that are not a Box are not
checked (their rows say null).

`ActionGuard` is that rule as a wrapper around the env the loop steps: every chunk is
admitted through it before any of its actions can reach `step`, and it counts what it
saw per episode (a reset starts the count again). Admission is per chunk, not per step,
because the policy answered with the whole chunk: under `fail` an action it returned
ends the episode when it is returned, even one the harness would never execute.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

OUT_OF_SPACE_RULES = ("fail", "clip", "record")
DEFAULT_OUT_OF_SPACE = "fail"
# An action this far past a bound still counts as inside: a float32 Box's bound and the
# float64 action a policy computed for it may differ in the last digits.
TOLERANCE = 1e-6

RULES_HELP = (
    "what to do with an action outside the env's action space (a Box's bounds): fail (default) "
    "ends that episode with a failure_reason naming the step, the value and the bounds; clip "
    "clips the chunk to the bounds before the env sees it; record passes it to the env "
    "unclipped. Every rule counts them per row (actions_out_of_space, max_action_excess); "
    "recorded in the manifest, and --resume keeps the rule the run started with"
)


class ActionOutOfSpace(ValueError):
    """A policy returned an action outside the action space under the `fail` rule."""


def check_rule(value: object, where: str) -> str:
    """The rule named by a flag or config value; anything else is a UsageError (exit 2)."""
    from harness.errors import UsageError

    if value not in OUT_OF_SPACE_RULES:
        raise UsageError(f"{where} {value!r} is not a rule; choose one of {', '.join(OUT_OF_SPACE_RULES)}")
    return str(value)


def box_bounds(space: gym.Space) -> tuple[np.ndarray, np.ndarray] | None:
    """The Box's bounds flattened to one action vector, or None for other spaces."""
    if not isinstance(space, gym.spaces.Box):
        return None
    return np.asarray(space.low, dtype=np.float64).ravel(), np.asarray(space.high, dtype=np.float64).ravel()


def excess(chunk: np.ndarray, low: np.ndarray, high: np.ndarray) -> np.ndarray:
    """Per element of `chunk` (actions x dim), its distance beyond the nearer bound (<= 0 inside)."""
    return np.maximum(low - chunk, chunk - high)


def describe(chunk: np.ndarray, low: np.ndarray, high: np.ndarray, first_step: int) -> str | None:
    """The first action of `chunk` outside the bounds, as a sentence naming its env step
    (0-based; `first_step` is the step of the chunk's first action), the worst element's
    value and its bounds, and how many of the chunk's actions are outside; None if none is."""
    beyond = excess(chunk, low, high)
    bad = (beyond > TOLERANCE).any(axis=1)
    if not bad.any():
        return None
    i = int(np.argmax(bad))
    j = int(np.argmax(beyond[i]))
    return (
        f"the action for env step {first_step + i} (0-based; action {i} of its chunk) is outside the "
        f"action space: element {j} is {chunk[i, j]:.6g}, bounds [{low[j]:.6g}, {high[j]:.6g}] "
        f"({int(bad.sum())} of the chunk's {len(chunk)} actions outside, largest excess {beyond.max():.3g})"
    )


# Beyond any action space a simulator clips to: a policy's arithmetic went wrong, and the
# episode's outcome would say nothing about the policy (an env clips it to a corner).
ABSURD_ACTION = 1e6


def check_chunk(actions: np.ndarray, action_dim: int) -> None:
    """A ValueError unless `actions` is one chunk (1, chunk >= 1, action_dim) of finite,
    sane numbers; the message says which of those it is not."""
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


class ActionGuard(gym.Wrapper):
    """The env as the episode loop steps it: chunks admitted under one rule, counted per episode."""

    def __init__(self, env: gym.Env, rule: str = DEFAULT_OUT_OF_SPACE):
        super().__init__(env)
        self.step = env.step  # type: ignore[method-assign]  # admission is per chunk; a step is the env's own
        self.rule = rule
        self.bounds = box_bounds(env.action_space)
        self.action_dim = int(np.prod(env.action_space.shape))
        self.outside = 0  # action vectors outside the bounds, this episode
        self.worst = 0.0  # largest distance of an element beyond its bound, this episode

    def reset(self, **kwargs: Any) -> Any:
        self.outside, self.worst = 0, 0.0
        return self.env.reset(**kwargs)

    def admit(self, actions: np.ndarray, first_step: int) -> np.ndarray:
        """The actions that may be executed from one returned chunk (1, chunk, action_dim):
        checked (ValueError), counted, and handled by the rule (ActionOutOfSpace under `fail`)."""
        check_chunk(actions, self.action_dim)
        chunk = actions[0]
        if self.bounds is None:
            return chunk
        low, high = self.bounds
        beyond = excess(chunk, low, high)
        bad = (beyond > TOLERANCE).any(axis=1)
        if bad.any():
            self.outside += int(bad.sum())
            self.worst = max(self.worst, float(beyond.max()))
            if self.rule == "fail":
                what = describe(chunk, low, high, first_step)
                raise ActionOutOfSpace(
                    f"{what}; --out-of-space fail (the default) ends the episode here: fix the policy, "
                    "or run with --out-of-space clip or record"
                )
        if self.rule == "clip":
            return np.clip(chunk, low, high)
        return chunk

    def columns(self) -> dict[str, int | float | None]:
        """The row's actions_out_of_space and max_action_excess (null when not checked)."""
        if self.bounds is None:
            return {"actions_out_of_space": None, "max_action_excess": None}
        return {"actions_out_of_space": self.outside, "max_action_excess": self.worst}
