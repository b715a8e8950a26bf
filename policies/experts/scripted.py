"""The bounds every learned policy sits between: Meta-World's own experts and random actions."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from adapters.base import derive_seed
from policies.base import ChunkBatch, EpisodeContext, Observation
from policies.spec import PolicySpec, param


@dataclass(frozen=True)
class ScriptedParams:
    action_noise: float = param(
        0.0, "std of Gaussian noise added to each expert action (degrades the expert)", low=0.0
    )
    seed: int = param(0, "seed of the action noise", low=0)


class MetaWorldExpert:
    """Meta-World's hand-written expert for the current task, one action per call."""

    def __init__(self, params: ScriptedParams):
        self.params = params
        self._experts: list = []
        self._rngs: list[np.random.Generator] = []
        self._bounds: tuple[np.ndarray, np.ndarray] = (np.array(-1.0), np.array(1.0))
        # The experts warn on most steps that their gains exceed [-1, 1]; their actions are
        # clipped to the action space here, which is what Meta-World's env does with them
        # anyway, so that the expert keeps the policy contract (the harness fails an episode
        # on an action outside the space). One filter for that message only, added once: a
        # per-call `catch_warnings` would cost more than the expert itself.
        warnings.filterwarnings("ignore", message=r"Constant\(s\) may be too high", category=UserWarning)

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        from metaworld.policies import ENV_POLICY_MAP

        self._experts, self._rngs = [], []
        space = episodes[0].action_space
        self._bounds = (np.asarray(space.low), np.asarray(space.high))
        for ep in episodes:
            if ep.task not in ENV_POLICY_MAP:
                raise ValueError(f"no Meta-World expert for task {ep.task!r}")
            self._experts.append(ENV_POLICY_MAP[ep.task]())
            if self.params.action_noise > 0:
                seed = derive_seed("scripted", self.params.seed, ep.task, ep.episode_index)
                self._rngs.append(np.random.default_rng(seed))

    def act(self, observations: Sequence[Observation]) -> ChunkBatch:
        if len(observations) == 1:  # the common case, without a per-step stack
            actions = self._experts[0].get_action(observations[0])[None]
        else:
            actions = np.stack([e.get_action(o) for e, o in zip(self._experts, observations, strict=True)])
        if self.params.action_noise > 0:
            noise = np.stack(
                [
                    r.normal(0, self.params.action_noise, a.shape)
                    for r, a in zip(self._rngs, actions, strict=True)
                ]
            )
            actions = actions + noise
        actions = np.clip(actions, *self._bounds)
        return ChunkBatch(actions=actions[:, None, :])


@dataclass(frozen=True)
class RandomParams:
    seed: int = param(0, "seed of the action sampler", low=0)
    chunk_length: int = param(1, "actions returned per call", low=1, high=64)


class RandomPolicy:
    """Uniform actions over the action space: the floor any learned policy must clear."""

    def __init__(self, params: RandomParams):
        self.params = params
        self._episodes: Sequence[EpisodeContext] = ()
        self._rngs: list[np.random.Generator] = []

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        self._episodes = episodes
        self._rngs = [
            np.random.default_rng(derive_seed("random", self.params.seed, ep.task, ep.episode_index, ep.seed))
            for ep in episodes
        ]

    def act(self, observations: Sequence[Observation]) -> ChunkBatch:
        chunks = []
        for ep, rng in zip(self._episodes, self._rngs, strict=False):
            space = ep.action_space
            shape = (self.params.chunk_length, *space.shape)
            chunks.append(rng.uniform(space.low, space.high, size=shape))
        return ChunkBatch(actions=np.stack(chunks))


SCRIPTED = PolicySpec(
    name="scripted",
    summary="Meta-World's expert for the current task (upper bound; no model, NFE 0)",
    params=ScriptedParams,
    build=MetaWorldExpert,
    suites=("metaworld/",),
    extra="metaworld",
)
RANDOM = PolicySpec(
    name="random",
    summary="uniform random actions (lower bound; no model, NFE 0)",
    params=RandomParams,
    build=RandomPolicy,
)
