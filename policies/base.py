"""The policy contract: everything that acts, from a scripted expert to a dVLA decoder.

Batched by design: `act` takes one observation per batch slot and returns one action
chunk per slot, so a torch policy can decode several environments in one forward pass.
The runner calls `act` with batch size 1; `--batch-envs K` (harness/episode/loop.py)
steps K environments in lockstep and needs the optional `act_batch` below, because their
episodes start and end at different times.

What a policy reports about itself is limited to what only it can know (how many action
tokens it decoded, an optional decode trace). Forward passes (NFE) and time are
measured by the harness around the call, never taken from the policy.

Instruction chains (CALVIN-like suites, docs/chains.md): the instruction changes within
an episode. When the env reports a new instruction in force, the runner drops what is
left of the action chunk and calls `reset([context])` again, with `context.instruction`
the new instruction and `context.subtask_index` its position in the chain, as CALVIN's
evaluation resets its model and hands it the new goal before each subtask; the env is
not reset. So every policy, plugins included, sees the instruction in force through the
one method it already has, and a policy written for single-instruction suites works
unchanged. Its time and forward passes in that reset count as the policy's.
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
    # Position of `instruction` in an instruction chain (0 for single-instruction suites).
    subtask_index: int = 0


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
#
# Optional too: `take_served()`, declared by a policy whose model runs in another process
# behind a policy server (policies/remote.py). It returns what the server's own hooks
# counted since the last take (harness/episode/timed.py ServedTotals: passes, counted
# work, the server's time, the client's waits to reconnect); the harness reads it after
# every call, adds its passes and work to what it counted here, splits the call's time
# into server and transport, and takes no CPU time for it (the client only waits).
# `served_by` (text, e.g. "the server at ws://...") names the server in messages.


class BatchPolicy(Policy, Protocol):
    """A policy that can serve episodes at different points of their run in one call.

    `--batch-envs K` needs this (checked before anything is written): the K slots' episodes
    start and end at different steps, and a slot whose action chunk is not used up needs no
    call, so one call serves any subset of the running episodes. `reset([context])` is
    still called once when each episode starts (checks, per-episode setup), but `act_batch`
    must not depend on which episodes were reset last: what it needs per episode comes
    from `episodes`, and nothing may carry over from one call to the next (a policy that
    keeps per-episode state between chunks, such as a scripted expert's phase or a KV
    cache kept across chunks, cannot declare it).
    """

    def act_batch(
        self, episodes: Sequence[EpisodeContext], observations: Sequence[Observation]
    ) -> ChunkBatch:
        """One action chunk per (episode, observation) pair, in their order."""
        ...


def can_batch(policy: object) -> bool:
    """Does `policy` declare `act_batch` (BatchPolicy), so --batch-envs K > 1 may use it?"""
    return callable(getattr(policy, "act_batch", None))
