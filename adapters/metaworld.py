"""Meta-World v3 suites: `metaworld/mt1/<task>`, `metaworld/mt10`, `metaworld/mt50`.

Two layout modes, a suite option like LIBERO's (docs/metaworld.md has the whole story):

`layouts=fixed` (the default; the suite name carries no option): Meta-World's own
benchmark object (`metaworld.MT1(task, seed)`) draws 50 object/goal layouts per task
from one seed; episode i starts from layout i, like LIBERO's fixed initial states. The
layout seed is derived from ("metaworld", split, task), not from the suite name, so
`mt1/reach-v3` and `mt10` evaluate the same reach layouts, and demonstrations collected
on the "train" split never share a layout with evaluation ("eval").

`layouts=upstream,seed=S` (e.g. `metaworld/mt10:layouts=upstream,seed=1`; seed 1 when
not given): exactly what Meta-World's own evaluation gives for `gym.make_vec(
"Meta-World/MT10", seed=S)` (MT50, MT1 alike). The layouts are `metaworld.MT10(seed=S)`'s
(all tasks' layouts drawn from one stream), and every reset picks one of the task's 50
at random with replacement (`RandomTaskSelectWrapper`, its env seeded with S). Those
picks are replayed from S when the suite is built, so episode j knows its layout
without running episodes 0..j-1. The train split stays the fixed mode's.

The train split offers TRAIN_LAYOUT_SETS x 50: episode j draws layout j % 50 of set
j // 50, so a policy trained on more than 50 demonstrations per task sees new goal and
object positions instead of repeats (the goal-conditioned tasks fail at the edge of what
was seen). Set 0 is the seed the train split always had, so earlier demonstrations stay
reproducible.

Meta-World does not end an episode on success; the runner does (as Meta-World's
evaluation does, with `terminate_on_success`).
"""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import gymnasium as gym
from gymnasium.utils import seeding

from adapters.base import (
    EpisodeSpec,
    MissingExtraError,
    Suite,
    SuiteInfo,
    SuiteOptionError,
    SuiteProvider,
    TaskSpec,
    UnknownSuiteError,
    derive_seed,
    refuse_repeated_options,
)
from harness.plugins import install_hint

SUITE_VERSION = "1"
MAX_STEPS = 500  # Meta-World's max_path_length for every v3 task.
LAYOUTS_PER_TASK = 50  # metaworld._N_GOALS: layouts drawn per task and seed.
TRAIN_LAYOUT_SETS = 20  # train split only: up to 1,000 distinct layouts per task.
# layouts=upstream: the seed when none is given, the default of the code behind Meta-World+'s
# published numbers (metaworld-algorithms: `MetaworldConfig.spawn(seed=1)`, its examples' seed).
DEFAULT_UPSTREAM_SEED = 1
UPSTREAM_EPISODES = 50  # metaworld.evaluation.evaluation(num_episodes=50), per task
MAX_SEED = 2**32 - 1  # np.random.seed's bound (metaworld._make_tasks seeds the global RNG)
VIDEO_CAMERA, VIDEO_SIZE = "corner", 256  # rollout videos (MetaWorldEpisodeEnv.video_frame)

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


@dataclass(frozen=True)
class Options:
    """`layouts=fixed` (our layout i for episode i) or `layouts=upstream,seed=S`."""

    layouts: str = "fixed"
    seed: int | None = None  # upstream only; DEFAULT_UPSTREAM_SEED when not given

    def suffix(self) -> str:
        """The canonical option string: empty for fixed, mode and seed for upstream."""
        return f":layouts=upstream,seed={self.seed}" if self.layouts == "upstream" else ""


_OPTIONS_HELP = "valid options: layouts=fixed|upstream, seed=N (upstream only)"


def parse_options(text: str) -> Options:
    refuse_repeated_options(text)
    values: dict[str, Any] = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        key, eq, value = (s.strip() for s in item.partition("="))
        if not eq:
            raise SuiteOptionError(f"suite option {item!r}: expected key=value; {_OPTIONS_HELP}")
        if key == "layouts":
            if value not in ("fixed", "upstream"):
                raise SuiteOptionError(f"suite option layouts={value!r}: choose fixed or upstream")
            values[key] = value
        elif key == "seed":
            if not (value.isascii() and value.isdigit()) or int(value) > MAX_SEED:
                raise SuiteOptionError(f"suite option seed={value!r}: expected an integer in [0, {MAX_SEED}]")
            values[key] = int(value)
        else:
            raise SuiteOptionError(f"unknown suite option {key!r}; {_OPTIONS_HELP}")
    layouts = values.get("layouts", "fixed")
    if layouts == "fixed":
        if "seed" in values:
            raise SuiteOptionError(
                "suite option seed= applies to layouts=upstream; fixed layouts derive their seeds "
                "from the task name (e.g. metaworld/mt10:layouts=upstream,seed=1)"
            )
        return Options()
    return Options("upstream", values.get("seed", DEFAULT_UPSTREAM_SEED))


