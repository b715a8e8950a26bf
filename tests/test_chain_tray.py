"""The scene that puts objects into a container and takes them out again
(adapters/chain_data/living_room_scene4.toml): its put-in / take-out pairs in the
precondition model, its stored chains, CALVIN's credit on a chain with a pair, the
expert's grip on an object resting in the tray, and (with the libero extra) the expert
putting the bowl into the tray and taking it out again on the live state."""

from __future__ import annotations

import numpy as np
import pytest

from adapters import chain_credit as cc
from adapters import chain_scenes as cs
from adapters import libero as lb
from tests.chain_live import expert_plays_a_pair
from tests.test_chain_stove import _fresh_caches, complementary_pairs  # noqa: F401 (an autouse fixture)

needs_libero = pytest.mark.skipif(not lb.installed(), reason="needs the libero extra")
SCENE = "living_room_scene4"
TRAY = "wooden_tray_1_contain_region"
# Each object and its starting region (LIVING_ROOM_SCENE4's BDDL), where a take-out puts it back.
OBJECTS = {
    "chocolate_pudding": ("chocolate_pudding_1", "living_room_table_chocolate_pudding_init_region"),
    "salad_dressing": ("new_salad_dressing_1", "living_room_table_salad_dressing_init_region"),
    "left_bowl": ("akita_black_bowl_1", "living_room_table_akita_black_bowl_left_init_region"),
}


def start_state() -> frozenset[cs.Predicate]:
    """The BDDL's :init of LIVING_ROOM_SCENE4 (what adapters.chain_scenes.scene_problem reads)."""
    return frozenset(
        {
            ("on", "chocolate_pudding_1", "living_room_table_chocolate_pudding_init_region"),
            ("on", "akita_black_bowl_1", "living_room_table_akita_black_bowl_left_init_region"),
            ("on", "akita_black_bowl_2", "living_room_table_akita_black_bowl_right_init_region"),
            ("on", "new_salad_dressing_1", "living_room_table_salad_dressing_init_region"),
            ("on", "wooden_tray_1", "living_room_table_wooden_tray_init_region"),
        }
    )


def test_every_take_out_undoes_its_put_in_in_the_model():
    scene = cs.load_scene(SCENE)
    assert set(complementary_pairs(scene)) == {(f"{o}_in_tray", f"{o}_out_of_tray") for o in OBJECTS}
    for name, (obj, region) in OBJECTS.items():
        put_in, take_out = scene.subtask(f"{name}_in_tray"), scene.subtask(f"{name}_out_of_tray")
        assert put_in.goal == (("in", obj, TRAY),) and take_out.goal == (("on", obj, region),)
        assert take_out.goal_not == (("in", obj, TRAY),)  # on its region and out of the tray
        assert take_out not in cs.eligible(scene, start_state())  # nothing in the tray at the start
        state = cs.apply(put_in, start_state())
        assert ("on", obj, region) not in state
        assert take_out in cs.eligible(scene, state) and put_in not in cs.eligible(scene, state)
        state = cs.apply(take_out, state)
        assert ("in", obj, TRAY) not in state and ("on", obj, region) in state
        assert put_in in cs.eligible(scene, state) and take_out not in cs.eligible(scene, state)


def test_the_stored_chains_are_the_samplers_and_take_out_what_they_put_in():
    scene, stored = cs.load_scene(SCENE), cs.load_chains(SCENE)
    assert len(stored.chains) == cs.CHAINS_PER_SCENE and stored.scene == SCENE
    for j, chain in enumerate(stored.chains):
        cs.check_chain(scene, chain, start_state(), f"chain {j}")
    cs.check_distinct(stored.chains, cs.INITIAL_STATES, SCENE)
    sampled = cs.sample_chains(scene, start_state(), len(stored.chains), stored.seed, cs.INITIAL_STATES)
    assert sampled == list(stored.chains) and sampled[:50] == cs.sample_chains(scene, start_state(), 50, 0)
    # Three objects and five subtasks: every chain takes out something it put in.
    assert all(any(s.endswith("_out_of_tray") for s in c) for c in stored.chains)


