"""SimplerEnv-like suites on ManiSkill3: `simpler/<task>` and `simpler/all`.

SimplerEnv evaluates one policy under a canonical scene ("visual matching") and under
perturbed variants of it ("variant aggregation"). SimplerEnv itself runs on ManiSkill2
with real-to-sim assets fetched from a hub, neither of which is possible here; ManiSkill3
(`mani-skill` on PyPI) runs here and ships its tabletop tasks' assets. These suites are
therefore **SimplerEnv-like: its protocol and metrics on ManiSkill3 tasks, not
SimplerEnv** (docs/simpler.md), and their numbers are not comparable with published
SimplerEnv rows.

Every task is a single Panda arm on ManiSkill3's table scene, driven by a 7-D delta
end-effector pose + gripper action (ManiSkill's `pd_ee_delta_pose`, normalised to
[-1, 1]: the VLA convention, as LIBERO's), with ManiSkill's own success test and step
budget. An episode is a fixed seed: ManiSkill draws the initial poses from it, so the
same spec always starts from the same layout. SAPIEN needs a Vulkan device even for
state observations; adapters/vulkan.py provides a private CPU driver.
"""

from __future__ import annotations

import importlib.util
import warnings
from dataclasses import dataclass
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from adapters.base import EpisodeSpec, Suite, SuiteInfo, TaskSpec, derive_seed
from adapters.registry import MissingExtraError, SuiteProvider, UnknownSuiteError

SUITE_VERSION = "1"
# SimplerEnv's WidowX (Bridge) tasks run 24 episodes each; ours likewise, per task, in
# the canonical setting (variant aggregation multiplies them by the variants).
EPISODES_PER_TASK = 24
TRAIN_EPISODES = 1000  # the train split's fixed seeds per task (demonstrations), disjoint
CONTROL_MODE = "pd_ee_delta_pose"
ACTION_DIM = 7


@dataclass(frozen=True)
class SimplerTask:
    """A ManiSkill3 task as this suite uses it: its id, words, and where its state dict
    holds the objects' poses and the goals' positions (world frame)."""

    name: str
    env_id: str
    instruction: str
    objects: tuple[str, ...]  # `extra` keys holding a 7-D pose (position, wxyz quaternion)
    goals: tuple[str, ...]  # `extra` keys holding a 3-D position
    max_steps: int  # ManiSkill's own max_episode_steps for the task (upstream budget)


TASKS: dict[str, SimplerTask] = {
    t.name: t
    for t in (
        SimplerTask("pick_cube", "PickCube-v1", "pick up the red cube and lift it to the goal", ("obj_pose",), ("goal_pos",), 50),
        SimplerTask("push_cube", "PushCube-v1", "push the blue cube to the target", ("obj_pose",), ("goal_pos",), 50),
        SimplerTask("pull_cube", "PullCube-v1", "pull the blue cube back to the target", ("obj_pose",), ("goal_pos",), 50),
        SimplerTask("stack_cube", "StackCube-v1", "stack the red cube on the green cube", ("cubeA_pose", "cubeB_pose"), (), 50),
        SimplerTask("place_sphere", "PlaceSphere-v1", "place the blue ball in the bin", ("obj_pose",), ("bin_pos",), 50),
    )
}  # fmt: skip
ALL = tuple(TASKS)

# The state vector: the hand, then each object's pose, then each goal's position.
PROPRIO = (("tcp_pos", 3), ("tcp_quat", 4), ("gripper", 2), ("arm_joints", 7))


def state_layout(task: SimplerTask) -> list[tuple[str, int, int]]:
    """(name, start, stop) of each field of the state vector; the expert reads it too."""
    fields = [*PROPRIO, *((k, 7) for k in task.objects), *((k, 3) for k in task.goals)]
    layout, start = [], 0
    for name, width in fields:
        layout.append((name, start, start + width))
        start += width
    return layout


def state_positions(task: SimplerTask) -> tuple[int, ...]:
    """Where the state holds world positions: the hand's, each object's, each goal's."""
    return (0, *(start for name, start, _ in state_layout(task) if name in task.objects + task.goals))


def _installed() -> bool:
    return importlib.util.find_spec("mani_skill") is not None


def _require_maniskill() -> None:
    if not _installed():
        raise MissingExtraError(
            "simpler/ suites need the 'maniskill' extra: pip install 'dvla-harness[maniskill]', then "
            "`python -m adapters.vulkan install` for a CPU Vulkan driver (docs/simpler.md)"
        )


def _numpy(value: Any) -> np.ndarray:
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    return np.asarray(value, dtype=np.float32).reshape(-1)