def upstream_layout_ids(seed: int, episodes: int = UPSTREAM_EPISODES) -> tuple[int, ...]:
    """The layout each of the first `episodes` resets picks in Meta-World's evaluation.

    `metaworld._init_each_env` seeds every task's env with the benchmark seed
    (`SawyerXYZEnv.seed`: `gymnasium.utils.seeding.np_random(seed)`), and on each reset
    `RandomTaskSelectWrapper._set_random_task` draws `np_random.choice(len(tasks))`; nothing
    else draws from that generator (layouts are frozen once set). Replaying the draws here
    gives episode j's layout without running resets 0..j-1. The same for every task of a
    benchmark: all its envs get the same seed.
    """
    rng, _ = seeding.np_random(seed)
    return tuple(int(rng.choice(LAYOUTS_PER_TASK)) for _ in range(episodes))


@lru_cache(maxsize=64)
def _mt1_layouts(task: str, seed: int) -> tuple[Any, ...]:
    """Meta-World's own `MT1(task, seed=...)`: the task's 50 layouts, in order."""
    import metaworld

    return tuple(metaworld.MT1(task, seed=seed).train_tasks)


@lru_cache(maxsize=2)
def _benchmark_layouts(benchmark: str, seed: int) -> dict[str, tuple[Any, ...]]:
    """Meta-World's own `MT10(seed=...)` / `MT50(seed=...)`: each task's 50 layouts, in order."""
    import metaworld

    layouts: dict[str, list[Any]] = {}
    for task in getattr(metaworld, benchmark)(seed=seed).train_tasks:
        layouts.setdefault(task.env_name, []).append(task)
    return {name: tuple(tasks) for name, tasks in layouts.items()}


def _installed() -> bool:
    return importlib.util.find_spec("metaworld") is not None


def _require_metaworld() -> None:
    if not _installed():
        raise MissingExtraError(f"Meta-World suites need the 'metaworld' extra: {install_hint('metaworld')}")


class MetaWorldEpisodeEnv(gym.Wrapper):
    """One Meta-World task whose `reset` honours the episode spec (seed + layout id).

    `benchmark` says which of Meta-World's benchmark objects the spec's seed builds:
    "MT1" (`MT1(task, seed)`, fixed layouts and mt1 upstream), "MT10" or "MT50" (the whole
    benchmark from one seed, upstream layouts).
    """

    # Meta-World v3's 39-D observation: hand position (0:3), gripper opening (3), two
    # objects' position + quaternion (4:11, 11:18; zeros where a task has one), the
    # previous frame's 18 (18:36), the goal position (36:39). World frame throughout.
    state_positions = (0, 4, 11, 36)
    proprio_dim = 4  # hand position and gripper opening

    def __init__(self, task_name: str, benchmark: str = "MT1"):
        import metaworld.env_dict

        super().__init__(metaworld.env_dict.ALL_V3_ENVIRONMENTS[task_name]())
        self.task_name = task_name
        self.benchmark = benchmark
        # Meta-World computes its observation space once, while the goal is still hidden
        # (bounds 0 for 36:39), then reveals the goal in every observation (set_task makes
        # the task fully observable): the space must say what the env returns. Found by
        # `dvla-harness check suite`.
        space, goal = self.env.observation_space, self.env.unwrapped.goal_space
        low, high = space.low.copy(), space.high.copy()
        low[36:39], high[36:39] = goal.low, goal.high
        self.observation_space = gym.spaces.Box(low, high, dtype=space.dtype)

    def layouts(self, seed: int) -> tuple[Any, ...]:
        """The task's 50 layouts (`metaworld.Task`s) that `seed` draws, in Meta-World's order
        (computed once per process: MT1 takes ~0.5 s, MT10 ~6 s, MT50 ~30 s on a 2-core CPU)."""
        if self.benchmark == "MT1":
            return _mt1_layouts(self.task_name, seed)
        return _benchmark_layouts(self.benchmark, seed)[self.task_name]

    def _layout(self, seed: int, layout_id: int) -> Any:
        layouts = self.layouts(seed)
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

    def video_frame(self) -> Any:
        """The scene from Meta-World's `corner` camera, VIDEO_SIZE px square, for rollout
        videos (harness/episode/video.py). A renderer of its own (offscreen: EGL or OSMesa)
        reads the simulator's state and steps nothing; shadows and reflections are off (on
        a CPU they cost 5x the frame time and show nothing about the task)."""
        if getattr(self, "_video", None) is None:
            import mujoco

            from adapters.libero_sim import offscreen_renderer

            renderer = offscreen_renderer(self.env.unwrapped.model, VIDEO_SIZE)
            for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION):
                renderer.scene.flags[flag] = False
            self._video = renderer
        self._video.update_scene(self.env.unwrapped.data, camera=VIDEO_CAMERA)
        return self._video.render()[::-1]  # the corner camera is mounted upside down

    def close(self) -> None:
        if getattr(self, "_video", None) is not None:
            self._video.close()
            self._video = None
        super().close()


