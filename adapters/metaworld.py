"""Meta-World v3 suites: `metaworld/mt1/<task>`, `metaworld/mt10`, `metaworld/mt50`.

Episode protocol: Meta-World's own benchmark object (`metaworld.MT1(task, seed)`)
draws 50 object/goal layouts per task from one seed; episode i starts from layout i,
like LIBERO's fixed initial states. The layout seed is derived from ("metaworld",
split, task), not from the suite name, so `mt1/reach-v3` and `mt10` evaluate the same
reach layouts, and demonstrations collected on the "train" split never share a layout
with evaluation ("eval").

Evaluation keeps the protocol's 50 layouts per task. The train split offers
TRAIN_LAYOUT_SETS x 50: episode j draws layout j % 50 of set j // 50, so a policy
trained on more than 50 demonstrations per task sees new goal and object positions
instead of repeats (the goal-conditioned tasks fail at the edge of what was seen).
Set 0 is the seed the train split always had, so earlier demonstrations stay
reproducible.

Meta-World does not end an episode on success; the runner does.
"""

from __future__ import annotations

import importlib.util
from typing import Any

import gymnasium as gym

from adapters.base import EpisodeSpec, Suite, SuiteInfo, TaskSpec, derive_seed
from adapters.registry import MissingExtraError, SuiteProvider, UnknownSuiteError

SUITE_VERSION = "1"
MAX_STEPS = 500  # Meta-World's max_path_length for every v3 task.
LAYOUTS_PER_TASK = 50  # metaworld._N_GOALS: layouts drawn per task and seed.
TRAIN_LAYOUT_SETS = 20  # train split only: up to 1,000 distinct layouts per task.

# Every v3 task with an English instruction (Meta-World ships names only).
INSTRUCTIONS: dict[str, str] = {
    "assembly-v3": "put the ring on the peg",
    "basketball-v3": "dunk the ball into the basket",
    "bin-picking-v3": "move the cube from one bin to the other",
    "box-close-v3": "put the lid on the box",
    "button-press-topdown-v3": "press the button from the top",
    "button-press-topdown-wall-v3": "press the button from the top behind the wall",
    "button-press-v3": "press the button",
    "button-press-wall-v3": "press the button behind the wall",
    "coffee-button-v3": "push the button on the coffee machine",
    "coffee-pull-v3": "pull the mug away from the coffee machine",
    "coffee-push-v3": "push the mug under the coffee machine",
    "dial-turn-v3": "turn the dial",
    "disassemble-v3": "pick the ring off the peg",
    "door-close-v3": "close the door",
    "door-lock-v3": "lock the door by turning the lock",
    "door-open-v3": "open the door",
    "door-unlock-v3": "unlock the door by turning the lock",
    "hand-insert-v3": "insert the hand into the hole",
    "drawer-close-v3": "close the drawer",
    "drawer-open-v3": "open the drawer",
    "faucet-open-v3": "turn the faucet on",
    "faucet-close-v3": "turn the faucet off",
    "hammer-v3": "hammer the nail into the wall",
    "handle-press-side-v3": "press the handle down from the side",
    "handle-press-v3": "press the handle down",
    "handle-pull-side-v3": "pull the handle up from the side",
    "handle-pull-v3": "pull the handle up",
    "lever-pull-v3": "pull the lever up",
    "pick-place-wall-v3": "pick up the puck and place it at the goal behind the wall",
    "pick-out-of-hole-v3": "pick the peg out of the hole",
    "pick-place-v3": "pick up the puck and place it at the goal",
    "plate-slide-v3": "slide the plate into the cabinet",
    "plate-slide-side-v3": "slide the plate into the cabinet from the side",
    "plate-slide-back-v3": "slide the plate out of the cabinet",
    "plate-slide-back-side-v3": "slide the plate out of the cabinet to the side",
    "peg-insert-side-v3": "insert the peg into the hole from the side",
    "peg-unplug-side-v3": "unplug the peg from the side",
    "soccer-v3": "kick the ball into the goal",
    "stick-push-v3": "grasp the stick and push the box with it",
    "stick-pull-v3": "grasp the stick and pull the box with it",
    "push-v3": "push the puck to the goal",
    "push-wall-v3": "push the puck to the goal behind the wall",
    "push-back-v3": "push the puck back to the goal",
    "reach-v3": "reach the goal position",
    "reach-wall-v3": "reach the goal position behind the wall",
    "shelf-place-v3": "place the puck on the shelf",
    "sweep-into-v3": "sweep the puck into the hole",
    "sweep-v3": "sweep the puck off the table",
    "window-open-v3": "slide the window open",
    "window-close-v3": "slide the window closed",
}

# metaworld.env_dict.MT10_V3, in Meta-World's order.
MT10 = (
    "reach-v3",
    "push-v3",
    "pick-place-v3",
    "door-open-v3",
    "drawer-open-v3",
    "drawer-close-v3",
    "button-press-topdown-v3",
    "peg-insert-side-v3",
    "window-open-v3",
    "window-close-v3",
)
MT50 = tuple(INSTRUCTIONS)


