"""SimplerEnv-like suites on ManiSkill3: `simpler/<task>` and `simpler/all`.

SimplerEnv evaluates one policy in "visual matching" (real images overlaid on the
simulator) and under perturbed variants of its scenes ("variant aggregation"). Here the
reference is ManiSkill3's canonical scene, which is not visual matching. SimplerEnv itself runs on ManiSkill2
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
import logging
import warnings
from dataclasses import dataclass
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from adapters import simpler_variants as sv
from adapters.base import (
    EpisodeSpec,
    MissingExtraError,
    Suite,
    SuiteInfo,
    SuiteProvider,
    TaskSpec,
    UnknownSuiteError,
    derive_seed,
    refuse_repeated_options,
)
from harness.plugins import install_hint

SUITE_VERSION = "1"
# SimplerEnv's WidowX (Bridge) tasks run 24 episodes each; ours likewise, per task, in
# the canonical setting (variant aggregation multiplies them by the variants).
EPISODES_PER_TASK = 24
TRAIN_EPISODES = 1000  # the train split's fixed seeds per task (demonstrations), disjoint
CONTROL_MODE = "pd_ee_delta_pose"
DISTRACTOR_HALF = 0.02  # m; the size of ManiSkill's task cubes
# Distractors stand in the workspace, beside the task's objects (as SimplerEnv's stand
# among its objects), on a 2.5 cm grid over the table's reachable area, each at the free
# point nearest the first task object: at least DISTRACTOR_CLEARANCE from every object,
# goal and the straight paths between them (so no push is blocked outright, nothing
# overlaps at reset), and 2 * DISTRACTOR_HALF + 2 cm from one another.
DISTRACTOR_GRID = np.stack(
    np.meshgrid(np.arange(-0.2, 0.2001, 0.025), np.arange(-0.2, 0.2001, 0.025), indexing="ij"), axis=-1
).reshape(-1, 2)
DISTRACTOR_CLEARANCE = 0.09  # m, centre to the nearest object, goal or path
CAMERA = "base_camera"  # ManiSkill's camera for these tasks
DEFAULT_IMAGE_SIZE = 128  # ManiSkill3's own base_camera size for these tasks
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
            f"simpler/ suites need the 'maniskill' extra: {install_hint('maniskill')}, then "
            "`python -m adapters.vulkan install` for a CPU Vulkan driver (docs/simpler.md)"
        )


def _quiet(record: logging.LogRecord) -> bool:
    """Drop ManiSkill's notices that it renders on the CPU for want of CUDA, and that its
    PushCube/PullCube goal marker has no initial pose (printed at every scene rebuild);
    SAPIEN's fallback to its own Vulkan loader is a Python warning, filtered beside it."""
    return not any(note in record.getMessage() for note in ("sapien_cuda", "No initial pose set"))


def _numpy(value: Any) -> np.ndarray:
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    return np.asarray(value, dtype=np.float32).reshape(-1)