def test_calvins_credit_on_a_chain_that_puts_in_and_takes_out():
    """The take-out counts only once its object has left the tray for its starting region
    after the take-out took over. An object counted In the tray and On its region at once
    (the tray under it) has not been taken out: the take-out stays in force until the
    object is on its region and out of the tray."""
    scene = cs.load_scene(SCENE)
    ids = ("left_bowl_in_tray", "left_bowl_out_of_tray", "chocolate_pudding_in_tray")
    chain = tuple(scene.subtask(i) for i in (*ids, "chocolate_pudding_out_of_tray", "left_bowl_in_tray"))
    bowl, region = OBJECTS["left_bowl"]
    true: set[cs.Predicate] = {("on", bowl, region)}
    credit = cc.ChainCredit.begin(chain, lambda p: tuple(p) in true)
    assert not credit.after_step(lambda p: tuple(p) in true)
    true = {("in", bowl, TRAY)}  # lifted off its region and put in the tray
    assert not credit.after_step(lambda p: tuple(p) in true)
    assert [r["outcome"] for r in credit.records[:2]] == [cc.COMPLETED, cc.IN_PROGRESS]
    assert not credit.after_step(lambda p: tuple(p) in true)  # still in the tray
    true = {("on", bowl, region)}  # back on its starting region
    assert not credit.after_step(lambda p: tuple(p) in true)
    assert credit.completed == 2 and credit.records[1]["steps"] == 2
    assert credit.records[2]["outcome"] == cc.IN_PROGRESS

    carried = cc.ChainCredit.begin(chain, lambda p: False)
    both = {("in", bowl, TRAY), ("on", bowl, region)}  # in the tray, the tray on its region
    assert not carried.after_step(lambda p: tuple(p) in both)
    assert [r["outcome"] for r in carried.records[:2]] == [cc.COMPLETED, cc.IN_PROGRESS]
    assert not carried.records[1]["goal_held_at_start"]
    assert not carried.after_step(lambda p: tuple(p) in both)  # the tray carried there is no take-out
    assert carried.completed == 1
    assert not carried.after_step(lambda p: tuple(p) in {("on", bowl, region)})  # out of the tray
    assert carried.completed == 2 and carried.records[1]["outcome"] == cc.COMPLETED


@needs_libero
def test_on_the_live_state_a_tray_carried_to_the_region_is_not_a_take_out():
    """LIBERO's On and In hold together when the tray is set down with the pudding in it
    over the pudding's starting region (the expert's revision 5 lifts the tray with the pudding,
    its far finger pinching the tray's wall): the take-out's goal is then false, and true
    once the pudding stands on its region out of the tray."""
    from adapters import chains
    from adapters.base import EpisodeSpec

    scene = cs.load_scene(SCENE)
    take_out = scene.subtask("chocolate_pudding_out_of_tray")
    obj, region = OBJECTS["chocolate_pudding"]
    chain = ("chocolate_pudding_in_tray", "chocolate_pudding_out_of_tray", "left_bowl_in_tray",
             "salad_dressing_in_tray", "chocolate_pudding_out_of_tray")  # fmt: skip
    suite = chains.load_suite(f"chains/{SCENE}")
    env = suite.make_env(suite.tasks[0])
    try:
        env.reset(options={"episode": EpisodeSpec(index=0, seed=0, init_state_id=0, chain=chain)})
        sim = env.inner.libero.env.sim
        assert env.holds(("on", obj, region)) and not env.holds(("in", obj, TRAY))  # at the start
        pudding = sim.data.get_joint_qpos(f"{obj}_joint0").copy()
        tray = sim.data.get_joint_qpos("wooden_tray_1_joint0").copy()
        tray[:2] = pudding[:2]  # the tray under the pudding, on the pudding's region
        pudding[2] += 0.04  # onto the tray's floor
        sim.data.set_joint_qpos("wooden_tray_1_joint0", tray)
        sim.data.set_joint_qpos(f"{obj}_joint0", pudding)
        sim.forward()
        for _ in range(200):  # settle
            sim.step()
        assert env.holds(("in", obj, TRAY)) and env.holds(("on", obj, region))
        assert not cc.goal_holds(take_out, env.holds)
        tray[:2] += [0.0, 0.45]  # the tray away; the pudding back on the table
        pudding[2] -= 0.04
        sim.data.set_joint_qpos("wooden_tray_1_joint0", tray)
        sim.data.set_joint_qpos(f"{obj}_joint0", pudding)
        sim.forward()
        for _ in range(200):
            sim.step()
        assert not env.holds(("in", obj, TRAY)) and env.holds(("on", obj, region))
        assert cc.goal_holds(take_out, env.holds)
    finally:
        env.close()


