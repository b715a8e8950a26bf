"""The `lerobot` policy's mapping between this harness's suites and LeRobot's feature names
(policies/lerobot.py), without LeRobot: what it sends a LeRobot policy and what it
executes of its actions. The round trip through a served LeRobot ACT is tests/lerobot/."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from policies.lerobot import ENV_STATE, STATE, LeRobotParams, _build, lerobot_observation, map_action

METAWORLD = gym.spaces.Box(-1.0, 1.0, (4,), np.float32)
LIBERO = gym.spaces.Box(-1.0, 1.0, (7,), np.float32)


def test_actions_keep_their_order_and_are_clipped_to_the_suites_bounds():
    out = map_action(np.array([[0.5, -2.0, 3.0, -0.25]]), METAWORLD)
    assert out.dtype == np.float32 and out.shape == (4,)
    assert out.tolist() == [0.5, -1.0, 1.0, -0.25]
    libero = map_action(np.arange(7, dtype=np.float64) / 10 - 0.3, LIBERO)
    assert np.allclose(libero, np.arange(7) / 10 - 0.3)  # the gripper stays last, -1 open / +1 closed


def test_an_action_of_another_size_is_refused_naming_both():
    with pytest.raises(ValueError, match="returns 7-D actions, the suite takes 4-D"):
        map_action(np.zeros(7), METAWORLD)


def test_the_state_splits_into_the_robots_own_and_the_whole_vector():
    state = np.arange(39, dtype=np.float64)
    out = lerobot_observation(state, 4, {STATE: (4,), ENV_STATE: (39,)})
    assert out[STATE].tolist() == [[0.0, 1.0, 2.0, 3.0]] and out[STATE].dtype == np.float32
    assert out[ENV_STATE].shape == (1, 39) and out[ENV_STATE][0, 38] == 38.0


def test_camera_images_become_chw_in_unit_range_and_only_what_the_policy_reads_is_sent():
    image = np.zeros((6, 8, 3), np.uint8)
    image[1, 2] = (255, 0, 51)
    out = lerobot_observation(
        {"state": np.zeros(9), "agentview": image}, 9, {"observation.images.agentview": (3, 6, 8)}
    )
    assert list(out) == ["observation.images.agentview"]
    assert out["observation.images.agentview"].shape == (1, 3, 6, 8)
    assert out["observation.images.agentview"][0, :, 1, 2].tolist() == pytest.approx([1.0, 0.0, 0.2])


def test_a_feature_the_suite_lacks_or_of_another_shape_is_refused():
    with pytest.raises(
        ValueError, match=r"reads 'observation\.images\.top'.*gives: observation\.environment_state"
    ):
        lerobot_observation(np.zeros(39), 4, {"observation.images.top": (3, 8, 8)})
    with pytest.raises(ValueError, match=r"suite gives shape \[39\], the policy takes \[40\]"):
        lerobot_observation(np.zeros(39), 4, {ENV_STATE: (40,)})


def test_a_folder_that_is_not_a_pretrained_policy_is_refused_naming_the_files(tmp_path):
    with pytest.raises(ValueError, match=r"missing config\.json, model\.safetensors"):
        _build(LeRobotParams(path=str(tmp_path)))
