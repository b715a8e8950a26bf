"""A LeRobot env plugin: LeRobot's own Meta-World env, observed through the state vector.

Why it exists: LeRobot 0.6.1's Meta-World env gives pixel observations only (its
`obs_type="state"` raises NotImplementedError), so `lerobot-eval` cannot evaluate a policy
trained on this harness's state-only Meta-World export (`observation.state`, the 4-D hand
position and gripper opening, and `observation.environment_state`, the whole 39-D
observation; harness/export_lerobot.py). This plugin registers the env type
`metaworld_state`: LeRobot's `MetaworldEnv` (its Meta-World construction, layout seeding,
500-step limit, success and auto-reset) with only the observation replaced by the raw 39-D
vector under those two keys, as this harness's Meta-World adapter and the `lerobot` policy
give it. Everything else stays LeRobot's: `lerobot-eval`'s rollout loop, its seeds, its
`eval_info.json`. It runs only in LeRobot's environment (Python 3.12, lerobot 0.6.1):

    PYTHONPATH=. lerobot-eval --env.discover_packages_path=benchmarks.lerobot_metaworld_state \\
        --env.type=metaworld_state --env.task=reach-v3,push-v3 --policy.path=DIR ...

(docs/lerobot.md, "The round trip on MT10").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.envs import metaworld as lerobot_metaworld
from lerobot.envs.configs import EnvConfig
from lerobot.envs.configs import MetaworldEnv as MetaworldEnvConfig
from lerobot.envs.utils import _LazyAsyncVectorEnv
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_STATE

STATE_DIM = 39  # Meta-World v3's observation: hand, gripper, two objects, previous frame, goal
PROPRIO_DIM = lerobot_metaworld.OBS_DIM  # the leading 4: hand position and gripper opening


class MetaworldStateEnv(lerobot_metaworld.MetaworldEnv):
    """LeRobot's Meta-World env whose observation is the state: `agent_pos` (the leading 4
    entries, as LeRobot's `pixels_agent_pos` gives them) and `environment_state` (all 39),
    which `lerobot-eval`'s `preprocess_observation` maps to `observation.state` and
    `observation.environment_state`. No frame is rendered for the observation; `render()`
    (the eval's videos) is LeRobot's."""

    def __init__(self, task: str, render_mode: str = "rgb_array", **kwargs: Any):
        # LeRobot's constructor refuses "state"; build it as "pixels_agent_pos" (nothing is
        # rendered until an observation is formatted) and replace the observation.
        super().__init__(task, obs_type="pixels_agent_pos", render_mode=render_mode, **kwargs)
        self.obs_type = "state"
        self.observation_space = spaces.Dict(
            {
                "agent_pos": spaces.Box(-np.inf, np.inf, shape=(PROPRIO_DIM,), dtype=np.float64),
                "environment_state": spaces.Box(-np.inf, np.inf, shape=(STATE_DIM,), dtype=np.float64),
            }
        )

    def _format_raw_obs(self, raw_obs: np.ndarray) -> dict[str, np.ndarray]:
        state = np.asarray(raw_obs, dtype=np.float64)
        return {"agent_pos": state[:PROPRIO_DIM].copy(), "environment_state": state.copy()}


def _state_features() -> dict[str, PolicyFeature]:
    return {
        "action": PolicyFeature(type=FeatureType.ACTION, shape=(lerobot_metaworld.ACTION_DIM,)),
        "agent_pos": PolicyFeature(type=FeatureType.STATE, shape=(PROPRIO_DIM,)),
        "environment_state": PolicyFeature(type=FeatureType.ENV, shape=(STATE_DIM,)),
    }


def _state_features_map() -> dict[str, str]:
    return {"action": ACTION, "agent_pos": OBS_STATE, "environment_state": OBS_ENV_STATE}


@EnvConfig.register_subclass("metaworld_state")
@dataclass
class MetaworldStateEnvConfig(MetaworldEnvConfig):
    """`--env.type=metaworld_state`: LeRobot's `metaworld` config (task names and groups,
    fps 80) with the state observation; `obs_type` is "state" and nothing else."""

    obs_type: str = "state"
    features: dict[str, PolicyFeature] = field(default_factory=_state_features)
    features_map: dict[str, str] = field(default_factory=_state_features_map)

    def __post_init__(self) -> None:
        if self.obs_type != "state":
            raise ValueError(
                f"env type metaworld_state gives obs_type 'state' only, not {self.obs_type!r} "
                "(LeRobot's own --env.type=metaworld gives 'pixels' and 'pixels_agent_pos')"
            )

    @property
    def gym_kwargs(self) -> dict:
        return {"render_mode": self.render_mode}

    def create_envs(self, n_envs: int, use_async_envs: bool = False) -> dict[str, dict[int, Any]]:
        """{group: {task id: vector env of n_envs}}, the groups as LeRobot's Meta-World env
        reads `--env.task` (a difficulty group or a task name, comma-separated)."""
        if not self.task:
            raise ValueError("env type metaworld_state needs --env.task (task names or difficulty groups)")
        if n_envs < 1:
            raise ValueError(f"n_envs must be at least 1, not {n_envs}")
        out: dict[str, dict[int, Any]] = {}
        for group in (g.strip() for g in self.task.split(",") if g.strip()):
            tasks = lerobot_metaworld.DIFFICULTY_TO_TASKS.get(group, [group])
            out[group] = {}
            for task_id, task in enumerate(tasks):
                fns = [lambda t=task: MetaworldStateEnv(t, **self.gym_kwargs) for _ in range(n_envs)]
                if use_async_envs and n_envs > 1:
                    out[group][task_id] = _LazyAsyncVectorEnv(fns)
                else:
                    out[group][task_id] = gym.vector.SyncVectorEnv(fns)
        return out
