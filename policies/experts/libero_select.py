"""Which LIBERO expert acts on a task's goal (`expert_for`, `plan_for`), and how a chain's
next subtask starts (`Handover`).

The experts themselves live beside this module: pick-and-place in
policies/experts/libero_pick.py, the drawer, drag and knob experts in libero_drawer.py,
libero_push.py and libero_knob.py. This module reads the task's BDDL problem (in a chain
suite, the scene's problem with the goal of the subtask in force) and the state layout,
and builds the one that fits.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from policies.base import EpisodeContext
from policies.experts.libero_geometry import category, geometry
from policies.experts.libero_pick import (
    MAX_DELTA_RAD,
    OPEN,
    LiberoScriptedParams,
    PickPlace,
    PickPlaceExpert,
    quat_to_mat,
    rotation_error,
)

if TYPE_CHECKING:
    from policies.experts.libero_drawer import OpenThenExpert


def _problem(context: EpisodeContext) -> tuple[dict, dict[str, slice]]:
    """A task's BDDL problem and where each entity and goal site sits in the state; in a
    chain suite, the scene's problem with the goal of the subtask in force."""
    from adapters import libero, libero_layout

    if context.suite.startswith("chains/"):
        from adapters import chains

        return chains.subtask_problem(context.task, context.instruction)

    key = context.suite.partition(":")[0].removeprefix("libero/")
    problem = libero.suite_task_problem(context.suite, _task_index(key, context.task))
    return problem, {name: slice(a, b) for name, a, b in libero_layout.state_layout(problem)}


def expert_for(context: EpisodeContext, params: LiberoScriptedParams, rng: np.random.Generator | None):
    """The expert for a task's goal: a drawer pull for `Open` a drawer (a press-and-pull
    where its bar is too low to pinch, policies/experts/libero_drawer_low.py), a push past
    LIBERO's `Close` threshold for `Close` one, and before
    putting something `In` one (policies/experts/libero_drawer.py), a drag for an object too wide
    to grip going to a table region (policies/experts/libero_push.py), a wrist turn for a stove's
    knob (policies/experts/libero_knob.py), turned on or back off, else pick-and-place. `action_noise` (rng) degrades only
    pick-and-place, the experts whose demonstrations are trained on so far."""
    from adapters import libero_layout
    from policies.experts.libero_drawer import (
        AJAR,
        CLOSED_PAST,
        DrawerExpert,
        OpenThenExpert,
        ShutExpert,
        drawer_plan,
    )
    from policies.experts.libero_drawer_low import PressPullExpert, pressed
    from policies.experts.libero_knob import KNOBS, Knob, KnobExpert, turn_off
    from policies.experts.libero_push import PUSHED, PushExpert, push_plan

    problem, slices = _problem(context)
    _check_privileged_state(context, slices)
    goals = problem["goal_state"]
    entities = libero_layout.entity_names(problem)
    drawer = drawer_plan(slices, entities, goals[0][-1]) if len(goals) == 1 else None
    standing = _standing(problem, slices)
    if drawer is not None and goals[0][0] == "close":  # a chain's authored close
        return ShutExpert(drawer, params, shut_to=CLOSED_PAST)
    if drawer is not None and goals[0][0] == "open" and pressed(drawer):  # a bar too low to pinch
        return _shut_first(PressPullExpert(drawer, params), slices, entities, params, but=drawer)
    if drawer is not None and goals[0][0] == "open":
        expert = DrawerExpert(drawer, params, obstacles=standing)
        return _shut_first(expert, slices, entities, params, but=drawer)
    if drawer is not None and goals[0][0] == "in":
        plan = dataclasses.replace(plan_for(context), across=drawer.cabinet)
        opener = DrawerExpert(drawer, params, AJAR, obstacles=standing)
        expert = OpenThenExpert(opener, PickPlaceExpert(plan, params, rng))
        return _shut_first(expert, slices, entities, params, but=drawer)
    if len(goals) == 1 and goals[0][0] == "turnon" and category(goals[0][1]) in KNOBS:
        return KnobExpert(Knob(body=slices[goals[0][1]]), params)
    if (
        len(goals) == 1 and goals[0][0] == "turnoff" and category(goals[0][1]) in KNOBS
    ):  # a chain's authored off
        return KnobExpert(turn_off(slices[goals[0][1]]), params)
    if len(goals) == 1 and goals[0][0] == "on" and category(goals[0][1]) in PUSHED:
        _, obj, region = goals[0]
        if region not in entities and problem["regions"].get(region, {}).get("ranges"):
            plan = push_plan(slices, obj, problem["regions"][region], PUSHED[category(obj)])
            expert = PushExpert(plan, slices[region], params)
            return _shut_first(expert, slices, entities, params)
    plan = plan_for(context)
    expert = PickPlaceExpert(plan, params, rng)
    return _shut_first(expert, slices, entities, params, near=_hand_points(plan))


