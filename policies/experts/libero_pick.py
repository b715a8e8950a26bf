"""Scripted LIBERO experts from privileged state: the demonstrators LIBERO does not ship.

LIBERO's human demonstrations are not reachable offline, so demonstrations come from
these experts. They read object poses and goal-region positions from the state vector
(adapters/libero.py documents its layout), the goal from the task's BDDL, and drive the
OSC_POSE controller with proportional control on the end-effector position through
waypoints: above the object, down, close, lift, over the target, down, open. Two other
goals have their own experts, picked by `expert_for` (policies/experts/libero_select.py,
with a chain's `Handover`): a plate dragged into a table region
(policies/experts/libero_push.py), a stove's knob turned on
(policies/experts/libero_knob.py) and a drawer opened (policies/experts/libero_drawer.py).
Other goals (`Close`, two-step goals) raise at reset. The parameters
(`LiberoScriptedParams`) and the controller's scales here serve all of these experts; the
policy that runs them is policies/experts/libero_scripted.py.

Object geometry (where a body's origin sits relative to its bottom and top, where to
grip) is a table per object category (policies/experts/libero_geometry.py), measured once
from each category's collision geoms in the simulator (docs/libero.md, "Scripted experts").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from policies.experts.libero_geometry import Geometry
from policies.spec import param

MAX_DELTA_M = 0.05  # OSC_POSE maps a position action of 1 to a 5 cm goal offset
MAX_DELTA_RAD = 0.5  # and a rotation action of 1 to 0.5 rad
WRIST = 15  # the Panda's 7th joint (the wrist's turn about the fingers) in the state vector
OPEN, CLOSE, HOLD = -1.0, 1.0, 0.0
RELEASE_ABOVE = 0.008  # open once the object is this close above its place point (m)
# The Panda hand's footprint (half-lengths along the closing axis and across it, m), the
# radius assumed for a neighbouring object, and the gap a grasp should leave between them.
HAND_HALF = (0.105, 0.035)
OBSTACLE_RADIUS = 0.035
HAND_CLEARANCE = 0.01
# (yaw in rad, shift in units of Geometry.slide) tried in this order for flat boxes.
GRASP_CANDIDATES = [(0.0, 0.0)] + [
    (yaw, shift)
    for shift in (0.0, 1.0, -1.0)
    for yaw in (0.0, 0.3, -0.3, 0.5, -0.5)
    if (yaw, shift) != (0.0, 0.0)
]
# An object lifted by its handle (a frying pan) only slides along the handle: gripped askew,
# the 20 cm pan turned in the hand as it came up, and a turned pan failed its way off the
# stove or blocked the moka pot (tried: 8 of the first 28 kitchen_scene3 chains lost).
HANDLE_CANDIDATES = [(0.0, shift) for shift in (0.0, 0.5, -0.5, 1.0, -1.0)]
HANDLE_RADIUS = 0.012  # another object's handle, as an obstacle: a 1.4 cm bar and a margin
# Gripper steps closed from fully open before reaching into a drawer, then held: each
# finger joint ends near 0.026 m of its 0.04 m, narrow enough to pass the side walls.
# A fixed count, not a feedback loop on the finger joint: a policy that executes a chunk
# of actions open loop can copy a count, not a correction it cannot see coming.
DRAWER_CLOSE_STEPS = 3
DRAWER_OPENING = 0.024  # revision 1: finger joint position (m) held by feedback in a drawer
# Revision 2 lifts once the fingers have settled on the object (the finger joint moved
# less than SETTLE in a step, after at least MIN_CLOSE steps), and in that very step.
# Revision 1 waited a fixed 12 steps: up to 7 identical observations in a row that
# demonstrate "stay", then one "lift", which a policy decoding its chunk left to right
# resolves as "stay" for ever (the libero-object student on the tomato sauce).
SETTLE = 2e-4
MIN_CLOSE = 3
# Revision 3 closes once the descending hand has stopped (moved less than STOP_Z in height
# for STOPPED_STEPS steps in a row) within REACHED of the grip point, and lets go once the
# lowered object has stopped within REACHED of its place point. Revisions 1-2 closed within
# 8 mm or after 40 steps, and let go only centred within 1 cm or after 60: where the hand
# came to rest short of that (a finger on the rim, a bowl on the plate's rim) they sat
# 10-40 steps on one observation, then acted, and a policy trained on that sat there for
# ever (spatial task 9: open above the bowl, then pressing the bowl down beside the plate).
STOP_Z = 5e-4
STOPPED_STEPS = 2
REACHED = 0.03
# Revision 4 puts an object going into a container with a known floor (a tray) on the
# free spot farthest from what is already in it; revisions 1-3 aimed every object at the
# region's centre, so in a chain the fifth grocery landed on the other four and stayed
# above the tray's contain region (chains/living_room_scene3: 6 of its 50 chains).
SPOT_MARGIN = 0.04  # m from the container's walls to an object's centre
# Revision 6: an open Panda hand reaches this far along its closing axis from the grip
# point (a finger's collision mesh, 5.1 cm out and 1.4 cm thick), so gripping an object
# that rests near a tray's wall put the far finger on the wall, and the closing fingers
# lifted the tray with the object (chains/living_room_scene4, the pudding's take-out).
# The grip point then moves toward the container's centre, at most WALL_SHIFT.
OPEN_REACH = 0.064
FINGER_BELOW = 0.011  # and its mesh reaches this far below the grip point
WALL_SHIFT = 0.02
# Revision 5 puts an object going on a top surface (a cabinet's `top_side`) on the free
# point of a grid on it nearest the robot: SURFACE_MARGIN in from its edges, SURFACE_CLEAR
# from what already stands there (a bowl's and a wine bottle's radii and a centimetre).
# Revisions 1-4 aimed at the surface's centre: the wine bottle went down onto the bowl
# already there (chains/libero_goal, 3 of 15 bottles), and reaching that far and high the
# elbow straightened to its limit, where the arm could not bring the hand back (5 chains
# stopped on the subtask after). ROBOT_XY is where LIBERO mounts the Panda (robot0_base).
SURFACE_MARGIN = 0.06
SURFACE_CLEAR = 0.1
ROBOT_XY = np.array([-0.66, 0.0])
# Revision 5 goes back to grip an object again once it hangs DROPPED (m) further below the
# hand than when it was lifted; revisions 1-4 carried on with an empty hand (a bowl that
# slipped out of a rim grip in chain 9 of chains/libero_goal).
DROPPED = 0.04
# Revision 5 (chains/libero_goal) also changes the drawer expert (libero_drawer.py: the
# line-up from above, a drawer in the way shut first), the drag's descent
# (libero_push.py) and the handover (libero_select.py); docs/libero.md, "Revisions".
# An object carried by its handle (Geometry.grip_xy: a moka pot, a frying pan) is lifted
# HANDLE_LIFT (m) higher: at the usual height the pan, 20 cm across, swept the moka pot
# standing between it and the stove off the table (chains/kitchen_scene3, chain 13).
HANDLE_LIFT = 0.08
REVISIONS = (1, 2, 3, 4, 5, 6)


def quat_to_mat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of an xyzw quaternion (robosuite's order)."""
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_error(target: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Axis-angle (world frame) that turns `current` into `target` (both 3x3)."""
    r = target @ current.T
    angle = np.arccos(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))
    if angle < 1e-6:
        return np.zeros(3)
    if angle > np.pi - 1e-3:  # a half turn: the antisymmetric part vanishes, r = 2aa' - I
        outer = (r + np.eye(3)) / 2
        axis = outer[:, int(np.argmax(np.diag(outer)))]
        return axis / np.linalg.norm(axis) * angle
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / (2 * np.sin(angle))
    return axis * angle


@dataclass(frozen=True)
class LiberoScriptedParams:
    gain: float = param(
        10.0, "proportional gain on eef position error (action per metre)", low=1.0, high=50.0
    )
    lift: float = param(0.12, "clearance above the target when carrying (m)", low=0.03, high=0.3)
    action_noise: float = param(
        0.0, "std of Gaussian noise on position actions (degrades the expert)", low=0.0
    )
    seed: int = param(0, "seed of the action noise", low=0)
    revision: int = param(
        6,
        "expert revision: 6 = grips an object in a tray with the open hand clear of its walls; "
        "5 = lines up on a drawer from above and shuts a drawer in the way first; "
        "4 = puts an object going into a tray on its free spot; "
        "3 = closes as soon as the descending hand stops near the grip; "
        "2 = fixed-count finger narrowing for drawers and a lift once the grip has settled; "
        "1 = the first expert (policies/checkpoints/README.md says which each set saw)",
        choices=REVISIONS,
    )


@dataclass
class PickPlace:
    """Pick `obj` and put it on/in `target` (an entity or a goal-region site)."""

    obj: slice
    obj_geom: Geometry
    target: slice
    target_geom: Geometry | None  # None for a region site (its point is the place point)
    into: bool  # `In` (drop inside the region) rather than `On`
    holder: slice | None = None  # pose of the cabinet whose drawer holds `obj` at the start
    # Pose of a cabinet to grip a bowl across (its x axis) though it starts on the table:
    # one going into that cabinet's drawer, where the hand's length along y would hit it.
    across: slice | None = None
    others: tuple[slice, ...] = ()  # poses of the other objects (obstacles for the hand)
    # handles of other objects (their pose and Geometry.grip_xy), obstacles as well: a moka
    # pot's handle stands 7.4 cm out from the origin the `others` disc is centred on
    other_handles: tuple[tuple[slice, tuple[float, float]], ...] = ()
    # `In` a region of a container with a known floor (Geometry.inner): its pose and geometry
    container: slice | None = None
    container_geom: Geometry | None = None
    # A container with a known floor the goal does not name, which `obj` may rest in (a
    # chain's take-out): its pose and geometry. Gripped there, the hand closes along the
    # container's long side (`_in_source`).
    source: slice | None = None
    source_geom: Geometry | None = None
    # `On` the top surface of a piece of furniture (Geometry.surface): its pose and geometry
    surface: slice | None = None
    surface_geom: Geometry | None = None


class PickPlaceExpert:
    """Waypoint state machine for one episode; `act` returns one 7-D action."""

    def __init__(self, plan: PickPlace, params: LiberoScriptedParams, rng: np.random.Generator | None):
        self.plan, self.params, self.rng = plan, params, rng
        self.phase, self.count, self.retries = "approach", 0, 0
        self.home_rot: np.ndarray | None = None
        self.grip_rot: np.ndarray | None = None
        self.grip_point: np.ndarray | None = None
        self.lift_z = 0.0
        self.last_z: float | None = None
        self.last_finger: float | None = None
        self.stalled = 0
        self.unwind: float | None = None  # with `across`: the sign of the quarter turn
        self.spot: np.ndarray | None = None  # revision 4: the free spot chosen in a container
        self.held = 0.0  # the hand's height above the object once lifted

    @property
    def lowering(self) -> bool:
        """Whether an object held by its handle is still on its way down: LIBERO counts a
        moka pot On the stove's cook region ~3 cm above the burner, so a chain's next
        subtask begins there, and let go there the pot fell and lay on its side, where no
        handle grip reaches it (chains/kitchen_scene3, chain 5); likewise a bottle that
        tips when dropped (`Geometry.set_down`). A chain's handover lets the placement
        finish (policies/experts/libero_select.py, `lowering`)."""
        g = self.plan.obj_geom
        return self.phase == "lower" and (g.grip_xy != (0.0, 0.0) or g.set_down)

    def _grip_point(self, obs: np.ndarray, closing_axis: np.ndarray) -> np.ndarray:
        pos = obs[self.plan.obj][:3]
        g = self.plan.obj_geom
        point = pos + np.array([0.0, 0.0, g.grip_z])
        if g.grip_xy != (0.0, 0.0):  # a handle: the grip is off the origin, in the body's frame
            point[:2] += quat_to_mat(obs[self.plan.obj][3:7])[:2, :2] @ np.asarray(g.grip_xy)
        if g.rim > 0:  # grip the wall on the side of the closing axis farther from the robot base
            # (the robot stands at -x: a bowl gripped across a cabinet, along x, is gripped
            # on its +x side; otherwise the +y side, as the shipped demonstrations were)
            toward = 0 if self.plan.across is not None else 1
            axis = closing_axis * np.sign(closing_axis[toward] or 1.0)
            if self._in_source(obs):  # the side toward the container's centre, clear of its walls
                inward = obs[self.plan.source][:2] - pos[:2]
                axis = closing_axis * np.sign(float(closing_axis[:2] @ inward) or 1.0)
            point[:2] += g.rim * axis[:2] / max(np.linalg.norm(axis[:2]), 1e-6)
        if self.params.revision >= 6 and g.rim <= 0 and self._below_walls(obs, point):
            point[:2] += self._clear_of_walls(obs, point, closing_axis)
        return point

    def _below_walls(self, obs: np.ndarray, point: np.ndarray) -> bool:
        """Whether the object rests in the source container and the open fingers, reaching
        FINGER_BELOW under the grip point, come down past the top of its walls (a bottle
        gripped high is not; a bowl's rim grip sits toward the centre already)."""
        plan = self.plan
        if not self._in_source(obs):
            return False
        assert plan.source is not None and plan.source_geom is not None
        return bool(point[2] - FINGER_BELOW < obs[plan.source][2] + plan.source_geom.top)

    def _clear_of_walls(self, obs: np.ndarray, point: np.ndarray, closing_axis: np.ndarray) -> np.ndarray:
        """How far to move the grip point along the closing axis so the open hand (OPEN_REACH
        each way) stays inside the source container's floor, at most WALL_SHIFT: the
        fingers then push the object off the wall as they close."""
        plan = self.plan
        assert plan.source is not None and plan.source_geom is not None and plan.source_geom.inner is not None
        rot = quat_to_mat(obs[plan.source][3:7])[:2, :2]
        axis = rot.T @ closing_axis[:2]
        axis = axis / max(float(np.linalg.norm(axis)), 1e-6)
        local = rot.T @ (point[:2] - obs[plan.source][:2])
        inner = np.asarray(plan.source_geom.inner)

        def to_wall(direction: np.ndarray) -> float:
            steps = [
                (np.sign(c) * h - x) / c
                for c, h, x in zip(direction, inner, local, strict=True)
                if abs(c) > 1e-6
            ]
            return max(min(steps), 0.0)

        ahead, behind = to_wall(axis), to_wall(-axis)
        shift = min(ahead - OPEN_REACH, 0.0) + max(OPEN_REACH - behind, 0.0)
        return float(np.clip(shift, -WALL_SHIFT, WALL_SHIFT)) * (rot @ axis)

    def _grip_rotation(self, obs: np.ndarray) -> np.ndarray:
        """The start orientation turned about z so the fingers close along the object's
        `align` axis (the closing axis is the gripper's y axis; its sign does not matter)."""
        g = self.plan.obj_geom
        cabinet = self.plan.holder if self.plan.holder is not None else self.plan.across
        if g.rim > 0 and cabinet is not None:
            # In a drawer: the front and back walls are too close to the rim for a finger,
            # the side walls are not, so close along the cabinet's x axis (across the drawer).
            want = quat_to_mat(obs[cabinet][3:7])[:, 0]
        elif g.align < 0 and self._in_source(obs):
            want = quat_to_mat(obs[self.plan.source][3:7])[:, 0]
        elif g.align >= 0:
            want = quat_to_mat(obs[self.plan.obj][3:7])[:, g.align]
        else:
            return self.home_rot
        have = self.home_rot[:, 1]
        angle = np.arctan2(have[0] * want[1] - have[1] * want[0], have[0] * want[0] + have[1] * want[1])
        angle = (angle + np.pi / 2) % np.pi - np.pi / 2
        if self.plan.across is not None:
            # A quarter turn either way grips the same: turn the way that unwinds the wrist
            # joint (a world yaw of +a turns it by -a), decided once. Wound further, the arm
            # swung into the open drawer instead of turning.
            if self.unwind is None:
                self.unwind = float(np.sign(obs[WRIST]) or 1.0)
            if np.sign(angle) != self.unwind:
                angle += np.pi * self.unwind
        return yaw_matrix(angle) @ self.home_rot

    def _in_source(self, obs: np.ndarray) -> bool:
        """Whether the object rests inside `plan.source` (over its floor). A tray's walls
        stand 3.2 cm beyond its floor across its short side: a bowl in it gripped at its
        rim along that side put the outer finger on the wall (chains/living_room_scene4,
        every take-out of the bowl), so the hand closes along the long side instead."""
        plan = self.plan
        if plan.source is None or plan.source_geom is None or plan.source_geom.inner is None:
            return False
        rot = quat_to_mat(obs[plan.source][3:7])[:2, :2]
        local = np.abs(rot.T @ (obs[plan.obj][:2] - obs[plan.source][:2]))
        return bool((local <= np.asarray(plan.source_geom.inner)).all())

    def _grasp(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gripper orientation and grip point. A flat box may be gripped off-centre along
        its long side and a little askew, when that keeps the hand (long along the closing
        axis) clear of a neighbouring object and its handle: the first candidate, least
        moved first, with HAND_CLEARANCE to spare, else the one with the most. An object
        lifted by its handle only slides along it (HANDLE_CANDIDATES)."""
        rot = self._grip_rotation(obs)
        point = self._grip_point(obs, rot[:, 1])
        g = self.plan.obj_geom
        if g.align < 0 or g.slide <= 0 or not self.plan.others:
            return rot, point
        handles = [
            obs[s][:2] + quat_to_mat(obs[s][3:7])[:2, :2] @ np.asarray(xy)
            for s, xy in self.plan.other_handles
        ]
        obstacles = np.array([obs[s][:2] for s in self.plan.others] + handles)
        radius = np.array([OBSTACLE_RADIUS] * len(self.plan.others) + [HANDLE_RADIUS] * len(handles))
        by_handle = g.grip_xy != (0.0, 0.0)
        best, best_clearance = (rot, point), -np.inf
        for yaw, shift in HANDLE_CANDIDATES if by_handle else GRASP_CANDIDATES:
            turned = yaw_matrix(yaw) @ rot
            close_axis = turned[:2, 1] / np.linalg.norm(turned[:2, 1])
            along = np.array([-close_axis[1], close_axis[0]])
            grip = point.copy()
            grip[:2] += shift * g.slide * along  # slide along the box (perpendicular to the closing axis)
            rel = obstacles - grip[:2]
            u, v = np.abs(rel @ close_axis), np.abs(rel @ along)
            gap = np.hypot(np.maximum(u - HAND_HALF[0], 0.0), np.maximum(v - HAND_HALF[1], 0.0))
            clearance = float((gap - radius).min())
            if clearance >= HAND_CLEARANCE:
                return turned, grip
            if clearance > best_clearance:
                best, best_clearance = (turned, grip), clearance
        return best

    def _grid(
        self, obs: np.ndarray, pose: slice, half: tuple[float, float], margin: float, counts: tuple[int, int]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The target region's centre, the 2-D rotation of the body at `pose`, and a grid of
        counts[0] x counts[1] points in that body's frame, `margin` in from the edges of a
        rectangle of half-sizes `half` about the centre: where revisions 4 and 5 look for a
        free spot (a container's floor, a top surface)."""
        centre = obs[self.plan.target][:3]
        rot = quat_to_mat(obs[pose][3:7])[:2, :2]
        xs = np.linspace(-(half[0] - margin), half[0] - margin, counts[0])
        ys = np.linspace(-(half[1] - margin), half[1] - margin, counts[1])
        return centre, rot, np.array([(x, y) for x in xs for y in ys])

    def _free_spot(self, obs: np.ndarray) -> np.ndarray:
        """The point of the container's floor grid farthest from the objects already in
        it (the region's centre when it is empty), chosen once per subtask."""
        plan = self.plan
        assert plan.container is not None and plan.container_geom is not None
        hx, hy = plan.container_geom.inner  # type: ignore[misc]
        centre, rot, grid = self._grid(obs, plan.container, (hx, hy), SPOT_MARGIN, (7, 3))
        inside = [
            local
            for other in plan.others
            if other != plan.container
            for local in [rot.T @ (obs[other][:2] - centre[:2])]
            if abs(local[0]) < hx + 0.02 and abs(local[1]) < hy + 0.02
        ]
        if not inside:
            return centre.copy()
        clearance = np.min(np.linalg.norm(grid[:, None, :] - np.array(inside)[None], axis=2), axis=1)
        best = grid[np.lexsort((np.linalg.norm(grid, axis=1), -np.round(clearance, 3)))[0]]
        return np.append(centre[:2] + rot @ best, centre[2])

    def _surface_spot(self, obs: np.ndarray) -> np.ndarray:
        """Revision 5: the point of a grid on the surface that keeps SURFACE_CLEAR from
        what stands on it and is nearest the robot; on an empty surface, the one that
        keeps the farther of it and the nearest point then left for a second object
        nearest (the clearest point if none is free); chosen once per subtask. Two
        objects on a cabinet's top cannot both stand at its edge nearest the robot: the
        first takes a corner of it and leaves the second the top's middle, not its far
        side, where the arm straightened to its elbow's limit."""
        plan = self.plan
        assert plan.surface is not None and plan.surface_geom is not None
        hx, hy = plan.surface_geom.surface  # type: ignore[misc]
        centre, rot, grid = self._grid(obs, plan.surface, (hx, hy), SURFACE_MARGIN, (7, 5))
        points = np.array([centre[:2] + rot @ p for p in grid])
        reach = np.linalg.norm(points - ROBOT_XY, axis=1)
        apart = np.linalg.norm(points[:, None, :] - points[None], axis=2)
        on = [obs[o][:2] for o in plan.others if abs(obs[o][2] - centre[2]) < 0.05]
        if not on:  # the farther of the two as near as it can be, then this one nearest
            second = np.where(apart >= SURFACE_CLEAR, reach[None, :], np.inf).min(axis=1)
            return np.append(points[int(np.argmin(np.maximum(reach, second) + 1e-3 * reach))], centre[2])
        clear = np.min(np.linalg.norm(points[:, None, :] - np.array(on)[None], axis=2), axis=1)
        free = clear >= SURFACE_CLEAR
        best = int(np.argmin(np.where(free, reach, np.inf))) if free.any() else int(np.argmax(clear))
        return np.append(points[best], centre[2])

    def _place_point(self, obs: np.ndarray) -> np.ndarray:
        """Where the held object's origin should end up."""
        t = obs[self.plan.target]
        point = t[:3].copy()
        if self.plan.container is not None and self.params.revision >= 4:
            if self.spot is None:
                self.spot = self._free_spot(obs)
            point[:2] = self.spot[:2]
        if self.plan.surface is not None and self.params.revision >= 5:
            if self.spot is None:
                self.spot = self._surface_spot(obs)
            point[:2] = self.spot[:2]
        g = self.plan.obj_geom
        if self.plan.target_geom is not None:
            tg = self.plan.target_geom
            point[2] += (tg.top if tg.seat is None else tg.seat) + g.bottom + 0.01
        elif not self.plan.into:
            point[2] += g.bottom + 0.01
        return point

    def act(self, obs: np.ndarray) -> np.ndarray:
        eef, rot = obs[0:3], quat_to_mat(obs[3:7])
        if self.home_rot is None:
            self.home_rot = self.grip_rot = rot
        obj = obs[self.plan.obj][:3]
        self.count += 1
        grip, target = OPEN, eef.copy()
        p = self.params
        if self.phase in ("approach", "descend"):
            if self.grip_point is None or self.phase == "approach":
                self.grip_rot, self.grip_point = self._grasp(obs)
            above = self.grip_point + np.array([0.0, 0.0, 0.08])
            target = above if self.phase == "approach" else self.grip_point
            if self.plan.holder is not None:  # narrow the fingers to pass the drawer's side wall
                grip = self._narrowed_grip(float(obs[7]))
            err = target - eef
            if self.phase == "approach" and np.linalg.norm(err[:2]) < 0.01 and abs(err[2]) < 0.02:
                self._next("descend")
            elif self.phase == "descend" and (
                np.linalg.norm(err) < 0.008 or self.count > 40 or self._stopped_near(eef, err)
            ):
                self._next("close")
        elif self.phase == "close":
            target, grip = self.grip_point, CLOSE
            if self.count >= 12 or (p.revision >= 2 and self._grip_settled(float(obs[7]))):
                self.lift_z = max(self._place_point(obs)[2], obj[2]) + self.plan.obj_geom.bottom + p.lift
                self.lift_z += self.grip_point[2] - obj[2]
                if self.plan.obj_geom.grip_xy != (0.0, 0.0):
                    self.lift_z += HANDLE_LIFT
                self.obj_z0 = obj[2]
                self._next("lift")
                if p.revision >= 2:
                    target = np.array([self.grip_point[0], self.grip_point[1], self.lift_z])
        elif self.phase == "lift":
            grip = CLOSE
            target = np.array([self.grip_point[0], self.grip_point[1], self.lift_z])
            if self.count > 8 and obj[2] - self.obj_z0 < 0.01:  # did not come up: try again
                self.retries += 1
                self._next("release_retry")
            elif abs(target[2] - eef[2]) < 0.02:
                self.held = float(eef[2] - obj[2])
                self._next("carry")
        elif self.phase == "release_retry":
            target = eef + np.array([0.0, 0.0, 0.05])
            if self.count >= 8:
                self._next("approach")
        elif self.phase in ("carry", "lower") and self._dropped(eef, obj):
            self.retries += 1  # revision 5: it slipped out of the hand: go and grip it again
            self._next("release_retry")
        elif self.phase == "carry":
            grip = CLOSE
            place = self._place_point(obs)
            target = eef + np.append(place[:2] - obj[:2], 0.0)
            target[2] = self.lift_z
            if np.linalg.norm(place[:2] - obj[:2]) < 0.015 or self.count > 60:
                self._next("lower")
        elif self.phase == "lower":
            grip = CLOSE
            place = self._place_point(obs)
            target = eef + (place - obj)
            self._count_stalled(eef)
            off = float(np.linalg.norm(place[:2] - obj[:2]))
            centred = off < 0.01
            resting = p.revision >= 3 and self.stalled >= STOPPED_STEPS and off < REACHED
            if (
                (centred and (obj[2] - place[2] < RELEASE_ABOVE or self.stalled >= 4))
                or resting
                or self.count > 60
            ):
                self._next("release")
        elif self.phase == "release":
            target = eef.copy() if self.count < 10 else eef + np.array([0.0, 0.0, 0.05])
        self.last_z = float(eef[2])
        return self._action(target, eef, rot, grip)

    def _dropped(self, eef: np.ndarray, obj: np.ndarray) -> bool:
        """Revision 5: the object hangs DROPPED further below the hand than when it came up."""
        return self.params.revision >= 5 and float(eef[2] - obj[2]) - self.held > DROPPED

    def _narrowed_grip(self, finger: float) -> float:
        if self.params.revision == 1:
            return _hold_opening(finger, DRAWER_OPENING)
        return CLOSE if self.phase == "approach" and self.count <= DRAWER_CLOSE_STEPS else HOLD

    def _count_stalled(self, eef: np.ndarray) -> None:
        """Steps in a row the hand's height has not changed (by STOP_Z)."""
        stuck = self.last_z is not None and abs(self.last_z - eef[2]) < STOP_Z
        self.stalled = self.stalled + 1 if stuck else 0

    def _stopped_near(self, eef: np.ndarray, err: np.ndarray) -> bool:
        if self.params.revision < 3:
            return False
        self._count_stalled(eef)
        return self.stalled >= STOPPED_STEPS and float(np.linalg.norm(err)) < REACHED

    def _grip_settled(self, finger: float) -> bool:
        settled = self.last_finger is not None and abs(finger - self.last_finger) < SETTLE
        self.last_finger = finger
        return settled and self.count >= MIN_CLOSE

    def _next(self, phase: str) -> None:
        self.phase, self.count, self.stalled, self.last_finger = phase, 0, 0, None

    def _action(self, target: np.ndarray, eef: np.ndarray, rot: np.ndarray, grip: float) -> np.ndarray:
        move = np.clip((target - eef) * self.params.gain, -1.0, 1.0)
        if self.rng is not None and self.params.action_noise > 0:
            move = move + self.rng.normal(0.0, self.params.action_noise, 3)
        turn = np.clip(rotation_error(self.grip_rot, rot) / MAX_DELTA_RAD, -1.0, 1.0)
        return np.concatenate([move, turn, [grip]]).astype(np.float32)


def yaw_matrix(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _hold_opening(finger: float, opening: float) -> float:
    """Revision 1's gripper action that keeps one finger's joint near `opening` (m).

    Panda's gripper action moves its command by a fixed step per control step (only the
    action's sign counts), so 0 holds the command and the fingers stop where they are."""
    if finger > opening + 0.003:
        return CLOSE
    if finger < opening - 0.003:
        return OPEN
    return HOLD
