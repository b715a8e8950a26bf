"""The kitchen scene with opposites (adapters/chain_data/kitchen_scene1.toml): its
authored complements in the precondition model, its stored chains, and (with the libero
extra) an authored close undoing its open on the live state, done by the scripted expert."""

from __future__ import annotations

import pytest

from adapters import chain_scenes as cs
from adapters import libero as lb
from tests.chain_live import expert_plays_a_pair

needs_libero = pytest.mark.skipif(not lb.installed(), reason="needs the libero extra")
SCENE = "kitchen_scene1"
DRAWERS = ("top", "middle", "bottom")


@pytest.fixture(autouse=True)
def _fresh_caches():
    yield
    cs.load_scene.cache_clear()
    cs.load_chains.cache_clear()


def start_state() -> frozenset[cs.Predicate]:
    """The BDDL's :init of KITCHEN_SCENE1 (what adapters.chain_scenes.scene_problem reads)."""
    return frozenset(
        {
            ("on", "akita_black_bowl_1", "kitchen_table_akita_black_bowl_init_region"),
            ("on", "plate_1", "kitchen_table_plate_init_region"),
            ("on", "wooden_cabinet_1", "kitchen_table_wooden_cabinet_init_region"),
        }
    )


def test_every_authored_close_undoes_its_open_in_the_model():
    scene = cs.load_scene(SCENE)
    authored = [s for s in scene.subtasks if s.source == "authored"]
    assert {s.id for s in authored} == {
        "close_top_drawer",
        "close_middle_drawer",
        "close_bottom_drawer",
        "open_middle_drawer",
    }
    for drawer in DRAWERS:
        opened, closed = scene.subtask(f"open_{drawer}_drawer"), scene.subtask(f"close_{drawer}_drawer")
        state = cs.apply(opened, start_state())
        assert closed in cs.eligible(scene, state) and opened not in cs.eligible(scene, state)
        state = cs.apply(closed, state)
        assert set(opened.goal).isdisjoint(state) and set(closed.goal) <= state
        assert opened in cs.eligible(scene, state)  # and it can be opened again
        assert closed not in cs.eligible(scene, start_state())  # nothing to close at the start
    # one drawer out at a time: with the top one open, no other opens
    state = cs.apply(scene.subtask("open_top_drawer"), start_state())
    assert {s.id for s in cs.eligible(scene, state) if s.id.startswith("open_")} == set()


def test_the_stored_chains_are_valid_and_undo_what_they_did():
    scene, stored = cs.load_scene(SCENE), cs.load_chains(SCENE)
    assert len(stored.chains) == cs.CHAINS_PER_SCENE == 200 and stored.scene == SCENE
    for j, chain in enumerate(stored.chains):
        cs.check_chain(scene, chain, start_state(), f"chain {j}")
    sampled = cs.sample_chains(scene, start_state(), len(stored.chains), stored.seed, cs.INITIAL_STATES)
    assert sampled == list(stored.chains)
    undoing = [c for c in stored.chains if any(s.startswith("close_") for s in c)]
    assert len(undoing) >= 10  # the point of the scene: chains that undo an earlier subtask


@needs_libero
def test_the_suite_loads_and_re_checks_the_chains_from_the_bddl():
    from adapters import chains

    suite = chains.load_suite(f"chains/{SCENE}")
    (task,) = suite.tasks
    assert [e.chain for e in task.episodes] == list(cs.load_chains(SCENE).chains)
    assert cs.initial_state(cs.scene_problem(cs.load_scene(SCENE))) == start_state()
    assert suite.name == f"chains/{SCENE}:seeding=openvla"


@needs_libero
def test_the_expert_closes_what_it_opened_on_the_live_state():
    """The scripted expert opens the bottom drawer (LIBERO-90's task; its bar is too low
    to pinch, so it presses on the bar and pulls), then closes it (the authored
    complement): LIBERO's predicates on the live state say the close undid the open, as
    the model's `removes` says, and both subtasks are credited."""
    chain = ("open_bottom_drawer", "close_bottom_drawer", "bowl_on_plate", "bowl_on_cabinet", "bowl_on_plate")
    region = "wooden_cabinet_1_bottom_region"
    opened, closed = ("open", region), ("close", region)
    at_start, seen, first, second = expert_plays_a_pair(SCENE, chain, opened, closed)
    assert not at_start[0]
    assert seen == [(True, False), (False, True)]  # opened, then closed: undone
    assert first["outcome"] == second["outcome"] == "completed"
    assert second["start_step"] == first["end_step"] and not second["goal_held_at_start"]


@needs_libero
@pytest.mark.parametrize(("level", "kind"), [("top", "DrawerExpert"), ("bottom", "PressPullExpert")])
def test_the_bottom_drawer_is_pressed_open_and_the_others_pinched(level, kind):
    """Which opening the expert picks from the subtask's goal: the pitched pinch reaches
    the top and middle bars, not the bottom one, 4 cm above the table."""
    from adapters import chains
    from policies.base import EpisodeContext
    from policies.experts.libero_scripted import LiberoScriptedParams
    from policies.experts.libero_select import expert_for

    suite = chains.load_suite(f"chains/{SCENE}")
    scene = cs.load_scene(SCENE)
    instruction = next(s.instruction for s in scene.subtasks if s.id == f"open_{level}_drawer")
    env = suite.make_env(suite.tasks[0])
    try:
        ctx = EpisodeContext(
            suite.name, suite.tasks[0].name, instruction, env.action_space, env.observation_space,
            cs.STEPS_PER_SUBTASK, 0,
        )  # fmt: skip
        expert = expert_for(ctx, LiberoScriptedParams(), None)
    finally:
        env.close()
    opener = getattr(expert, "then", expert)  # ShutFirst wraps it when other drawers are in the state
    assert type(opener).__name__ == kind
    assert opener.plan.level == level
