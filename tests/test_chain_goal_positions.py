"""`goal_positions=on`, the chain suites' one option of their own: the state gains the
positions of the goal arguments of the subtask in force, read from the state itself,
and switching with the instruction (docs/chains-policies.md, "Goal positions")."""

from __future__ import annotations

import numpy as np
import pytest

from adapters import libero as lb
from adapters.base import EpisodeSpec
from adapters.libero_options import SuiteOptionError
from policies.base import EpisodeContext

SCENE = "living_room_scene3"


def test_the_option_is_taken_out_before_liberos_parse():
    from adapters.chains import split_chain_options

    assert split_chain_options("goal_positions=on,seeding=openpi") == ("seeding=openpi", True, None)
    assert split_chain_options("obs=images") == ("obs=images", False, None)
    assert split_chain_options("goal_positions=off") == ("", False, None)
    assert split_chain_options("chains=my.json,obs=images") == ("obs=images", False, "my.json")
    with pytest.raises(SuiteOptionError, match="expected on or off"):
        split_chain_options("goal_positions=maybe")


def test_a_subtask_with_two_goal_predicates_is_refused_not_half_described():
    from adapters import chain_scenes as cs
    from adapters.chains import goal_arguments

    one = cs.Subtask("a", "open it", (("open", "drawer_1"),), (), (), (), "authored")
    assert goal_arguments(one) == ("drawer_1", "drawer_1")
    two = cs.Subtask(
        "b", "do both", (("open", "drawer_1"), ("on", "bowl_1", "plate_1")), (), (), (), "authored"
    )
    with pytest.raises(cs.ChainDataError, match="2 goal predicates"):
        goal_arguments(two)


def test_an_unknown_option_names_the_chain_option_too():
    from adapters.chains import load_suite

    with pytest.raises(SuiteOptionError, match=r"goal_positions=on\|off"):
        load_suite(f"chains/{SCENE}:goal=on")


@pytest.mark.skipif(not lb.installed(), reason="needs the libero extra")
def test_goal_positions_follow_the_subtask_in_force():
    from adapters import chains
    from policies.experts.libero_scripted import LiberoScripted, LiberoScriptedParams

    plain = chains.load_suite(f"chains/{SCENE}")
    suite = chains.load_suite(f"chains/{SCENE}:goal_positions=on")
    assert suite.name == f"chains/{SCENE}:seeding=openvla,goal_positions=on" and plain.name != suite.name
    spec = EpisodeSpec(
        index=0,
        seed=0,
        init_state_id=0,
        chain=(
            "butter_in_tray",
            "ketchup_in_tray",
            "alphabet_soup_in_tray",
            "cream_cheese_in_tray",
            "tomato_sauce_in_tray",
        ),
    )
    ref = plain.make_env(plain.tasks[0])
    try:  # one LIBERO env at a time in a process
        base, positions, layout = ref.observation_space.shape[0], ref.state_positions, ref.layout
        same, _ = ref.reset(options={"episode": spec})
    finally:
        ref.close()
    env = suite.make_env(suite.tasks[0])
    try:
        assert env.observation_space.shape == (base + 6,)
        assert env.state_positions == (*positions, base, base + 3)
        obs, info = env.reset(options={"episode": spec})
        np.testing.assert_array_equal(obs[:base], same)  # the scene's state is untouched
        at = {name: start for name, start, _ in layout}

        def where(name: str) -> np.ndarray:
            return obs[at[name] : at[name] + 3]

        np.testing.assert_array_equal(
            obs[base:], np.concatenate([where("butter_1"), where("wooden_tray_1_contain_region")])
        )
        ctx = EpisodeContext(
            suite.name, SCENE, info["instruction"], env.action_space, env.observation_space, 360, 0
        )
        expert = LiberoScripted(LiberoScriptedParams())
        expert.reset([ctx])
        for _ in range(360):
            obs, _, _, _, info = env.step(expert.act([obs]).actions[0, 0])
            if info["subtask_index"] == 1:
                break
        assert info["subtasks_completed"] == 1  # the observation after the switch: the next goal
        np.testing.assert_array_equal(obs[base : base + 3], where("ketchup_1"))
        np.testing.assert_array_equal(obs[base + 3 :], where("wooden_tray_1_contain_region"))
    finally:
        env.close()
