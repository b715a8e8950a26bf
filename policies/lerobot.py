"""The `lerobot` policy: a LeRobot pretrained policy directory, acting in this harness's suites.

`--policy lerobot:path=DIR` loads `DIR/config.json` + `DIR/model.safetensors` (and the
policy's pre/post-processors saved beside them: normalisation, device) with LeRobot's own
loaders, and acts as `lerobot-eval` does: each step, the observation in LeRobot's
feature names, `preprocessor`, `select_action` (the policy's own action queue: ACT's and
Diffusion Policy's chunks, temporal ensembling), `postprocessor`. So one call returns one
action, and the NFE hooks see the step on which the policy decodes a new chunk (1 pass
for ACT, the denoising steps for Diffusion Policy) and the steps served from its queue
(0 passes).

LeRobot 0.6 needs Python >= 3.12 and its own torch, so this module runs in the LeRobot
environment behind `dvla-harness serve` (docs/lerobot.md), and the main environment
evaluates it with `--policy remote:url=...`: the server's hooks count its passes and
work. Imports nothing of LeRobot's until a policy is built, so `list policies` shows it
everywhere.

Observations map onto LeRobot's names as the export writes them (harness/export_lerobot.py:
`observation.state` the robot's own leading `proprio_dims` entries, `observation.environment_state`
the whole state vector, `observation.images.<camera>` each camera as float [0, 1] CHW),
and the policy reads those its config lists as inputs. Actions map onto the suite's
action space by `map_action` (docs/lerobot.md has the table per suite).
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from policies.base import ChunkBatch, EpisodeContext, Observation
from policies.spec import PolicySpec, param

STATE = "observation.state"
ENV_STATE = "observation.environment_state"
IMAGE_PREFIX = "observation.images."
FILES = ("config.json", "model.safetensors")


@dataclass(frozen=True)
class LeRobotParams:
    path: str = param("", "a LeRobot pretrained policy directory (config.json + model.safetensors)")
    proprio_dim: int = param(
        0, "leading state entries that are observation.state (0: as many as the policy reads)", low=0
    )


def map_action(action: np.ndarray, space: gym.spaces.Box) -> np.ndarray:
    """A LeRobot action as the suite's: the same dimensions in the same order (Meta-World's
    4: hand delta xyz, gripper; LIBERO's 7: delta position, delta axis-angle, gripper -1
    open / +1 closed, as LeRobot's LIBERO env steps robosuite), clipped to the space's
    bounds as the suite's env clips what it executes. A policy trained on another action
    layout is refused, not reshaped."""
    action = np.asarray(action, dtype=np.float32).reshape(-1)
    if action.shape != space.shape:
        raise ValueError(
            f"the LeRobot policy returns {action.size}-D actions, the suite takes {space.shape[0]}-D; "
            "evaluate it on a suite with its action space (docs/lerobot.md)"
        )
    return np.clip(action, space.low, space.high).astype(np.float32)


def lerobot_observation(
    observation: Observation, proprio_dim: int, wanted: Mapping[str, Any]
) -> dict[str, np.ndarray]:
    """The harness's observation under LeRobot's feature names, batch 1, as float32 (images
    CHW in [0, 1], as LeRobot's `preprocess_observation` makes them); only the features
    the policy reads (`wanted`), each checked against the shape the policy was trained on."""
    images: Mapping[str, Any] = observation if isinstance(observation, Mapping) else {}
    state = np.asarray(images["state"] if images else observation, dtype=np.float32).reshape(-1)
    out: dict[str, np.ndarray] = {}
    for key, shape in wanted.items():
        if key == STATE:
            value = state[:proprio_dim]
        elif key == ENV_STATE:
            value = state
        elif key.startswith(IMAGE_PREFIX) and key.removeprefix(IMAGE_PREFIX) in images:
            value = np.asarray(images[key.removeprefix(IMAGE_PREFIX)], np.float32).transpose(2, 0, 1) / 255.0
        else:
            raise ValueError(
                f"the LeRobot policy reads {key!r}, which this suite's observation does not give "
                f"(it gives: {', '.join(sorted(offered(state.size, proprio_dim, images)))})"
            )
        if list(value.shape) != list(shape):
            raise ValueError(
                f"{key}: the suite gives shape {list(value.shape)}, the policy takes {list(shape)}"
            )
        out[key] = value[None]
    return out


def offered(state_dim: int, proprio_dim: int, images: Mapping[str, Any]) -> list[str]:
    cameras = [IMAGE_PREFIX + k for k in images if k != "state"]
    return [f"{STATE} ({proprio_dim})", f"{ENV_STATE} ({state_dim})", *cameras]


class LeRobotPolicy:
    """One LeRobot policy with its processors; one episode at a time (its action queue is
    per episode), as lerobot-eval runs it per env."""

    def __init__(self, params: LeRobotParams):
        import torch
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.policies import make_pre_post_processors
        from lerobot.policies.factory import get_policy_class

        path = Path(params.path)
        self.params = params
        # LeRobot prints "Loading weights from local directory"; `serve`'s first line must be
        # where it listens (clients and scripts read it), so that print is dropped
        with contextlib.redirect_stdout(io.StringIO()):
            config = PreTrainedConfig.from_pretrained(path)
            config.device = "cpu"
            self.policy = get_policy_class(config.type).from_pretrained(path, config=config)
            self.pre, self.post = make_pre_post_processors(
                policy_cfg=config,
                pretrained_path=str(path),
                preprocessor_overrides={"device_processor": {"device": "cpu"}},
            )
        self.policy.eval()
        self.inputs = {k: tuple(f.shape) for k, f in config.input_features.items()}
        self.torch = torch
        self.proprio_dim = params.proprio_dim
        self.space: gym.spaces.Box | None = None
        self.instruction = ""

    def check_spaces(self, observation_space: gym.spaces.Space, action_space: gym.spaces.Space) -> None:
        """Refuse a suite whose observation lacks a feature the policy reads or whose
        action space has another size, before anything is written."""
        sample = observation_space.sample()
        lerobot_observation(sample, self._proprio(observation_space), self.inputs)
        assert isinstance(action_space, gym.spaces.Box)
        map_action(np.zeros(self.policy.config.output_features["action"].shape, np.float32), action_space)

    def _proprio(self, observation_space: gym.spaces.Space) -> int:
        """The leading state entries that are `observation.state`: the parameter, else as
        many as the policy was trained on (the export wrote the robot's own entries there)."""
        if self.proprio_dim:
            return self.proprio_dim
        if STATE in self.inputs:
            return int(self.inputs[STATE][0])
        state = (
            observation_space["state"]
            if isinstance(observation_space, gym.spaces.Dict)
            else observation_space
        )
        return int(state.shape[0])

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        if len(episodes) != 1:
            raise ValueError(
                "the lerobot policy runs one episode at a time (its action queue is per episode)"
            )
        episode = episodes[0]
        assert isinstance(episode.action_space, gym.spaces.Box)
        self.space, self.instruction = episode.action_space, episode.instruction
        self.proprio_dim = self._proprio(episode.observation_space)
        self.policy.reset()

    def act(self, observations: Sequence[Observation]) -> ChunkBatch:
        assert self.space is not None, "reset before act"
        torch = self.torch
        arrays = lerobot_observation(observations[0], self.proprio_dim, self.inputs)
        batch: dict[str, Any] = {k: torch.from_numpy(v) for k, v in arrays.items()}
        batch["task"] = [self.instruction]
        with torch.inference_mode():
            action = self.post(self.policy.select_action(self.pre(batch)))
        mapped = map_action(action.detach().cpu().numpy(), self.space)
        return ChunkBatch(actions=mapped[None, None])


def _build(params: LeRobotParams) -> LeRobotPolicy:
    import importlib.util

    path = Path(params.path)
    missing = [f for f in FILES if not (path / f).is_file()]
    if not params.path or missing:
        raise ValueError(
            f"lerobot: path={params.path!r} is not a LeRobot pretrained policy directory "
            f"(missing {', '.join(missing or FILES)}); give path=DIR as `lerobot-train` saves it "
            "(outputs/train/.../checkpoints/last/pretrained_model)"
        )
    if importlib.util.find_spec("lerobot") is None:
        raise ValueError(
            "lerobot is not installed in this environment: LeRobot 0.6 needs Python >= 3.12, so "
            "serve the policy from the LeRobot environment (`tox -e lerobot` builds one) with "
            "`dvla-harness serve --policy lerobot:path=DIR --suite SUITE`, and evaluate it here with "
            "--policy remote:url=ws://... (docs/lerobot.md)"
        )
    return LeRobotPolicy(params)


LEROBOT = PolicySpec(
    name="lerobot",
    summary="a LeRobot pretrained policy (ACT, Diffusion, ...); runs in the LeRobot environment (docs/lerobot.md)",
    params=LeRobotParams,
    build=_build,
)
