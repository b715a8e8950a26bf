"""NFE is counted by the harness's hooks on the policy's torch modules, not reported."""

from __future__ import annotations

import numpy as np
import torch

from adapters.base import EpisodeSpec
from harness.episode import run_episode
from harness.nfe import NFECounter, find_modules
from policies.base import ChunkBatch
from tests.fakes import CountdownEnv, context


class TinyModel(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.embed = torch.nn.Linear(2, 8)
        self.block = torch.nn.Sequential(torch.nn.Linear(8, 8), torch.nn.ReLU())
        self.head = torch.nn.Linear(8, 2)

    def forward(self, x):
        return self.head(self.block(self.embed(x)))


class RefiningPolicy:
    """Runs `passes` forward passes per chunk; may also call a sub-module directly."""

    def __init__(self, passes: int, sneaky: bool = False, hide_in_list: bool = False):
        model = TinyModel()
        self.models = [model] if hide_in_list else None
        self.model = None if hide_in_list else model
        self.passes, self.sneaky = passes, sneaky
        self.claimed_nfe = 0  # a policy's own report is never read

    def _model(self) -> TinyModel:
        return self.models[0] if self.models else self.model

    def reset(self, episodes):
        pass

    def act(self, observations):
        x = torch.zeros(1, 2)
        with torch.inference_mode():
            for _ in range(self.passes):
                x = self._model()(x)
            if self.sneaky:  # skips the model's forward, still a forward pass
                self._model().block(torch.zeros(1, 8))
        return ChunkBatch(actions=np.zeros((1, 4, 2)), action_tokens=8)


def _episode(policy, succeed_at=8):
    counter = NFECounter(policy)
    out = run_episode(CountdownEnv(succeed_at), policy, counter, context(), EpisodeSpec(0))
    counter.close()
    return out


def test_counts_forward_passes_per_chunk():
    out = _episode(RefiningPolicy(passes=3))
    assert out.chunks == 2
    assert out.nfe_total == 6  # nested sub-module calls inside one forward count once


def test_direct_submodule_calls_are_counted():
    out = _episode(RefiningPolicy(passes=2, sneaky=True))
    assert out.nfe_total == 2 * (2 + 1)


def test_modules_in_containers_are_found():
    policy = RefiningPolicy(passes=1, hide_in_list=True)
    assert len(find_modules(policy)) == 1
    assert _episode(policy).nfe_total == 2


def test_policies_without_modules_count_zero():
    class NoModel(RefiningPolicy):
        def act(self, observations):
            return ChunkBatch(actions=np.zeros((1, 4, 2)))

    policy = NoModel(passes=0)
    policy.model = None
    assert find_modules(policy) == []
    assert _episode(policy).nfe_total == 0


def test_counter_is_reset_between_episodes_and_removable():
    policy = RefiningPolicy(passes=1)
    counter = NFECounter(policy)
    assert counter.hooked_modules == 6  # model, embed, block, block[0], block[1], head
    policy.model(torch.zeros(1, 2))
    assert counter.take() == 1 and counter.take() == 0
    counter.close()
    policy.model(torch.zeros(1, 2))
    assert counter.take() == 0
