"""The policy contract: everything that acts, from a scripted expert to a dVLA decoder.

Batched by design: `act` takes one observation per batch slot and returns one action
chunk per slot, so a torch policy can decode several environments in one forward pass.
The runner uses batch size 1 today.

What a policy reports about itself is limited to what only it can know (how many action
tokens it decoded, an optional decode trace). Forward passes (NFE) and time are
measured by the harness around the call, never taken from the policy.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import gymnasium as gym
import numpy as np

Observation = Any  # an np.ndarray (state) or a mapping of named arrays (state, images)


@dataclass(frozen=True)
class EpisodeContext:
    """What a policy is told at the start of an episode."""

    suite: str
    task: str
    instruction: str
    action_space: gym.spaces.Space
    observation_space: gym.spaces.Space
    max_steps: int
    episode_index: int
    seed: int | None = None
    init_state_id: int | None = None


@dataclass
class ChunkBatch:
    """The result of one `act` call.

    actions: shape (batch, chunk_length, action_dim); the runner executes the first
      `replan_every` of them (or all) before asking again.
    action_tokens: discrete action tokens decoded in this call, summed over the batch
      (0 for policies that do not decode tokens); gives tokens/s.
    trace: optional per-slot decode trace (which positions were committed at each
      forward pass), recorded only when the policy was asked to.
    """

    actions: np.ndarray
    action_tokens: int = 0
    trace: Sequence[Mapping[str, Any]] | None = field(default=None)


@runtime_checkable
class Policy(Protocol):
    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        """Start new episodes, one context per batch slot."""
        ...

    def act(self, observations: Sequence[Observation]) -> ChunkBatch:
        """Return the next action chunk for each batch slot."""
        ...


# Optional, beside the contract: `check_spaces(observation_space, action_space)` raising
# ValueError when the policy cannot act in a suite (a checkpoint trained on other
# observations). The runner calls it once before it writes anything, so a mismatch is a
# usage error (exit 2) instead of one failed row per episode.