def _bowl_plan(tray_yaw: float):
    from policies.experts.libero_geometry import GEOMETRY
    from policies.experts.libero_pick import LiberoScriptedParams, PickPlace, PickPlaceExpert

    obs = np.zeros(40)
    obs[0:7] = [0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]  # the hand, pointing down (xyzw)
    obs[10:17] = [0.0, 0.3, 0.44, 0.0, 0.0, np.sin(tray_yaw / 2), np.cos(tray_yaw / 2)]  # the tray
    along = 0.05 * np.array([np.cos(tray_yaw), np.sin(tray_yaw)])  # 5 cm along the tray's long side
    obs[20:27] = [along[0], 0.3 + along[1], 0.445, 0.0, 0.0, 0.0, 1.0]  # the bowl, in it off centre
    obs[27:30] = [-0.1, -0.15, 0.44]  # its starting region, on the table
    plan = PickPlace(
        obj=slice(20, 27), obj_geom=GEOMETRY["akita_black_bowl"], target=slice(27, 30), target_geom=None,
        into=False, others=(slice(10, 17),), source=slice(10, 17), source_geom=GEOMETRY["wooden_tray"],
    )  # fmt: skip
    expert = PickPlaceExpert(plan, LiberoScriptedParams(), None)
    expert.home_rot = np.diag([1.0, -1.0, -1.0])  # the xyzw quaternion above
    return expert, obs


@pytest.mark.parametrize("tray_yaw", [0.0, np.pi / 2])
def test_a_bowl_in_the_tray_is_gripped_along_the_trays_long_side_toward_its_centre(tray_yaw):
    """The tray's walls stand 3.2 cm beyond its floor across its short side, so a rim grip
    across it puts a finger on the wall: in the tray, the fingers close along its long side
    and grip the rim on the side toward its centre; on the table, as before."""
    expert, obs = _bowl_plan(tray_yaw)
    long_side = np.array([np.cos(tray_yaw), np.sin(tray_yaw)])
    rot, point = expert._grasp(obs)
    assert abs(rot[:2, 1] @ long_side) == pytest.approx(1.0)  # closing along the long side
    rim = point[:2] - obs[20:22]
    assert np.linalg.norm(rim) == pytest.approx(0.045)
    assert rim @ (obs[10:12] - obs[20:22]) > 0  # the side toward the tray's centre
    obs[20:22] = [0.5, -0.3]  # out of the tray, on the table
    rot, point = expert._grasp(obs)
    assert rot == pytest.approx(expert.home_rot) and point[:2] - obs[20:22] == pytest.approx([0.0, 0.045])


def _pudding_plan(tray_yaw: float, revision: int = 6):
    """The pudding resting in the tray 3.5 cm off its long axis (as after chain 35's put-in),
    its box lined up with the tray, and the expert about to take it out."""
    from policies.experts.libero_geometry import GEOMETRY
    from policies.experts.libero_pick import LiberoScriptedParams, PickPlace, PickPlaceExpert

    rot = np.array([[np.cos(tray_yaw), -np.sin(tray_yaw)], [np.sin(tray_yaw), np.cos(tray_yaw)]])
    quat = [0.0, 0.0, np.sin(tray_yaw / 2), np.cos(tray_yaw / 2)]  # xyzw
    obs = np.zeros(40)
    obs[0:7] = [0.0, 0.0, 1.0, 1.0, 0.0, 0.0, 0.0]  # the hand, pointing down (xyzw)
    obs[10:17] = [0.0, 0.3, 0.437, *quat]  # the tray
    obs[20:27] = [*(np.array([0.0, 0.3]) + rot @ [0.1, 0.035]), 0.486, *quat]  # the pudding, near a long wall
    obs[27:30] = [-0.1, -0.15, 0.44]  # its starting region, on the table
    plan = PickPlace(
        obj=slice(20, 27), obj_geom=GEOMETRY["chocolate_pudding"], target=slice(27, 30), target_geom=None,
        into=False, others=(slice(10, 17),), source=slice(10, 17), source_geom=GEOMETRY["wooden_tray"],
    )  # fmt: skip
    expert = PickPlaceExpert(plan, LiberoScriptedParams(revision=revision), None)
    expert.home_rot = np.diag([1.0, -1.0, -1.0])  # the xyzw quaternion above
    return expert, obs, rot


