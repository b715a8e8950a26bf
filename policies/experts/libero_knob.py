"""Scripted knob turning for LIBERO goals `TurnOn OBJ` (the flat stove's knob).

The knob is a hinge about the vertical axis through the stove's origin, with a bar
across its top; LIBERO counts the stove as on once the hinge passes 0.5 rad
(`FlatStove.turn_on`, default_turnon_ranges [0.5, 2.1]). Pushing the bar round with a
fingertip stalls (the finger rides onto the bar and the knob's arms), so the expert
grips the bar over the axis and turns its wrist: the knob turns with the hand. It reads
the stove's pose from the state vector and the goal from the BDDL, like the other experts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from policies.experts.libero_scripted import (
    CLOSE,
    MAX_DELTA_RAD,
    OPEN,
    LiberoScriptedParams,
    quat_to_mat,
    rotation_error,
    yaw_matrix,
)

GRIP_HEIGHT = 0.04  # the knob's bar, gripped this far above the stove's origin (m)
KNOBS = ("flat_stove",)  # categories whose `TurnOn` is this knob
TURN_TO = 1.0  # wrist turn (rad, counter-clockwise: the hinge's positive direction)
TURN_RATE = 0.1  # rad per control step


@dataclass(frozen=True)
class Knob:
    body: slice  # pose of the object whose knob turns (its origin is on the hinge axis)


class KnobExpert:
    """Above the knob, down, close on the bar, turn the wrist; `act` returns one 7-D action."""

    def __init__(self, plan: Knob, params: LiberoScriptedParams):
        self.plan, self.params = plan, params
        self.phase, self.count = "approach", 0
        self.home_rot: np.ndarray | None = None

    def act(self, obs: np.ndarray) -> np.ndarray:
        eef, rot = obs[0:3], quat_to_mat(obs[3:7])
        if self.home_rot is None:
            self.home_rot = rot
        self.count += 1
        grip_point = obs[self.plan.body][:3] + np.array([0.0, 0.0, GRIP_HEIGHT])
        target, grip, want = grip_point, OPEN, self.home_rot
        if self.phase == "approach":
            target = grip_point + np.array([0.0, 0.0, 0.08])
            if np.linalg.norm(target - eef) < 0.01 or self.count > 80:
                self._next("descend")
        elif self.phase == "descend":
            if abs(eef[2] - grip_point[2]) < 0.005 or self.count > 40:
                self._next("close")
        elif self.phase == "close":
            grip = CLOSE
            if self.count > 12:
                self._next("turn")
        elif self.phase == "turn":
            grip = CLOSE
            want = yaw_matrix(min(TURN_TO, TURN_RATE * self.count)) @ self.home_rot
        move = np.clip((target - eef) * self.params.gain, -1.0, 1.0)
        turn = np.clip(rotation_error(want, rot) / MAX_DELTA_RAD, -1.0, 1.0)
        return np.concatenate([move, turn, [grip]]).astype(np.float32)

    def _next(self, phase: str) -> None:
        self.phase, self.count = phase, 0