def _layout_seed(split: str, task: str, layout_set: int) -> int:
    if layout_set == 0:
        return derive_seed("metaworld", split, task)
    return derive_seed("metaworld", split, task, layout_set)


def _fixed_episodes(split: str, task: str) -> tuple[EpisodeSpec, ...]:
    return tuple(
        EpisodeSpec(
            index=j,
            seed=_layout_seed(split, task, j // LAYOUTS_PER_TASK),
            init_state_id=j % LAYOUTS_PER_TASK,
        )
        for j in range(LAYOUTS_PER_TASK * (TRAIN_LAYOUT_SETS if split == "train" else 1))
    )


def _check_disjoint_from_train(seed: int, task_names: tuple[str, ...]) -> None:
    """Refuse an upstream seed that is a train-split layout seed: `MT1(task, seed)` and the
    first task of `MT10/MT50(seed)` would then be the demonstrations' own layouts.

    Any other seed gives none in practice: a benchmark draws its layouts from one
    `np.random.seed(seed)` stream (MT19937), so the first task's layouts equal a train set's
    only for the same seed, and the later tasks' come from the middle of that stream, where
    a freshly seeded one would have to land on the same state."""
    for task in task_names:
        for layout_set in range(TRAIN_LAYOUT_SETS):
            if _layout_seed("train", task, layout_set) == seed:
                raise SuiteOptionError(
                    f"suite option seed={seed}: that is the train split's layout seed for {task} "
                    f"(set {layout_set}), so evaluation would start from the demonstrations' layouts; "
                    "choose another seed"
                )


def build_suite(
    name: str, task_names: tuple[str, ...], split: str = "eval", options: Options | None = None
) -> Suite:
    options = options or Options()
    upstream = options.layouts == "upstream" and split == "eval"
    if options.layouts == "upstream":
        assert options.seed is not None
        _check_disjoint_from_train(options.seed, task_names)
        # MT1(task, seed) for one task, else the whole benchmark from the one seed
        benchmark = "MT1" if name.startswith("metaworld/mt1/") else name.removeprefix("metaworld/").upper()
        picks = upstream_layout_ids(options.seed)
    else:
        benchmark = "MT1"

    def episodes(task: str) -> tuple[EpisodeSpec, ...]:
        if upstream:
            return tuple(
                EpisodeSpec(index=j, seed=options.seed, init_state_id=k) for j, k in enumerate(picks)
            )
        return _fixed_episodes(split, task)

    tasks = tuple(
        TaskSpec(
            name=task,
            instruction=INSTRUCTIONS[task],
            max_steps=MAX_STEPS,
            index=i,
            episodes=episodes(task),
        )
        for i, task in enumerate(task_names)
    )

    def make_env(task: TaskSpec) -> gym.Env:
        _require_metaworld()
        # the train split of an upstream suite is the fixed mode's, MT1 per layout seed
        env = MetaWorldEpisodeEnv(task.name, benchmark if upstream else "MT1")
        if task.episodes:  # draw the layouts now, so no episode's wall-clock pays for them
            env.layouts(task.episodes[0].seed)
        return env

    if upstream:
        mode = f"layouts as Meta-World's evaluation picks them ({benchmark}, seed {options.seed})"
    else:
        mode = "fixed layouts" if split == "eval" else "train-split layouts"
    return Suite(
        name=name + options.suffix(),
        version=SUITE_VERSION,
        tasks=tasks,
        make_env=make_env,
        description=f"Meta-World v3, {len(tasks)} task(s), {mode}, state observations (39-D), 4-D actions",
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
        "metaworld/mt1/<task> (see `dvla-harness list tasks metaworld/mt50`; "
        "option: metaworld/mt10:layouts=upstream,seed=1)"
    )


def load_suite(name: str, split: str = "eval") -> Suite:
    """`metaworld/<suite>[:layouts=fixed|upstream[,seed=S]]`; see the module docstring."""
    base, _, opts = name.partition(":")
    return build_suite(base, _suite_tasks(base), split, parse_options(opts))


def list_suites() -> list[SuiteInfo]:
    installed = _installed()
    rows = [
        ("metaworld/mt10", "Meta-World MT10: ten manipulation tasks", len(MT10)),
        ("metaworld/mt50", "Meta-World MT50: all fifty v3 tasks", len(MT50)),
        ("metaworld/mt1/<task>", "one Meta-World task, e.g. metaworld/mt1/reach-v3", 1),
        # every Meta-World suite also takes :layouts=upstream[,seed=S] (docs/metaworld.md)
    ]
    return [SuiteInfo(name, desc, n, LAYOUTS_PER_TASK, "metaworld", installed) for name, desc, n in rows]


PROVIDER = SuiteProvider(prefix="metaworld/", list_suites=list_suites, load_suite=load_suite)