def _installed() -> bool:
    return importlib.util.find_spec("metaworld") is not None


def _require_metaworld() -> None:
    if not _installed():
        raise MissingExtraError(
            "Meta-World suites need the 'metaworld' extra: pip install 'dvla-harness[metaworld]'"
        )


class MetaWorldEpisodeEnv(gym.Wrapper):
    """One Meta-World task whose `reset` honours the episode spec (seed + layout id)."""

    # Meta-World v3's 39-D observation: hand position (0:3), gripper opening (3), two
    # objects' position + quaternion (4:11, 11:18; zeros where a task has one), the
    # previous frame's 18 (18:36), the goal position (36:39). World frame throughout.
    state_positions = (0, 4, 11, 36)

    def __init__(self, task_name: str):
        import metaworld.env_dict

        super().__init__(metaworld.env_dict.ALL_V3_ENVIRONMENTS[task_name]())
        self.task_name = task_name
        self._layouts: dict[int, list[Any]] = {}

    def _layout(self, seed: int, layout_id: int) -> Any:
        import metaworld

        if seed not in self._layouts:
            self._layouts[seed] = metaworld.MT1(self.task_name, seed=seed).train_tasks
        layouts = self._layouts[seed]
        if not 0 <= layout_id < len(layouts):
            raise ValueError(f"layout id {layout_id} outside 0..{len(layouts) - 1}")
        return layouts[layout_id]

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        spec: EpisodeSpec | None = (options or {}).get("episode")
        if spec is None:
            raise ValueError("reset needs options={'episode': EpisodeSpec}")
        assert spec.seed is not None and spec.init_state_id is not None
        self.env.unwrapped.set_task(self._layout(spec.seed, spec.init_state_id))
        obs, info = self.env.reset()
        info["success"] = False
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        info["success"] = bool(info.get("success", 0.0))
        return obs, reward, terminated, truncated, info


def _make_env(task: TaskSpec) -> gym.Env:
    _require_metaworld()
    env = MetaWorldEpisodeEnv(task.name)
    if task.episodes:  # draw the layouts now, so no episode's wall-clock pays for them
        env._layout(task.episodes[0].seed, 0)
    return env


def _layout_seed(split: str, task: str, layout_set: int) -> int:
    if layout_set == 0:
        return derive_seed("metaworld", split, task)
    return derive_seed("metaworld", split, task, layout_set)


def build_suite(name: str, task_names: tuple[str, ...], split: str = "eval") -> Suite:
    tasks = tuple(
        TaskSpec(
            name=task,
            instruction=INSTRUCTIONS[task],
            max_steps=MAX_STEPS,
            index=i,
            episodes=tuple(
                EpisodeSpec(
                    index=j,
                    seed=_layout_seed(split, task, j // LAYOUTS_PER_TASK),
                    init_state_id=j % LAYOUTS_PER_TASK,
                )
                for j in range(LAYOUTS_PER_TASK * (TRAIN_LAYOUT_SETS if split == "train" else 1))
            ),
        )
        for i, task in enumerate(task_names)
    )
    return Suite(
        name=name,
        version=SUITE_VERSION,
        tasks=tasks,
        make_env=_make_env,
        description=f"Meta-World v3, {len(tasks)} task(s), state observations (39-D), 4-D actions",
        extra="metaworld",
        simulator_packages=("metaworld", "mujoco"),
    )


def _suite_tasks(name: str) -> tuple[str, ...]:
    if name == "metaworld/mt10":
        return MT10
    if name == "metaworld/mt50":
        return MT50
    if name.startswith("metaworld/mt1/"):
        task = name.removeprefix("metaworld/mt1/")
        if task in INSTRUCTIONS:
            return (task,)
        raise UnknownSuiteError(
            f"unknown Meta-World task {task!r} in {name!r}; valid tasks: {', '.join(MT50)}"
        )
    raise UnknownSuiteError(
        f"unknown suite {name!r}; Meta-World suites: metaworld/mt10, metaworld/mt50, "
        "metaworld/mt1/<task> (see `dvla-harness list tasks metaworld/mt50`)"
    )


def load_suite(name: str, split: str = "eval") -> Suite:
    return build_suite(name, _suite_tasks(name), split)


def list_suites() -> list[SuiteInfo]:
    installed = _installed()
    rows = [
        ("metaworld/mt10", "Meta-World MT10: ten manipulation tasks", len(MT10)),
        ("metaworld/mt50", "Meta-World MT50: all fifty v3 tasks", len(MT50)),
        ("metaworld/mt1/<task>", "one Meta-World task, e.g. metaworld/mt1/reach-v3", 1),
    ]
    return [SuiteInfo(name, desc, n, LAYOUTS_PER_TASK, "metaworld", installed) for name, desc, n in rows]


PROVIDER = SuiteProvider(prefix="metaworld/", list_suites=list_suites, load_suite=load_suite)
