"""A LeRobot ACT, built from its config (no pretrained weights), saved as `lerobot-train`
saves it, served by `dvla-harness serve --policy lerobot:path=DIR` and evaluated through
`--policy remote:url=...`: the rows carry the served policy's NFE and counted work (FLOPs)
as the harness's hooks count them, checked against torch's flop counter, and the actions
are LeRobot's own. Runs in the LeRobot
environment (tox -e lerobot)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytest.importorskip("lerobot", reason="LeRobot's environment only: tox -e lerobot (docs/lerobot.md)")

import torch

from policies.lerobot import ENV_STATE, STATE
from tests import test_remote

serve_process = test_remote.serve_process  # the fixture: `serve` in its own process
CHUNK, STEPS = 5, 3  # ACT's chunk_size and n_action_steps


def tiny_act(folder: Path) -> Path:
    """A 2-layer ACT on Meta-World's state (4 + 39) and 4-D actions, with normalisation."""
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies import make_pre_post_processors
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy

    config = ACTConfig(
        input_features={
            STATE: PolicyFeature(FeatureType.STATE, (4,)),
            ENV_STATE: PolicyFeature(FeatureType.ENV, (39,)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (4,))},
        chunk_size=CHUNK,
        n_action_steps=STEPS,
        dim_model=32,
        n_heads=2,
        dim_feedforward=64,
        n_encoder_layers=1,
        n_decoder_layers=1,
        n_vae_encoder_layers=1,
        pretrained_backbone_weights=None,
        device="cpu",
    )
    torch.manual_seed(0)
    policy = ACTPolicy(config)
    stats = {
        STATE: {"mean": torch.zeros(4), "std": torch.full((4,), 0.5)},
        "action": {"mean": torch.zeros(4), "std": torch.full((4,), 0.3)},
    }
    pre, post = make_pre_post_processors(config, dataset_stats=stats)
    for part in (policy, pre, post):
        part.save_pretrained(folder)
    return folder


@pytest.fixture(scope="module")
def act_folder(tmp_path_factory) -> Path:
    return tiny_act(tmp_path_factory.mktemp("act"))


def act_flops_per_pass(folder: Path) -> int:
    """FLOPs of one ACT chunk decode as torch.utils.flop_counter counts them, on LeRobot's
    own policy (not the bridge): the reference for the served rows."""
    from lerobot.policies.act.modeling_act import ACTPolicy
    from torch.utils.flop_counter import FlopCounterMode

    policy = ACTPolicy.from_pretrained(folder)
    batch = {STATE: torch.zeros(1, 4), ENV_STATE: torch.zeros(1, 39)}
    with torch.inference_mode(), FlopCounterMode(display=False) as flops:
        policy.predict_action_chunk(batch)
    return flops.get_total_flops()


def test_served_act_rows_carry_its_passes(act_folder, serve_process, tmp_path):
    from harness.cli import main

    suite = "metaworld/mt1/reach-v3"
    url = serve_process("--policy", f"lerobot:path={act_folder}", "--suite", suite)
    out = tmp_path / "run"
    assert main(["run", "--suite", suite, "--policy", f"remote:url={url}", "--episodes-per-task", "2",
                 "--out", str(out)]) in (0, 1)  # fmt: skip
    rows = pd.read_parquet(out / "episodes.parquet")
    per_pass = act_flops_per_pass(act_folder)
    assert len(rows) == 2 and rows["failure_reason"].isna().all(), rows["failure_reason"].tolist()
    for row in rows.itertuples():
        # one call per step; ACT decodes a chunk on every STEPS-th and serves the rest from its queue
        assert row.nfe_total == math.ceil(row.steps / STEPS) > 0
        # counted work, its cross-attention's keyword arguments included: torch's count per pass
        assert row.flops_total == row.nfe_total * per_pass


def test_the_bridge_acts_as_lerobots_own_select_action(act_folder):
    """The policy the server runs, against LeRobot's own preprocess / select_action /
    postprocess on the same observations, step by step through a chunk boundary."""
    import gymnasium as gym
    from lerobot.policies import make_pre_post_processors
    from lerobot.policies.act.modeling_act import ACTPolicy

    from policies.base import EpisodeContext
    from policies.lerobot import LeRobotParams, LeRobotPolicy

    bridge = LeRobotPolicy(LeRobotParams(path=str(act_folder)))
    space = gym.spaces.Box(-1.0, 1.0, (4,), np.float32)
    observation_space = gym.spaces.Box(-np.inf, np.inf, (39,), np.float64)
    bridge.reset([EpisodeContext("metaworld/mt10", "reach-v3", "reach", space, observation_space, 500, 0)])
    policy = ACTPolicy.from_pretrained(act_folder)
    pre, post = make_pre_post_processors(policy.config, pretrained_path=str(act_folder))
    policy.reset()
    rng = np.random.default_rng(0)
    for _ in range(2 * STEPS + 1):
        state = rng.normal(size=39).astype(np.float32)
        got = bridge.act([state]).actions
        batch = {
            STATE: torch.from_numpy(state[None, :4]),
            ENV_STATE: torch.from_numpy(state[None]),
            "task": ["reach"],
        }
        with torch.inference_mode():
            expected = np.clip(post(policy.select_action(pre(batch))).numpy(), -1, 1)
        assert got.shape == (1, 1, 4)
        np.testing.assert_array_equal(got[0], expected)


@pytest.mark.parametrize("threaded", [False, True])
def test_acts_counted_work_is_torchs_flop_count_on_the_same_call(act_folder, threaded):
    """The NFE hooks' FLOPs of each bridge call (a chunk decode, or a step served from the
    queue) against FlopCounterMode around the same call: alone, the single-thread pass
    that wraps the counted modules; beside another thread (as in a server), the
    process-wide hooks, whose pre-hook does not see keyword arguments."""
    import threading

    import gymnasium as gym
    from torch.utils.flop_counter import FlopCounterMode

    from harness.episode.nfe import NFECounter
    from policies.base import EpisodeContext
    from policies.lerobot import LeRobotParams, LeRobotPolicy

    bridge = LeRobotPolicy(LeRobotParams(path=str(act_folder)))
    space = gym.spaces.Box(-1.0, 1.0, (4,), np.float32)
    observation_space = gym.spaces.Box(-np.inf, np.inf, (39,), np.float64)
    bridge.reset([EpisodeContext("metaworld/mt10", "reach-v3", "reach", space, observation_space, 500, 0)])
    counter = NFECounter(bridge)
    stop = threading.Event()
    other = threading.Thread(target=stop.wait)
    if threaded:
        other.start()
    try:
        rng = np.random.default_rng(0)
        decodes = 0
        for _ in range(STEPS + 1):
            with counter.counting(), FlopCounterMode(display=False) as flops:
                bridge.act([rng.normal(size=39).astype(np.float32)])
            passes, work = counter.take(), counter.take_work()
            decodes += passes
            assert work.flops == flops.get_total_flops() and (work.flops > 0) == (passes == 1)
        assert decodes == 2  # a chunk, its queue, the next chunk
    finally:
        stop.set()
        if threaded:
            other.join()
