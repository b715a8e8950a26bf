"""vla-eval's protocol without its bytes: its message types, and which observation its
benchmarks send, in this harness's suites' terms (policies/vlaeval_wire.py encodes;
this module needs no msgpack, so listing policies never imports it).

vla-eval's benchmarks each build their own observation map (`make_obs` in
`vla_eval/benchmarks/<name>/benchmark.py`), and a model server written for one reads
exactly those keys. So a suite of this harness speaks to a vla-eval model server as the
vla-eval benchmark of the same family would, and only where the observation exists here:

| vla-eval benchmark | suites here | images (vla-eval key <- ours) | `states` | episode_start `task` |
|---|---|---|---|---|
| LIBERO | `libero/*:obs=upstream` (256 px) | agentview <- agentview, wrist <- wrist | 8-D eef position, axis-angle, gripper qpos | name (the instruction), suite `libero_<key>`, task_id, episode_idx |
| SimplerEnv | `simpler/*:obs=images` | primary <- base_camera | none: its state is the hand in the robot base's frame | name, task_name, episode_idx |
| CALVIN | `chains/*:obs=upstream` with `benchmark=calvin` | rgb_static <- agentview, rgb_gripper <- wrist | none: its state is CALVIN's robot_obs | name, seq_idx, episode_idx |

Every observation carries `task_description` (the instruction in force); SimplerEnv's
also `task_name`, and CALVIN's `episode_restart: True` on the first observation of a new
subtask. The server's `observation_params` (its hello) switch on what the benchmark
sends optionally, as they switch vla-eval's benchmark's constructor arguments:
`send_wrist_image`, `send_state` and, for LIBERO, `quat_no_antipodal` (without it the
rotation is folded to the quaternion's w >= 0 before axis-angle, as vla-eval's default
does; this harness's state, like openpi's and robosuite's, is not folded). Parameters
that would change the episode itself (`absolute_action`, `num_steps_wait`) are refused
when they differ from this harness's protocol.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from typing import Any

import gymnasium as gym
import numpy as np

from policies.base import EpisodeContext, Observation

TYPES = ("hello", "observation", "action", "episode_start", "episode_end", "error")
PROTOCOL_VERSION = 1  # vla-eval's PROTOCOL_VERSION, sent in both hellos
IMAGE_FORMATS = ("png", "raw", "jpeg")  # how its client may send a camera image (png by default)
LIBERO_IMAGE_SIZE = 256  # vla-eval's LIBERO_ENV_RESOLUTION, as openpi's and OpenVLA's scripts
# LIBERO constructor arguments a server may ask for, and the value this harness's protocol
# fixes them at (adapters/libero.py: settle steps, delta actions).
LIBERO_FIXED = {"num_steps_wait": 10, "absolute_action": False}


@dataclass(frozen=True)
class Mapping:
    """One vla-eval benchmark's observation, in terms of this harness's suites."""

    benchmark: str  # "libero", "simpler", "calvin"
    cameras: tuple[tuple[str, str], ...]  # (vla-eval image key, this harness's observation key)
    optional_camera: str | None  # the image key sent only with send_wrist_image
    state: bool  # whether the 8-D `states` exists here
    image_size: int | None  # the size the benchmark renders, where a server depends on it
    suites: str  # the suites here that give this observation, for messages


MAPPINGS = {
    "libero": Mapping(
        "libero",
        (("agentview", "agentview"), ("wrist", "wrist")),
        "wrist",
        True,
        LIBERO_IMAGE_SIZE,
        "libero/<suite>:obs=upstream",
    ),
    "simpler": Mapping(
        "simpler", (("primary", "base_camera"),), None, False, None, "simpler/<task>:obs=images"
    ),
    "calvin": Mapping(
        "calvin",
        (("rgb_static", "agentview"), ("rgb_gripper", "wrist")),
        "rgb_gripper",
        False,
        None,
        "chains/<scene>:obs=upstream",
    ),
}
BENCHMARKS = ("auto", *MAPPINGS)
ALL_SUITES = "; ".join(f"{m.benchmark}: {m.suites}" for m in MAPPINGS.values())


@dataclass(frozen=True)
class Sending:
    """What the benchmark sends besides the required images (the server's asks)."""

    wrist: bool = False
    state: bool = False
    fold_quaternion: bool = True  # LIBERO: vla-eval's default (quat_no_antipodal false)


def choose(benchmark: str, observation_space: gym.Space, hint: str = "") -> Mapping:
    """The mapping for a suite's observation space (`benchmark`: auto picks by its keys),
    or ValueError naming the suites that have one (`hint`: which suites to name)."""
    hint = hint or f"suites with a vla-eval observation: {ALL_SUITES}"
    spaces = observation_space.spaces if isinstance(observation_space, gym.spaces.Dict) else {}
    if benchmark == "auto":
        benchmark = "simpler" if "base_camera" in spaces else "libero"
    mapping = MAPPINGS[benchmark]
    needed = [ours for _, ours in mapping.cameras] + (["state"] if mapping.state else [])
    missing = [key for key in needed if key not in spaces]
    if missing:
        raise ValueError(
            f"vla-eval's {mapping.benchmark} observation needs {', '.join(missing)}, which this suite's "
            f"observation lacks; {hint}"
        )
    if mapping.state and spaces["state"].shape != (8,):
        raise ValueError(
            f"vla-eval's LIBERO sends an 8-D state; this suite's is {list(spaces['state'].shape)}-D "
            f"(privileged state); {hint}"
        )
    if mapping.image_size is not None:
        for _, ours in mapping.cameras:
            shape = spaces[ours].shape
            if tuple(shape[:2]) != (mapping.image_size, mapping.image_size):
                raise ValueError(
                    f"vla-eval's {mapping.benchmark} renders {mapping.image_size} px images; this suite's "
                    f"{ours} is {shape[0]} x {shape[1]}; {hint} (at its default size)"
                )
    return mapping


def sending(mapping: Mapping, params: Any) -> Sending:
    """What the benchmark sends, from the server's `observation_params`; ValueError for
    an ask this harness cannot meet (a state it does not have, another protocol)."""
    if not isinstance(params, dict):
        raise ValueError(f"the server's observation_params must be a map, got {type(params).__name__}")
    state = params.get("send_state", False) is True
    if state and not mapping.state:
        raise ValueError(
            f"the server asks for vla-eval's {mapping.benchmark} state (send_state), which has no "
            f"counterpart in this harness's suites; only LIBERO's 8-D state maps ({MAPPINGS['libero'].suites})"
        )
    if mapping.benchmark == "libero":
        for key, value in LIBERO_FIXED.items():
            if key in params and params[key] != value:
                raise ValueError(
                    f"the server asks vla-eval's LIBERO for {key}={params[key]!r}; this harness's "
                    f"LIBERO protocol fixes {key}={value!r}"
                )
    wrist = mapping.optional_camera is not None and params.get("send_wrist_image", False) is True
    return Sending(wrist, state, fold_quaternion=params.get("quat_no_antipodal", False) is not True)


def fold_axis_angle(rotation: np.ndarray) -> np.ndarray:
    """robosuite's axis-angle (no folding: an angle in (pi, 2 pi] where the quaternion's
    w < 0) as vla-eval's `quat_to_axisangle` gives it, which first folds the quaternion
    to w >= 0: the same rotation, the angle 2 pi - angle about the opposite axis."""
    angle = float(np.linalg.norm(rotation))
    if angle <= math.pi:
        return rotation
    return rotation * ((angle - 2 * math.pi) / angle)


def payload(
    mapping: Mapping, send: Sending, obs: Observation, context: EpisodeContext, restart: bool = False
) -> dict[str, Any]:
    """The observation message vla-eval's benchmark would send for this step."""
    images = {
        theirs: np.ascontiguousarray(obs[ours])
        for theirs, ours in mapping.cameras
        if theirs != mapping.optional_camera or send.wrist
    }
    out: dict[str, Any] = {"images": images, "task_description": context.instruction}
    if mapping.benchmark == "simpler":
        out["task_name"] = context.task
    if send.state:
        state = np.asarray(obs["state"], dtype=np.float64)
        if send.fold_quaternion:
            state = np.concatenate([state[:3], fold_axis_angle(state[3:6]), state[6:]])
        out["states"] = state
    if restart:
        out["episode_restart"] = True
    return out


@cache
def _task_index(suite: str, task: str) -> int | None:
    from adapters.registry import load_suite

    try:
        return load_suite(suite).task(task).index
    except (LookupError, ValueError):
        return None


def task_info(mapping: Mapping, context: EpisodeContext) -> dict[str, Any]:
    """episode_start's `task`, as vla-eval's runner sends it (the task's plain fields)."""
    episode = context.episode_index if context.init_state_id is None else context.init_state_id
    if mapping.benchmark == "simpler":
        return {"name": context.task, "task_name": context.task, "episode_idx": episode}
    if mapping.benchmark == "calvin":
        return {"name": context.task, "seq_idx": context.episode_index, "episode_idx": context.episode_index}
    key = context.suite.partition(":")[0].removeprefix("libero/")
    info: dict[str, Any] = {"name": context.instruction, "suite": f"libero_{key}", "episode_idx": episode}
    index = _task_index(context.suite, context.task)
    return info | ({"task_id": index} if index is not None else {})


def observation(mapping: Mapping, message: dict[str, Any]) -> dict[str, Any]:
    """A vla-eval observation as this harness's flat observation map (state under
    "state", each camera under its key here), for the server to check (it refuses what
    is missing or misshapen)."""
    images = message.get("images")
    if not isinstance(images, dict):
        raise ValueError(f"a vla-eval observation needs an images map (keys: {sorted(map(str, message))})")
    out = {ours: images[theirs] for theirs, ours in mapping.cameras if theirs in images}
    if "states" in message:
        out["state"] = message["states"]
    return out


def observation_params(mapping: Mapping) -> dict[str, Any]:
    """What a server here asks vla-eval's benchmark for (its hello): everything this
    harness's observation has, the state unfolded as this harness gives it."""
    params: dict[str, Any] = {"send_wrist_image": True} if mapping.optional_camera else {}
    if mapping.state:
        params |= {"send_state": True, "quat_no_antipodal": True}
    return params