@pytest.mark.parametrize("tray_yaw", [0.0, np.pi / 2, np.pi])
def test_an_object_near_the_trays_wall_is_gripped_with_the_open_hand_clear_of_it(tray_yaw):
    """Revision 6: the open hand reaches OPEN_REACH along its closing axis; gripped at its
    centre, 4.3 cm from the tray's long wall, the pudding put the far finger on the wall and
    the tray came up with it (chains 30, 34, 35). The grip point moves toward the tray's
    centre until the hand clears the wall, by at most WALL_SHIFT; in the middle of the tray,
    on the table, or under revision 5 it stays on the pudding."""
    from policies.experts.libero_geometry import GEOMETRY
    from policies.experts.libero_pick import OPEN_REACH, WALL_SHIFT

    expert, obs, rot = _pudding_plan(tray_yaw)
    grip_rot, point = expert._grasp(obs)
    closing = rot.T @ grip_rot[:2, 1]
    assert abs(closing[1]) == pytest.approx(1.0, abs=1e-6)  # across the tray, the pudding's short side
    local = rot.T @ (point[:2] - obs[10:12])
    moved = local - [0.1, 0.035]
    assert (
        moved[0] == pytest.approx(0.0, abs=1e-9) and -WALL_SHIFT - 1e-9 <= moved[1] < 0
    )  # toward the centre
    wall = GEOMETRY["wooden_tray"].inner[1]
    assert local[1] + OPEN_REACH == pytest.approx(wall, abs=1e-9) or moved[1] == pytest.approx(-WALL_SHIFT)

    obs[20:22] = obs[10:12] + rot @ [0.0, 0.0]  # in the middle of the tray: room either side
    assert expert._grasp(obs)[1][:2] == pytest.approx(obs[20:22])
    obs[20:22] = [0.5, -0.3]  # on the table: no walls
    assert expert._grasp(obs)[1][:2] == pytest.approx(obs[20:22])
    old, obs, _ = _pudding_plan(tray_yaw, revision=5)
    assert old._grasp(obs)[1][:2] == pytest.approx(obs[20:22])


@needs_libero
def test_the_expert_takes_out_of_the_tray_what_it_put_in_on_the_live_state():
    """The scripted expert puts the salad dressing into the tray (LIBERO-90's task), then
    takes it out to its starting region (the authored complement): LIBERO's predicates on
    the live state say the take-out undid the put-in, and both subtasks are credited. The
    bottle is set down, not dropped: let go where LIBERO first counts it In, from initial
    state 1 it landed on its side, where the hand closed on nothing. (The bowl's grip in
    the tray, along its long side, is the test above; one live pair keeps the suite short.)"""
    chain = ("salad_dressing_in_tray", "salad_dressing_out_of_tray", "left_bowl_in_tray",
             "chocolate_pudding_in_tray", "salad_dressing_in_tray")  # fmt: skip
    obj, region = OBJECTS["salad_dressing"]
    at_start, seen, first, second = expert_plays_a_pair(
        SCENE, chain, ("in", obj, TRAY), ("on", obj, region), init_state_id=1
    )
    assert at_start == (False, True)
    assert seen == [(True, False), (False, True)]  # in the tray, then out on its region: undone
    assert first["outcome"] == second["outcome"] == "completed"
    assert second["start_step"] == first["end_step"] and not second["goal_held_at_start"]
