"""The scripted LIBERO expert in chain suites: the handover between subtasks, where it
puts objects (a tray's free spot, a cabinet top beside what stands there), and chains of
chains/libero_goal that earlier revisions failed, replayed in the simulator."""

from __future__ import annotations

import numpy as np
import pytest

from adapters import libero as lb
from policies.base import EpisodeContext

needs_libero = pytest.mark.skipif(not lb.installed(), reason="needs the libero extra")


def test_the_next_subtasks_expert_starts_from_the_chains_starting_pose():
    from policies.experts.libero_select import HOME_STEPS, Handover

    class Next:
        def act(self, obs):
            return np.full(7, 0.5)

    home = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])  # position, xyzw quaternion
    handover = Handover(Next(), home, gain=10.0)
    obs = np.concatenate([[0.0, 0.0, 0.9], home[3:], np.zeros(2)])  # 10 cm below home, open
    first = handover.act(obs)
    assert first[2] == pytest.approx(1.0) and first[6] == -1.0 and not first[3:6].any()  # up, open
    obs[2] = 0.995  # within 2 cm: back
    assert (handover.act(obs) == 0.5).all() and (handover.act(obs) == 0.5).all()  # the next expert, for good
    stuck = Handover(Next(), home, gain=10.0)  # never reaching home: the next expert after HOME_STEPS
    obs[2] = 0.5
    actions = [stuck.act(obs)[0] for _ in range(HOME_STEPS + 3)]
    assert actions[:HOME_STEPS] == [0.0] * HOME_STEPS and actions[HOME_STEPS:] == [0.5] * 3


def test_the_expert_puts_a_trays_next_object_on_its_free_spot():
    """Revision 4 aims at the floor point farthest from what the tray already holds (the
    region's centre when empty); revision 3 aims at the centre whatever is there."""
    from policies.experts.libero_geometry import GEOMETRY
    from policies.experts.libero_pick import LiberoScriptedParams, PickPlace, PickPlaceExpert

    tray = GEOMETRY["wooden_tray"]
    obs = np.zeros(40)
    obs[10:17] = [0.0, 0.3, 0.44, 0.0, 0.0, 1.0, 0.0]  # the tray, turned 180 degrees about z
    obs[17:20] = [0.0, 0.3, 0.48]  # its contain region's centre
    obs[20:23] = [0.05, 0.3, 0.5]  # a can already in the tray, right of centre
    obs[23:26] = [0.5, 0.5, 0.45]  # a box on the table, not in the tray
    plan = PickPlace(
        obj=slice(30, 37), obj_geom=GEOMETRY["ketchup"], target=slice(17, 20), target_geom=None, into=True,
        others=(slice(10, 17), slice(20, 27), slice(23, 30)), container=slice(10, 17), container_geom=tray,
    )  # fmt: skip
    spot = PickPlaceExpert(plan, LiberoScriptedParams(revision=4), None)._place_point(obs)
    assert spot[0] < -0.05 and abs(spot[1] - 0.3) <= tray.inner[1]  # the far end of the long axis
    assert abs(spot[0]) <= tray.inner[0] and spot[2] == pytest.approx(0.48)
    old = PickPlaceExpert(plan, LiberoScriptedParams(revision=3), None)._place_point(obs)
    assert old[:2] == pytest.approx([0.0, 0.3])
    obs[20:23] = [0.5, -0.5, 0.45]  # nothing in the tray: its centre
    empty = PickPlaceExpert(plan, LiberoScriptedParams(revision=4), None)._place_point(obs)
    assert empty[:2] == pytest.approx([0.0, 0.3])


def test_the_expert_puts_an_object_on_a_cabinet_top_beside_what_stands_there():
    """Revision 5 puts an object going on a cabinet's top near the robot (at -x) and
    SURFACE_CLEAR from what already stands there, the first leaving the second room no
    farther than the centre; revisions 1-4 aimed at the top's centre, where a wine bottle
    (4 cm in radius) meets a bowl (5.5 cm) standing by it (chains/libero_goal)."""
    from policies.experts.libero_geometry import GEOMETRY
    from policies.experts.libero_pick import (
        ROBOT_XY,
        SURFACE_CLEAR,
        LiberoScriptedParams,
        PickPlace,
        PickPlaceExpert,
    )

    obs = np.zeros(40)
    obs[10:17] = [0.04, -0.234, 0.905, 0.0, 0.0, 1.0, 0.0]  # the cabinet, turned 180 degrees
    obs[17:20] = [0.036, -0.25, 1.127]  # its top_side site
    obs[20:23] = [0.036, -0.25, 1.127]  # the top's centre, for the first object
    obs[23:26] = [-0.05, 0.13, 0.909]  # cream cheese on the table
    plan = PickPlace(
        obj=slice(30, 37), obj_geom=GEOMETRY["wine_bottle"], target=slice(17, 20), target_geom=None,
        into=False, others=(slice(20, 27), slice(23, 30)), surface=slice(10, 17),
        surface_geom=GEOMETRY["wooden_cabinet"],
    )  # fmt: skip
    obs[22] = 0.0  # nothing on the top yet: the first object takes a corner near the robot
    first = PickPlaceExpert(plan, LiberoScriptedParams(revision=5), None)._place_point(obs)
    reach = np.linalg.norm(obs[17:19] - ROBOT_XY)  # the top's centre, where revision 4 aims
    assert np.linalg.norm(first[:2] - ROBOT_XY) < reach - 0.04
    obs[20:23] = first  # a bowl standing there: the next one goes beside it, no farther than the centre
    spot = PickPlaceExpert(plan, LiberoScriptedParams(revision=5), None)._place_point(obs)
    assert np.linalg.norm(spot[:2] - first[:2]) >= SURFACE_CLEAR
    assert np.linalg.norm(spot[:2] - ROBOT_XY) < reach + 0.015
    assert abs(spot[0] - 0.036) <= 0.125 and abs(spot[1] + 0.25) <= 0.094  # on the top
    old = PickPlaceExpert(plan, LiberoScriptedParams(revision=4), None)._place_point(obs)
    assert old[:2] == pytest.approx([0.036, -0.25])  # the centre, against the bowl's rim
    assert np.linalg.norm(old[:2] - obs[20:22]) < 0.055 + 0.04