def _standing(problem: dict, slices: dict[str, slice]) -> tuple[tuple[slice, float, float], ...]:
    """Every movable object's pose slice, footprint radius and top above its origin."""
    from policies.experts.libero_drawer import FOOTPRINT_RADIUS

    names = [n for ns in problem["objects"].values() for n in ns if n in slices]
    return tuple((slices[n], FOOTPRINT_RADIUS.get(category(n), 0.04), geometry(n).top) for n in names)


def _hand_points(plan: PickPlace):
    """Where pick-and-place's fingertips will be: at the grip, and at the place (roughly:
    the target's top, the object's bottom and its grip above it), from the state."""
    g, tg = plan.obj_geom, plan.target_geom
    above = 0.0 if tg is None else (tg.top if tg.seat is None else tg.seat)
    lift = np.array([0.0, 0.0, g.grip_z])
    place = np.array([0.0, 0.0, above + g.bottom + g.grip_z])

    def points(obs: np.ndarray) -> list[np.ndarray]:
        return [obs[plan.obj][:3] + lift, obs[plan.target][:3] + place]

    return points


def _shut_first(
    expert, slices: dict[str, slice], entities: list[str], params: LiberoScriptedParams, but=None, near=None
):
    """Revision 5: the drawer and drag experts first shut any other drawer that is out,
    pick-and-place one that is out where its hand will work (`near`; ShutExpert in
    policies/experts/libero_drawer.py says why). Only a chain's state holds drawers the
    goal does not name, so single LIBERO tasks get the expert itself."""
    from policies.experts.libero_drawer import ShutExpert, ShutFirst, drawers_in_state

    if params.revision < 5:
        return expert
    others = [d for d in drawers_in_state(slices, entities) if d != but]
    return ShutFirst([ShutExpert(d, params, near) for d in others], expert) if others else expert


def _check_privileged_state(context: EpisodeContext, slices: dict[str, slice]) -> None:
    """The experts read object poses from the state; obs=upstream has none (8-D proprio)."""
    import gymnasium as gym

    space = context.observation_space
    state = space["state"] if isinstance(space, gym.spaces.Dict) else space
    need = max(s.stop for s in slices.values())
    if state.shape[0] < need:
        raise ValueError(
            f"libero_scripted reads object poses from the privileged state ({need}+ numbers); "
            f"{context.suite} gives {state.shape[0]} (obs=upstream has no object poses): use "
            "obs=state or obs=images"
        )


def plan_for(context: EpisodeContext) -> PickPlace:
    """The pick-and-place plan of a task, from its BDDL goal and the state layout."""
    from adapters import libero_layout

    problem, slices = _problem(context)
    goals = problem["goal_state"]
    if len(goals) != 1 or goals[0][0] not in ("on", "in"):
        raise ValueError(f"libero_scripted has no script for the goal {goals} of {context.task!r}")
    _, obj, target = goals[0]
    entities = libero_layout.entity_names(problem)
    entity = target in entities
    holder_name = target.removesuffix("_contain_region")
    container = None
    if not entity and holder_name != target and holder_name in slices and geometry(holder_name).inner:
        container = holder_name
    source = next(  # a container the object may be taken out of (a chain's take-out)
        (n for n in entities if n != container and n in slices and geometry(n).inner and not entity), None
    )
    furniture = target.removesuffix("_top_side")
    if entity or furniture == target or furniture not in slices or not geometry(furniture).surface:
        furniture = None
    return PickPlace(
        obj=slices[obj],
        obj_geom=geometry(obj),
        target=slices[target],
        target_geom=geometry(target) if entity else None,
        into=goals[0][0] == "in",
        holder=_drawer_holder(problem, obj, entities, slices),
        others=tuple(
            slices[n] for names in problem["objects"].values() for n in names if n not in (obj, target)
        ),
        other_handles=tuple(
            (slices[n], geometry(n).grip_xy)
            for names in problem["objects"].values()
            for n in names
            if n not in (obj, target) and geometry(n).grip_xy != (0.0, 0.0)
        ),
        container=slices[container] if container else None,
        container_geom=geometry(container) if container else None,
        surface=slices[furniture] if furniture else None,
        surface_geom=geometry(furniture) if furniture else None,
        source=slices[source] if source else None,
        source_geom=geometry(source) if source else None,
    )


