"""The `metaworld_state` LeRobot env plugin (benchmarks/lerobot_metaworld_state): LeRobot's
own Meta-World env observed through the state vector, so that `lerobot-eval` evaluates a
policy trained on this harness's state-only Meta-World export. Runs in the LeRobot
environment (tox -e lerobot)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("lerobot", reason="LeRobot's environment only: tox -e lerobot (docs/lerobot.md)")

import torch

from policies.lerobot import ENV_STATE, STATE, lerobot_observation

PLUGIN = "benchmarks.lerobot_metaworld_state"


@pytest.fixture(scope="module")
def plugin():
    """The plugin as `lerobot-eval --env.discover_packages_path` loads it."""
    import importlib

    from lerobot.configs.parser import load_plugin

    load_plugin(PLUGIN)
    return importlib.import_module(PLUGIN)


def test_the_env_type_is_registered_and_refuses_pixels(plugin):
    from lerobot.envs.configs import EnvConfig
    from lerobot.envs.factory import make_env_config

    assert EnvConfig.get_choice_class("metaworld_state") is plugin.MetaworldStateEnvConfig
    with pytest.raises(ValueError, match="obs_type 'state' only"):
        make_env_config("metaworld_state", task="reach-v3", obs_type="pixels")


def test_the_observation_is_what_the_policy_was_trained_on(plugin):
    """Reset and steps give the raw 39-D Meta-World observation: `environment_state` whole,
    `agent_pos` its leading 4; through LeRobot's `preprocess_observation` they become the
    tensors this harness's `lerobot` policy builds from the same state (the export's
    features), with the shapes the env config declares to the policy."""
    from lerobot.envs.utils import env_to_policy_features, preprocess_observation

    config = plugin.MetaworldStateEnvConfig(task="reach-v3")
    assert env_to_policy_features(config) == {
        "action": config.features["action"],
        STATE: config.features["agent_pos"],
        ENV_STATE: config.features["environment_state"],
    }
    vec = config.create_envs(n_envs=1)["reach-v3"][0]
    env = vec.envs[0]
    env._ensure_env()
    raws: list[np.ndarray] = []  # what Meta-World itself returns, reset then each step
    reset, step = env._env.reset, env._env.step
    env._env.reset = lambda **kw: (out := reset(**kw), raws.append(out[0]))[0]
    env._env.step = lambda action: (out := step(action), raws.append(out[0]))[0]
    try:
        observation, _ = vec.reset(seed=[7])
        for _ in range(3):
            raw = raws[-1]
            np.testing.assert_array_equal(observation["environment_state"][0], raw)
            np.testing.assert_array_equal(observation["agent_pos"][0], raw[:4])
            assert vec.observation_space.contains(observation)
            lerobot = preprocess_observation(observation)
            harness = lerobot_observation(raw, 4, {STATE: (4,), ENV_STATE: (39,)})
            assert set(lerobot) == {STATE, ENV_STATE}
            for key in (STATE, ENV_STATE):
                assert lerobot[key].dtype == torch.float32
                np.testing.assert_array_equal(lerobot[key].numpy(), harness[key])
            observation, _, terminated, truncated, _ = vec.step(np.full((1, 4), 0.5, np.float32))
            assert not terminated[0] and not truncated[0]
        assert len(raws) == 4 and not np.array_equal(raws[0], raws[-1])
        assert vec.call("_max_episode_steps")[0] == 500  # LeRobot's episode length, unchanged
    finally:
        vec.close()
