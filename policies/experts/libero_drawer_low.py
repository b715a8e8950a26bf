"""Opening a drawer whose handle is too low for the pitched pinch of libero_drawer.py:
press the closed fingertips down on the top of its bar and pull, by friction.

The wooden cabinet's bottom bar is 4 cm above the table and 5.3 cm under the middle
drawer's, which stands as far out. Pitched (fingers into the cabinet, closing
vertically) the hand reaches 10.5 cm below its fingers and met the table 5 cm above the
bar; closing along the bar, the bar (8.9 cm) is longer than the fingers open (8 cm); a
finger hooked behind it from above has the palm meet the middle drawer (traced in
docs/chains.md, "Opposites"). What does reach it: the hand upright with its long side
along the drawer's front (as ShutExpert pushes), fingers closed, leaned 0.9 rad out so
the fingertips point down into the cabinet and the hand stays in front of both bars.
It comes down in front of the bars, moves in between them until the fingertips are over
the lower bar, presses down and pulls the drawer out past LIBERO's `Open`, then rises
straight up (the drawer is out, so nothing is above the fingers) and turns upright.
"""

from __future__ import annotations

import numpy as np

from policies.experts.libero_drawer import (
    OPEN_AT,
    RISE,
    TURNED,
    Drawer,
    _DrawerHand,
    closing_along,
    drawer_state,
    leaning_out,
)
from policies.experts.libero_pick import CLOSE, LiberoScriptedParams, rotation_error

# Per cabinet category, the drawers opened this way: the ones whose handle is too near
# the table for the pitched hand (measured: the wooden cabinet's bottom bar).
PRESSED: dict[str, tuple[str, ...]] = {"wooden_cabinet": ("bottom",)}
PRESS_LEAN = 0.9  # rad out from upright: at LEAN (0.5) the fingers came down on the middle bar
FRONT = 0.07  # come down this far in front of the handle's centre (m): clear of both bars
ABOVE = 0.035  # then move in this far above it (m): the fingertips between the two bars
OVER_BAR = 0.008  # to this far in front of it (m): the fingertips over the bar's top
# Aim this far below the handle's centre while pressing and pulling (m), and pull toward
# a point LEAD ahead of the handle. Pressing 2 cm down, the fingertips slid off the bar
# with the drawer 11-13 cm out from 4 of 6 chains' starts (chains/kitchen_scene1);
# pulling toward 3 cm ahead, the drawer was 5-6 cm out when the 360 steps ran out.
DOWN = 0.035
LEAD = 0.05


def pressed(plan: Drawer) -> bool:
    """Whether this drawer is opened by pressing on its bar rather than pinching it."""
    return plan.level in PRESSED.get(plan.category, ())


class PressPullExpert(_DrawerHand):
    """Over, down in front, in over the bar, press, pull, rise, turn upright; then `done`."""

    def __init__(self, plan: Drawer, params: LiberoScriptedParams, open_to: float = OPEN_AT):
        self.plan, self.params, self.open_to = plan, params, open_to
        self.phase, self.count = "over", 0
        self.home_rot: np.ndarray | None = None
        self.leaned: np.ndarray | None = None

    def act(self, obs: np.ndarray) -> np.ndarray:
        eef, rot, cabinet, pull = self._sense(obs)
        if self.home_rot is None:  # in a chain, ShutFirst may have set it already
            self.home_rot = rot
        if self.leaned is None:
            self.leaned = leaning_out(closing_along(self.home_rot, cabinet[:, 0]), pull, PRESS_LEAN)
        handle, q = drawer_state(self.plan, obs)
        up = np.array([0.0, 0.0, 1.0])
        self.count += 1
        target, want = eef.copy(), self.leaned
        if self.phase == "over" and self.count == 1 and q < self.open_to:
            self._next("done")  # already open
            want = self.home_rot
        elif self.phase == "over":  # turning on the way, high in front of the cabinet
            target = handle + pull * FRONT + up * (ABOVE + RISE)
            turned = np.linalg.norm(rotation_error(want, rot)) < TURNED
            if (turned and np.linalg.norm(target - eef) < 0.02) or self.count > 80:
                self._next("down")
        elif self.phase == "down":
            target = handle + pull * FRONT + up * ABOVE
            if np.linalg.norm(target - eef) < 0.01 or self.count > 40:
                self._next("in")
        elif self.phase == "in":
            target = handle + pull * OVER_BAR + up * ABOVE
            if np.linalg.norm(target - eef) < 0.006 or self.count > 30:
                self._next("press")
        elif self.phase == "press":
            target = handle + pull * OVER_BAR - up * DOWN
            if self.count > 10:
                self._next("pull")
        elif self.phase == "pull":  # the bar moves with the hand: aim ahead of it
            target = handle + pull * (OVER_BAR + LEAD) - up * DOWN
            if q < self.open_to or self.count > 150:
                self._next("rise")
        elif self.phase == "rise":  # straight up, still leaned: nothing is above the fingers
            target = handle + pull * OVER_BAR + up * RISE
            if np.linalg.norm(target - eef) < 0.02 or self.count > 30:
                self._next("turn_back")
        elif self.phase == "turn_back":
            target, want = handle + pull * OVER_BAR + up * RISE, self.home_rot
            if np.linalg.norm(rotation_error(want, rot)) < 2 * TURNED or self.count > 30:
                self._next("done")
        else:  # done: hold still, upright (a next expert takes over from here)
            want = self.home_rot
        return self._action(target, want, eef, rot, CLOSE)