class ManiSkillEpisodeEnv(gym.Env):
    """One ManiSkill3 task behind the harness's env contract (adapters/base.py): a flat
    float32 state, 7-D actions, `info["success"]` from ManiSkill's own evaluation."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, task: SimplerTask, obs: str = "state", image_size: int = DEFAULT_IMAGE_SIZE):
        from adapters import vulkan

        self.task = task
        self.vulkan_driver = vulkan.activate()
        # ManiSkill runs np.isnan on a torch action every step, which numpy 2 warns about;
        # one filter for that message, not a per-step catch_warnings.
        warnings.filterwarnings(
            "ignore", message=r"__array_wrap__ must accept context", category=DeprecationWarning
        )
        # Notices that are expected on a CPU machine and say nothing about a run (_quiet).
        warnings.filterwarnings("ignore", message=r"Failed to find system libvulkan", category=UserWarning)
        from mani_skill.utils.logging_utils import logger as maniskill_logger

        maniskill_logger.addFilter(_quiet)  # the same function each time: added once
        import mani_skill.envs  # noqa: F401  (registers the tasks)

        try:
            cameras = {"sensor_configs": {CAMERA: {"width": image_size, "height": image_size}}}
            self.env = gym.make(
                task.env_id,
                obs_mode="state_dict" if obs == "state" else "state_dict+rgb",
                **(cameras if obs == "images" else {}),
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
        self.proprio_dim = sum(width for _, width in PROPRIO)  # the robot's own, leading
        self.variant = sv.CANONICAL_VARIANT  # what the scene holds now (distractors read it)
        scene_loader = self.env.unwrapped._load_scene

        def load_scene(options: dict) -> None:  # distractors are built with the scene
            scene_loader(options)
            self._build_distractors()

        self.env.unwrapped._load_scene = load_scene
        dim = self.layout[-1][2]
        self.images = obs == "images"
        state_space = gym.spaces.Box(-np.inf, np.inf, (dim,), np.float32)
        pixels = gym.spaces.Box(0, 255, (image_size, image_size, 3), np.uint8)
        self.observation_space = (
            gym.spaces.Dict({"state": state_space, CAMERA: pixels}) if self.images else state_space
        )
        self.action_space = gym.spaces.Box(-1.0, 1.0, (ACTION_DIM,), np.float32)

    def video_frame(self) -> np.ndarray:
        """ManiSkill3's human render camera (its task's `render_camera`), for rollout videos
        (harness/episode/video.py): a capture of the scene as it is, which steps nothing."""
        frame = self.env.unwrapped.render_rgb_array()
        if hasattr(frame, "detach"):
            frame = frame.detach().cpu().numpy()
        return np.asarray(frame, dtype=np.uint8).reshape(frame.shape[-3:])

    def _observation(self, obs: dict[str, Any]) -> Any:
        state = self._state(obs)
        if not self.images:
            return state
        rgb = obs["sensor_data"][CAMERA]["rgb"]
        return {"state": state, CAMERA: np.asarray(rgb.cpu().numpy()[0], dtype=np.uint8)}

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
        variant = sv.of_spec(spec.variant) or sv.CANONICAL_VARIANT
        self.variant = variant
        # Every episode rebuilds the scene from ManiSkill's canonical one (about 0.3 s).
        # Measured: after a plain reset, PhysX's contact state from the previous episode
        # carries over, and 29 of 50 expert episodes replayed in one env diverged from
        # their first run within ~10 steps (a few even changed outcome); rebuilt, 0 of 50.
        # It also means nothing a variant level changed can leak into the next episode.
        obs, _ = self.env.reset(seed=spec.seed, options={"reconfigure": True})
        if variant != sv.CANONICAL_VARIANT:
            self._apply(variant, obs)  # a level scales what it finds: once, on the fresh scene
            obs = self.env.unwrapped.get_obs()  # cameras see the level from the first step
        return self._observation(obs), {"success": False, "variant": variant.label}

    # --- variants ------------------------------------------------------------------

    def _level(self, axis: str) -> dict[str, Any] | None:
        if self.variant.axis != axis:
            return None
        return sv.axes()[axis].levels[self.variant.level]

    def _build_distractors(self) -> None:
        import sapien

        level = self._level("distractors")
        if level is None:
            return
        scene = self.env.unwrapped.scene
        for i, rgba in enumerate(level["colors"]):
            builder = scene.create_actor_builder()
            builder.add_box_collision(half_size=[DISTRACTOR_HALF] * 3)
            builder.add_box_visual(
                half_size=[DISTRACTOR_HALF] * 3, material=sapien.render.RenderMaterial(base_color=rgba)
            )
            # parked off the table until the layout is known (_place_distractors)
            builder.initial_pose = sapien.Pose(p=[0.0, 2.0 + 0.1 * i, DISTRACTOR_HALF])
            builder.build(name=f"distractor_{i}")

    def _place_distractors(self, obs: dict[str, Any]) -> None:
        """Move the level's distractors beside this layout's objects (DISTRACTOR_GRID)."""
        import sapien

        extra = obs["extra"]
        points = [_numpy(extra[key])[:2] for key in (*self.task.objects, *self.task.goals)]
        spots = [
            a + (b - a) * t
            for i, a in enumerate(points)
            for b in points[i + 1 :]
            for t in np.linspace(0, 1, 9)
        ]
        keep_off = np.array([*points, *spots])
        placed: list[np.ndarray] = []
        actors = self.env.unwrapped.scene.actors
        for name in sorted(n for n in actors if n.startswith("distractor_")):
            free = np.min(np.linalg.norm(DISTRACTOR_GRID[:, None] - keep_off[None], axis=2), axis=1)
            ok = free >= DISTRACTOR_CLEARANCE
            if placed:
                apart = np.min(
                    np.linalg.norm(DISTRACTOR_GRID[:, None] - np.array(placed)[None], axis=2), axis=1
                )
                ok &= apart >= 2 * DISTRACTOR_HALF + 0.02
            if not ok.any():
                raise RuntimeError(f"{self.task.name}: no free spot on the table for {name}")
            near = np.linalg.norm(DISTRACTOR_GRID - points[0], axis=1)
            spot = DISTRACTOR_GRID[np.flatnonzero(ok)[np.argmin(near[ok])]]
            actors[name].set_pose(sapien.Pose(p=[float(spot[0]), float(spot[1]), DISTRACTOR_HALF]))
            placed.append(spot)

    def _task_bodies(self) -> list[Any]:
        """The physx bodies of the task's objects (not the table, ground, goal markers or distractors)."""
        import sapien

        out = []
        for name, actor in self.env.unwrapped.scene.actors.items():
            if name.startswith("distractor_"):
                continue
            for obj in actor._objs:
                body = obj.find_component_by_type(sapien.physx.PhysxRigidDynamicComponent)
                if body is not None and not body.kinematic:
                    out.append(body)
        return out

    def _recolour(self, actor: str, rgba: list[float]) -> None:
        """One flat colour on an actor's every render part, its texture removed."""
        import sapien

        for obj in self.env.unwrapped.scene.actors[actor]._objs:
            body = obj.find_component_by_type(sapien.render.RenderBodyComponent)
            for shape in body.render_shapes:
                for part in shape.parts:
                    part.material.base_color_texture = None
                    part.material.base_color = rgba

    def _apply(self, variant: sv.Variant, obs: dict[str, Any]) -> None:
        """Set one axis to its level on a freshly built canonical scene (obs: its first
        observation, where the layout's objects are)."""
        import sapien

        level = sv.axes()[variant.axis].levels[variant.level]
        unwrapped = self.env.unwrapped
        scene = unwrapped.scene
        if variant.axis == "lighting":
            scene.set_ambient_light(level["ambient"])
            for sub in scene.sub_scenes:
                for entity in sub.entities:
                    for c in entity.components:
                        if isinstance(c, sapien.render.RenderDirectionalLightComponent):
                            c.color = level["directional"]
        elif variant.axis == "table":
            self._recolour("table-workspace", level["rgba"])
        elif variant.axis == "background":
            self._recolour("ground", level["rgba"])  # the floor around the table, the frame's top
        elif variant.axis == "distractors":
            self._place_distractors(obs)  # built with the scene (_build_distractors)
        elif variant.axis == "camera":
            for sensor in unwrapped._sensors.values():
                pose = sensor.camera.get_local_pose()
                raw = pose.raw_pose[0].cpu().numpy()
                sensor.camera.set_local_pose(sapien.Pose(p=raw[:3] + np.asarray(level["offset"]), q=raw[3:]))
        elif variant.axis == "friction":
            for body in self._task_bodies():
                for shape in body.collision_shapes:
                    m = shape.physical_material
                    scale = level["scale"]
                    shape.set_physical_material(
                        sapien.physx.PhysxMaterial(
                            m.static_friction * scale, m.dynamic_friction * scale, m.restitution
                        )
                    )
        elif variant.axis == "mass":
            for body in self._task_bodies():
                body.mass = body.mass * level["scale"]

    def step(self, action):
        action = np.asarray(action, dtype=np.float32).reshape(1, ACTION_DIM)
        obs, reward, terminated, truncated, info = self.env.step(action)
        success = bool(np.asarray(_numpy(info.get("success", 0.0))).any())
        out = {"success": success}
        return (
            self._observation(obs),
            float(_numpy(reward)[0]),
            bool(_numpy(terminated)[0]),
            bool(_numpy(truncated)[0]),
            out,
        )

    def close(self) -> None:
        self.env.close()


