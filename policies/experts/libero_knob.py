"""Scripted knob turning for LIBERO goals `TurnOn OBJ` and `TurnOff OBJ` (the flat stove's knob).

The knob is a hinge about the vertical axis through the stove's origin, with a bar
across its top; LIBERO counts the stove as on once the hinge passes 0.5 rad
(`FlatStove.turn_on`, default_turnon_ranges [0.5, 2.1]). Pushing the bar round with a
fingertip stalls (the finger rides onto the bar and the knob's arms), so the expert
grips the bar over the axis and turns its wrist: the knob turns with the hand. It reads
the stove's pose from the state vector and the goal from the BDDL, like the other experts.

Turning it off (a chain's authored complement of turning it on) is the same motion
backwards: LIBERO counts the stove as off only below 0.0 rad, the knob's stop being at
-0.005, so the bar is turned back past where it started. The knob's angle is not among
the poses the experts read, so the hand comes down turned as the turn-on left the bar
(TURN_TO) and closing the fingers lines the bar up with them; then it turns OFF_PAST
beyond the start, against the stop. KITCHEN_SCENE8's initial states draw the knob
anywhere in LIBERO's on range (0.5-2.1 rad); from past ~2.0 the bar slips out of fingers
closed at 1.0 rad partway round (traced: 2.09 to 0.80), so a turn-off that ends with the
stove still on lets go, rises and grips again from TURN_TO (RETRY_OFF): the bar is then
within reach of the fingers. A chain's subtask ends the step its goal holds, so a retry
only ever follows a turn that failed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from policies.experts.libero_pick import (
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
OFF_PAST = 0.3  # turning off: the wrist turns this far (rad) past the knob's start, into its stop
RETRY_OFF = 3  # turning off: grips in all, each after the last turn ended with the stove still on
HOLD_TURNED = 10  # steps the turned wrist is held before a turn-off lets go to grip again
# Letting go to grip again (steps into the release): open in place until LET_GO, rise
# with the wrist as turned until TURN_BACK, then turn back and approach after RELEASE.
LET_GO, TURN_BACK, RELEASE = 8, 20, 35


@dataclass(frozen=True)
class Knob:
    body: slice  # pose of the object whose knob turns (its origin is on the hinge axis)
    turn_from: float = 0.0  # wrist turn (rad, from the start orientation) at which the bar is gripped
    turn_to: float = TURN_TO  # and to which it is turned: below turn_from turns the stove off


def turn_off(body: slice) -> Knob:
    """The knob turned back from where the turn-on leaves it to past its start."""
    return Knob(body=body, turn_from=TURN_TO, turn_to=-OFF_PAST)


class KnobExpert:
    """Above the knob, down, close on the bar, turn the wrist; `act` returns one 7-D action."""

    def __init__(self, plan: Knob, params: LiberoScriptedParams):
        self.plan, self.params = plan, params
        self.phase, self.count = "approach", 0
        self.home_rot: np.ndarray | None = None
        self.grips = 1

    def act(self, obs: np.ndarray) -> np.ndarray:
        eef, rot = obs[0:3], quat_to_mat(obs[3:7])
        if self.home_rot is None:
            self.home_rot = rot
        self.count += 1
        grip_point = obs[self.plan.body][:3] + np.array([0.0, 0.0, GRIP_HEIGHT])
        start, end = self.plan.turn_from, self.plan.turn_to
        target, grip, want = grip_point, OPEN, yaw_matrix(start) @ self.home_rot
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
            turned = min(abs(end - start), TURN_RATE * self.count)
            want = yaw_matrix(start + np.sign(end - start) * turned) @ self.home_rot
            held = self.count - abs(end - start) / TURN_RATE
            if end < start and self.grips < RETRY_OFF and held > HOLD_TURNED:
                self.grips += 1
                self._next("release")
        elif self.phase == "release":  # open in place, rise, turn back, then grip again
            above = grip_point + np.array([0.0, 0.0, 0.08])
            target = eef if self.count <= LET_GO else above
            want = yaw_matrix(end if self.count <= TURN_BACK else start) @ self.home_rot
            if self.count > RELEASE:
                self._next("approach")
        move = np.clip((target - eef) * self.params.gain, -1.0, 1.0)
        turn = np.clip(rotation_error(want, rot) / MAX_DELTA_RAD, -1.0, 1.0)
        return np.concatenate([move, turn, [grip]]).astype(np.float32)

    def _next(self, phase: str) -> None:
        self.phase, self.count = phase, 0