@needs_libero
@pytest.mark.parametrize(("revision", "completed"), [(4, 2), (5, 3)])
def test_the_expert_drags_the_plate_from_under_the_drawer_it_opened(revision, completed):
    """Chain 21 of chains/libero_goal: the bowl onto the cabinet, the middle drawer, then
    the plate to the stove's front. Revision 4's pitched hand swept the plate further
    under the drawer it opened, and the open drawer covers the plate's far half: no
    revision-4 chain pushed the plate after opening that drawer. Revision 5 lines up on
    the handle from above and pushes the drawer back in before it drags the plate."""
    assert _chain(21)[:3] == ("bowl_on_cabinet", "open_middle_drawer", "plate_to_stove_front")
    assert _goal_chain(21, revision, 3) == completed


def _goal_chain(index: int, revision: int, subtasks: int) -> int:
    """Subtasks the expert of `revision` completes of the first `subtasks` of chain
    `index` of chains/libero_goal, stepping the chain env as the runner would."""
    from adapters import chains
    from policies.experts.libero_scripted import LiberoScripted, LiberoScriptedParams

    suite = chains.load_suite("chains/libero_goal")
    task = suite.tasks[0]
    spec = task.episodes[index]
    env = suite.make_env(task)
    try:
        obs, info = env.reset(seed=spec.seed, options={"episode": spec})
        expert = LiberoScripted(LiberoScriptedParams(revision=revision))
        k = -1
        while info["subtasks_completed"] < subtasks:
            if info["subtask_index"] != k:
                k = info["subtask_index"]
                ctx = EpisodeContext(
                    suite.name, task.name, info["instruction"], env.action_space, env.observation_space,
                    360, index, subtask_index=k,
                )  # fmt: skip
                expert.reset([ctx])
            obs, _, terminated, _, info = env.step(expert.act([obs]).actions[0, 0])
            if terminated:
                break
        return info["subtasks_completed"]
    finally:
        env.close()


def test_the_handover_lets_a_drawer_placement_finish_before_it_opens():
    """LIBERO counts the bowl In the top drawer ~5 cm above its floor, so a chain's next
    subtask begins mid-placement; revision 5's handover lowers it on (the placing expert
    acts while it is `lowering`), then opens in place. Revisions 1-4 go on at once."""
    from policies.experts.libero_drawer import OpenThenExpert
    from policies.experts.libero_scripted import LiberoScriptedParams
    from policies.experts.libero_select import handover, lowering

    class Drawer:
        done = True

    class Placing:
        phase = "lower"

        def act(self, obs):
            self.phase = "release"  # let go after one more step down
            return np.full(7, 0.25)

    class Next:
        def act(self, obs):
            return np.full(7, 0.5)

    placement = OpenThenExpert(Drawer(), Placing())  # type: ignore[arg-type]
    placement.act = lambda obs: placement.then.act(obs)  # type: ignore[method-assign]
    assert lowering(placement) is placement
    home = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0])
    obs = np.concatenate([[0.0, 0.0, 0.9], home[3:], np.zeros(8)])  # fingers closed (obs[7] = 0)
    assert handover(Next(), placement, home, LiberoScriptedParams(revision=4)).finish is None
    chained = handover(Next(), placement, home, LiberoScriptedParams(revision=5))
    assert (chained.act(obs) == 0.25).all()  # still lowering: the placement's own action
    assert lowering(placement) is None  # let go: no longer lowering
    opening = chained.act(obs)
    assert opening[6] == -1.0 and not opening[:6].any()  # then opens in place


@needs_libero
@pytest.mark.parametrize("finish", [False, True])
def test_the_bowl_put_into_the_top_drawer_lets_it_shut(monkeypatch, finish):
    """Chain 36 of chains/libero_goal: the bowl into the top drawer, then the middle
    drawer. Let go where LIBERO first counts it In (revision 5 at first: at PLACE_Y, no
    finishing), the bowl fell onto the ajar drawer's front wall and wedged tilted under
    the cabinet's top, the top drawer stuck ~5 cm out over the middle drawer's handle;
    put deeper and lowered to the floor, it pushes the drawer out until it fits, lies flat
    and the drawer shuts."""
    from policies.experts import libero_drawer, libero_select

    if not finish:
        monkeypatch.setattr(libero_select, "lowering", lambda expert: None)
        monkeypatch.setattr(libero_drawer, "PLACE_Y_DEEPER", libero_drawer.PLACE_Y)
    assert _chain(36)[:2] == ("bowl_in_top_drawer", "open_middle_drawer")
    assert _goal_chain(36, 5, 2) == (2 if finish else 1)


def _chain(index: int) -> tuple[str, ...]:
    """The subtask ids of chain `index` of chains/libero_goal."""
    from adapters import chains

    return tuple(chains.load_suite("chains/libero_goal").tasks[0].episodes[index].chain)
