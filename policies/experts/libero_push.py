"""Scripted dragging for LIBERO goals `On OBJ REGION` whose object is too wide to grip.

libero/goal's "push the plate to the front of the stove" puts a ~15 cm plate into a
table region; the Panda's fingers open 8 cm, so the plate is moved without a grasp: the
closed fingers press on its inner rim (PushExpert says why from inside), re-aiming
every step from where the plate is now (a round plate moved at one point drifts
sideways). It aims at the point of the region nearest the plate, `MARGIN` inside its
edge, so the plate travels as little as possible past the other objects. Reads only
the state vector and the BDDL, like the pick-and-place expert (policies/experts/libero_pick.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from policies.experts.libero_pick import (
    CLOSE,
    MAX_DELTA_RAD,
    STOP_Z,
    STOPPED_STEPS,
    LiberoScriptedParams,
    quat_to_mat,
    rotation_error,
    yaw_matrix,
)

PUSHED = {"plate": 0.048}  # categories dragged instead of gripped: inner radius of the rim (m)
MARGIN = 0.02  # aim this far inside the goal region's edge (m)
# Set point for the fingertips below the plate's floor (m): they press down and cannot
# climb the low rim.
DRAG_HEIGHT = -0.005
PRESS = 0.02  # the fingers' set point this far past the inner rim: they press while they move
DONE_WITHIN = 0.006  # stop once the plate's centre is this close to the aim point (m)
LOST = 0.025  # fingers this far outside the inner rim: the plate got away, go in again (m)


@dataclass(frozen=True)
class Push:
    obj: slice  # pose of the pushed object
    radius: float
    low: np.ndarray  # (2,) xy corner of the goal region, lowest x and y
    high: np.ndarray  # (2,) the opposite corner


def push_plan(slices: dict[str, slice], obj: str, region: dict, radius: float) -> Push:
    """The region's `ranges` are in its target's frame; LIBERO's table regions sit on the
    table whose frame the state's region site shares in x/y, so the bounds are taken
    around the site (obs) at run time: here only their half-extents are kept."""
    x0, y0, x1, y1 = region["ranges"][0]
    half = np.array([(x1 - x0) / 2, (y1 - y0) / 2])
    return Push(obj=slices[obj], radius=radius, low=-half, high=half)


class PushExpert:
    """Fingers into the plate, drag it by its rim, lift away; `act` returns one 7-D action.

    Pushing from outside needs room behind the plate, and in libero/goal the cabinet
    stands there (the hand, 21 cm along its closing axis, hits it). So the closed fingers
    go down inside the dished plate and press against the inner rim on the goal's side:
    the plate moves with them from wherever it is. The hand is turned so its long axis
    lies along the direction of travel: across it, the hand sweeps a 21 cm swath and
    knocks over the bowl beside the plate's path.
    """

    def __init__(self, plan: Push, site: slice, params: LiberoScriptedParams):
        self.plan, self.site, self.params = plan, site, params
        self.phase, self.count = "approach", 0
        self.home_rot: np.ndarray | None = None
        self.drag_rot: np.ndarray | None = None
        self.last_z, self.stalled = np.inf, 0  # revision 5: steps the descending hand has not moved

    def _aim(self, obs: np.ndarray) -> np.ndarray:
        centre = obs[self.site][:2]
        inner_low = centre + self.plan.low + MARGIN
        inner_high = centre + self.plan.high - MARGIN
        return np.clip(obs[self.plan.obj][:2], inner_low, np.maximum(inner_low, inner_high))

    def _along(self, d: np.ndarray) -> np.ndarray:
        """The start orientation turned about z so the closing axis lies along `d`."""
        have, want = self.home_rot[:, 1], d
        angle = np.arctan2(have[0] * want[1] - have[1] * want[0], have[0] * want[0] + have[1] * want[1])
        return yaw_matrix((angle + np.pi / 2) % np.pi - np.pi / 2) @ self.home_rot

    def act(self, obs: np.ndarray) -> np.ndarray:
        eef, rot = obs[0:3], quat_to_mat(obs[3:7])
        if self.home_rot is None:
            self.home_rot = rot
        self.count += 1
        pose = obs[self.plan.obj]
        plate, aim = pose[:2], self._aim(obs)
        to_goal = aim - plate
        distance = float(np.linalg.norm(to_goal))
        d = to_goal / max(distance, 1e-6)
        if self.drag_rot is None:
            self.drag_rot = self._along(d)
        low_z = pose[2] + DRAG_HEIGHT
        target = eef.copy()
        new = self.params.revision >= 5
        if self.phase == "approach":
            target = np.array([plate[0], plate[1], low_z + 0.08])
            if np.linalg.norm(target - eef) < 0.015 or self.count > 80:
                self._next("descend")
        elif self.phase == "descend":
            target = np.array([plate[0], plate[1], low_z])
            # revision 5 also once the fingers rest on the plate's floor (the set point
            # is below it): revisions 1-4 waited there for the 40 steps to run out
            self.stalled = self.stalled + 1 if new and abs(eef[2] - self.last_z) < STOP_Z else 0
            if abs(eef[2] - low_z) < 0.006 or self.count > 40 or self.stalled >= STOPPED_STEPS:
                self._next("drag")
        elif self.phase == "drag":
            lead = plate + d * (self.plan.radius + PRESS)  # past the rim: keeps pressing on it
            target = np.array([lead[0], lead[1], low_z])
            if distance < DONE_WITHIN:
                self._next("retreat")
            elif np.linalg.norm(eef[:2] - plate) > self.plan.radius + LOST:
                self._next("approach")  # out of the plate: go in again
        elif self.phase == "retreat":
            target = eef + np.array([0.0, 0.0, 0.05])
        self.last_z = float(eef[2])
        move = np.clip((target - eef) * self.params.gain, -1.0, 1.0)
        turn = np.clip(rotation_error(self.drag_rot, rot) / MAX_DELTA_RAD, -1.0, 1.0)
        return np.concatenate([move, turn, [CLOSE]]).astype(np.float32)

    def _next(self, phase: str) -> None:
        self.phase, self.count, self.stalled = phase, 0, 0
