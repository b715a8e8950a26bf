"""Warm-up: a policy's one-off first-call cost is paid before its first timed
episode, recorded in the manifest, and charged to no row (neither time nor NFE)."""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np
import torch

from harness.run.folder import OpenMode
from harness.run.runner import run
from policies.base import ChunkBatch, EpisodeContext
from results.store import RunDir
from tests.fakes import fake_resolved

FIRST_CALL_S = 0.4
LATER_CALL_S = 0.02  # long enough that a loaded machine's jitter is small beside it


class SlowStart:
    """A torch policy whose first act pays a one-off cost (like lazy kernel set-up), then
    runs its model once per chunk."""

    def __init__(self) -> None:
        self.model = torch.nn.Linear(1, 2)
        self.acted = 0

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        pass  # nothing carried between episodes; the one-off cost is per process

    def act(self, observations: Sequence[object]) -> ChunkBatch:
        time.sleep(FIRST_CALL_S if self.acted == 0 else LATER_CALL_S)
        self.acted += 1
        with torch.inference_mode():
            out = self.model(torch.zeros(1, 1))
        actions = np.repeat(np.tanh(out.numpy())[:, None, :], 2, axis=1)
        return ChunkBatch(actions=actions, action_tokens=4)


def test_the_first_episode_is_not_charged_the_policys_first_call(tmp_path):
    policy = SlowStart()
    resolved = fake_resolved(policy, episodes=4, succeed_at=6)
    run(resolved, tmp_path / "r")
    assert len(resolved.made_envs) == 1  # the warm-up's env is the first episode's
    rows = RunDir(tmp_path / "r").read_episodes().sort_values("episode_index")
    speeds = rows["tokens_per_s"].to_numpy()
    assert (rows["chunks"] == 3).all()
    # without the warm-up, row 0 would hold the 0.4 s call: ~8x slower than the rest
    assert speeds[0] > 0.5 * speeds[1:].min()
    assert rows["policy_time_s"].iloc[0] < FIRST_CALL_S / 2
    assert (rows["nfe_total"] == 3).all()  # the warm-up's forward pass is in no row
    (entry,) = RunDir(tmp_path / "r").read_manifest()["warm_up"]
    (warmed,) = entry["policies"]
    assert warmed["policy_config_id"] == "fakeconfig01" and warmed["error"] is None
    assert warmed["seconds"] >= FIRST_CALL_S
    assert policy.acted == 1 + 4 * 3


def test_a_resumed_run_warms_up_again_and_a_raising_warm_up_is_left_to_the_episodes(tmp_path):
    class Broken(SlowStart):
        def act(self, observations):
            raise SystemExit(3)  # not an Exception: the warm-up must not let it end the run

    resolved = fake_resolved(Broken(), episodes=2)
    report = run(resolved, tmp_path / "r")
    assert report.failed == 2  # the episodes say why, as they would without a warm-up
    (entry,) = RunDir(tmp_path / "r").read_manifest()["warm_up"]
    assert entry["policies"][0]["error"] == "SystemExit: 3"
    run(resolved, tmp_path / "r", OpenMode.RETRY_FAILED)
    assert len(RunDir(tmp_path / "r").read_manifest()["warm_up"]) == 2