class ManiSkillEpisodeEnv(gym.Env):
    """One ManiSkill3 task behind the harness's env contract (adapters/base.py): a flat
    float32 state, 7-D actions, `info["success"]` from ManiSkill's own evaluation."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, task: SimplerTask):
        from adapters import vulkan

        self.task = task
        self.vulkan_driver = vulkan.activate()
        # ManiSkill runs np.isnan on a torch action every step, which numpy 2 warns about;
        # one filter for that message, not a per-step catch_warnings.
        warnings.filterwarnings(
            "ignore", message=r"__array_wrap__ must accept context", category=DeprecationWarning
        )
        import mani_skill.envs  # noqa: F401  (registers the tasks)

        try:
            self.env = gym.make(
                task.env_id,
                obs_mode="state_dict",
                control_mode=CONTROL_MODE,
                num_envs=1,
                sim_backend="physx_cpu",
                render_mode=None,
                max_episode_steps=task.max_steps,
            )
        except RuntimeError as exc:
            if "vk::" in str(exc) or "Vulkan" in str(exc):
                raise vulkan.VulkanSetupError(
                    f"SAPIEN found no usable Vulkan device ({exc}); run `python -m adapters.vulkan "
                    "install` (a private CPU driver, no system change), then `python -m adapters.vulkan check`"
                ) from None
            raise
        self.layout = state_layout(task)
        self.state_positions = state_positions(task)
        dim = self.layout[-1][2]
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (dim,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)

    def _state(self, obs: dict[str, Any]) -> np.ndarray:
        agent, extra = obs["agent"], obs["extra"]
        qpos = _numpy(agent["qpos"])
        tcp = _numpy(extra["tcp_pose"])
        w, x, y, z = tcp[3:7]
        parts = [tcp[:3], np.array([x, y, z, w], np.float32), qpos[7:9], qpos[:7]]
        for key in self.task.objects:
            pose = _numpy(extra[key])
            w, x, y, z = pose[3:7]
            parts += [pose[:3], np.array([x, y, z, w], np.float32)]
        parts += [_numpy(extra[key])[:3] for key in self.task.goals]
        return np.concatenate(parts, dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        spec: EpisodeSpec | None = (options or {}).get("episode")
        if spec is None or spec.seed is None:
            raise ValueError("reset needs options={'episode': EpisodeSpec} with a seed")
        obs, _ = self.env.reset(seed=spec.seed)
        return self._state(obs), {"success": False}

    def step(self, action):
        action = np.asarray(action, dtype=np.float32).reshape(1, ACTION_DIM)
        obs, reward, terminated, truncated, info = self.env.step(action)
        success = bool(np.asarray(_numpy(info.get("success", 0.0))).any())
        out = {"success": success}
        return (
            self._state(obs),
            float(_numpy(reward)[0]),
            bool(_numpy(terminated)[0]),
            bool(_numpy(truncated)[0]),
            out,
        )

    def close(self) -> None:
        self.env.close()


def _episodes(split: str, task: str) -> tuple[EpisodeSpec, ...]:
    count = EPISODES_PER_TASK if split == "eval" else TRAIN_EPISODES
    return tuple(EpisodeSpec(index=j, seed=derive_seed("maniskill", split, task, j)) for j in range(count))


def build_suite(name: str, task_names: tuple[str, ...], split: str = "eval") -> Suite:
    tasks = tuple(
        TaskSpec(
            name=t,
            instruction=TASKS[t].instruction,
            max_steps=TASKS[t].max_steps,
            index=i,
            episodes=_episodes(split, t),
        )
        for i, t in enumerate(task_names)
    )

    def make_env(task: TaskSpec) -> gym.Env:
        _require_maniskill()
        return ManiSkillEpisodeEnv(TASKS[task.name])

    from adapters import vulkan

    return Suite(
        name=name,
        version=SUITE_VERSION,
        tasks=tasks,
        make_env=make_env,
        description=(
            f"SimplerEnv-like on ManiSkill3 (not SimplerEnv): {len(tasks)} task(s), canonical scene, "
            "state observations, 7-D delta end-effector pose + gripper"
        ),
        extra="maniskill",
        simulator_packages=("mani_skill", "sapien"),
        provenance={"vulkan_driver": vulkan.describe()},
    )


def load_suite(name: str, split: str = "eval") -> Suite:
    tail = name.removeprefix("simpler/")
    if tail == "all":
        return build_suite(name, ALL, split)
    if tail in TASKS:
        return build_suite(name, (tail,), split)
    raise UnknownSuiteError(
        f"unknown suite {name!r}; SimplerEnv-like suites: simpler/all, "
        + ", ".join(f"simpler/{t}" for t in TASKS)
    )


def list_suites() -> list[SuiteInfo]:
    installed = _installed()
    rows = [("simpler/all", "SimplerEnv-like on ManiSkill3: five tabletop tasks", len(TASKS))]
    rows += [(f"simpler/{t.name}", f"SimplerEnv-like: {t.instruction}", 1) for t in TASKS.values()]
    return [SuiteInfo(n, d, k, EPISODES_PER_TASK, "maniskill", installed) for n, d, k in rows]


PROVIDER = SuiteProvider(prefix="simpler/", list_suites=list_suites, load_suite=load_suite)