def variant_number(variant: sv.Variant) -> int:
    """0 for the canonical scene, then 1, 2, ... in the variants file's order: fixed, so an
    episode's index does not depend on which variants a run selected."""
    return 0 if variant == sv.CANONICAL_VARIANT else 1 + sv.all_variants().index(variant)


def _episodes(split: str, task: str, variants: tuple[sv.Variant, ...]) -> tuple[EpisodeSpec, ...]:
    """Episode j of variant v has index v * count + j and episode j's seed (its layout):
    every variant replays the canonical layouts."""
    count = EPISODES_PER_TASK if split == "eval" else TRAIN_EPISODES
    return tuple(
        EpisodeSpec(
            index=variant_number(v) * count + j,
            seed=derive_seed("maniskill", split, task, j),
            variant=v.as_spec(),
        )
        for v in variants
        for j in range(count)
    )


@dataclass(frozen=True)
class Options:
    variants: sv.Selection = sv.CANONICAL_SELECTION
    obs: str = "state"  # state | images (state + the base camera's RGB)
    image_size: int = DEFAULT_IMAGE_SIZE

    def suffix(self) -> str:
        """The options not at their defaults, in one order: what the suite name records."""
        parts = []
        if self.variants.name != sv.CANONICAL:
            parts.append(f"variants={self.variants.name}")
        if self.obs != "state":
            parts.append(f"obs={self.obs}")
        if self.image_size != DEFAULT_IMAGE_SIZE:
            parts.append(f"image_size={self.image_size}")
        return ":" + ",".join(parts) if parts else ""


