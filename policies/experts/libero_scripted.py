"""The `libero_scripted` policy: each episode acted by the LIBERO expert its goal calls for.

The policy stands above the selection (policies/experts/libero_select.py: `expert_for`,
and a chain's `handover` between subtasks), which stands above the experts and the
parameters they share (libero_pick.py; libero_push.py, libero_knob.py, libero_drawer.py),
so each of these modules imports only those below it.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from adapters.base import derive_seed
from policies.base import ChunkBatch, EpisodeContext, Observation
from policies.experts.libero_pick import LiberoScriptedParams
from policies.experts.libero_select import expert_for, handover
from policies.spec import PolicySpec


class LiberoScripted:
    def __init__(self, params: LiberoScriptedParams):
        self.params = params
        self._experts: list = []  # one of the experts `expert_for` picks, per episode
        self._episodes: list[tuple[str, int]] = []  # (task, episode index) of each slot
        self._homes: dict[tuple[str, int], np.ndarray] = {}  # each episode's first hand pose

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        running = dict(zip(self._episodes, self._experts, strict=True))
        self._experts, self._episodes = [], []
        homes = {}
        for ep in episodes:
            rng = None
            if self.params.action_noise > 0:
                rng = np.random.default_rng(
                    derive_seed("libero_scripted", self.params.seed, ep.task, ep.episode_index)
                )
            expert = expert_for(ep, self.params, rng)
            key = (ep.task, ep.episode_index)
            if ep.subtask_index > 0 and key in running:  # a chain's next instruction
                expert = handover(expert, running[key], self._homes.get(key), self.params)
                if key in self._homes:
                    homes[key] = self._homes[key]
            self._experts.append(expert)
            self._episodes.append(key)
        self._homes = homes

    def act(self, observations: Sequence[Observation]) -> ChunkBatch:
        states = [o["state"] if isinstance(o, dict) else np.asarray(o) for o in observations]
        for key, state in zip(self._episodes, states, strict=True):
            if key not in self._homes:  # the episode's first observation: where chains return
                self._homes[key] = np.array(state[:7])
        actions = [e.act(o) for e, o in zip(self._experts, states, strict=True)]
        return ChunkBatch(actions=np.stack(actions)[:, None, :])


LIBERO_SCRIPTED = PolicySpec(
    name="libero_scripted",
    summary="scripted LIBERO expert from privileged state: pick-and-place, drag, knob, drawer (no model, NFE 0)",
    params=LiberoScriptedParams,
    build=LiberoScripted,
    suites=("libero/", "chains/"),
    extra="libero",
)
