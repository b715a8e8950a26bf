"""LIBERO-PRO perturbations as a suite option: parsing, files, instructions, env states, resets."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from adapters import libero as lb
from adapters import libero_pro as lp
from adapters.libero_options import SuiteOptionError, parse_options
from adapters.registry import list_suites

pytestmark = pytest.mark.libero
needs_libero = pytest.mark.skipif(not lb.installed(), reason="needs the libero extra")


@pytest.mark.parametrize(
    ("text", "combo"),
    [
        ("swap", ("swap",)),
        ("lan+swap", ("swap", "lan")),
        ("lan + env", ("env", "lan")),
        ("task", ("task",)),
        ("object+swap", ("swap", "object")),
        ("lan+object+env+swap", ("swap", "env", "object", "lan")),
    ],
)
def test_perturbations_parse_into_libero_pros_order(text, combo):
    assert lp.parse_perturb(text) == combo
    options = parse_options(f"perturb={text}")
    assert options.perturb == combo
    assert options.suffix().startswith(f":perturb={'+'.join(combo)},")


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("task+lan", "task perturbation combines with nothing"),
        ("swap+object+task", "docs/libero-pro.md, 'Combinations'"),
        ("colour", "perturbations are"),
        ("swap+swap", "perturbations are"),
    ],
)
def test_forbidden_combinations_name_the_allowed_ones(text, needle):
    with pytest.raises(SuiteOptionError) as err:
        lp.parse_perturb(text)
    assert needle in str(err.value)
    allowed = str(err.value).split("allowed: ")[1].split(", ")
    assert allowed[:5] == ["swap", "env", "object", "lan", "swap+env"] and allowed[-1] == "task"
    assert len(allowed) == 16 and "swap+env+object+lan" in allowed  # 15 combinations, and task alone


def test_a_forbidden_combination_exits_2_naming_the_allowed_ones():
    out = subprocess.run(
        [sys.executable, "-m", "harness", "list", "tasks", "libero/goal:perturb=task+swap"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert out.returncode == 2
    assert "combines with nothing" in out.stderr and "object+lan" in out.stderr


def test_libero_90_has_no_perturbations():
    with pytest.raises(SuiteOptionError, match="perturbed suites: libero/spatial"):
        lb._split_name("libero/90:perturb=lan")


def test_perturbed_suites_are_listed_without_the_simulator():
    names = [s.name for s in list_suites()]
    for key in lp.SUITES:
        for p in ("lan", "object", "swap", "task", "env"):
            assert f"libero/{key}:perturb={p}" in names
    assert "libero/90:perturb=lan" not in names


def test_language_is_read_from_and_written_into_the_bddl():
    text = "(define (problem x)\n  (:language Pick the bowl\n   up)\n  (:goal (And (On a b)))\n)"
    assert lp.bddl_language(text) == "Pick the bowl up"
    assert lp.bddl_language(lp.with_language(text, "lift the bowl")) == "lift the bowl"
    assert "(:goal (And (On a b)))" in lp.with_language(text, "lift the bowl")


@needs_libero
def test_the_instruction_source_decides_what_the_policy_hears():
    """`filename` (the default, LIBERO-PRO's published path: OpenVLA's get_libero_env gives
    task.language): the standard words under every perturbation, lan and task included.
    `bddl` (LIBERO-PRO's evaluation runner: env.language_instruction): each BDDL's own
    (:language), the paraphrase under lan, LIBERO's raw text where the words are unchanged."""
    standard = lb.load_suite("libero/spatial")
    lan = lb.load_suite("libero/spatial:perturb=lan")
    lan_bddl = lb.load_suite("libero/spatial:perturb=lan,instruction=bddl")
    swap_lan = lb.load_suite("libero/spatial:perturb=swap+lan,instruction=bddl")
    swap_bddl = lb.load_suite("libero/spatial:perturb=swap,instruction=bddl")
    standard_bddl = lb.load_suite("libero/spatial:instruction=bddl")
    task = lb.load_suite("libero/spatial:perturb=task")
    task_bddl = lb.load_suite("libero/spatial:perturb=task,instruction=bddl")
    assert lan.version != standard.version and lan.version == lan_bddl.version
    assert lan.name == "libero/spatial:perturb=lan,instruction=filename,seeding=openvla"
    assert lan_bddl.name == "libero/spatial:perturb=lan,instruction=bddl,seeding=openvla"
    assert standard.name == "libero/spatial:seeding=openvla"  # the default stays unnamed on a standard suite
    assert standard_bddl.name == "libero/spatial:instruction=bddl,seeding=openvla"
    # a scene perturbation hears the standard words under the default, so its name (and every
    # row) is the one without the option; under lan and task the source is always named
    swap = lb.load_suite("libero/spatial:perturb=swap")
    assert swap.name == "libero/spatial:perturb=swap,seeding=openvla"
    assert swap_bddl.name == "libero/spatial:perturb=swap,instruction=bddl,seeding=openvla"
    assert lb.load_suite("libero/spatial:perturb=swap,instruction=filename").name == swap.name
    assert task.name == "libero/spatial:perturb=task,instruction=filename,seeding=openvla"
    assert [t.instruction for t in swap.tasks] == [t.instruction for t in standard.tasks]
    bench = lb.benchmark("spatial")
    for i, t in enumerate(lan_bddl.tasks):
        name = bench.get_task(i).bddl_file
        assert t.instruction == lp.bddl_language(
            (lp._root() / "bddl_files" / "libero_spatial_lan" / name).read_text()
        )
        assert t.instruction != standard.tasks[i].instruction
        assert lan.tasks[i].instruction == task.tasks[i].instruction == standard.tasks[i].instruction
        assert swap_lan.tasks[i].instruction == t.instruction
        assert (
            swap_bddl.tasks[i].instruction == standard_bddl.tasks[i].instruction
        )  # the scene moves, not the words
        assert standard_bddl.tasks[i].instruction == lp.bddl_language(
            Path(bench.get_task_bddl_file_path(i)).read_text()
        )
        assert task_bddl.tasks[i].instruction != standard_bddl.tasks[i].instruction  # the new goal's words
    assert (
        sum(a.instruction != b.instruction for a, b in zip(standard.tasks, standard_bddl.tasks, strict=True))
        > 0
    )
    with pytest.raises(SuiteOptionError, match="instruction='words': choose filename or bddl"):
        parse_options("instruction=words")
    from adapters import chains

    with pytest.raises(SuiteOptionError, match="chain suites take no instruction="):
        chains.load_suite("chains/libero_goal:instruction=bddl")


@needs_libero
def test_a_combined_bddl_is_the_scene_with_the_paraphrase(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    task = lb.benchmark("goal").get_task(1)
    bddl, states = lb.task_files("goal", 1, ("object", "lan"))
    assert str(bddl).startswith(str(tmp_path))
    obj, obj_states = lb.task_files("goal", 1, ("object",))
    lan, _ = lb.task_files("goal", 1, ("lan",))
    text = Path(bddl).read_text()
    assert lp.bddl_language(text) == lp.bddl_language(Path(lan).read_text())
    assert lp.with_language(Path(obj).read_text(), lp.bddl_language(text)) == text
    assert np.array_equal(states, obj_states)
    assert task.bddl_file == Path(bddl).name


@needs_libero
def test_env_states_generate_identically_twice(tmp_path):
    bddl = lp.task_bddl("goal", ("env",), *_files("goal", 0))
    first = lp.generate_states(bddl, bddl.stem, n=2)
    second = lp.generate_states(bddl, bddl.stem, n=2)
    assert first.shape[0] == 2 and np.array_equal(first, second)
    assert not np.array_equal(first[0], first[1])  # each state its own draw
    other = lp.generate_states(bddl, bddl.stem, n=1, seed=1)
    assert not np.array_equal(other[0], first[0])  # the recorded seed decides them


@needs_libero
def test_env_states_match_the_recorded_checksums(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    name = lb.benchmark("goal").get_task(0).name
    want = lp.recorded_checksums()[f"goal/{name}"]
    _, states = lb.task_files("goal", 0, ("env",))
    assert states.shape[0] == lp.STATES_PER_TASK
    assert lp.states_sha256(states) == want
    cached = next((tmp_path / "dvla-harness").rglob(f"{name}.npz"))
    np.savez_compressed(cached, states=states + 1e-3)  # a cache from another simulator version
    with pytest.raises(RuntimeError, match="differ from the recorded"):
        lb.task_files("goal", 0, ("env",))


@needs_libero
@pytest.mark.parametrize("key", lp.SUITES)
def test_every_shipped_object_choice_is_rebuilt_by_the_packages_perturbator(key, env_cache):
    """The object step of a combination makes the single `_object` file's choice: for every
    task, its replacements rebuild that file exactly (object_replacements refuses otherwise)."""
    bench = lb.benchmark(key)
    for i in range(bench.get_num_tasks()):
        replacements = lp.object_replacements(key, *_files(key, i))
        assert replacements and all(a != b for a, b in replacements.items())


@needs_libero
def test_a_scene_combination_applies_each_single_perturbations_choice_in_libero_pros_order(env_cache):
    files = _files("spatial", 0)
    swap = Path(lb.task_files("spatial", 0, ("swap",))[0]).read_text()
    obj = Path(lb.task_files("spatial", 0, ("object",))[0]).read_text()
    both = Path(lp.task_bddl("spatial", ("swap", "object"), *files)).read_text()
    replacements = lp.object_replacements("spatial", *files)
    assert both == lp._replace_objects("spatial", files[0], swap, replacements)  # swap first, then object
    assert (
        both not in (swap, obj)
        and "yellow_plate_1" in both
        and "(On yellow_plate_1 main_table_box_region)" in both
    )
    everything = Path(lp.task_bddl("spatial", ("swap", "env", "object", "lan"), *files)).read_text()
    assert "(On yellow_plate_1 living_room_table_box_region)" in everything
    lan = Path(lb.task_files("spatial", 0, ("lan",))[0]).read_text()
    assert lp.bddl_language(everything) == lp.bddl_language(lan)


@needs_libero
def test_combined_scene_states_are_seeded_apart_from_env_and_generate_identically(env_cache):
    bddl = lp.task_bddl("spatial", ("swap", "object"), *_files("spatial", 0))
    first = lp.generate_states(bddl, bddl.stem, n=2, scene="swap+object")
    again = lp.generate_states(bddl, bddl.stem, n=2, scene="swap+object")
    assert np.array_equal(first, again) and not np.array_equal(first[0], first[1])
    assert lp.state_seed(bddl.stem, 0, scene="swap+object") != lp.state_seed(bddl.stem, 0)
    assert lp.checksum_key("spatial", "swap+object", bddl.stem) == f"swap+object/spatial/{bddl.stem}"


@needs_libero
def test_combined_scene_states_match_the_recorded_checksums(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    name = lb.benchmark("spatial").get_task(0).name
    want = lp.recorded_checksums()[f"swap+object/spatial/{name}"]
    _, states = lb.task_files("spatial", 0, ("swap", "object", "lan"))  # a paraphrase moves nothing
    assert states.shape[0] == lp.STATES_PER_TASK and lp.states_sha256(states) == want


@needs_libero
def test_every_generated_scene_of_every_task_has_a_recorded_checksum():
    """A machine that draws other states for any task is told so, not only for task 0: the
    data file records env and each scene combination for every task of the four suites,
    and nothing else (a stale key would check nothing)."""
    recorded = lp.recorded_checksums()
    scenes = lp.GENERATED_SCENES
    assert scenes == ("env", "swap+env", "swap+object", "env+object", "swap+env+object")
    want = {
        lp.checksum_key(key, scene, lb.benchmark(key).get_task(i).name)
        for key in lp.SUITES
        for scene in scenes
        for i in range(lb.benchmark(key).get_num_tasks())
    }
    assert set(recorded) == want and len(want) == 5 * 40
    assert all(len(digest) == 64 for digest in recorded.values())


@pytest.fixture(scope="module")
def env_cache(tmp_path_factory):
    """Generated files go to a temporary cache, shared by the module's tests, not the user's."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("XDG_CACHE_HOME", str(tmp_path_factory.mktemp("cache")))
        yield


def _files(key: str, i: int) -> tuple[str, str]:
    task = lb.benchmark(key).get_task(i)
    return task.bddl_file, task.init_states_file


@needs_libero
@pytest.mark.parametrize(
    ("key", "perturb"),
    [(k, p) for k in lp.SUITES for p in ("lan", "object", "swap", "task", "env")]
    + [("goal", "swap+object"), ("10", "swap+env+object+lan")],
)
def test_each_perturbation_loads_and_resets_under_the_upstream_protocol(key, perturb, env_cache):
    suite = lb.load_suite(f"libero/{key}:perturb={perturb}")
    task = suite.tasks[0]
    assert task.max_steps == lb.MAX_STEPS[key]
    assert [(e.seed, e.init_state_id) for e in task.episodes] == [(0, j) for j in range(50)]
    env = suite.make_env(task)
    try:
        assert env._bddl != lb.benchmark(key).get_task_bddl_file_path(0)
        obs, info = env.reset(options={"episode": task.episodes[1]})
        assert obs.shape == env.observation_space.shape and info == {"success": False}
        again, _ = env.reset(options={"episode": task.episodes[1]})
        np.testing.assert_array_equal(obs, again)  # the same start, settled the same way
    finally:
        env.close()


@needs_libero
def test_the_expert_reads_the_perturbed_problem():
    standard = lb.suite_task_problem("libero/spatial:seeding=openvla", 0)
    perturbed = lb.suite_task_problem("libero/spatial:perturb=object,seeding=openvla", 0)
    assert perturbed["objects"] != standard["objects"]  # other assets
    assert lb.suite_task_problem("libero/spatial:perturb=task", 0)["goal_state"] != standard["goal_state"]


def _expert_context(suite: str, i: int):
    import gymnasium as gym

    from policies.base import EpisodeContext

    key = suite.partition(":")[0].removeprefix("libero/")
    size = max(stop for _, _, stop in lb.state_layout(lb.suite_task_problem(suite, i)))
    return EpisodeContext(
        suite=suite,
        task=lb.benchmark(key).get_task(i).name,
        instruction="",
        action_space=gym.spaces.Box(-1, 1, (7,)),
        observation_space=gym.spaces.Box(-np.inf, np.inf, (size,)),
        max_steps=lb.MAX_STEPS[key],
        episode_index=0,
    )


@needs_libero
def test_the_expert_follows_the_task_perturbations_new_goal(env_cache):
    """Under `task` the expert acts on the new goal: spatial's picks the other bowl; it
    attempts every single-goal task whose predicate it scripts (On, In, Open, TurnOn, TurnOff),
    and refuses libero/10's two-step goals, as it does on the standard suites."""
    from policies.experts.libero_scripted import LiberoScriptedParams
    from policies.experts.libero_select import _problem, expert_for, plan_for

    context = _expert_context("libero/spatial:perturb=task", 0)
    _, slices = _problem(context)
    assert plan_for(context).obj == slices["akita_black_bowl_2"]  # the standard goal's is bowl 1
    attempted = {}
    for key in lp.SUITES:
        attempted[key] = []
        for i in range(lb.benchmark(key).get_num_tasks()):
            try:
                expert_for(_expert_context(f"libero/{key}:perturb=task", i), LiberoScriptedParams(), None)
            except ValueError as exc:
                assert "no script for the goal" in str(exc)
            else:
                attempted[key].append(i)
    assert attempted == {
        "spatial": list(range(10)),
        "object": list(range(10)),
        "goal": list(range(10)),
        "10": [5],
    }


@needs_libero
def test_the_expert_reads_a_stand_in_asset_as_the_one_it_replaces(cli, tmp_path):
    """Under `object` the new assets keep their originals' collision geoms (only the look
    changes), so the expert grips a `black_bowl` as the akita bowl, opens a
    `yellow_cabinet`'s drawer by the wooden cabinet's handles, and solves the episode."""
    from policies.experts.libero_drawer import DrawerExpert
    from policies.experts.libero_geometry import GEOMETRY, geometry
    from policies.experts.libero_scripted import LiberoScriptedParams
    from policies.experts.libero_select import expert_for, plan_for
    from results.store import RunDir

    spatial = _expert_context("libero/spatial:perturb=object,seeding=openvla", 0)
    assert plan_for(spatial).obj_geom == GEOMETRY["akita_black_bowl"]
    assert geometry("yellow_plate_1") == GEOMETRY["plate"] and geometry(
        "bigger_alphabet_soup_1"
    ) != GEOMETRY.get("alphabet_soup")  # a can 1.5x as wide is not the small one
    drawer = expert_for(
        _expert_context("libero/goal:perturb=object,seeding=openvla", 0), LiberoScriptedParams(), None
    )
    assert isinstance(drawer, DrawerExpert) and drawer.plan.category == "wooden_cabinet"
    out = _expert_run(cli, tmp_path, "libero/spatial:perturb=object")
    assert RunDir(out).read_episodes()["success"].tolist() == [True]


def _expert_run(cli, tmp_path, suite: str):
    """The scripted expert on task 0 of `suite`, one episode; the run folder."""
    out = tmp_path / "run"
    code, _, err = cli(
        "run", "--suite", suite, "--tasks", "0", "--policy", "libero_scripted",
        "--episodes-per-task", "1", "--out", str(out), "--quiet",
    )  # fmt: skip
    assert code == 0, err
    return out


@needs_libero
def test_missing_perturbation_files_are_refused_when_the_suite_loads(tmp_path, monkeypatch):
    monkeypatch.setattr(lp, "_root", lambda: tmp_path)
    with pytest.raises(SuiteOptionError, match=r"LIBERO-PRO file missing: .*libero_object_swap"):
        lb.load_suite("libero/object:perturb=swap")


@needs_libero
def test_a_perturbed_run_records_the_paraphrase_and_its_version(cli, tmp_path, monkeypatch):
    import pyarrow.parquet as pq

    from policies.base import EpisodeContext
    from policies.experts import libero_select

    seen: list[EpisodeContext] = []
    problem = libero_select._problem
    monkeypatch.setattr(libero_select, "_problem", lambda context: seen.append(context) or problem(context))
    out = _expert_run(cli, tmp_path, "libero/spatial:perturb=lan,instruction=bddl")
    row = pq.read_table(out / "episodes.parquet").to_pylist()[0]
    paraphrase = lb.load_suite("libero/spatial:perturb=lan,instruction=bddl").tasks[0].instruction
    assert seen and seen[0].instruction == paraphrase == row["instruction"]  # what the policy was given
    assert row["suite"] == "libero/spatial:perturb=lan,instruction=bddl,seeding=openvla"
    assert row["suite_version"] == "1+pro1"
    assert row["success"]  # the expert reads poses, not words: the paraphrase cannot stop it