def _drawer_holder(problem: dict, obj: str, entities: list[str], slices: dict[str, slice]) -> slice | None:
    """The pose slice of the cabinet whose drawer region holds `obj` in the BDDL's initial state."""
    for predicate in problem["initial_state"]:
        if predicate[0] == "in" and predicate[1] == obj:
            for name in entities:
                if predicate[2].startswith(name + "_") and "cabinet" in category(name):
                    return slices[name]
    return None


def _task_index(key: str, task: str) -> int:
    from adapters import libero_sim

    names = [t.name for t in libero_sim.benchmark(key).tasks]
    return names.index(task)


# In a chain, steps the hand may take to go back to where the chain started before the
# next subtask's expert acts (see Handover), and how close counts as back (m, rad).
HOME_STEPS = 60
HOME_REACHED = (0.02, 0.1)
# After a placement into a drawer or onto a top (`placed`), revision 5 opens the hand in
# place before it moves: until a finger joint is past OPENED (m) or for at most
# OPEN_STEPS steps. Revisions 1-4 opened and left at once, so a bowl that had just
# counted as In the top drawer (LIBERO's region reaches above it) was dragged by the
# opening fingers: it pulled the drawer out to its stop and came to rest tilted on the
# drawer's side wall. (After the knob, rising first took the twisted arm into the wine
# rack on its way home; into a tray, it lost 1 of 20 tray chains: not there.)
OPENED = 0.035
OPEN_STEPS = 10
# and then rises RISE_FIRST (m, at most RISE_STEPS steps) before it heads home: going
# straight home, the opened fingers swept the wine bottle just stood on the cabinet off it.
RISE_FIRST = 0.06
RISE_STEPS = 12
# Revision 5 also bends an elbow left straight, at its joint limit, before heading home:
# reaching a cabinet's far top the arm straightened (joint 4 at -0.07 rad, past STRAIGHT),
# and there no move of the hand bends it back, the arm stuck; a turn of the hand about
# the world's y axis does (joint 4 from -0.07 to -1.1 rad in 16 steps, chain 15). For at
# most BEND_STEPS steps, until the joint (ELBOW in the state) is past STRAIGHT.
ELBOW = 12
STRAIGHT = -0.3
BEND_STEPS = 25


def handover(
    following: object, previous: object, home: np.ndarray | None, params: LiberoScriptedParams
) -> Handover:
    """The `Handover` to a chain's next subtask after `previous`, the last one's expert:
    revision 5 finishes a placement into a drawer (`lowering`), opens in place after one
    into a drawer or onto a top (`placed`), and bends a straightened elbow."""
    late = params.revision >= 5
    finish = lowering(previous) if late else None
    return Handover(following, home, params.gain, late and placed(previous), late, finish)


def _unwrapped(expert: object) -> object:
    """The expert a chain's subtask runs, without its handover and drawer shutting."""
    from policies.experts.libero_drawer import ShutFirst

    while isinstance(expert, Handover | ShutFirst):
        expert = expert.following if isinstance(expert, Handover) else expert.then
    return expert


def lowering(expert: object) -> OpenThenExpert | PickPlaceExpert | None:
    """The drawer placement (OpenThenExpert) still lowering its object, if `expert` is
    one: LIBERO counts a bowl In the top drawer ~5 cm above the drawer's floor, so a
    chain's next subtask begins while it is still on its way down. Let go there (revision
    5 at first), the bowl fell onto the drawer's front wall and wedged under the
    cabinet's top; the handover lets the placement finish first (PLACE_Y_DEEPER in
    policies/experts/libero_drawer.py says why it then fits). Likewise a pot held by its
    handle or a bottle that tips (`PickPlaceExpert.lowering`)."""
    from policies.experts.libero_drawer import OpenThenExpert

    expert = _unwrapped(expert)
    return expert if isinstance(expert, OpenThenExpert | PickPlaceExpert) and expert.lowering else None


