"""Scripted experts for the SimplerEnv-like ManiSkill3 suites, from privileged state.

ManiSkill's own motion-planning solutions need `mplib`, which crashes under numpy 2 (the
project's numpy), so these are our own: closed-loop, one 7-D delta end-effector pose +
gripper action per step, read from the suite's state vector (adapters/simpler.py:
the hand, then each object's pose, then each goal's position, world frame). Each task is
a short list of phases (reach above, descend, grip, carry, release), each ending on a
condition of the state, so a slip shows up in the state and the phase goes back.

Action scale (ManiSkill's `pd_ee_delta_pose`, normalised): 1.0 moves the hand 0.1 m or
turns it 0.1 rad in one step; gripper +1 opens, -1 closes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from adapters.simpler import TASKS, state_layout
from policies.base import ChunkBatch, EpisodeContext, Observation
from policies.spec import PolicySpec, param

OPEN, CLOSE = 1.0, -1.0
STEP_M, STEP_RAD = 0.1, 0.1  # what an action of 1.0 does in one step
CUBE_HALF = 0.02  # ManiSkill's cube half size for PickCube/PushCube/PullCube/StackCube
# A positive rotation action about z turns the hand's heading (_yaw) this way: measured,
# ManiSkill applies the delta in a frame whose z points along the hand, i.e. down.
ROTATION_SIGN = -1.0


@dataclass(frozen=True)
class ManiSkillScriptedParams:
    gain: float = param(1.0, "proportional gain of the hand's position and yaw control", low=0.1, high=5.0)


def _yaw(quat_xyzw: np.ndarray) -> float:
    """Heading of the body's x axis in the world's xy plane: the same for an upright
    cube and for a hand pointing down, whatever order the quaternion composes them in."""
    x, y, z, w = quat_xyzw
    return math.atan2(2 * (x * y + w * z), 1 - 2 * (y * y + z * z))


def _wrap(angle: float, period: float) -> float:
    """The angle in (-period/2, period/2]: a cube looks the same every quarter turn."""
    return (angle + period / 2) % period - period / 2


Reading = dict[str, np.ndarray]  # the state vector by name (adapters/simpler.py's layout)


@dataclass
class TaskExpert:
    task: str
    gain: float
    phase: int = 0
    held: int = 0  # steps the current phase has lasted (gripping takes a few)
    layout: list[tuple[str, int, int]] = field(default_factory=list)
    # The hand's heading for the grasp, chosen once: a cube at 45 degrees is as well
    # gripped turning either way, and re-choosing every step would dither between them.
    grasp_yaw: float | None = None

    def read(self, state: np.ndarray) -> Reading:
        return {name: state[a:b] for name, a, b in self.layout}

    def move(self, s: Reading, target: np.ndarray, grip: float, yaw_to: float | None = None) -> np.ndarray:
        action = np.zeros(7, dtype=np.float32)
        action[:3] = np.clip(self.gain * (target - s["tcp_pos"]) / STEP_M, -1, 1)
        if yaw_to is not None:
            turn = _wrap(yaw_to - _yaw(s["tcp_quat"]), 2 * math.pi)
            action[5] = np.clip(ROTATION_SIGN * self.gain * turn / STEP_RAD, -1, 1)
        action[6] = grip
        return action

    def next_phase(self) -> None:
        self.phase += 1
        self.held = 0

    def act(self, state: np.ndarray) -> np.ndarray:
        s = self.read(state)
        self.held += 1
        return getattr(self, f"_{self.task}")(s)

    # --- grasping a cube from above --------------------------------------------------

    def _grasp(self, s: Reading, key: str) -> np.ndarray | None:
        """Phases 0-2: above the object, down to it, close; None once it is held."""
        obj = s[key][:3]
        if self.grasp_yaw is None:
            hand = _yaw(s["tcp_quat"])
            self.grasp_yaw = hand + _wrap(_yaw(s[key][3:7]) - hand, math.pi / 2)
        yaw = self.grasp_yaw
        tcp = s["tcp_pos"]
        if self.phase == 0:
            above = obj + np.array([0, 0, 0.06])
            turn = abs(_wrap(yaw - _yaw(s["tcp_quat"]), 2 * math.pi))
            if np.linalg.norm(above[:2] - tcp[:2]) < 0.008 and turn < 0.05:
                self.next_phase()
            return self.move(s, above, OPEN, yaw)
        if self.phase == 1:
            if abs(tcp[2] - obj[2]) < 0.006 and np.linalg.norm(obj[:2] - tcp[:2]) < 0.01:
                self.next_phase()
            return self.move(s, obj, OPEN, yaw)
        if self.phase == 2:
            if self.held > 4:
                self.next_phase()
            return self.move(s, obj, CLOSE)
        return None

    def _pick_cube(self, s: Reading) -> np.ndarray:
        grasp = self._grasp(s, "obj_pose")
        if grasp is not None:
            return grasp
        return self.move(s, s["goal_pos"], CLOSE)

    def _stack_cube(self, s: Reading) -> np.ndarray:
        grasp = self._grasp(s, "cubeA_pose")
        if grasp is not None:
            return grasp
        target = s["cubeB_pose"][:3] + np.array([0, 0, 2 * CUBE_HALF + 0.004])
        tcp = s["tcp_pos"]
        if self.phase == 3:  # carry high, then lower onto cube B
            high = target + np.array([0, 0, 0.04])
            if np.linalg.norm(high[:2] - tcp[:2]) < 0.006:
                self.next_phase()
            return self.move(s, high, CLOSE)
        if self.phase == 4:
            if abs(tcp[2] - target[2]) < 0.004:
                self.next_phase()
            return self.move(s, target, CLOSE)
        if self.phase == 5:  # let go, then back off upwards
            if self.held > 3:
                self.next_phase()
            return self.move(s, target, OPEN)
        return self.move(s, target + np.array([0, 0, 0.05]), OPEN)

    def _place_sphere(self, s: Reading) -> np.ndarray:
        grasp = self._grasp(s, "obj_pose")
        if grasp is not None:
            return grasp
        tcp = s["tcp_pos"]
        above = s["bin_pos"] + np.array([0, 0, 0.06])
        if self.phase == 3:
            if np.linalg.norm(above[:2] - tcp[:2]) < 0.006:
                self.next_phase()
            return self.move(s, above, CLOSE)
        return self.move(s, above, OPEN)

    # --- pushing and pulling along x -------------------------------------------------

    def _slide(self, s: Reading, side: float) -> np.ndarray:
        """Push (side -1: from behind, towards +x) or pull (side +1: from beyond, back)."""
        cube, goal, tcp = s["obj_pose"][:3], s["goal_pos"], s["tcp_pos"]
        behind = cube + np.array([side * (CUBE_HALF + 0.025), 0, 0])
        if self.phase == 0:
            high = behind + np.array([0, 0, 0.06])
            if np.linalg.norm(high[:2] - tcp[:2]) < 0.008:
                self.next_phase()
            return self.move(s, high, CLOSE)
        if self.phase == 1:
            low = np.array([behind[0], behind[1], CUBE_HALF])
            if abs(tcp[2] - low[2]) < 0.006:
                self.next_phase()
            return self.move(s, low, CLOSE)
        target = np.array([goal[0] + side * (CUBE_HALF + 0.01), goal[1], CUBE_HALF])
        target[1] += 1.5 * (goal[1] - cube[1])  # steer the cube's y back onto the goal's
        return self.move(s, target, CLOSE)

    def _push_cube(self, s: Reading) -> np.ndarray:
        return self._slide(s, -1.0)

    def _pull_cube(self, s: Reading) -> np.ndarray:
        return self._slide(s, +1.0)


class ManiSkillExpert:
    def __init__(self, params: ManiSkillScriptedParams):
        self.params = params
        self._experts: list[TaskExpert] = []

    def reset(self, episodes: Sequence[EpisodeContext]) -> None:
        self._experts = []
        for ep in episodes:
            if ep.task not in TASKS:
                raise ValueError(f"no ManiSkill expert for task {ep.task!r}; tasks: {', '.join(TASKS)}")
            self._experts.append(TaskExpert(ep.task, self.params.gain, layout=state_layout(TASKS[ep.task])))

    def act(self, observations: Sequence[Observation]) -> ChunkBatch:
        states = [o["state"] if isinstance(o, dict) else o for o in observations]  # obs=images: its state
        actions = [e.act(np.asarray(o, dtype=np.float32)) for e, o in zip(self._experts, states, strict=True)]
        return ChunkBatch(actions=np.stack(actions)[:, None, :])


MANISKILL_SCRIPTED = PolicySpec(
    name="maniskill_scripted",
    summary="scripted expert for the SimplerEnv-like ManiSkill3 suites, from privileged state (NFE 0)",
    params=ManiSkillScriptedParams,
    build=ManiSkillExpert,
    suites=("simpler/",),
    extra="maniskill",
)