_OPTIONS_HELP = (
    "valid options: variants=canonical|all|simplerenv|<axis>[+<axis>.<level>...], obs=state|images, image_size=N "
    "(16-1024)"
)


def parse_options(text: str) -> Options:
    refuse_repeated_options(text)
    values: dict[str, Any] = {}
    for item in filter(None, (t.strip() for t in text.split(","))):
        key, _, value = item.partition("=")
        if key == "variants" and value:
            values["variants"] = sv.parse_selection(value)
        elif key == "obs" and value in ("state", "images"):
            values["obs"] = value
        elif key == "image_size" and value.isdigit() and 16 <= int(value) <= 1024:
            values["image_size"] = int(value)
        else:
            raise UnknownSuiteError(f"bad simpler/ suite option {item!r}; {_OPTIONS_HELP}")
    options = Options(**values)
    if options.image_size != DEFAULT_IMAGE_SIZE and options.obs != "images":
        raise UnknownSuiteError(f"image_size={options.image_size} needs obs=images; {_OPTIONS_HELP}")
    return options


def build_suite(
    name: str, task_names: tuple[str, ...], split: str = "eval", options: Options | None = None
) -> Suite:
    options = options or Options()
    settings = {t: options.variants.for_task(t) for t in task_names}
    tasks = tuple(
        TaskSpec(
            name=t,
            instruction=TASKS[t].instruction,
            max_steps=TASKS[t].max_steps,
            index=i,
            episodes=_episodes(split, t, settings[t]),
        )
        for i, t in enumerate(task_names)
    )

    def make_env(task: TaskSpec) -> gym.Env:
        _require_maniskill()
        return ManiSkillEpisodeEnv(TASKS[task.name], options.obs, options.image_size)

    from adapters import vulkan

    counts = "-".join(str(n) for n in sorted({len(v) - 1 for v in settings.values()}))
    setting = "canonical scene" if counts == "0" else f"canonical + {counts} variants"
    if options.variants.per_task_sets:
        setting += " (each task's SimplerEnv set)"
    return Suite(
        name=name + options.suffix(),
        version=SUITE_VERSION,
        tasks=tasks,
        make_env=make_env,
        description=(
            f"SimplerEnv-like on ManiSkill3 (not SimplerEnv): {len(tasks)} task(s), {setting}, "
            + ("state observations" if options.obs == "state" else f"state + {options.image_size} px RGB")
            + ", 7-D delta end-effector pose + gripper"
        ),
        extra="maniskill",
        simulator_packages=("mani_skill", "sapien"),
        provenance={"vulkan_driver": vulkan.describe()},
    )


def load_suite(name: str, split: str = "eval") -> Suite:
    """`simpler/<task>|all[:variants=...]` (adapters/simpler_variants.py)."""
    base, _, opts = name.partition(":")
    tail = base.removeprefix("simpler/")
    if tail == "all":
        return build_suite(base, ALL, split, parse_options(opts))
    if tail in TASKS:
        return build_suite(base, (tail,), split, parse_options(opts))
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