def placed(expert: object) -> bool:
    """Whether a chain's last subtask put something into a drawer or on a piece of
    furniture's top, or put down something held by its handle (the opening fingers drag
    a handle) or a bottle that tips (`Geometry.set_down`): revision 5 lets go of it in place and rises first. (Into a tray it
    moves at once, as revisions 1-4 did: opening in place there lost 1 of 20 tray chains.)"""
    from policies.experts.libero_drawer import OpenThenExpert

    expert = _unwrapped(expert)
    return isinstance(expert, OpenThenExpert) or (
        isinstance(expert, PickPlaceExpert)
        and (
            expert.plan.surface is not None
            or expert.plan.obj_geom.grip_xy != (0.0, 0.0)
            or expert.plan.obj_geom.set_down
        )
    )


class Handover:
    """A chain's next subtask, started from where every expert was written to start.

    The experts plan from LIBERO's starting pose (the hand high over the table, fingers
    down, open). In a chain the next subtask begins wherever the last one ended, often
    low, turned, or still holding what it placed (LIBERO's `In` holds as soon as an
    object is inside a container's region, which reaches well above a tray). So the
    hand opens where it is (the goal holds, so what it holds is where the goal wants it)
    and returns to the chain's starting pose (at most HOME_STEPS steps of the next
    subtask's budget), then the next subtask's expert acts. Measured on both chain
    scenes against switching experts at once and against finishing the last placement
    first (docs/chains.md).
    """

    def __init__(
        self,
        following: object,
        home: np.ndarray | None,
        gain: float,
        open_first: bool = False,
        unbend: bool = False,
        finish: OpenThenExpert | PickPlaceExpert | None = None,
    ):
        from policies.experts.libero_drawer import ShutFirst

        self.following = following
        self.home, self.gain = home, gain
        if isinstance(following, ShutFirst) and home is not None:  # back there, not where it began
            for shut in following.shut:
                shut.home = np.array(home[:3])
        self.home_steps = 0
        self.opening = OPEN_STEPS if open_first else 0  # revision 5: steps left to open in place
        self.rising = RISE_STEPS if open_first else 0  # and then to rise
        self.anchor: np.ndarray | None = None  # where the hand was when the subtask began
        self.bending = BEND_STEPS if unbend else 0  # revision 5: steps left to bend the elbow
        self.finish = finish  # revision 5: a placement to finish first (`lowering`)

    def act(self, obs: np.ndarray) -> np.ndarray:
        if self.finish is not None and self.finish.lowering:
            return self.finish.act(obs)
        self.finish = None
        if self.home is not None and self.opening == 0 and self.bending > 0 and obs[ELBOW] > STRAIGHT:
            self.bending -= 1  # (after letting go) pitch the hand: that bends the elbow
            return np.array([0, 0, 0, 0, 1, 0, OPEN], dtype=np.float32)
        if self.home is not None and self.opening + self.rising > 0:
            if self.anchor is None:  # held where the hand is (a zero action lets it sag)
                self.anchor = np.array(obs[:3])
            target = self.anchor.copy()
            if self.opening > 0 and obs[7] < OPENED:
                self.opening -= 1
            else:
                self.opening = 0
                target[2] += RISE_FIRST
                self.rising = self.rising - 1 if obs[2] < target[2] - 0.01 else 0
            move = np.clip((target - obs[:3]) * self.gain, -1.0, 1.0)
            return np.concatenate([move, [0.0, 0.0, 0.0, OPEN]]).astype(np.float32)
        if self.home is not None:
            err = self.home[:3] - obs[:3]
            turn = rotation_error(quat_to_mat(self.home[3:7]), quat_to_mat(obs[3:7]))
            reached = np.linalg.norm(err) < HOME_REACHED[0] and np.linalg.norm(turn) < HOME_REACHED[1]
            if reached or self.home_steps >= HOME_STEPS:
                self.home = None
            else:
                self.home_steps += 1
                move = np.clip(err * self.gain, -1.0, 1.0)
                return np.concatenate([move, np.clip(turn / MAX_DELTA_RAD, -1.0, 1.0), [OPEN]]).astype(
                    np.float32
                )
        return self.following.act(obs)  # type: ignore[attr-defined]
