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
    [("swap", ("swap",)), ("lan+swap", ("swap", "lan")), ("lan + env", ("env", "lan")), ("task", ("task",))],
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
        ("swap+object", "two scene perturbations"),
        ("colour", "perturbations are"),
        ("swap+swap", "perturbations are"),
    ],
)
def test_forbidden_combinations_name_the_allowed_ones(text, needle):
    with pytest.raises(SuiteOptionError) as err:
        lp.parse_perturb(text)
    assert needle in str(err.value)
    assert "allowed: swap, env, object, lan, task, swap+lan, env+lan, object+lan" in str(err.value)


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
def test_the_policy_receives_the_perturbed_instruction_and_the_suite_is_versioned():
    standard = lb.load_suite("libero/spatial")
    lan = lb.load_suite("libero/spatial:perturb=lan")
    swap_lan = lb.load_suite("libero/spatial:perturb=swap+lan")
    swap = lb.load_suite("libero/spatial:perturb=swap")
    task = lb.load_suite("libero/spatial:perturb=task")
    assert lan.version != standard.version and lan.version == swap.version
    assert lan.name == "libero/spatial:perturb=lan,seeding=openvla"
    bench = lb.benchmark("spatial")
    for i, t in enumerate(lan.tasks):
        bddl = lp._root() / "bddl_files" / "libero_spatial_lan" / bench.get_task(i).bddl_file
        assert t.instruction == lp.bddl_language(bddl.read_text())
        assert t.instruction != standard.tasks[i].instruction  # the benchmark reports the original
        assert swap_lan.tasks[i].instruction == t.instruction
        assert swap.tasks[i].instruction == standard.tasks[i].instruction  # the scene moves, not the words
    assert any(a.instruction != b.instruction for a, b in zip(task.tasks, standard.tasks, strict=True))


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
    first = lp.generate_env_states(bddl, bddl.stem, n=2)
    second = lp.generate_env_states(bddl, bddl.stem, n=2)
    assert first.shape[0] == 2 and np.array_equal(first, second)
    assert not np.array_equal(first[0], first[1])  # each state its own draw
    other = lp.generate_env_states(bddl, bddl.stem, n=1, seed=1)
    assert not np.array_equal(other[0], first[0])  # the recorded seed decides them


@needs_libero
def test_env_states_match_the_recorded_checksums(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    name = lb.benchmark("goal").get_task(0).name
    want = lp.recorded_env_checksums()[f"goal/{name}"]
    _, states = lb.task_files("goal", 0, ("env",))
    assert states.shape[0] == lp.ENV_STATES_PER_TASK
    assert lp.states_sha256(states) == want
    cached = next((tmp_path / "dvla-harness").rglob(f"{name}.npz"))
    np.savez_compressed(cached, states=states + 1e-3)  # a cache from another simulator version
    with pytest.raises(RuntimeError, match="differ from the recorded"):
        lb.task_files("goal", 0, ("env",))


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
@pytest.mark.parametrize("key", lp.SUITES)
@pytest.mark.parametrize("perturb", ["lan", "object", "swap", "task", "env"])
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
    out = tmp_path / "run"
    code, _, err = cli(
        "run", "--suite", "libero/spatial:perturb=lan", "--tasks", "0", "--policy", "libero_scripted",
        "--episodes-per-task", "1", "--out", str(out), "--quiet",
    )  # fmt: skip
    assert code == 0, err
    row = pq.read_table(out / "episodes.parquet").to_pylist()[0]
    paraphrase = lb.load_suite("libero/spatial:perturb=lan").tasks[0].instruction
    assert seen and seen[0].instruction == paraphrase == row["instruction"]  # what the policy was given
    assert row["suite"] == "libero/spatial:perturb=lan,seeding=openvla" and row["suite_version"] == "1+pro1"
    assert row["success"]  # the expert reads poses, not words: the paraphrase cannot stop it
